"""Fast DDS discovery that does not wait for the periodic announcement.

A participant Fast DDS creates announces itself 5 times, 100 ms apart, then every 3 s. On
this project's stacks (five node processes, a bring-up's or a test's probe) a new node was
sometimes missed by its initial announcements and found by the next periodic one:
a service created beside five running participants was seen 2.8-3.3 s after its creation in
2 of 6 tries, and a five-process bring-up took 4.5-5.0 s to be ready (bench/RESULTS.md,
"sixth session"). :data:`PROFILE_FILE` (``config/fastdds_discovery.xml``) raises the initial
announcements to 20 over 2 s and announces every second after them (the measurements are in
the file). Reliable writers send their periodic heartbeat every 0.1 s instead of every 3 s:
a reader acknowledges when a heartbeat asks, and ``Publisher.wait_for_all_acked`` (the
trajectory node's last statuses at shutdown, a bag replay's pacing) waited 2.1-2.6 s for one
sample to one live reader. Nothing else of the participant changes. Fast DDS 2 (Humble,
Jazzy) reads the same profile from :data:`PROFILE_FILE_2` (its XML spells the writer's times
in camel case, and refuses the whole file otherwise).

:func:`use_discovery_profile` points Fast DDS at it, in the process's environment (so the
process itself and every process it starts read it), unless the user chose a profile of
their own or another RMW. Every entry point calls it before ``rclpy.init``.
"""
from __future__ import annotations

import os
from collections.abc import MutableMapping

__all__ = ['FAST_DDS_2_DISTROS', 'PROFILE_FILE', 'PROFILE_FILE_2', 'PROFILE_VARIABLES',
           'use_discovery_profile']

#: the profile, in the package's config directory (Fast DDS 3's XML)
PROFILE_FILE = 'fastdds_discovery.xml'
#: the same profile in Fast DDS 2's XML (:data:`FAST_DDS_2_DISTROS`)
PROFILE_FILE_2 = 'fastdds2_discovery.xml'

#: where Fast DDS looks for a profile file: 3.x (Kilted) reads the first, 2.x (Humble,
#: Jazzy) the second; Kilted's RMW warns at every participant when the second is set
PROFILE_VARIABLES = ('FASTDDS_DEFAULT_PROFILES_FILE', 'FASTRTPS_DEFAULT_PROFILES_FILE')

#: the distributions whose Fast DDS (2.x) reads only ``FASTRTPS_DEFAULT_PROFILES_FILE``
#: (``ROS_DISTRO``, set by their ``setup.bash``; unset, as with the PyPI wheels: Kilted)
FAST_DDS_2_DISTROS = ('humble', 'iron', 'jazzy')


def use_discovery_profile(environ: MutableMapping[str, str] | None = None) -> str | None:
    """Point Fast DDS at :data:`PROFILE_FILE` in ``environ`` (default: this process's) and
    return its path: ``FASTDDS_DEFAULT_PROFILES_FILE``; on a distribution of
    :data:`FAST_DDS_2_DISTROS` both variables, at :data:`PROFILE_FILE_2`. ``None`` (nothing
    set) when either variable is already set (the user's profile wins), when
    ``RMW_IMPLEMENTATION`` names another middleware than Fast DDS, or when the file is
    missing."""
    env = os.environ if environ is None else environ
    if any(env.get(name) for name in PROFILE_VARIABLES):
        return None
    rmw = env.get('RMW_IMPLEMENTATION', '')
    if rmw and not rmw.startswith('rmw_fastrtps'):
        return None
    from ..config import config_dir
    fast_dds_2 = env.get('ROS_DISTRO', '').strip().lower() in FAST_DDS_2_DISTROS
    path = config_dir() / (PROFILE_FILE_2 if fast_dds_2 else PROFILE_FILE)
    if not path.is_file():
        return None
    env[PROFILE_VARIABLES[0]] = str(path)
    if fast_dds_2:
        env[PROFILE_VARIABLES[1]] = str(path)
    return str(path)
