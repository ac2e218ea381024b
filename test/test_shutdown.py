"""Every node stops cleanly on SIGINT and SIGTERM as its own process (``ros2 run``, launch,
``brace-bringup --processes``): exit code 0 and nothing on stderr but log lines, no
``Traceback``, no ``Exception ignored in ...`` from objects torn down at interpreter exit.

Each node is started the way ``ros2 run brace_control <node>`` starts it (its module's
``main``, the device file as parameter file; the CAN driver with its simulated brace). It
is "up" when it answers a probe node's parameter request and, for the driver, when it has
published its state (the drives booted); only then does it get the signal.
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys

import pytest
from diagnostic_msgs.msg import DiagnosticStatus

from brace_control.nodes import topics
from ros_helpers import LUMBAR_YAML, REPO

pytestmark = [pytest.mark.ros, pytest.mark.slow]

NODES = ('trajectory_node', 'ik_node', 'kinetics_node', 'can_driver_node')
#: what a clean stop must never print (CPython's unraisable-exception hook, a traceback)
NOT_ON_STDERR = ('Exception ignored', 'Traceback')


def _start(name: str) -> subprocess.Popen:
    args = [sys.executable, '-m', f'brace_control.nodes.{name}',
            '--ros-args', '--params-file', str(LUMBAR_YAML)]
    if name == 'can_driver_node':
        # its own virtual bus (the simulated brace runs in the driver's process)
        args += ['-p', f'can.channel:=shutdown-{os.getpid()}']
    return subprocess.Popen(args, cwd=REPO, env=dict(os.environ), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


# docs/safety.md §20
@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGTERM], ids=['SIGINT', 'SIGTERM'])
@pytest.mark.parametrize('name', NODES)
def test_node_process_stops_cleanly(ros, name, sig):
    probe = ros.node(f'probe_{name}_{sig.name.lower()}')
    states = (ros.collect(probe, DiagnosticStatus, topics.DRIVER_STATE, topics.LATCHED_QOS)
              if name == 'can_driver_node' else [])
    proc = _start(name)
    try:
        # up = it answers (a node of a killed process can stay in the graph: ros_helpers)
        ros.wait_node_answers(probe, name, timeout=30, stop=lambda: proc.poll() is not None)
        ros.spin_until(lambda: name != 'can_driver_node' or bool(states) or proc.poll() is not None,
                       timeout=30, what=f'{name} state')
        assert proc.poll() is None, f'{name} ended before it was up:\n' + proc.communicate()[1][-3000:]
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, f'{name} exit code {proc.returncode} on {sig.name}:\n{err[-3000:]}'
    for text in NOT_ON_STDERR:
        assert text not in err, f'{name} printed {text!r} on {sig.name}:\n{err[-3000:]}'
