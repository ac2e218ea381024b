"""Never unsupervised (issue 28): a closed terminal, a dead bring-up, a second master, hostile files.

Oracles: the process table (``/proc``: which node processes still run), exit codes, the
bus's own frame log (``can.frame_log``: the last controlword the master sent each drive and
the last statusword each drive answered, CiA 402 bit patterns), the bag's bytes, the
simulator's truth. None of them come from the code under test.
"""
from __future__ import annotations

import contextlib
import copy
import itertools
import math
import os
import signal
import sqlite3
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import yaml

from brace_control.can.framelog import read_frames
from brace_control.nodes.spin import BackgroundSpinner
from ros_helpers import process_alive, wait_until


REPO = Path(__file__).resolve().parent.parent
LUMBAR = REPO / 'config' / 'lumbar_brace.yaml'
_ids = itertools.count()

# CiA 402: controlword commands that leave the drive unable to move (disable voltage: bit 1
# clear; quick stop: bits 1, 2 = 1, 0) and the statusword states that hold no torque-driven
# motion (table 30: SWITCH ON DISABLED, QUICK STOP ACTIVE)
_SWITCH_ON_DISABLED = (0x4F, 0x40)
_QUICK_STOP_ACTIVE = (0x6F, 0x07)


def _stopping_controlword(cw: int) -> bool:
    return not cw & 0x02 or cw & 0x06 == 0x02


def _describe(pid: int) -> str:
    """A process as a failure names it: its command's node, its state and what the kernel
    has it wait on (``pipe_write``: blocked writing to a full pipe; ``futex_wait_queue``: a
    lock)."""
    def read(name: str) -> str:
        try:
            with open(f'/proc/{pid}/{name}', 'rb') as f:
                return f.read().decode(errors='replace')
        except OSError:
            return '?'
    cmd = read('cmdline').split('\0')
    name = next((os.path.basename(c) for c in cmd if c.endswith('_node') or 'can.process' in c), cmd[0])
    stat = read('stat')
    state = stat.rsplit(')', 1)[1].split()[0] if ')' in stat else '?'
    return f'{pid} {name} state {state} waiting in {read("wchan") or "-"}'


def _wait_nodes_gone(tag: str, t_end: float, bound: float | None = None) -> None:
    """Every node of the bring-up ``tag`` gone within ``bound`` s (default NODES_GONE_S) of
    ``t_end``; else fail, naming what was left, where each waits, and whether it ended in 15 s
    more (slow or stuck)."""
    bound = NODES_GONE_S if bound is None else bound
    end = t_end + bound
    while _node_pids(tag) and time.monotonic() < end:
        time.sleep(0.05)
    left = _node_pids(tag)
    if not left:
        return
    seen = [_describe(pid) for pid in left]
    later = time.monotonic() + 15.0
    while _node_pids(tag) and time.monotonic() < later:
        time.sleep(0.1)
    after = _node_pids(tag)
    fate = (f'still there 15 s later: {[_describe(pid) for pid in after]}' if after else
            f'all gone {time.monotonic() - t_end:.1f} s after the bring-up\'s end')
    pytest.fail(f'node processes not gone within {bound} s of the bring-up\'s end: '
                f'{seen}; {fate}')


def _node_pids(tag: str) -> list[int]:
    """Processes whose command line holds ``tag`` (every node of a bring-up gets the same
    ``-p can.channel:=<tag>``)."""
    out = []
    for entry in os.listdir('/proc'):
        if not entry.isdigit():
            continue
        try:
            with open(f'/proc/{entry}/cmdline', 'rb') as f:
                cmd = f.read().decode(errors='replace')
            with open(f'/proc/{entry}/stat') as f:
                zombie = f.read().rsplit(')', 1)[1].split()[0] == 'Z'
        except OSError:
            continue
        if tag in cmd and 'brace_control.bringup' not in cmd and not zombie:
            out.append(int(entry))
    return out


#: s from a bring-up's end to the end of its last node
NODES_GONE_S = 3.5


def _wait(predicate, timeout, what):
    end = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > end:
            pytest.fail(f'{what} not within {timeout} s')
        time.sleep(0.02)
    return True


# ------------------------------------------------------------------ a dead or closed bring-up

#: brace-bringup whose call of the driver's disable service never returns, holding the
#: interpreter lock the way a native call deadlocked inside Fast DDS does (ctypes.PyDLL keeps
#: the GIL during the call)
_STUCK_DISABLE = r"""
import ctypes, sys
import brace_control.bringup as bringup


def _stuck_disable(*args, **kwargs):
    print('the disable call, stuck', flush=True)
    ctypes.PyDLL(None).sleep(120)


bringup.disable_drives = _stuck_disable
sys.exit(bringup.main(sys.argv[1:]))
"""

# docs/safety.md §20
@pytest.mark.ros
@pytest.mark.slow
@pytest.mark.parametrize('sig', [signal.SIGHUP, signal.SIGKILL, 'stuck'],
                         ids=['SIGHUP', 'SIGKILL', 'SIGINT, its shutdown stuck in native code'])
def test_bringup_ended_mid_motion_ends_every_node_with_the_drives_stopped(ros, tmp_path, sig):
    """``brace-bringup --processes``, homed, enabled, a goal running: SIGHUP (a closed
    terminal, an SSH drop) or SIGKILL of the bring-up, or a Ctrl-C whose shutdown then hangs
    in a native call holding the interpreter lock (as a DDS call deadlocked inside Fast DDS
    does, eProsima/Fast-DDS#6502; here the disable service's call, through ctypes.PyDLL): the
    kernel ends that bring-up after SHUTDOWN_DDS_S, status TEARDOWN_CUT, with its stacks on
    stderr. Every node process is gone within NODES_GONE_S of the bring-up's end (the hung
    bring-up: or by its own spin-stall cut, SPIN_STALL_S later), and the
    bus's own log ends with every drive commanded to stop (disable voltage or quick stop) and
    answering SWITCH ON DISABLED or QUICK STOP ACTIVE. A failure shows the bring-up's stderr."""
    tag = f'unsup{os.getpid()}x{next(_ids)}'
    log = tmp_path / 'bus.log'
    start = ['-m', 'brace_control.bringup'] if sig != 'stuck' else ['-c', _STUCK_DISABLE]
    # the bring-up's output in files: read on a failure (a pipe nobody reads could also fill
    # and block the node processes' logging)
    out_path, err_path = tmp_path / 'bringup.out', tmp_path / 'bringup.err'
    with open(out_path, 'w') as out, open(err_path, 'w') as err_file:
        proc = subprocess.Popen(
            [sys.executable, *start, str(LUMBAR), '--processes', '--ros-args',
             '-p', f'can.channel:={tag}', '-p', f'can.frame_log:={log}', '-p', 'trajectory.fitts_a:=2.0'],
            cwd=REPO, stdout=out, stderr=err_file, text=True)
    try:
        _run_ended_mid_motion(ros, proc, tag, sig)
    except (Exception, pytest.fail.Exception) as exc:
        raise AssertionError(f'{exc}\n--- the bring-up\'s stderr (last 4000 characters):\n'
                             f'{err_path.read_text()[-4000:]}') from exc
    if sig == 'stuck':
        err = err_path.read_text()
        assert 'the disable call, stuck' in out_path.read_text()
        assert 'Timeout' in err and '_stuck_disable' in err, err[-3000:]
    _check_the_drives_stopped_moving(log)


def _run_ended_mid_motion(ros, proc: subprocess.Popen, tag: str, sig) -> None:
    """The bring-up ``proc`` homes, enables and moves; then ``sig`` ends it (``'stuck'``:
    SIGINT to a bring-up whose driver's disable never returns; ``'hung'``: a rival's
    announcement to a one-process bring-up whose handling of it hangs) and every node is gone
    in time."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticStatus
    from geometry_msgs.msg import PoseStamped
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import JointState

    from brace_control.bringup import SHUTDOWN_DDS_S, call_trigger, wait_for_links, wait_until_ready
    from brace_control.nodes import topics
    from brace_control.nodes.runner import SPIN_STALL_S, TEARDOWN_CUT
    node = rclpy.create_node(f'probe_{tag}', context=ros.context)
    executor = SingleThreadedExecutor(context=ros.context)
    executor.add_node(node)
    spinner = BackgroundSpinner(executor, 'probe-executor').start()
    joints: list = []
    node.create_subscription(JointState, topics.JOINT_STATES, joints.append, 10)
    try:
        deadline = time.monotonic() + 40
        for what in ('home', 'enable'):
            while True:
                ok, msg = call_trigger(node, f'/can_driver_node/{what}', timeout=10, executor=executor)
                if ok or time.monotonic() > deadline or proc.poll() is not None:
                    break
                time.sleep(0.2)                              # the driver still coming up
            assert ok, f'{what}: {msg}; bring-up: {proc.poll()}'
        wait_for_links(node, timeout=30)          # DDS discovery between the node processes
        wait_until_ready(node, timeout=30)
        statuses: list = []
        node.create_subscription(DiagnosticStatus, topics.GOAL_STATUS, statuses.append, topics.STATUS_QOS)
        pub = node.create_publisher(PoseStamped, topics.POSE_GOAL, topics.GOAL_QOS)
        _wait(lambda: pub.get_subscription_count() >= 1, 20, 'the trajectory node subscribed')
        goal = PoseStamped()
        goal.header.frame_id = 'brace_base'
        goal.pose.position.y = 0.410                       # a 20 mm lift, over ~2.5 s
        goal.pose.orientation.z, goal.pose.orientation.w = math.sin(0.0436), math.cos(0.0436)
        pub.publish(goal)
        _wait(lambda: any(max(abs(v) for v in m.velocity) > 1e-3 for m in joints[-5:]), 20,
              f'the brace moving (goal status: {[s.message for s in statuses]})')
        cycles = _cycle_processes(proc.pid)      # the one-process bring-up's control cycle
        t_signal = time.monotonic()
        if sig == 'hung':
            _announce(node, started=1, nodes=['ik_node'])     # its handling hangs (_HUNG_ON_A_RIVAL)
        else:
            os.kill(proc.pid, signal.SIGINT if sig == 'stuck' else sig)
        proc.wait(timeout=30)
        t_end = time.monotonic()
        if sig == 'stuck':
            assert proc.returncode == TEARDOWN_CUT, proc.returncode
            assert SHUTDOWN_DDS_S <= t_end - t_signal <= SHUTDOWN_DDS_S + 5.0, t_end - t_signal
        if sig == 'hung':
            assert cycles, 'no control cycle process found under the one-process bring-up'
            assert proc.returncode == TEARDOWN_CUT, proc.returncode
            # the stall from the announcement's arrival (discovery: up to 2 s), then the watch's
            # 3 s, re-armed up to 1 s before, and the half second to SIGALRM
            assert t_end - t_signal <= 2.0 + HUNG_STALL_S + 1.0 + 0.5 + 1.0, t_end - t_signal
            _wait(lambda: not any(process_alive(pid) for pid in cycles), NODES_GONE_S,
                  f'the control cycle process(es) {cycles} gone after their bring-up\'s end')
        # each node disables what it drives, then ends: 2.45 s and 2.8 s seen in full suite
        # runs on a host giving this VM less CPU (bench/RESULTS.md, "Test suite time"). The
        # bring-up whose shutdown hung: one of its nodes once stopped spinning meanwhile (a
        # native call that never returned, the Fast DDS kind; a full run, a killed bring-up's
        # participant expiring beside it) and never saw its parent's end: such a node ends
        # by its own spin-stall cut (runner.SPIN_STALL_S) instead
        _wait_nodes_gone(tag, t_end, NODES_GONE_S + (SPIN_STALL_S + 1.0 if sig == 'stuck' else 0.0))
    finally:
        spinner.stop()                        # no spin on a context being shut down
        executor.shutdown()
        node.destroy_node()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        for pid in _node_pids(tag):
            os.kill(pid, signal.SIGKILL)


def _cycle_processes(pid: int) -> list[int]:
    """The control cycle processes (``brace_control.can.process``) whose parent is ``pid``."""
    out = []
    for entry in os.listdir('/proc'):
        if not entry.isdigit():
            continue
        try:
            with open(f'/proc/{entry}/stat') as f:
                ppid = int(f.read().rsplit(')', 1)[1].split()[1])
            with open(f'/proc/{entry}/cmdline', 'rb') as f:
                cmd = f.read().decode(errors='replace')
        except (OSError, ValueError, IndexError):
            continue
        if ppid == pid and 'brace_control.can.process' in cmd:
            out.append(int(entry))
    return out


#: brace-bringup (one process) whose helper node, in its executor's thread, never returns from
#: handling another bring-up's announcement (its own, at the start, passes), holding the
#: interpreter lock (ctypes.PyDLL) as a DDS call deadlocked inside Fast DDS would: every
#: thread of the process stops, its main loop and its signal handlers with it
_HUNG_ON_A_RIVAL = r"""
import ctypes, os, sys
import brace_control.bringup as bringup

_take = bringup.RivalWatch._on_announcement


def _hung_announcement(self, msg):
    if all(kv.value != str(os.getpid()) for kv in msg.values if kv.key == 'pid'):
        print('the rival watch, stuck', flush=True)
        ctypes.PyDLL(None).sleep(120)
    _take(self, msg)


bringup.RivalWatch._on_announcement = _hung_announcement
sys.exit(bringup.main(sys.argv[1:]))
"""
#: s the hung one-process bring-up's watch allows its main loop (BRACE_SPIN_STALL_S)
HUNG_STALL_S = 3.0


# docs/safety.md §20
@pytest.mark.ros
@pytest.mark.slow
def test_a_one_process_bringup_hung_mid_motion_ends_and_its_cycle_stops_the_drives(tmp_path):
    """``brace-bringup`` in one process, homed, enabled, a goal running, when a DDS callback of
    one of its executor threads hangs in native code holding the interpreter lock: nothing of
    it runs again, not its main loop, not a Ctrl-C's handler. The kernel ends it after
    BRACE_SPIN_STALL_S (SIGALRM, TEARDOWN_CUT, its stacks on stderr), and its control cycle's
    process, its link closed, disables the drives and ends: the bus's frame log ends with
    every drive commanded to stop and answering so. On its own ROS domain with a context of
    its own: the hung process's endpoints stay matched in others until its lease runs out."""
    import types

    import rclpy
    from rclpy.context import Context

    from brace_control.nodes.runner import SPIN_STALL_ENV
    from conftest import DOMAIN_BLOCK
    tag = f'hung{os.getpid()}x{next(_ids)}'
    log = tmp_path / 'bus.log'
    base, ours = int(os.environ['BRACE_TEST_DOMAIN_BASE']), os.environ['ROS_DOMAIN_ID']
    # the second spare of the run's block (the stuck rival watch's test takes the first)
    spare = [d for d in range(base + DOMAIN_BLOCK - 1, base, -1) if str(d) != ours][1]
    ctx = Context()
    rclpy.init(context=ctx, domain_id=spare)
    out_path, err_path = tmp_path / 'bringup.out', tmp_path / 'bringup.err'
    with open(out_path, 'w') as out, open(err_path, 'w') as err_file:
        proc = subprocess.Popen(
            [sys.executable, '-c', _HUNG_ON_A_RIVAL, str(LUMBAR), '--ros-args',
             '-p', f'can.channel:={tag}', '-p', f'can.frame_log:={log}', '-p', 'trajectory.fitts_a:=2.0'],
            cwd=REPO, stdout=out, stderr=err_file, text=True,
            env={**os.environ, SPIN_STALL_ENV: f'{HUNG_STALL_S:g}', 'ROS_DOMAIN_ID': str(spare)})
    try:
        _run_ended_mid_motion(types.SimpleNamespace(context=ctx), proc, tag, 'hung')
    except (Exception, pytest.fail.Exception) as exc:
        raise AssertionError(f'{exc}\n--- the bring-up\'s stderr (last 4000 characters):\n'
                             f'{err_path.read_text()[-4000:]}') from exc
    finally:
        rclpy.shutdown(context=ctx)
    assert 'the rival watch, stuck' in out_path.read_text()
    err = err_path.read_text()
    assert 'Timeout' in err and '_hung_announcement' in err, err[-3000:]
    _check_the_drives_stopped_moving(log)


def _check_the_drives_stopped_moving(log) -> None:
    """The frame log: every drive's last controlword stops it, its last statusword says so,
    and the targets were changing before (it was moving when the bring-up ended)."""
    frames = list(read_frames(log))
    for node_id in (1, 2, 3):
        rpdo = [bytes(m.data) for m in frames if m.arbitration_id == 0x200 + node_id]
        tpdo = [bytes(m.data) for m in frames if m.arbitration_id == 0x180 + node_id]
        assert rpdo and tpdo, f'node {node_id}: no PDO in the log'
        cw = int.from_bytes(rpdo[-1][:2], 'little')
        sw = int.from_bytes(tpdo[-1][:2], 'little')
        assert _stopping_controlword(cw), f'node {node_id}: last controlword {cw:04X}h'
        assert any(sw & m == v for m, v in (_SWITCH_ON_DISABLED, _QUICK_STOP_ACTIVE)), \
            f'node {node_id}: last statusword {sw:04X}h'
    # it was moving when the bring-up ended: the log holds changing targets before the stop
    targets = {int.from_bytes(bytes(m.data)[2:6], 'little', signed=True)
               for m in frames if m.arbitration_id == 0x202 and len(m.data) >= 6}
    assert len(targets) > 10


#: brace-bringup whose rival watch, in its spinner thread, never returns from handling its own
#: announcement, holding the interpreter lock (ctypes.PyDLL), as a deadlocked DDS call would
_STUCK_WATCH = r"""
import ctypes, sys
import brace_control.bringup as bringup


def _stuck_announcement(self, msg):
    print('the rival watch, stuck', flush=True)
    ctypes.PyDLL(None).sleep(120)


bringup.RivalWatch._on_announcement = _stuck_announcement
sys.exit(bringup.main(sys.argv[1:]))
"""


# docs/safety.md §20
@pytest.mark.ros
@pytest.mark.slow
def test_a_bringup_stuck_in_native_code_while_running_ends_and_so_do_its_nodes():
    """``brace-bringup --processes`` whose own DDS work (the rival watch's spinner) hangs in
    a native call holding the interpreter lock while the stack runs: its main loop stops
    turning, no signal handler of it could run, yet its nodes must not live on unsupervised.
    The kernel ends it after BRACE_SPIN_STALL_S (SIGALRM, TEARDOWN_CUT, stacks on stderr)
    and every node process then ends, seeing its parent gone."""
    from brace_control.nodes.runner import SPIN_STALL_ENV, TEARDOWN_CUT
    from conftest import DOMAIN_BLOCK
    tag = f'stuckwatch{os.getpid()}x{next(_ids)}'
    # on a domain of the run's block that no worker uses: the killed bring-up's readers stay
    # matched in other participants until its lease runs out (20 s), and a later test's
    # reliable writer would wait for their acknowledgements (the rival test did, once)
    base, ours = int(os.environ['BRACE_TEST_DOMAIN_BASE']), os.environ['ROS_DOMAIN_ID']
    spare = next(str(d) for d in range(base + DOMAIN_BLOCK - 1, base, -1) if str(d) != ours)
    proc = subprocess.Popen(
        [sys.executable, '-c', _STUCK_WATCH, str(LUMBAR), '--processes', '--ros-args',
         '-p', f'can.channel:={tag}'],
        cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        env={**os.environ, SPIN_STALL_ENV: '2', 'ROS_DOMAIN_ID': spare})
    try:
        assert proc.stdout.readline().strip() == 'the rival watch, stuck', proc.poll()
        t_stuck = time.monotonic()
        proc.wait(timeout=30)
        t_end = time.monotonic()
        assert proc.returncode == TEARDOWN_CUT, proc.returncode
        assert t_end - t_stuck <= 2.0 + 0.5 + 1.0 + 2.0, t_end - t_stuck  # armed <= 1 s before
        _wait_nodes_gone(tag, t_end, NODES_GONE_S + 2.0 + 1.0)  # or their own 2 s stall cut
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        for pid in _node_pids(tag):
            os.kill(pid, signal.SIGKILL)
    err = proc.stderr.read()
    assert 'Timeout' in err and '_stuck_announcement' in err, err[-3000:]


# docs/safety.md §20
@pytest.mark.ros
@pytest.mark.slow
def test_a_second_bringup_is_refused_while_one_runs(ros):
    tag = f'second{os.getpid()}x{next(_ids)}'
    first = subprocess.Popen(
        [sys.executable, '-m', 'brace_control.bringup', str(LUMBAR), '--nodes', 'ik_node', '--ros-args',
         '-p', f'can.channel:={tag}'], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        probe = ros.node(f'probe_{tag}')
        ros.wait_node_answers(probe, 'ik_node', 30, stop=lambda: first.poll() is not None)
        second = subprocess.run(
            [sys.executable, '-m', 'brace_control.bringup', str(LUMBAR), '--processes', '--ros-args',
             '-p', f'can.channel:={tag}b'], cwd=REPO, capture_output=True, text=True, timeout=60)
        assert second.returncode == 1, second.stderr[-2000:]
        assert 'already running' in second.stderr and 'ik_node' in second.stderr, second.stderr[-2000:]
        assert first.poll() is None                       # the first one is untouched
    finally:
        first.send_signal(signal.SIGINT)
        first.communicate(timeout=30)


def _announce(node, *, started: int, nodes, namespace: str = '/', pid: int = 4242, host: str = 'elsewhere'):
    """A brace-bringup's announcement on /brace/bringup, as another process would send it."""
    from diagnostic_msgs.msg import DiagnosticStatus

    from brace_control.nodes import topics
    from brace_control.nodes.msgs import status_msg
    pub = node.create_publisher(DiagnosticStatus, topics.BRINGUP, topics.LATCHED_QOS)
    pub.publish(status_msg('brace_bringup', 'running', started=started, host=host, pid=pid,
                           namespace=namespace, nodes=list(nodes)))
    return pub


@pytest.mark.ros
def test_a_bringup_learns_of_an_earlier_one_running_its_nodes_whenever_discovery_finds_it(ros):
    """RivalWatch: the announcement is latched, so it arrives however late discovery is; only
    an EARLIER bring-up, in the same namespace, running one of these nodes, is a rival."""
    from brace_control.bringup import RivalWatch
    me = ros.node(f'rival_me_{next(_ids)}')
    watch = RivalWatch(me, ['ik_node', 'kinetics_node'])
    others = ros.node(f'rival_others_{next(_ids)}')
    t = watch.key[0]
    # not rivals: later, another namespace, no shared node; each announced before the rival,
    # and the rival last, so that once it is seen the others have been delivered too
    pubs = [_announce(others, started=t + 10**9, nodes=['ik_node'], pid=1),
            _announce(others, started=t - 10**9, nodes=['ik_node'], namespace='/left', pid=2),
            _announce(others, started=t - 10**9, nodes=['trajectory_node'], pid=3)]
    ros.spin_until(lambda: all(p.get_subscription_count() >= 1 for p in pubs), 10, 'the announcements matched')
    ros.spin_for(0.5)
    assert watch.rival is None, watch.rival
    pubs.append(_announce(others, started=t - 3 * 10**9, nodes=['kinetics_node', 'ik_node'], pid=4))
    ros.spin_until(lambda: watch.rival is not None, 10, 'the earlier bring-up to be seen')
    assert watch.rival['pid'] == 4 and watch.rival['nodes'] == ['ik_node', 'kinetics_node']
    assert watch.rival['before_s'] == pytest.approx(3.0)
    text = watch.describe()
    assert 'ik_node, kinetics_node already running' in text and 'pid 4 on elsewhere' in text, text


_ANNOUNCER = r"""
import sys, time
import rclpy
from diagnostic_msgs.msg import DiagnosticStatus
from brace_control.nodes import topics
from brace_control.nodes.msgs import status_msg
rclpy.init()
node = rclpy.create_node('rival_announcer')
pub = node.create_publisher(DiagnosticStatus, topics.BRINGUP, topics.LATCHED_QOS)
pub.publish(status_msg('brace_bringup', 'running', started=int(sys.argv[1]), host='elsewhere',
                       pid=4242, namespace='/', nodes=['ik_node']))
print('announced', flush=True)
matched = None
t0 = time.monotonic()
while True:                                   # until the test ends it (SIGTERM)
    count = pub.get_subscription_count()
    if count != matched:
        matched = count
        print(f'matched {count} at {time.monotonic() - t0:.1f} s', flush=True)
    time.sleep(0.1)
"""


@contextlib.contextmanager
def _announcer(started: int):
    """An earlier bring-up's announcement (``_announce``), published by a process of its own:
    a fresh participant, not the test process's long-lived one. Yields the lines it printed
    (``matched N`` whenever its count of matched readers changes)."""
    proc = subprocess.Popen([sys.executable, '-c', _ANNOUNCER, str(started)], cwd=REPO,
                            stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)
    lines: list[str] = []

    def read() -> None:
        for line in proc.stdout:
            lines.append(line.strip())
    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    try:
        wait_until(lambda: 'announced' in lines or proc.poll() is not None, 30, 'the announcement')
        assert 'announced' in lines, lines
        yield lines
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        reader.join(timeout=5)


@pytest.mark.ros
@pytest.mark.slow
@pytest.mark.parametrize('mode', [[], ['--processes']], ids=['one-process', 'processes'])
def test_a_bringup_that_finds_an_earlier_one_after_its_start_stops_its_stack(mode):
    """Discovery slower than the graph watch before the start (seen in a full test run on a
    loaded host: the second bring-up started a whole stack beside the first): the bring-up
    still learns of the earlier one from its announcement, stops its own nodes and exits 1
    with the reason. The earlier one here is an announcement only (no node answers), so the
    watch before the start finds nothing. The announcement comes from a process of its own,
    which says when the bring-up's reader matched it: that told the loss in full runs (the
    reader kept one announcement, the bring-up's own replaced the earlier one's unread; see
    the next test) from a discovery that never happened."""
    with _announcer(time.time_ns() - 5 * 10**9) as announcer:
        proc = subprocess.Popen(
            [sys.executable, '-m', 'brace_control.bringup', str(LUMBAR), *mode, '--nodes', 'ik_node',
             'kinetics_node', '--ros-args', '-p', f'can.channel:=rival{os.getpid()}x{next(_ids)}'],
            cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        try:
            try:
                err = proc.communicate(timeout=60)[1]
            except subprocess.TimeoutExpired:
                proc.send_signal(signal.SIGINT)
                try:
                    err = proc.communicate(timeout=15)[1]
                except subprocess.TimeoutExpired:
                    proc.kill()
                    err = proc.communicate()[1]
                seen = 'already running' in err
                pytest.fail(f'the later bring-up did not stop within 60 s ('
                            f'{"it saw the earlier one: its shutdown hung" if seen else "it never saw the earlier one"}'
                            f'; the announcer said {announcer}); its stderr: {err[-3000:]}')
            assert proc.returncode == 1, err[-2000:]
            assert 'ik_node already running' in err and 'pid 4242 on elsewhere' in err, err[-2000:]
            # it had started its nodes (the graph watch found nothing) and stopped them
            assert 'started as processes' in err or ' up (' in err, err[-2000:]
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.communicate()


# docs/safety.md §20
def test_a_second_master_on_the_bus_is_refused_and_the_first_keeps_running():
    from brace_control.can import BraceMaster, DriverInitializationError
    from brace_control.config import load_device_config
    from brace_control.sim import SimulatedBrace
    cfg = load_device_config(LUMBAR)
    channel = f'master2-{os.getpid()}-{next(_ids)}'
    sim = SimulatedBrace(cfg, channel=channel)
    first = BraceMaster.from_device_config(cfg, channel=channel)
    second = BraceMaster.from_device_config(cfg, channel=channel)
    try:
        first.boot()
        first.home()
        first.enable()
        with pytest.raises(DriverInitializationError, match=r'another CANopen master.*SYNC frames \(COB-ID 080h\)'):
            second.boot()
        second.shutdown()
        # the refused master sent nothing that disturbs the first (no heartbeat of its own)
        time.sleep(0.3)
        assert not first.supervisor.latched, first.supervisor.summary()
        assert first.state.value == 'enabled'
    finally:
        second.shutdown()
        first.shutdown()
        sim.shutdown()


# ------------------------------------------------------------------ hostile device files

def _params() -> dict:
    return yaml.safe_load(LUMBAR.read_text())['/**']['ros__parameters']


def _write(tmp_path: Path, params: dict | None = None, text: str | bytes | None = None) -> Path:
    path = tmp_path / f'hostile{next(_ids)}.yaml'
    if params is not None:
        params['can']['eds'] = str(REPO / 'config' / 'lumbar_drive.eds')
        text = yaml.safe_dump({'/**': {'ros__parameters': params}}, sort_keys=False)
    if isinstance(text, bytes):
        path.write_bytes(text)
    else:
        path.write_text(text)
    return path


def _set(**changes):
    """A params edit: ``section__key=value``."""
    def edit(p):
        for name, value in changes.items():
            section, key = name.split('__')
            p[section][key] = value
        return p
    return edit


HOSTILE = {
    'not UTF-8': (lambda tmp: _write(tmp, text=LUMBAR.read_bytes().replace(b'Lumbar', b'Lumb\xe9r')), 'not UTF-8'),
    'not a mapping': (lambda tmp: _write(tmp, text='/**: [1, 2]\n'), '"/**" must hold'),
    'max_force 0': (_set(actuator__max_force=0.0), 'actuator.max_force'),
    'force_axes x4': (_set(interaction__force_axes=[False, True, True, True]), 'interaction.force_axes'),
    'rest_pose x2': (_set(sim__rest_pose=[0.0, 0.39]), 'sim.rest_pose'),
    'pose_tolerance x2': (_set(safety__pose_tolerance=[0.002, 0.002]), 'safety.pose_tolerance'),
    'singular home': (lambda p: (p['mechanism'].__setitem__('home_pose', [0.0, 0.39, 0.0]),
                                 p['sim'].__setitem__('rest_pose', [0.0, 0.39, 0.0]), p)[-1],
                      'mechanism.home_pose'),
    'zero wrench limits': (_set(safety__max_wrench=[0.0, 0.0, 0.0]), 'safety.max_wrench'),
    'sync 1 Hz': (_set(can__sync_rate_hz=1.0), 'can.sync_rate_hz'),
    'key twice': (lambda tmp: _write(tmp, text=LUMBAR.read_text().replace(
        '      force_limit: 250.0 ', '      force_limit: 250.0\n      force_limit: 2500.0 ').replace(
        'eds: lumbar_drive.eds', f'eds: {REPO / "config" / "lumbar_drive.eds"}')), "'force_limit' is given twice"),
    'force_limit above max_force': (_set(safety__force_limit=2500.0), 'safety.force_limit'),
    'stroke inverted': (lambda p: (p['mechanism'].__setitem__('stroke_min', 0.45), p)[-1], 'stroke'),
    'duplicate node ids': (_set(can__node_ids=[1, 1, 3]), 'can.node_ids'),
    'unreachable home': (lambda p: (p['mechanism'].__setitem__('home_pose', [0.0, 0.60, 0.087]), p)[-1],
                         'mechanism.home_pose'),
    'no such EDS': (lambda tmp: _write(tmp, text=LUMBAR.read_text().replace(
        'eds: lumbar_drive.eds', 'eds: no_such_drive.eds')), "can.eds = 'no_such_drive.eds'"),
    'bad load cell object': (_set(can__load_cell_object='analog one'), 'can.load_cell_object'),
}


def _hostile_file(tmp_path: Path, case: str) -> tuple[Path, str]:
    make, key = HOSTILE[case]
    try:
        path = make(tmp_path)
    except (TypeError, AttributeError, KeyError):
        path = _write(tmp_path, make(copy.deepcopy(_params())))
    return path, key


# docs/safety.md §18
@pytest.mark.parametrize('case', sorted(HOSTILE))
@pytest.mark.parametrize('mode', [[], ['--processes']], ids=['one-process', 'processes'])
def test_every_configuration_mistake_is_a_configuration_error(tmp_path, capsys, case, mode):
    """Table of hostile device files: ``brace-bringup`` answers exit 2 with one line naming
    the key, no traceback, before starting anything (no node process, no ROS)."""
    from brace_control.bringup import main
    path, key = _hostile_file(tmp_path, case)
    before = set(_node_pids(str(path)))
    rc = main([str(path), *mode])
    err = capsys.readouterr().err
    assert rc == 2, (case, err)
    assert key in err and 'configuration error' in err, (case, err)
    assert 'Traceback' not in err
    assert set(_node_pids(str(path))) == before


@pytest.mark.slow
@pytest.mark.parametrize('command', [['brace_control.bringup'], ['brace_control.bringup', '--processes'],
                                     ['brace_control.nodes.kinetics_node']], ids=['one-process', 'processes', 'node'])
# docs/safety.md §18
def test_a_configuration_error_exits_2_in_2_s_as_a_process(tmp_path, command):
    path, key = _hostile_file(tmp_path, 'max_force 0')
    args = [str(path)] if 'bringup' in command[0] else ['--ros-args', '--params-file', str(path)]
    t0 = time.monotonic()
    done = subprocess.run([sys.executable, '-m', *command[:1], *args, *command[1:]], cwd=REPO,
                          capture_output=True, text=True, timeout=60)
    elapsed = time.monotonic() - t0
    assert done.returncode == 2, done.stderr[-2000:]
    assert key in done.stderr and 'Traceback' not in done.stderr, done.stderr[-2000:]
    start = _python_start()
    assert elapsed <= 2.0 + start, (elapsed, start)


def _python_start() -> float:
    """This machine's cost, now, of starting Python with numpy, scipy and rclpy (the
    interpreter and its libraries, not our code): the 2 s budget is on top of it. Measured
    right after the run it is compared with (a figure taken once, on a quiet moment, failed
    the bound beside two busy loops: 6.2 s against 2 + 1.6 s)."""
    t0 = time.monotonic()
    subprocess.run([sys.executable, '-c', 'import numpy, scipy.optimize, yaml, rclpy'], check=True)
    return time.monotonic() - t0


# ------------------------------------------------------------------ goals nobody can parse

# docs/safety.md §6, §12
@pytest.mark.ros
def test_a_goal_that_cannot_be_parsed_is_rejected_with_its_reason(ros, tmp_path):
    """A bag of two goals whose frame_id string length is corrupted (the file intact): the
    trajectory node answers each with ``rejected`` and why; ``brace-bag replay --wait-goals``
    counts both outcomes and reports them."""
    from brace_control.exercise import Goal, write_goal_bag
    from brace_control.nodes.trajectory_node import TrajectoryNode
    bag = write_goal_bag(tmp_path / 'goals', [Goal(0.1, (0.0, 0.39, 0.0873), 'a'),
                                              Goal(0.3, (0.0, 0.40, 0.0873), 'b')],
                         frame_id='brace_base', storage='sqlite3')
    db = next(bag.glob('*.db3'))
    with sqlite3.connect(db) as con:
        rows = con.execute('SELECT id, data FROM messages').fetchall()
        for rid, data in rows:
            data = bytearray(data)
            assert int.from_bytes(data[12:16], 'little') == len('brace_base') + 1   # CDR string length
            data[12:16] = (0x7FFFFF00).to_bytes(4, 'little')
            con.execute('UPDATE messages SET data = ? WHERE id = ?', (bytes(data), rid))
    ros.device_node(TrajectoryNode)
    done = {}

    def replay():
        done['run'] = subprocess.run(
            [sys.executable, '-m', 'brace_control.bag', 'replay', str(bag), '--wait-goals', '10',
             '--wait-for-subscribers', '1'], cwd=REPO, capture_output=True, text=True, timeout=90)
    import threading
    t = threading.Thread(target=replay)
    t.start()
    ros.spin_until(lambda: not t.is_alive(), 90, 'the replay to end')
    err = done['run'].stderr
    assert 'goal outcomes: 2 of 2 goal(s) replayed ended (2 rejected)' in err, err[-2000:]
    assert err.count('malformed goal') == 2 and 'not a PoseStamped' in err, err[-2000:]
    assert done['run'].returncode == 0, err[-2000:]


@pytest.mark.parametrize('option, value', [('--wait-timeout', 'nan'), ('--delay', 'nan'), ('--delay', '-5'),
                                           ('--wait-for-subscribers', '-3'), ('--rate', '0'),
                                           ('--ack-timeout', 'inf')])
def test_bag_replay_arguments_are_checked(tmp_path, capsys, option, value):
    from brace_control.bag import main
    assert main(['replay', str(tmp_path / 'none'), option, value]) == 1
    err = capsys.readouterr().err
    assert option in err and 'expected a finite number' in err, err


def test_bag_record_into_a_missing_directory_is_an_error(tmp_path):
    from brace_control.bag import BagError, Recorder
    with pytest.raises(BagError, match='does not exist'):
        Recorder(None, tmp_path / 'missing' / 'x.mcap', ['/a'])


def test_a_duplicate_key_the_ros_parser_would_take_is_refused(tmp_path):
    from brace_control.config import ConfigError, load_device_config
    path, key = _hostile_file(tmp_path, 'key twice')
    with pytest.raises(ConfigError, match=r"'force_limit' is given twice in one mapping \(lines \d+ and \d+\)"):
        load_device_config(path)
    # without our loader the last would silently win
    assert yaml.safe_load(path.read_text())['/**']['ros__parameters']['safety']['force_limit'] == 2500.0
    assert key


@pytest.mark.ros
def test_a_rivals_announcement_is_not_lost_behind_later_ones_before_it_is_taken(ros):
    """The reader keeps every bring-up's announcement until it is taken: an earlier
    bring-up's, then three others and this one's own, all delivered (acknowledged) before
    the node spins once. With the reader's depth 1 only the last was left and the rival was
    never seen (a later bring-up then ran beside an earlier one in full test runs)."""
    from rclpy.duration import Duration

    from brace_control.bringup import RivalWatch
    others = ros.node(f'rival_late_others_{next(_ids)}')
    me = ros.node(f'rival_late_me_{next(_ids)}')
    watch = RivalWatch(me, ['ik_node', 'kinetics_node'])
    t = watch.key[0]
    pubs = [_announce(others, started=t - 10**9, nodes=['ik_node'], pid=7)]          # the rival
    pubs += [_announce(others, started=t + k * 10**9, nodes=['ik_node'], pid=10 + k) for k in (1, 2, 3)]
    for pub in [*pubs, watch._pub]:
        wait_until(lambda pub=pub: pub.get_subscription_count() >= 1, 10, 'the reader matched')
        assert pub.wait_for_all_acked(Duration(seconds=10)), 'an announcement not acknowledged'
    ros.spin_until(lambda: len(watch.seen) >= 5, 10, 'five announcements taken')
    assert watch.rival is not None and watch.rival['pid'] == 7, (watch.rival, watch.seen)
