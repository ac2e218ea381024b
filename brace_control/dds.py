"""DDS settings of brace_control's processes, applied before ``rclpy.init``.

:func:`use_packaged_profiles` points Fast DDS at ``fastdds_profiles.xml`` (next to this
module) unless the user chose a profiles file of their own. The file raises one QoS: how
long a service server waits for the caller's response reader to be matched before it
drops the answer (rmw_fastrtps' ``max_blocking_time`` check in ``rmw_send_response``;
100 ms by default). Discovery of a client created just before its call can take longer
on a loaded host; the driver then homes or enables the drives and the caller never hears
so. Other RMW implementations ignore the variables.
"""
from __future__ import annotations

import os
from pathlib import Path

__all__ = ['PROFILES_FILE', 'PROFILE_VARIABLES', 'FAST_DDS_2_DISTROS', 'use_packaged_profiles']

#: the packaged Fast DDS XML profiles
PROFILES_FILE = Path(__file__).with_name('fastdds_profiles.xml')
#: Fast DDS 3 (Kilted on) reads the first, Fast DDS 2 (Humble, Jazzy) the second
PROFILE_VARIABLES = ('FASTDDS_DEFAULT_PROFILES_FILE', 'FASTRTPS_DEFAULT_PROFILES_FILE')
#: the distributions that ship Fast DDS 2 (Kilted's rmw warns that the old name is deprecated)
FAST_DDS_2_DISTROS = ('humble', 'iron', 'jazzy')


def use_packaged_profiles(environ: dict | None = None) -> bool:
    """Point Fast DDS at :data:`PROFILES_FILE` in ``environ`` (``os.environ``) unless a
    profiles file is set already; ``True`` when set here. ``FASTDDS_DEFAULT_PROFILES_FILE``
    always, ``FASTRTPS_DEFAULT_PROFILES_FILE`` too where ``ROS_DISTRO`` is one of
    :data:`FAST_DDS_2_DISTROS`.

    Call before ``rclpy.init``: Fast DDS reads its profiles when the first participant is
    made. Child processes inherit the variables.
    """
    env = os.environ if environ is None else environ
    if any(env.get(v) for v in PROFILE_VARIABLES):
        return False
    env[PROFILE_VARIABLES[0]] = str(PROFILES_FILE)
    if env.get('ROS_DISTRO', '').lower() in FAST_DDS_2_DISTROS:
        env[PROFILE_VARIABLES[1]] = str(PROFILES_FILE)
    return True
