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
import threading
import time
from pathlib import Path

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
    except BaseException:
        _kill(proc)
        raise
    _stops_cleanly(proc, sig, f'{name} on {sig.name}')


def _kill(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.kill()
        proc.wait()


def _stops_cleanly(proc: subprocess.Popen, sig: int, what: str) -> None:
    """``sig`` to ``proc``: it ends with exit code 0 and prints nothing of NOT_ON_STDERR."""
    try:
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=30)
    finally:
        _kill(proc)
    assert proc.returncode == 0, f'{what}: exit code {proc.returncode}:\n{err[-3000:]}'
    for text in NOT_ON_STDERR:
        assert text not in err, f'{what}: printed {text!r}:\n{err[-3000:]}'


#: how a node's process is started: ``ros2 run`` (the console script), ``python -m``, and
#: the bring-up's fallback (``brace_control.bringup.find_executable``)
START_FORMS = {
    'console_script': lambda name: [str(Path(sys.executable).parent / name)],
    'python_m': lambda name: [sys.executable, '-m', f'brace_control.nodes.{name}'],
    'python_c': lambda name: [sys.executable, '-c',
                              f'import sys; from brace_control.nodes.{name} import main; sys.exit(main())'],
}


def _importing_rclpy(pid: int) -> bool:
    """rclpy's native module is loaded: the process is in its imports, past
    ``brace_control.nodes``' own (rclpy is imported by the node's module, after it)."""
    try:
        return '_rclpy_pybind11' in Path(f'/proc/{pid}/maps').read_text()
    except OSError:
        return False


# docs/safety.md §20
@pytest.mark.parametrize('form', sorted(START_FORMS))
def test_a_node_stopped_while_it_still_imports_ends_cleanly(form):
    """SIGINT while the node's process imports rclpy and its messages (about a second after
    ``ros2 run``; a bring-up that stops its nodes as they start): exit code 0, no
    ``KeyboardInterrupt`` traceback."""
    proc = subprocess.Popen([*START_FORMS[form]('kinetics_node'), '--ros-args', '--params-file',
                             str(LUMBAR_YAML)], cwd=REPO, env=dict(os.environ),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 30
        while not _importing_rclpy(proc.pid) and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.002)
        assert proc.poll() is None, 'the node ended by itself:\n' + proc.communicate()[1][-3000:]
    except BaseException:
        _kill(proc)
        raise
    _stops_cleanly(proc, signal.SIGINT, f'kinetics_node ({form}) while importing')


_STUCK_TEARDOWN = r"""
import ctypes, sys
from rclpy.node import Node
from brace_control.nodes.runner import run_node


class StuckAtTeardown(Node):
    '''A node whose DDS teardown never returns, holding the interpreter lock the way a native
    call deadlocked inside Fast DDS does (ctypes.PyDLL keeps the GIL during the call).'''

    def __init__(self):
        super().__init__('stuck_teardown')
        self.create_timer(0.05, lambda: print('spinning', flush=True))

    def shutdown(self):
        print('work done', flush=True)

    def destroy_node(self):
        ctypes.PyDLL(None).sleep(120)


sys.exit(run_node(StuckAtTeardown, executable='stuck', summary='test'))
"""


# docs/safety.md §20
def test_a_teardown_stuck_in_native_code_is_cut_short_with_its_stacks():
    """After the node's own work, a DDS teardown that deadlocks in native code holding the
    interpreter lock (eProsima/Fast-DDS#6502) no longer holds the process: its threads'
    stacks go to stderr after TEARDOWN_S and the kernel ends it with SIGALRM
    (``TEARDOWN_CUT``), which the bring-up tells apart from an error."""
    import time

    from brace_control.nodes.runner import TEARDOWN_CUT, TEARDOWN_S
    proc = subprocess.Popen([sys.executable, '-c', _STUCK_TEARDOWN], cwd=REPO, env=dict(os.environ),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == 'spinning'
        proc.send_signal(signal.SIGINT)
        t0 = time.monotonic()
        out, err = proc.communicate(timeout=TEARDOWN_S + 10)
        took = time.monotonic() - t0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert 'work done' in out
    assert proc.returncode == TEARDOWN_CUT, (proc.returncode, err[-2000:])
    assert TEARDOWN_S <= took <= TEARDOWN_S + 5, took
    assert 'Timeout' in err and 'destroy_node' in err, err[-2000:]


_STUCK_SPIN = r"""
import ctypes, sys
from rclpy.node import Node
from brace_control.nodes.runner import run_node


class StuckInACallback(Node):
    '''A node whose callback, after a few turns, never returns from a native call holding the
    interpreter lock (ctypes.PyDLL keeps the GIL), as a call deadlocked inside Fast DDS or the
    executor does: its spin loop stops turning, and no signal handler can run any more.'''

    def __init__(self):
        super().__init__('stuck_in_a_callback')
        self.turns = 0
        self.create_timer(0.05, self.tick)

    def tick(self):
        self.turns += 1
        print('spinning', flush=True)
        if self.turns == 60:                  # 3 s of spinning: longer than the limit, 2 s
            print('stuck', flush=True)
            ctypes.PyDLL(None).sleep(120)


sys.exit(run_node(StuckInACallback, executable='stuck', summary='test'))
"""


# docs/safety.md §20
def test_a_spin_loop_stuck_in_native_code_ends_the_node_with_its_stacks():
    """A node whose spin loop stops turning (a native call that never returns, holding the
    interpreter lock: no Python code of the process runs again, no stop signal's handler, no
    parent watch) ends itself after BRACE_SPIN_STALL_S with its threads' stacks on stderr
    (SIGALRM, TEARDOWN_CUT), instead of living on unsupervised; while it spins (3 s here) it
    keeps running past that time."""
    import time

    from brace_control.nodes.runner import SPIN_STALL_ENV, TEARDOWN_CUT
    env = {**os.environ, SPIN_STALL_ENV: '2'}
    proc = subprocess.Popen([sys.executable, '-c', _STUCK_SPIN], cwd=REPO, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        while (line := proc.stdout.readline().strip()) != 'stuck':
            assert line == 'spinning', (line, proc.poll())
        t0 = time.monotonic()
        out, err = proc.communicate(timeout=20)
        took = time.monotonic() - t0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == TEARDOWN_CUT, (proc.returncode, err[-2000:])
    assert took <= 2.0 + 0.5 + 1.0 + 2.0, took           # armed up to 1 s before, + slack
    assert 'Timeout' in err and 'tick' in err, err[-2000:]


@pytest.mark.parametrize('value', ['soon', '-1', 'nan'])
def test_a_spin_stall_limit_that_is_no_number_of_seconds_is_a_configuration_error(value):
    from brace_control.nodes.runner import EXIT_CONFIG, SPIN_STALL_ENV
    proc = subprocess.run([sys.executable, '-m', 'brace_control.nodes.ik_node', '--ros-args',
                           '--params-file', str(LUMBAR_YAML)], cwd=REPO, capture_output=True,
                          text=True, timeout=60, env={**os.environ, SPIN_STALL_ENV: value})
    assert proc.returncode == EXIT_CONFIG, (proc.returncode, proc.stderr[-2000:])
    assert f'{SPIN_STALL_ENV}={value!r}: expected seconds >= 0' in proc.stderr, proc.stderr[-2000:]


def test_long_work_is_allowed_only_where_a_watch_runs_and_never_less_than_its_limit(monkeypatch):
    """allow_long_work: the process's newest StallWatch lets its loop stand still LONG_WORK_S
    (a driver's configure: the cycle process's start and the boot), re-armed to its limit by
    a later turn; with no watch (in-process bring-ups, tests, the demo) or a watch that is
    off (BRACE_SPIN_STALL_S=0) it arms nothing; after a shutdown began, nothing either."""
    import signal

    from brace_control.nodes import runner
    previous = signal.getsignal(signal.SIGALRM)
    monkeypatch.setattr(runner.StallWatch, 'active', None)
    armed: list = []
    monkeypatch.setattr(runner, 'cut_short_after', armed.append)
    runner.allow_long_work()
    assert armed == [] and signal.getitimer(signal.ITIMER_REAL)[0] == 0.0
    runner.StallWatch(0.0)
    runner.allow_long_work()
    assert armed == []                                   # the watch is off
    watch = runner.StallWatch(5.0)
    watch.turn()
    runner.allow_long_work()
    runner.allow_long_work(2.0)                          # never less than the watch's limit
    assert armed == [5.0, runner.LONG_WORK_S, 5.0]
    watch._armed -= 1.0                                  # the loop turns a second later
    watch.turn()
    assert armed[-1] == 5.0 and len(armed) == 4
    watch.allow(60.0)
    watch.rearm()                                        # the bring-up's rival watch starts
    assert armed[-2:] == [60.0, 5.0]
    runner.StallWatch.active = None                      # run_node's shutdown
    runner.allow_long_work()
    assert len(armed) == 6
    # an in-process bring-up: the watch is its main loop's; a driver's transition runs in an
    # executor thread while that loop turns on, and allows it nothing
    runner.StallWatch(5.0)
    worker = threading.Thread(target=runner.allow_long_work)
    worker.start()
    worker.join()
    assert len(armed) == 6
    signal.signal(signal.SIGALRM, previous)   # a watch sets SIGALRM's default action


def test_the_cut_is_rearmed_from_any_thread_its_action_set_by_the_main_one():
    """cut_short_after from a thread other than the main one (signal.signal would raise
    there) re-arms the timer; the action, SIGALRM's default, is the main thread's to set
    (StallWatch does, when it is made)."""
    import signal

    from brace_control.nodes import runner
    errors: list = []

    def rearm() -> None:
        try:
            runner.cut_short_after(300.0)
            errors.append(signal.getitimer(signal.ITIMER_REAL)[0])
        except Exception as exc:  # noqa: BLE001 - the failure this test looks for
            errors.append(exc)
        finally:
            runner.cut_short_after(None)
    before = signal.getsignal(signal.SIGALRM)
    try:
        worker = threading.Thread(target=rearm)
        worker.start()
        worker.join()
    finally:
        signal.signal(signal.SIGALRM, before)
    assert len(errors) == 1 and isinstance(errors[0], float) and 299.0 < errors[0] <= 300.5, errors
    assert signal.getitimer(signal.ITIMER_REAL)[0] == 0.0


def test_a_stop_whose_systemexit_an_import_swallowed_still_ends_the_node_at_once():
    """A stop signal during the imports raises SystemExit (nodes/__init__); should an import
    swallow it (a broad except, a finaliser), the signal would be lost and the node would run
    on (the twelfth session's final clones: kinetics_node idle in its spin loop, 30 s after
    the test's SIGINT). The handler also records it, and ``run_node`` ends at once, exit 0,
    before rclpy starts: here the record set by hand, as a swallowed SystemExit leaves it."""
    code = ('import sys, brace_control.nodes as n; n.STOPPED_WHILE_STARTING = True; '
            'from brace_control.nodes.kinetics_node import main; '
            f'sys.exit(main(["kinetics_node", "--ros-args", "--params-file", {str(LUMBAR_YAML)!r}]))')
    out = subprocess.run([sys.executable, '-c', code], cwd=REPO, env=dict(os.environ),
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr[-2000:]
    assert 'kinetics_node' not in out.stderr and 'Traceback' not in out.stderr, out.stderr[-2000:]
