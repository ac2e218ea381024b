"""What both demos share (:mod:`brace_control.demo`, :mod:`brace_control.demo_interaction`):
the topics a run records, the device file it runs, and the waits on the ROS graph.

Neither demo imports the other's helpers: both import this module.
"""
from __future__ import annotations

import math
import os
import signal
import subprocess
import time
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from .nodes import topics

__all__ = ['RECORDED_TOPICS', 'prepare_config', 'find_service', 'pkg_path', 'wait_recording', 'end_session',
           'launch_recorder', 'home_and_enable']


#: Every brace topic a run publishes, with its type: what ``OUT/run.mcap`` holds. Not the
#: teleoperation streams (``/brace/pose_setpoint``, ``/brace/actuator_setpoint``), the paths,
#: the wrench goal or the body's rest: nothing publishes them in a run, and ``brace-bag
#: record`` fails on a topic that never appears.
RECORDED_TOPICS = {
    topics.POSE_GOAL: 'geometry_msgs/msg/PoseStamped',
    topics.POSE_TRAJECTORY: 'trajectory_msgs/msg/MultiDOFJointTrajectory',
    topics.ACTUATOR_TRAJECTORY: 'trajectory_msgs/msg/JointTrajectory',
    topics.JOINT_STATES: 'sensor_msgs/msg/JointState',
    topics.POSE: 'geometry_msgs/msg/PoseStamped',
    topics.POSE_WITH_COVARIANCE: 'geometry_msgs/msg/PoseWithCovarianceStamped',
    topics.WRENCH: 'geometry_msgs/msg/WrenchStamped',
    topics.GOAL_STATUS: 'diagnostic_msgs/msg/DiagnosticStatus',
    topics.EXECUTION_STATUS: 'diagnostic_msgs/msg/DiagnosticStatus',
    topics.DRIVER_STATE: 'diagnostic_msgs/msg/DiagnosticStatus',
    topics.DIAGNOSTICS: 'diagnostic_msgs/msg/DiagnosticArray',
    topics.SIM_JOINT_STATES: 'sensor_msgs/msg/JointState',
    topics.SIM_POSE: 'geometry_msgs/msg/PoseStamped',
    topics.SIM_WRENCH: 'geometry_msgs/msg/WrenchStamped',
}


def prepare_config(device: str, out: Path) -> tuple[Path, str | None]:
    """The device file to run; ``(path, note)``.

    If the device's home pose is singular (the lumbar brace's ``theta = 0`` poses are:
    its anchor rows are parallel and the leg lines meet in one point), nothing can be
    planned from it, so the demo parks the brace tilted by the exercise's neutral tilt:
    a copy of the file with ``mechanism.home_pose`` and ``sim.rest_pose`` turned by it.
    """
    from .config import load_device_config, resolve_device_file
    from .exercise import NEUTRAL_TILT
    from .mechanisms import mechanism_from_config
    path = resolve_device_file(device)
    cfg = load_device_config(path)
    mech = mechanism_from_config(cfg)
    if mech.in_workspace(mech.home_pose) or mech.dof != 3:
        return path, None
    doc = yaml.safe_load(path.read_text())
    params = doc['/**']['ros__parameters']
    home = list(params['mechanism']['home_pose'])
    home[2] = float(home[2]) + NEUTRAL_TILT
    params['mechanism']['home_pose'] = home
    if 'sim' in params and 'rest_pose' in params['sim']:
        rest = list(params['sim']['rest_pose'])
        rest[2] = float(rest[2]) + NEUTRAL_TILT
        params['sim']['rest_pose'] = rest
    for key in ('eds',):
        if key in params.get('can', {}):
            params['can'][key] = str(cfg.relative_file(params['can'][key]))
    derived = out / path.name
    derived.write_text(f'# {path} with the brace parked at theta = {math.degrees(NEUTRAL_TILT):.1f} deg '
                       '(written by brace_control.demo)\n' + yaml.safe_dump(doc, sort_keys=False))
    note = (f'home pose {np.round(mech.home_pose, 4).tolist()} is singular (theta = 0); the brace '
            f'is parked at theta = {math.degrees(NEUTRAL_TILT):.1f} deg instead ({derived})')
    return derived, note


def find_service(node, suffix: str, timeout: float) -> str | None:
    """The name of the Trigger service ending in ``suffix`` once it is in the graph (``None``
    after ``timeout`` s)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for name, types in node.get_service_names_and_types():
            if name.rstrip('/').split('/')[-1] == suffix and 'std_srvs/srv/Trigger' in types:
                return name
        time.sleep(0.1)
    return None


def pkg_path() -> str:
    """``PYTHONPATH`` for the processes a demo starts: the caller's, then this checkout."""
    root = str(Path(__file__).resolve().parent.parent)
    return os.pathsep.join(p for p in (os.environ.get('PYTHONPATH', ''), root) if p)


def wait_recording(node, topics: list[str], proc, timeout: float = 20.0) -> None:
    """Until the recorder process subscribes every topic (it knows their types from the graph)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f'recorder exited: {proc.stderr.read()[-500:]}')
        subs = {t: node.get_subscriptions_info_by_topic(t) for t in topics}
        if all(any(i.node_name == 'brace_bag' for i in infos) for infos in subs.values()):
            return
        time.sleep(0.1)
    missing = [t for t in topics if not any(i.node_name == 'brace_bag'
                                            for i in node.get_subscriptions_info_by_topic(t))]
    raise RuntimeError(f'recorder did not subscribe {missing} within {timeout} s')


def end_session(node: Any, executor: Any, bringup: Any, recorder: Any, *, processes: bool,
                failure: str | None) -> str | None:
    """End a demo's session, drives first: the stack (processes: the driver's disable, then
    the nodes, whose exit codes must be 0), the recorder (SIGINT, its bag closed), the
    demo's own node. Returns the first failure (the one given, else one found here)."""
    import rclpy

    from .bringup import disable_drives
    if bringup is not None:
        if processes:
            ok, msg = disable_drives(node, executor=executor)
            print(f'disable: {"ok" if ok else "FAILED"} {msg}')
            codes = bringup.stop()
            if any(c != 0 for c in codes.values()):
                failure = failure or f'node exit codes {codes}'
        else:
            bringup.shutdown()                  # the in-process driver disables first
    if recorder is not None:
        recorder.send_signal(signal.SIGINT)
        try:
            _, err = recorder.communicate(timeout=30)
            if recorder.returncode != 0:
                failure = failure or f'recorder failed: {err[-500:]}'
        except subprocess.TimeoutExpired:
            recorder.kill()
            failure = failure or 'recorder did not stop'
    executor.shutdown()
    node.destroy_node()
    rclpy.try_shutdown()
    return failure


def launch_recorder(path: Path, topics: Any) -> subprocess.Popen:
    """``brace-bag record`` of ``topics`` into ``path`` in its own process (~900 messages/s
    of raw writes stay off this interpreter, which in one-process mode also runs the SYNC
    thread and the simulator). Wait for it with :func:`wait_recording`."""
    import sys
    return subprocess.Popen(
        [sys.executable, '-m', 'brace_control.bag', 'record', str(path), '--topics', *topics],
        stderr=subprocess.PIPE, text=True, start_new_session=True,
        env={**os.environ, 'PYTHONPATH': pkg_path()})


def home_and_enable(node: Any, services: dict[str, str], executor: Any) -> None:
    """The CAN driver's ``home`` then ``enable`` (``services``: their names in the graph).

    :raises RuntimeError: either refused (its answer)."""
    from .bringup import call_trigger
    for what in ('home', 'enable'):
        ok, msg = call_trigger(node, services[what], timeout=20.0, executor=executor)
        print(f'{what}: {"ok" if ok else "FAILED"} {msg}')
        if not ok:
            raise RuntimeError(f'{services[what]} failed: {msg}')
