"""The control cycle in a process of its own (issue 27, :mod:`brace_control.can.process`).

The master and the simulated brace run in a child; the parent reads them from snapshots and
commands them by call. Oracles: the simulator's truth (the child's own, sent with each
snapshot) and the minimum-jerk law (rpr_oracles), never the master's setpoints; for
supervision, the operating system's view of the processes.
"""
from __future__ import annotations

import itertools
import os
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

from brace_control.can import ActuatorTrajectory, DriverError, FaultKind, MasterConfig, MasterState
from brace_control.can.process import MasterProcess
from brace_control.config import load_device_config
from brace_control.mechanisms import mechanism_from_config
from ros_helpers import kernel_threads, process_alive
from rpr_oracles import min_jerk
from test_can_master import wait_for

CFG = load_device_config('lumbar_brace')
MECH = mechanism_from_config(CFG)
_ids = itertools.count()


def _config(**overrides) -> MasterConfig:
    return MasterConfig.from_device_config(CFG, mechanism=MECH,
                                           channel=f'proc-{os.getpid()}-{next(_ids)}', **overrides)


@pytest.fixture
def enabled():
    mp = MasterProcess(CFG, _config())
    try:
        mp.boot()
        mp.home()
        mp.enable()
        yield mp
    finally:
        mp.shutdown()


def test_a_trajectory_runs_in_the_child_and_the_truth_follows_it(enabled):
    """A 5 mm minimum-jerk lift of every leg, sent to the child: its events come back once
    each, in order, and the simulated legs end where the law ends (truth, 0.2 mm)."""
    mp = enabled
    assert mp.state is MasterState.ENABLED and mp.homed
    q0 = np.asarray(mp.sim.truth().lengths, float)
    t, q, v, a = min_jerk(q0, q0 + 0.005, 0.6, 61)
    tag = 42
    assert mp.execute(ActuatorTrajectory(t, q, v, a), start=time.perf_counter() + 0.05, tag=tag) is None
    events: list = []
    wait_for(lambda: events.extend(mp.execution_events()) or
             any(e.kind == 'finished' for e in events), 10.0, 'finished')
    kinds = [e.kind for e in events if e.tag == tag]
    assert kinds == ['accepted', 'started', 'finished'], kinds
    wait_for(lambda: np.max(np.abs(np.asarray(mp.sim.truth().lengths) - q[-1])) < 2e-4, 3.0,
             'the legs at the end of the law')
    # what the node publishes as the measurement: the drives' encoders, within a count
    fb = mp.feedback()
    assert fb.valid and np.max(np.abs(fb.position - np.asarray(mp.sim.truth().lengths))) < 1e-5


def test_bad_input_crosses_back_as_the_error_it_was(enabled):
    """A setpoint outside the stroke: ValueError naming the leg and the stroke, nothing
    moves; a command on a closed master: DriverError."""
    mp = enabled
    before = np.asarray(mp.sim.truth().lengths, float)
    with pytest.raises(ValueError, match=r'a1 = 9\.00000 m is outside the stroke'):
        mp.set_targets([9.0, 0.39, 0.39])
    with pytest.raises(ValueError, match='expected 3 target positions'):
        mp.set_targets([0.39, 0.39])
    time.sleep(0.05)
    assert np.max(np.abs(np.asarray(mp.sim.truth().lengths) - before)) < 1e-5
    assert not mp.latched


def test_faults_injected_in_the_child_latch_and_read_back(enabled):
    """The simulator's fault injection, reached by path from the parent: a load cell reading
    past safety.force_limit latches a FORCE_LIMIT stop (read from the snapshots)."""
    mp = enabled
    limit = float(CFG['safety']['force_limit'])
    mp.sim.faults.set_load_cell(2, 1.06 * limit)        # below the cell's saturation (95 % of 300 N)
    wait_for(lambda: mp.latched, 3.0, 'protective stop')
    assert mp.supervisor.has(FaultKind.FORCE_LIMIT)
    assert 'a2' in mp.fault_summary()
    # the rest of the master, reached by path: its answers are the child's
    assert mp.moving is False
    assert [f.kind for f in mp.supervisor.blocking()] == [FaultKind.FORCE_LIMIT]   # still pressing
    mp.sim.faults.set_load_cell(2, None)
    wait_for(lambda: not mp.supervisor.blocking(), 3.0, 'the cause gone')


@pytest.mark.parametrize('sig, said', [
    (signal.SIGKILL, 'the control cycle process was killed by SIGKILL'),
    (signal.SIGTERM, 'the control cycle process ended on SIGTERM after disabling the drives')])
def test_a_dead_child_is_a_fault_and_every_call_says_so(sig, said):
    """Killed, or ended by a SIGTERM of its own (it disables the drives first): a
    protective stop whose cause names the signal (a process-group SIGTERM reaches the child
    too: its stop is then no mystery in the node's log)."""
    mp = MasterProcess(CFG, _config())
    try:
        mp.boot()
        os.kill(mp.pid, sig)
        wait_for(lambda: mp.ended is not None, 5.0, 'the parent notices')
        assert mp.state is MasterState.FAULT and mp.supervisor.has(FaultKind.CYCLE_STOPPED)
        assert mp.ended.startswith(said), mp.ended
        with pytest.raises(DriverError, match='control cycle process'):
            mp.home()
    finally:
        mp.shutdown()
    assert not process_alive(mp.pid)


def test_terminal_signals_are_the_parents(enabled):
    """SIGINT and SIGHUP (a Ctrl-C, a closed terminal reach the whole process group) leave
    the child running: the parent disables the drives through it."""
    mp = enabled
    for sig in (signal.SIGINT, signal.SIGHUP):
        os.kill(mp.pid, sig)
    time.sleep(0.2)
    assert process_alive(mp.pid) and mp.ended is None
    mp.disable()
    assert mp.state is MasterState.DISABLED


PARENT = textwrap.dedent('''
    import sys, time
    from brace_control.can import MasterConfig
    from brace_control.can.process import MasterProcess
    from brace_control.config import load_device_config
    from brace_control.mechanisms import mechanism_from_config
    cfg = load_device_config('lumbar_brace')
    mp = MasterProcess(cfg, MasterConfig.from_device_config(
        cfg, mechanism=mechanism_from_config(cfg), channel=sys.argv[1]))
    mp.boot(); mp.home(); mp.enable()
    print(mp.pid, flush=True)
    time.sleep(600)
''')


@pytest.mark.parametrize('sig', [signal.SIGKILL, signal.SIGTERM])
def test_the_child_disables_the_drives_and_ends_with_its_parent(sig, tmp_path):
    """The parent killed (SIGKILL: no clean-up of its own at all): the child sees its link
    close, disables the drives (its last log line names their 402 states) and exits."""
    err = tmp_path / 'stderr'
    with open(err, 'w') as stderr:
        parent = subprocess.Popen([sys.executable, '-c', PARENT, f'proc-{os.getpid()}-{next(_ids)}'],
                                  stdout=subprocess.PIPE, stderr=stderr, text=True)
    try:
        child = int(parent.stdout.readline())
        assert process_alive(child)
        parent.send_signal(sig)
        parent.wait(10)
        wait_for(lambda: not process_alive(child), 10.0, 'the child ends', poll=0.02)
    finally:
        if parent.poll() is None:
            parent.kill()
            parent.wait()
    text = err.read_text()
    assert 'drives after shutdown: a1 SWITCH ON DISABLED, a2 SWITCH ON DISABLED, a3 SWITCH ON DISABLED' \
        in text, text[-2000:]


#: in a fresh interpreter: boot a master on the device's simulator, then run what the SYNC
#: cycle runs on the model (the platform wrench of consistent and of inconsistent positions,
#: a soft stop's reason with the wrench capacity, a singular square G's LP) and print what
#: that imported
_FIRST_USE = textwrap.dedent('''
    import os, sys
    import numpy as np
    from brace_control.can.master import BraceMaster
    from brace_control.can.process import wrench_capacity_context
    from brace_control.config import load_device_config
    from brace_control.mechanisms import mechanism_from_config
    from brace_control.safety import PlatformWrench
    from brace_control.sim.brace import SimulatedBrace
    cfg = load_device_config(sys.argv[1])
    mech = mechanism_from_config(cfg)
    channel = f'first-use-{os.getpid()}'
    sim = SimulatedBrace(cfg, channel=channel)
    master = BraceMaster.from_device_config(cfg, channel=channel)
    master.boot()
    before = set(sys.modules)
    rng = np.random.default_rng(4)
    home = np.asarray(mech.home_pose, float)
    platform = PlatformWrench(mech)
    q = np.asarray(mech.inverse(home), float)
    for k in range(20):
        platform(q + rng.normal(0.0, 2e-3, q.size) * (k % 2), rng.normal(0.0, 5.0, q.size), 0.1 * k)
    for k in range(5):                     # the in-cycle admittance's model calls, near home
        pose = home + rng.normal(0.0, 1e-3, home.size)
        try:
            qk = mech.inverse(pose)
        except ValueError:
            continue
        mech.jacobian(pose)
        mech.forward_nearest(qk, home)
    context = wrench_capacity_context(master, mech, float(cfg['actuator']['max_force']))
    context(0, 10.0)
    mech.wrench_capacity(home, np.ones(q.size))
    from brace_control.mechanisms.capacity import capacity_lp
    capacity_lp(np.array([[1.0, 1.0], [0.0, 0.0]]), -np.ones(2), np.ones(2))
    master.shutdown()
    sim.shutdown()
    print(sorted(m for m in set(sys.modules) - before if not m.startswith('brace_control')))
''')


@pytest.mark.parametrize('device', ['lumbar_brace', 'neck_brace_4rpr', 'neck_brace_3rrr', 'neck_brace_2r',
                                    'upper_limb_trainer', 'shoulder', 'continuum'])
def test_nothing_the_cycle_runs_on_the_model_imports_a_module_after_the_boot(device):
    """A first import in the SYNC thread (scipy's linprog for a soft stop's reason on the
    4-RPR) held the cycle past the drives' heartbeat consumer time (1016h: twice the
    master's 100 ms) and every drive stopped with EMCY 8130h. The boot runs each model path
    once (mechanisms.warm_up): after it, the platform wrench (consistent positions, and
    positions no pose fits), the admittance's inverse, Jacobian and forward kinematics, a
    soft stop's capacity context and the capacity LP import nothing."""
    out = subprocess.run([sys.executable, '-c', _FIRST_USE, device], capture_output=True, text=True,
                         timeout=120, env={**os.environ, 'PYTHONPATH': os.pathsep.join(sys.path)})
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stdout.strip().splitlines()[-1] == '[]', out.stdout[-2000:]


@pytest.mark.parametrize('array', [
    np.array([0.37369727, 0.39, 0.40763025]), np.array([7, -6, -5], dtype=np.int64),
    np.array([1, 2], dtype=np.int16), np.array([True, False]), np.arange(12.0).reshape(3, 4),
    np.asfortranarray(np.arange(6.0).reshape(2, 3)), np.array(2.5), np.zeros(0),
    np.array([np.nan, np.inf, -0.0]), np.array([1.5, 'a'], dtype=object)],
    ids=['float3', 'int64', 'int16', 'bool', '2d', 'fortran', '0d', 'empty', 'nonfinite', 'object'])
def test_the_links_pickler_gives_back_every_array_as_it_was(array):
    """The link's own array reduction (lists for vectors, bytes otherwise): what arrives has
    the sender's dtype, shape and values (NaN, signed zero), inside the dataclasses it travels in,
    and can be written to."""
    from brace_control.can.process import link_dumps, link_loads
    from brace_control.can.state import Feedback
    fb = Feedback(position=array, velocity=array, force=array, states=(), stamp=1.0, valid=True)
    got = link_loads(link_dumps(('snap', fb)))[1]
    for back in (got.position, got.force):
        assert back.dtype == array.dtype and back.shape == array.shape
        assert np.array_equal(back, array, equal_nan=array.dtype.kind == 'f')
        if array.dtype.kind == 'f':
            assert np.array_equal(np.signbit(back), np.signbit(array))
        assert back.flags.writeable
    assert got.position is got.velocity                      # one object stays one object


def test_the_snapshots_dataclasses_cross_as_records_with_every_field():
    """Snapshot, Feedback and the simulator's BraceTruth go as their constructor and values
    (process.send_as_record): every field comes back equal (arrays by value), and a class
    whose fields are not all constructor arguments is refused."""
    import dataclasses

    from brace_control.can.cia402 import State402
    from brace_control.can.process import Snapshot, link_dumps, link_loads, send_as_record
    from brace_control.can.state import Feedback
    from brace_control.control.execution import ExecutionEvent, ExecutionState
    from brace_control.sim.brace import BraceTruth
    send_as_record(BraceTruth)
    v = np.array([0.1, -0.0, 0.3])
    truth = BraceTruth(*[v + i if f.type != 'int' else i for i, f in enumerate(dataclasses.fields(BraceTruth))])
    fb = Feedback(v, v * 2, v * 3, (State402.OPERATION_ENABLED,) * 3, 12.5, True, 1.7e9)
    snap = Snapshot(MasterState.ENABLED, True, False, False, (), False, '', ExecutionState.HOLD,
                    (0.3, 0.4), True, v.copy(), fb, (ExecutionEvent(3, 'started', '', (0.1,), 2.0),), truth)
    back = link_loads(link_dumps(('snap', snap)))[1]
    for got, sent in ((back, snap), (back.feedback, fb), (back.truth, truth)):
        assert type(got) is type(sent)
        for f in dataclasses.fields(sent):
            a, b = getattr(got, f.name), getattr(sent, f.name)
            if isinstance(b, np.ndarray):
                assert np.array_equal(a, b) and np.array_equal(np.signbit(a), np.signbit(b)), f.name
            elif not dataclasses.is_dataclass(b):
                assert a == b, f.name

    @dataclasses.dataclass
    class Derived:
        a: int
        b: int = dataclasses.field(init=False, default=0)
    with pytest.raises(TypeError, match='not an __init__ argument'):
        send_as_record(Derived)


def test_the_cycle_trace_records_every_sync_and_each_goals_arrival_in_the_child(enabled):
    """``trace_cycles``: from the call on, the child records the wall time of each SYNC
    cycle (the SYNC period apart: can.sync_rate_hz) and of each interaction goal that reached
    the cycle, refused ones too; ``take_cycle_trace`` empties it; off, nothing is kept."""
    mp = enabled
    assert mp.take_cycle_trace() == {'cycles': [], 'commands': [], 'goals': []}
    period = 1.0 / float(CFG['can']['sync_rate_hz'])
    t0 = time.time()            # before the call: the child may trace a cycle before its reply comes back
    mp.trace_cycles(True)
    time.sleep(0.3)
    with pytest.raises(ValueError, match='no interaction is running'):
        mp.set_interaction_goal([0.0, 5.0, 0.0])
    t1 = time.time()
    got = mp.take_cycle_trace()
    cycles = np.array(got['cycles'])
    assert cycles.size > 0.2 / period and t0 - period < cycles[0] and cycles[-1] <= time.time()
    assert np.median(np.diff(cycles)) == pytest.approx(period, rel=0.05)
    assert len(got['goals']) == 1 and t0 + 0.3 <= got['goals'][0] <= t1 and got['commands'] == []
    assert len(mp.take_cycle_trace()['cycles']) < len(cycles)      # emptied: only the new ones
    mp.trace_cycles(False)
    assert mp.take_cycle_trace() == {'cycles': [], 'commands': [], 'goals': []}


def _threads_scheduling(pid: int) -> dict[str, tuple[int, int]]:
    """Each thread of ``pid``: its name -> (policy, real-time priority), as the kernel has
    them (:func:`ros_helpers.kernel_threads`)."""
    return {f'{t.name}/{t.tid}': (t.policy, t.rt_priority) for t in kernel_threads(pid)}


_START_UP_WORK = r"""
import json, os, sys, threading
from brace_control.can.process import start_up_work

P = int(sys.argv[1])

def policy(tid=0):
    return os.sched_getscheduler(tid), os.sched_getparam(tid).sched_priority

try:
    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(P))
except OSError as exc:
    print(json.dumps({'refused': str(exc)}))
    raise SystemExit(0)
out, hold, hold_other, entered = {}, threading.Event(), threading.Event(), threading.Event()
ids = {}
out['nice'] = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())

def park(key):
    ids[key] = threading.get_native_id()
    hold.wait()

def sync_like():                       # a thread that sets its own priority, one above
    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(P + 1))
    park('sync')

def other_start_up():                  # start-up work still going on when the first ends
    with start_up_work(P, -5):
        ids['other'] = threading.get_native_id()
        entered.set()
        hold_other.wait()

threads = [threading.Thread(target=park, args=('before',))]
threads[0].start()
threads.append(threading.Thread(target=other_start_up))
threads[-1].start()
entered.wait(5)
with start_up_work(P, -5):
    out['inside'] = policy() + (os.getpriority(os.PRIO_PROCESS, threading.get_native_id()),)
    for target, args in ((park, ('started_inside',)), (sync_like, ())):
        threads.append(threading.Thread(target=target, args=args))
        threads[-1].start()
    while len(ids) < 4:
        pass
    out['started_inside_while_starting'] = policy(ids['started_inside'])
out['after'] = policy()
for key in ('before', 'started_inside', 'sync', 'other'):
    out[key] = policy(ids[key])
hold_other.set()
threads[1].join(5)
out['main_after_both'] = policy()
hold.set()
print(json.dumps(out))
"""


@pytest.mark.parametrize('priority', [30, 1])
def test_start_up_work_runs_below_the_cycles_priority_and_its_threads_come_back_to_it(priority):
    """``start_up_work``, in a process of its own at SCHED_FIFO ``priority`` (it sets every
    thread of its process): inside, the calling thread runs at SCHED_FIFO one below (at
    priority 1: at normal scheduling with its own niceness), and a thread it starts inherits
    that; on leaving, every thread below is back at SCHED_FIFO ``priority``, the caller
    included, except one still inside such work; a thread that set its own priority (one
    above, as the SYNC thread does) keeps it. Oracle: the kernel's own view of each thread
    (sched_getscheduler, sched_getparam, getpriority)."""
    out = subprocess.run([sys.executable, '-c', _START_UP_WORK, str(priority)], capture_output=True,
                         text=True, timeout=60, env={**os.environ, 'PYTHONPATH': os.pathsep.join(sys.path)})
    assert out.returncode == 0, out.stderr[-3000:]
    got = __import__('json').loads(out.stdout.strip().splitlines()[-1])
    if 'refused' in got:
        pytest.skip(f'SCHED_FIFO refused here: {got["refused"]}')
    fifo, other = os.SCHED_FIFO, os.SCHED_OTHER
    starting = [fifo, priority - 1] if priority > 1 else [other, 0]
    assert got['inside'] == starting + [got['nice'] if priority > 1 else -5], got
    assert got['started_inside_while_starting'] == starting, got
    assert got['after'] == [fifo, priority], got
    assert got['before'] == [fifo, priority], got
    assert got['started_inside'] == [fifo, priority], got
    assert got['sync'] == [fifo, priority + 1], got
    assert got['other'] == starting, got          # still inside its own start-up work
    assert got['main_after_both'] == [fifo, priority], got


def test_after_the_boot_every_thread_of_the_cycle_runs_at_its_real_time_priority(enabled):
    """The child's construction and boot ran below the cycle's priority (``start_up_work``);
    once enabled, every thread of the child is at SCHED_FIFO ``can.cycle_priority`` and the
    SYNC thread one above (the kernel's view, /proc). Skipped where SCHED_FIFO is refused."""
    priority = int(CFG['can']['cycle_priority'])
    threads = _threads_scheduling(enabled.pid)
    if all(policy != os.SCHED_FIFO for policy, _ in threads.values()):
        pytest.skip('SCHED_FIFO refused here: the child runs at its niceness')
    sync = [name for name in threads if name.startswith('master-sync/')]
    assert len(sync) == 1, threads
    assert threads.pop(sync[0]) == (os.SCHED_FIFO, priority + 1), threads
    assert set(threads.values()) == {(os.SCHED_FIFO, priority)}, threads


def test_a_node_that_reads_nothing_for_seconds_still_gets_every_truth(enabled, caplog):
    """The node's process stops reading the link for 4 s (its reader held: a loaded host,
    runs 901 and 910): the child's pusher waits in its send once the link is full. Once the
    node reads again, the simulator's truths of those 4 s arrive all the same, at
    ``sim.truth_rate_hz``: no two consecutive truths the node has are more than 1.5 truth
    periods apart (they were 0.8-1.4 s apart in the interaction demo's record). Oracle: the
    truth stamps (the simulated drives' SYNC times) against the configured rate."""
    mp = enabled
    period = 1.0 / float(CFG['sim']['truth_rate_hz'])
    wait_for(lambda: len(mp.sim.truths_since(0.0)) > 3, 5, 'truths from the child')
    t0 = time.time()
    with mp._truths_lock:                 # the reader stops in its next sample's truth
        time.sleep(4.0)
    t1 = time.time()
    wait_for(lambda: any(t.stamp > t1 + 0.3 for t in mp.sim.truths_since(t0)), 10,
             'truths after the reader resumed')
    stamps = np.array([t.stamp for t in mp.sim.truths_since(t0 - 2 * period) if t.stamp <= t1 + 0.3])
    assert stamps[0] <= t0 and stamps[-1] >= t1, (stamps[0] - t0, stamps[-1] - t1)
    gaps = np.diff(stamps)
    assert gaps.max() <= 1.5 * period, f'a hole of {gaps.max():.3f} s in the truth (period {period} s)'
    assert mp.state is MasterState.ENABLED, mp.faults
    # and the log says whose the 4 s were: the node's (the child's stamps went on meanwhile)
    said = [r.getMessage() for r in caplog.records if 'no snapshot from the control cycle' in r.getMessage()]
    assert said and all('this process fell behind in reading the link' in m for m in said), said


def test_a_cycle_that_stood_still_is_named_in_the_log(enabled, caplog):
    """The child stopped for 1.5 s (SIGSTOP: the host did not run it; below CYCLE_SILENT_S,
    so it lives on): its first snapshot after says so, as a warning that names the child's side
    (nothing else waiting on the link), the evidence a hole in a recorded truth needs."""
    import signal
    mp = enabled
    wait_for(lambda: len(mp.sim.truths_since(0.0)) > 3, 5, 'truths from the child')
    os.kill(mp.pid, signal.SIGSTOP)
    try:
        time.sleep(1.5)
    finally:
        os.kill(mp.pid, signal.SIGCONT)
    wait_for(lambda: any('no snapshot from the control cycle' in r.getMessage() for r in caplog.records),
             5, 'the warning')
    said = [r.getMessage() for r in caplog.records if 'no snapshot from the control cycle' in r.getMessage()]
    assert len(said) == 1 and 'the cycle process did not run meanwhile' in said[0], said
    gap = float(said[0].split(' for ')[1].split(' s')[0])
    assert 1.4 < gap < 3.0, said
    assert mp.state is MasterState.ENABLED, mp.faults
