"""The CiA 402 master against the simulated brace on a python-can virtual bus.

Each test has its own channel. Waits poll a condition with a time limit (``wait_for``;
``stream_until`` while a setpoint stream must go on); the only sleeps pace a producer (a
setpoint stream at its rate, an arrival interval that is the test's input). The fault
matrix measures each reaction time against a stated bound (periods at 500 Hz:
2 ms; the bounds include ~50 ms of scheduling slack for a loaded 2-core machine).
"""
from __future__ import annotations

import itertools
import math
import os
import time

import can
import numpy as np
import pytest

from brace_control.can import (BraceMaster, DriverOperationError, FaultKind, FaultLatchedError,
                               MasterState, State402)
from brace_control.can.boot import LISTEN_S
from brace_control.can.framelog import BusMonitor
from brace_control.config import load_device_config
from brace_control.mechanisms import mechanism_from_config
from brace_control.sim import SimulatedBrace
from rpr_oracles import cable_lengths_4rpr

CFG = load_device_config('config/lumbar_brace.yaml')
MECH = mechanism_from_config(CFG)
HOME = np.asarray(MECH.home_pose, dtype=float)


def pose_delta(dpose):
    """Actuator length change that moves the ring by ``dpose`` from home (consistent lengths:
    the lumbar brace is stiff against inconsistent ones near its home pose)."""
    return MECH.inverse(HOME + np.asarray(dpose)) - MECH.inverse(HOME)
_ids = itertools.count()
SLACK = 0.05      # s of scheduling slack on every bound
#: s a test waits to see a latch it then judges by the latch's own time (``Fault.time``, taken
#: in the cycle), not by when this thread saw it: a test thread the host served late saw a
#: stale-feedback latch 60 ms after the mute (run 913; the bound is 6 ms + SLACK)
OBSERVE_S = 1.0
CPM = 8192 / 0.001            # counts per metre (YAML)
PERIOD = 0.002                # s, SYNC at 500 Hz (YAML)


def wait_for(cond, timeout, what='condition', *, poll=0.0005):
    """Seconds until ``cond()`` holds, polled every ``poll`` s; fails the test after ``timeout``."""
    t0 = time.perf_counter()
    while not cond():
        if time.perf_counter() - t0 > timeout:
            pytest.fail(f'{what} not reached within {timeout:.3f} s')
        time.sleep(poll)
    return time.perf_counter() - t0


def stream_until(master, q, cond, timeout, what, *, stamp=None):
    """Keep a 200 Hz setpoint stream holding ``q`` (stamped ``stamp + 0.005 k`` when given)
    until ``cond()`` holds; fails the test after ``timeout`` s or at a protective stop."""
    t0 = time.perf_counter()
    k = 0
    while not cond():
        if master.supervisor.latched:
            pytest.fail(f'{what}: protective stop: {master.supervisor.summary()}')
        if time.perf_counter() - t0 > timeout:
            pytest.fail(f'{what} not reached within {timeout:.3f} s')
        k += 1
        master.set_targets(q, stamp=None if stamp is None else stamp + 0.005 * k)
        time.sleep(0.005)                        # paces the stream (200 Hz), not a wait


@pytest.fixture
def rig():
    channel = f'cantest-{os.getpid()}-{next(_ids)}'
    sim = SimulatedBrace(CFG, channel=channel)
    master = BraceMaster.from_device_config(CFG, channel=channel)
    try:
        master.boot()
        master.home()
        master.enable()
        yield sim, master
    finally:
        master.shutdown()
        sim.shutdown()


def stopped(master):
    """The protective stop took effect: no drive is OPERATION ENABLED any more."""
    return all(s in (State402.QUICK_STOP_ACTIVE, State402.FAULT, State402.SWITCH_ON_DISABLED)
               for s in master.feedback().states)


def move(master, delta, duration, *, rate=200.0):
    """Stream setpoints q0 + delta·s (s: 0 → 1 over ``duration``) at ``rate`` Hz.

    s follows the clock, but advances at most two samples' worth per setpoint: a sender
    that is late catches up at twice its rate rather than in one jump. (A stall of this
    thread between reading the clock and sending used to send a setpoint 60 ms ahead of
    the one before, arriving 5 ms after it: the step limit stopped the test, as it should.)"""
    q0 = master.feedback().position.copy()
    t0 = time.perf_counter()
    s = 0.0
    while (t := time.perf_counter() - t0) < duration:
        s = min(t / duration, s + 2.0 / (rate * duration))
        master.set_targets(q0 + np.asarray(delta) * s)
        time.sleep(1.0 / rate)                   # paces the stream at ``rate``, not a wait
    while s < 1.0:                               # the catch-up, at the same bounded pace
        s = min(1.0, s + 2.0 / (rate * duration))
        master.set_targets(q0 + np.asarray(delta) * s)
        time.sleep(1.0 / rate)
    master.set_targets(q0 + np.asarray(delta))
    return q0


# ---------------------------------------------------------------------------- boot / motion

def test_boot_configures_three_drives_and_enables_them(rig):
    sim, master = rig
    st = master.status()
    assert st.state is MasterState.ENABLED and st.homed
    assert [d.nmt for d in st.drives] == ['OPERATIONAL'] * 3
    assert all(d.state is State402.OPERATION_ENABLED for d in st.drives)
    for node_id in (1, 2, 3):
        drive = sim.drive(node_id)
        assert drive.read_od(0x6060) == 8                      # CSP
        assert drive.read_od(0x605A) == 6
        assert drive.read_od(0x1017) == 50
        assert drive.read_od(0x1016, 1) == (127 << 16) | 200    # 2 x master_heartbeat_ms
        assert drive.read_od(0x607D, 1) == round(0.340 * 8192000)
        assert drive.read_od(0x1A00, 3) == 0x24010010         # load cell in TPDO1
    # homing method 35: the position is IK(home_pose) length in counts
    q_home = MECH.inverse(HOME)
    assert master.feedback().position == pytest.approx(q_home, abs=2e-7)


def test_sync_and_pdos_on_the_bus_at_the_control_rate(rig):
    """A passive listener on the channel sees SYNC at 500 Hz, at rest an RPDO1 per drive every
    50 SYNCs (every SYNC while moving: the trajectory tests below see one per SYNC), one TPDO1
    per drive per SYNC, and the master's heartbeat every 100 ms.

    A SYNC the master could not send on time (this test's process starved by a loaded host,
    or refused SCHED_FIFO: test/conftest.py) is skipped and counted as an overrun, never
    sent late in silence: the 250 periods plus the overruns counted meanwhile span the
    time the bus saw."""
    sim, master = rig
    tap = can.Bus(interface='virtual', channel=sim.channel)
    monitor = BusMonitor([1, 2, 3], master.scaling)
    sync, hb = _Stamps(0x80), _Stamps(0x77F)
    notifier = can.Notifier(tap, [monitor, sync, hb])
    overruns = master.stats.overruns
    try:
        # 250 SYNC periods (0.5 s at 500 Hz), timed by the frames' own bus timestamps
        wait_for(lambda: len(sync.stamps) > 250, 4.0, '251 SYNCs on the bus')
        missed = master.stats.overruns - overruns          # counted up to here: an upper bound
    finally:
        notifier.stop()
        tap.shutdown()
    first, last = sync.stamps[0], sync.stamps[250]
    assert 250 / (1.05 * 500) <= last - first <= (250 + missed) / (0.8 * 500), missed   # 400 .. 525 Hz
    syncs = monitor.syncs
    for rec in monitor.drives.values():
        # at rest an RPDO1 goes out every 50 SYNCs (its content unchanged); a TPDO1 answers each
        assert syncs / 50 - 2 <= rec.controlwords <= syncs / 50 + 2 and abs(rec.tpdos - syncs) <= 3
    beats = sum(first <= t <= last for t in hb.stamps)             # 100 ms apart
    assert 0.7 * (last - first) / 0.1 <= beats <= (last - first) / 0.1 + 1


class _Stamps(can.Listener):
    """Bus timestamps (s, the sender's clock) of the frames with one COB-ID."""

    def __init__(self, cob_id):
        self.cob_id, self.stamps = cob_id, []

    def on_message_received(self, msg):
        if msg.arbitration_id == self.cob_id:
            self.stamps.append(msg.timestamp)

    def stop(self):
        pass


def test_enable_starts_from_the_actual_position_without_a_jump(rig):
    sim, master = rig
    q = master.feedback().position
    assert master.status().drives[0].target == pytest.approx(q[0], abs=1e-6)
    assert np.all(np.abs(sim.truth().velocities) < 1e-9)


def true_window_rate(sim, master, wall: float, syncs: int = 5) -> np.ndarray:
    """The simulator's true actuator rates (m/s) over the ``syncs`` SYNC periods that end
    with the SYNC sent at ``wall``: its true lengths after each end's SYNC, over the longer
    of their send times' span and ``syncs`` periods (the feedback's own window: a drive's
    speed over its last six samples, receive.py)."""
    log_ = {i: w for w, _, i in tuple(master.clock.log)}
    index = next((i for i, w in log_.items() if w == wall), None)
    if index is None or index - syncs not in log_:
        return np.full(len(sim.drives), np.nan)
    w0 = log_[index - syncs]
    end, start = sim.truth_at(wall), sim.truth_at(w0)
    return (end.lengths - start.lengths) / max(wall - w0, syncs * PERIOD)


def test_target_stream_moves_the_drives_and_feedback_is_si(rig):
    sim, master = rig
    delta = pose_delta([0.001, 0.003, 0.01])       # the torso pushes back with a few N
    q0 = master.feedback().position.copy()
    seen = []
    t0 = time.perf_counter()
    while (t := time.perf_counter() - t0) < 0.5:    # constant rate: |v| = |delta| / 0.5 s
        master.set_targets(q0 + delta * t / 0.5)
        if 0.2 < t < 0.3:
            fb = master.feedback()
            seen.append((fb.velocity, true_window_rate(sim, master, fb.wall)))
        time.sleep(0.005)                         # paces the stream (200 Hz), not a wait
    # the stream goes on holding the final setpoint until the drives are at rest on it
    # (|v| below 5 encoder counts per 10 ms window)

    def at_rest_on_target():
        fb = master.feedback()
        return (np.allclose(fb.position, q0 + delta, rtol=0, atol=2e-6)
                and np.abs(fb.velocity).max() < 5 / CPM / 0.01)
    stream_until(master, q0 + delta, at_rest_on_target, 1.0, 'the drives at rest on the targets')
    # m/s, from positions over 10 ms windows, against the simulator's true lengths over the
    # same SYNCs, averaged over 0.1 s of the ramp (on a loaded machine this test's own 200 Hz
    # loop stalls and the drives catch up: their rate changes within a window, so only the
    # same window compares)
    assert not master.supervisor.latched, master.supervisor.summary()
    seen = [(v, t) for v, t in seen if np.all(np.isfinite(t))]
    assert len(seen) >= 5, 'too few feedback samples with their SYNCs still logged'
    v_fb = np.array([v for v, _ in seen])
    v_true = np.array([v for _, v in seen])
    assert v_fb.mean(axis=0) == pytest.approx(v_true.mean(axis=0), abs=2e-3)
    assert np.all(np.max(np.abs(v_fb), axis=0) > 0.3 * np.abs(delta) / 0.5)      # it moved
    fb = master.feedback()
    truth = sim.truth()
    # positions in m (encoder quantisation 1/8192000 m), forces in N from the load cells
    assert fb.position == pytest.approx(truth.lengths, abs=2e-6)
    assert fb.force == pytest.approx(truth.forces, abs=0.5)      # 0.05 N noise, 0.01 N/count
    assert np.any(np.abs(fb.force) > 1.0)                        # the torso pushes back
    assert not master.supervisor.latched


def test_a_stream_that_stops_decelerates_along_its_direction_and_holds(rig):
    """docs/safety.md §1: no setpoint for command_timeout -> the command decelerates to rest within
    a_max along its current direction (every axis together) and holds; reported, not
    latched. It does not travel on to the last setpoint: it stops within what the speed
    allows, v (timeout + a period) + v^2 / (2 a_max) past the last setpoint's place."""
    sim, master = rig
    delta = pose_delta([0.0, 0.004, 0.0])
    v = np.abs(delta).max() / 0.2                         # the stream's speed, ~20 mm/s
    q0 = move(master, delta, 0.2)
    # reported: the count and the warning, which stays until a setpoint comes (a loaded host
    # can make the test's own stream pause past command_timeout; the hold then counted is
    # reported too, and its warning goes with the stream's next setpoint: run 406)
    wait_for(lambda: master.status().stale_setpoint_holds >= 1 and
             any('stale' in w for w in master.status().warnings), 1.0, 'stale report')
    wait_for(lambda: not master.moving, 0.5, 'the command at rest')
    wait_for(lambda: np.allclose(master.feedback().position, master.executor.q, rtol=0, atol=3e-7), 0.3,
             'the drives settled at the command')
    settled = master.feedback()
    held = settled.position.copy()
    wait_for(lambda: master.feedback().stamp >= settled.stamp + 0.1, 0.5,
             '50 more SYNC periods of feedback')
    assert master.feedback().position == pytest.approx(held, abs=5e-7)      # holding
    past = (held - (q0 + delta)) / np.where(np.abs(delta) > 0, delta, 1.0)  # along the motion
    bound = v * (0.015 + 0.004) + v * v / (2 * 0.5) + 2e-6
    assert np.all(np.abs(held - (q0 + delta)) <= bound)
    assert np.all(past > -0.5)                      # no reversal towards the start
    # one direction, all axes together: the stop is the same fraction of each axis' motion
    frac = (held - q0) / delta
    assert np.ptp(frac) < 0.01
    assert not master.supervisor.latched and master.state is MasterState.ENABLED


def test_a_repeat_the_cycle_takes_alone_is_at_rest_in_the_senders_terms(rig):
    """A stream ramps at 3 mm/s, then repeats its last position (a sender holding, as a
    teleoperation client does). When the cycle takes only the newest of several setpoints that
    arrived between two SYNCs (a busy host), the repeat alone is what it sees: the rate handed
    to the executor is the sender's own between its last two setpoints (zero), not the ramp's
    from the last setpoint the cycle took, which a stream stopping there would brake on with
    (CI: 14 um past the last setpoint of a 0.5 mm lift)."""
    sim, master = rig
    delta = pose_delta([0.0, 0.0005, 0.0])
    q0 = master.feedback().position.copy()
    n, dt = 40, 0.004
    for k in range(1, n - 2):                            # 4 ms apart, stamped as sent
        master.set_targets(q0 + delta * k / n, stamp=k * dt)
        time.sleep(dt)
    wait_for(lambda: master.stream.taken_seq == master.stream.seq, 0.2, 'the ramp taken')
    ramp = master.executor._stream[1].copy()
    assert np.abs(ramp - delta / (n * dt)).max() < 0.05 * np.abs(delta).max() / (n * dt), ramp
    with master.motion.lock:                             # the cycle takes none of these three ...
        master.set_targets(q0 + delta * (n - 2) / n, stamp=(n - 2) * dt)
        master.set_targets(q0 + delta, stamp=(n - 1) * dt)
        master.set_targets(q0 + delta, stamp=n * dt)     # ... but this repeat of the last one
    wait_for(lambda: master.stream.taken_seq == master.stream.seq, 0.2, 'the repeat taken')
    position, rate, _ = master.executor._stream
    np.testing.assert_array_equal(position, q0 + delta)
    np.testing.assert_array_equal(rate, np.zeros(3))
    assert not master.supervisor.latched


# docs/safety.md §5, §6
def test_bad_setpoints_raise_and_send_nothing(rig):
    sim, master = rig
    with pytest.raises(ValueError, match='not finite'):
        master.set_targets([0.39, float('nan'), 0.39])
    with pytest.raises(ValueError, match='outside the stroke'):
        master.set_targets([0.39, 0.45, 0.39])
    with pytest.raises(ValueError, match='expected 3'):
        master.set_targets([0.39, 0.39])
    assert not master.supervisor.latched


def test_disable_halt_enable_cycle(rig):
    sim, master = rig
    master.halt()
    assert all(s is State402.QUICK_STOP_ACTIVE for s in master.feedback().states)
    master.enable()
    master.disable()
    assert all(s is State402.SWITCH_ON_DISABLED for s in master.feedback().states)
    master.enable()
    assert master.state is MasterState.ENABLED


def test_boot_timeout_names_the_missing_drive():
    channel = f'cantest-{os.getpid()}-{next(_ids)}'
    cfg = dict(CFG)
    cfg['can'] = dict(CFG['can'], boot_timeout=0.2, node_ids=[1, 2, 9])
    sim = SimulatedBrace(CFG, channel=channel)
    master = BraceMaster.from_device_config(cfg, channel=channel)
    try:
        with pytest.raises(Exception, match=r'a3 \(node 9\)'):
            master.boot()
        assert master.supervisor.has(FaultKind.BOOT_TIMEOUT, 'a3')
    finally:
        master.shutdown()
        sim.shutdown()


def test_shutdown_is_idempotent_and_disables(rig):
    sim, master = rig
    master.shutdown()
    master.shutdown()
    assert master.state is MasterState.CLOSED
    assert all(sim.drive(i).state.name == 'SWITCH_ON_DISABLED' for i in (1, 2, 3))


# ---------------------------------------------------------------------------- fault matrix

def _latched(master, kind, drive=...):
    return lambda: master.supervisor.has(kind, drive)


def _fault_after(master, kinds, t0_monotonic):
    """Seconds from ``t0`` to the first latched fault of one of ``kinds``."""
    times = [f.time for f in master.supervisor.faults if f.kind in kinds]
    return min(times) - t0_monotonic


def _recover_refused(master, kind):
    blocking = master.recover()
    assert any(f.kind is kind for f in blocking), master.supervisor.summary()
    assert master.supervisor.latched
    with pytest.raises(FaultLatchedError):
        master.enable()


def _recover_ok(master):
    assert master.recover() == [], master.supervisor.summary()
    assert not master.supervisor.latched and master.state is MasterState.DISABLED


def _recover_and_enable(master):
    _recover_ok(master)
    master.enable()
    assert master.state is MasterState.ENABLED


# docs/safety.md §2
def test_fault_heartbeat_silenced(rig):
    """Bound: consumer time 150 ms after the last heartbeat (≤ 150 ms) + slack."""
    sim, master = rig
    t0 = time.monotonic()
    sim.faults.silence_heartbeat(2)
    wait_for(_latched(master, FaultKind.HEARTBEAT_LOST, 'a2'), OBSERVE_S, 'heartbeat fault')
    wait_for(lambda: stopped(master), 0.05, 'protective stop')
    assert _fault_after(master, {FaultKind.HEARTBEAT_LOST}, t0) <= 0.15 + SLACK
    _recover_refused(master, FaultKind.HEARTBEAT_LOST)
    sim.faults.silence_heartbeat(2, False)
    wait_for(lambda: master.status().drives[1].heartbeat_age < 0.06, 0.2, 'heartbeat back')
    _recover_ok(master)
    master.enable()


class _StallingListener(can.Listener):
    """Holds canopen's Notifier thread (the master's only receive thread) for ``stall`` s
    at every ``every``-th frame: the frames queue on the bus meanwhile, as they do in the
    socket of a process the host did not schedule."""

    def __init__(self, stall: float, every: int) -> None:
        self.stall, self.every, self.frames, self.stalls = stall, every, 0, 0
        self.armed = True

    def on_message_received(self, msg: can.Message) -> None:
        self.frames += 1
        if self.armed and self.frames % self.every == 0:
            self.stalls += 1
            time.sleep(self.stall)


def test_a_receive_thread_behind_is_not_a_lost_heartbeat(rig):
    """docs/safety.md §4 judged on what the bus carried: the receive thread held 140 ms at a time
    (< the 150 ms consumer time, > its 100 ms margin over the drives' 50 ms heartbeat)
    eight times, at different phases of the heartbeat: every drive went on sending, so no
    heartbeat is lost. A drive that does fall silent meanwhile is still caught."""
    sim, master = rig
    stalls = _StallingListener(0.14, every=389)     # 389 frames: ~0.26 s at 3 TPDO / 2 ms
    master.network.notifier.add_listener(stalls)
    try:
        wait_for(lambda: stalls.stalls >= 8, 8.0, '8 stalls of the receive thread', poll=0.01)
        assert not master.supervisor.latched, master.supervisor.summary()
        sim.faults.silence_heartbeat(2)
        # one consumer time on the bus, plus at most one stall of the receive thread
        wait_for(_latched(master, FaultKind.HEARTBEAT_LOST, 'a2'), 0.15 + 0.14 + SLACK, 'heartbeat fault')
        assert [f.drive for f in master.supervisor.faults if f.kind is FaultKind.HEARTBEAT_LOST] == ['a2']
    finally:
        stalls.armed = False
        master.network.notifier.remove_listener(stalls)
        sim.faults.silence_heartbeat(2, False)


def test_time_this_process_did_not_run_does_not_age_a_heartbeat():
    """docs/safety.md §4: a heartbeat's age leaves out the time this process stood still (the
    SYNC thread woke that late, :meth:`Receiver.host_stalled`): the simulated drives stood
    still with it. A heartbeat heard 1.6 s before a TPDO that just arrived, 1.5 s of which the
    process did not run, is 0.1 s old; one heard after the stall counts in full. Oracle: the
    stamps set here."""
    from brace_control.can.state import _Node
    master = BraceMaster.from_device_config(CFG, channel='unused')     # the virtual bus
    receiver = master.receiver
    d = _Node(name='a2', node_id=2, node=None)
    now = time.time()
    d.hb_wall, d.hb_stalled = now - 1.6, receiver.stalled_s
    receiver.host_stalled(1.5)
    receiver.rx_wall = now
    assert receiver.heartbeat_age(d) == pytest.approx(0.1, abs=1e-6)
    receiver.host_stalled(-0.5)                          # an early wake is no stall
    assert receiver.heartbeat_age(d) == pytest.approx(0.1, abs=1e-6)
    d.hb_wall, d.hb_stalled = now - 0.3, receiver.stalled_s
    assert receiver.heartbeat_age(d) == pytest.approx(0.3, abs=1e-6)
    # on a real bus the drives did not stop with this process: their frames of meanwhile
    # wait in the socket with the kernel's times, and a silent drive's age is not discounted
    import copy
    real = copy.deepcopy(CFG)
    real['can']['interface'] = 'socketcan'
    on_socketcan = BraceMaster.from_device_config(real, channel='can0').receiver
    on_socketcan.host_stalled(1.5)
    assert on_socketcan.stalled_s == 0.0


def test_a_stall_of_the_whole_process_is_not_a_lost_heartbeat(rig):
    """Master and simulated drives in this process, held together for 1.5 s (a native call
    keeps the interpreter lock, as a host that did not run the process would): the world
    stood still, so no drive's heartbeat was late, and the brace stays enabled. A drive that
    falls silent afterwards is still caught within its consumer time."""
    import ctypes
    sim, master = rig
    wait_for(lambda: master.status().drives[1].heartbeat_age < 0.06, 1.0, 'a heartbeat')
    ctypes.PyDLL(None).usleep(1_500_000)
    time.sleep(0.5)                                      # every drive's heartbeat came since
    assert not master.supervisor.latched, master.supervisor.summary()
    t0, stalled = time.monotonic(), master.receiver.stalled_s
    sim.faults.silence_heartbeat(2)
    try:
        wait_for(_latched(master, FaultKind.HEARTBEAT_LOST, 'a2'), OBSERVE_S, 'heartbeat fault')
        # the consumer time on the simulated bus's clock: the times this process (and with it
        # the simulated drives) did not run meanwhile, on a loaded host, do not count
        assert _fault_after(master, {FaultKind.HEARTBEAT_LOST}, t0) <= \
            0.15 + SLACK + (master.receiver.stalled_s - stalled)
    finally:
        sim.faults.silence_heartbeat(2, False)


# docs/safety.md §4
def test_fault_emcy_with_drive_fault(rig):
    """Bound: the EMCY frame itself (≤ 1 period) + slack."""
    sim, master = rig
    t0 = time.monotonic()
    sim.faults.send_emcy(1, 0x7305, fault=True)
    wait_for(_latched(master, FaultKind.EMCY, 'a1'), OBSERVE_S, 'EMCY fault')
    wait_for(lambda: stopped(master), 0.02, 'protective stop')
    assert master.supervisor.first.code == 0x7305
    assert 'incremental sensor 1 fault' in master.supervisor.summary()
    assert _fault_after(master, {FaultKind.EMCY}, t0) < 0.002 + SLACK
    _recover_refused(master, FaultKind.EMCY)           # the drive stays in FAULT
    sim.faults.clear_emcy_fault(1)
    _recover_ok(master)
    master.enable()


# docs/safety.md §3
def test_fault_bus_off_and_failed_send(rig):
    """Bound: error frame → fault at once; the next send fails (≤ 1 period) + slack."""
    sim, master = rig
    sim.faults.bus_off(master.bus)
    wait_for(_latched(master, FaultKind.BUS_OFF), 0.002 + SLACK, 'bus-off fault')
    wait_for(_latched(master, FaultKind.SEND_FAILED), 0.002 + SLACK, 'send failure')
    _recover_refused(master, FaultKind.BUS_OFF)
    sim.faults.bus_on()
    wait_for(lambda: all(d.heartbeat_age < 0.06 for d in master.status().drives), 0.3,
             'drives back on the bus')
    _recover_ok(master)
    master.enable()


# docs/safety.md §3
def test_error_passive_warns_without_stopping(rig):
    sim, master = rig
    sim.faults.error_frame('passive')
    wait_for(lambda: master.status().bus.error_state == 'error passive', 0.05, 'error passive')
    assert not master.supervisor.latched and master.state is MasterState.ENABLED
    sim.faults.error_frame('active')
    wait_for(lambda: master.status().bus.error_state == 'active', 0.05, 'back to active')


# docs/safety.md §9
def test_fault_stale_tpdo(rig):
    """Bound: stale_periods (3) SYNC periods = 6 ms + slack."""
    sim, master = rig
    t0 = time.monotonic()
    sim.faults.mute_tpdo(3)
    wait_for(_latched(master, FaultKind.STALE_FEEDBACK, 'a3'), OBSERVE_S, 'stale fault')
    assert _fault_after(master, {FaultKind.STALE_FEEDBACK}, t0) < 0.006 + SLACK
    _recover_refused(master, FaultKind.STALE_FEEDBACK)
    sim.faults.mute_tpdo(3, False)
    _recover_ok(master)


# docs/safety.md §9
def test_fault_encoder_jump(rig):
    """Bound: the next TPDO (1 period) + slack; momentary, but the drive must be re-homed."""
    sim, master = rig
    sim.faults.jump_encoder(2, 0.003)
    wait_for(_latched(master, FaultKind.POSITION_JUMP, 'a2'), 0.002 + SLACK, 'jump fault')
    wait_for(lambda: stopped(master), 0.05, 'protective stop')
    _recover_ok(master)                                  # the jump is over ...
    with pytest.raises(DriverOperationError, match='not homed'):
        master.enable()                                  # ... but the reference is suspect
    sim.faults.jump_encoder(2, 0.0)
    master.home()
    master.enable()


# docs/safety.md §9, §11
def test_fault_encoder_frozen_is_caught_by_the_following_error(rig):
    """A frozen encoder is not stale (TPDOs still come): moving exposes it. Bound: the latch
    comes as the command passes path_tolerance (5 mm) from the frozen reading, within the
    few SYNCs a sample takes to come back (judged by where the command is when it latches,
    which a busy host does not move: a motion advances one period per SYNC); and in time,
    within 2 x SLACK of the setpoint that took the command past path_tolerance (the target
    moves 5 mm at 30 mm/s in ~167 ms; timed from the test's own stream, which a loaded host
    may send late: run 1101, 0.58 s from the stream's start)."""
    sim, master = rig
    frozen = master.feedback().position[0]
    tolerance = master.limits.path_tolerance
    at_latch = []
    react = master.supervisor._on_fault

    def on_fault(fault):
        at_latch.append((fault.kind, float(master.executor.q[0])))
        react(fault)
    master.supervisor._on_fault = on_fault
    past = []                            # when the stream's setpoint first passed the tolerance
    set_targets = master.set_targets

    def noting(q, *args, **kwargs):
        if not past and abs(float(q[0]) - frozen) >= tolerance:
            past.append(time.monotonic())
        return set_targets(q, *args, **kwargs)
    master.set_targets = noting
    try:
        sim.faults.freeze_encoder(1)
        move(master, pose_delta([0.0, 0.015, 0.0]), 0.5)
    finally:
        del master.set_targets
    wait_for(_latched(master, FaultKind.FOLLOWING_ERROR, 'a1'), 0.3, 'following error')
    kind, q_cmd = next(x for x in at_latch if x[0] is FaultKind.FOLLOWING_ERROR)
    assert tolerance <= abs(q_cmd - frozen) <= tolerance + 5 * master.limits.v_max * master.config.period, \
        (q_cmd - frozen) * 1e3
    assert past, 'the stream never took the command past the path tolerance'
    assert _fault_after(master, {FaultKind.FOLLOWING_ERROR}, past[0]) < 2 * SLACK
    wait_for(lambda: stopped(master), 0.05, 'protective stop')
    assert master.supervisor.has(FaultKind.FOLLOWING_ERROR, 'a1')
    sim.faults.freeze_encoder(1, False)


# docs/safety.md §9
def test_fault_load_cell_saturated(rig):
    """Bound: next TPDO (1 period) + slack."""
    sim, master = rig
    sim.faults.saturate_load_cell(1)
    wait_for(_latched(master, FaultKind.LOAD_CELL_SATURATED, 'a1'), 0.002 + SLACK, 'saturation')
    wait_for(lambda: stopped(master), 0.05, 'protective stop')
    _recover_refused(master, FaultKind.LOAD_CELL_SATURATED)
    sim.faults.saturate_load_cell(1, None)
    _recover_ok(master)


# docs/safety.md §8
def test_fault_force_limit(rig):
    sim, master = rig
    sim.faults.set_load_cell(2, -260.0)
    wait_for(_latched(master, FaultKind.FORCE_LIMIT, 'a2'), 0.002 + SLACK, 'force limit')
    _recover_refused(master, FaultKind.FORCE_LIMIT)
    sim.faults.set_load_cell(2, None)
    _recover_ok(master)


# docs/safety.md §11
def test_fault_stall_following_error(rig):
    """Stalled actuator a3 commanded at 30 mm/s (the others hold: no force builds up):
    the drive's window 6065h (3 mm) or the master's path tolerance (5 mm) trips.
    Bound: 5 mm at 30 mm/s ≈ 167 ms + slack."""
    sim, master = rig
    sim.faults.stall_actuator(3)
    t0 = time.monotonic()
    move(master, [0.0, 0.0, -0.006], 0.2)
    kinds = {FaultKind.FOLLOWING_ERROR, FaultKind.DRIVE_FAULT, FaultKind.EMCY}
    wait_for(lambda: any(master.supervisor.has(k, 'a3') for k in kinds), 0.3, 'following error')
    assert _fault_after(master, kinds, t0) < 0.005 / 0.03 + SLACK
    wait_for(lambda: stopped(master), 0.05, 'protective stop')
    blocking = master.recover()
    assert blocking and master.supervisor.latched        # still stalled: drive stays in FAULT
    sim.faults.stall_actuator(3, False)
    _recover_ok(master)
    master.enable()


# docs/safety.md §7
def test_fault_step_limit_rejects_the_stream_and_is_recoverable_once_still(rig):
    """Bound: next cycle (1 period) + slack. The stop's cause is the command, which recover
    discards: recover succeeds once the drives hold still, and the brace moves again."""
    sim, master = rig
    q = master.feedback().position.copy()
    # 3 mm at once: more than v_max·command_timeout + margin = 1.5 mm (first setpoint
    # after a hold), far more than v_max·dt + margin = 0.63 mm within a stream
    q_bad = q + np.array([0.0, 0.003, 0.0])
    master.set_targets(q_bad)
    wait_for(_latched(master, FaultKind.STEP_LIMIT, 'a2'), 0.002 + SLACK, 'step limit')
    wait_for(lambda: stopped(master), 0.05, 'protective stop')
    assert master.feedback().position == pytest.approx(q, abs=1e-5)   # nothing moved
    _recover_ok(master)
    master.enable()
    q2 = move(master, pose_delta([0.0, 0.001, 0.0]), 0.1)
    assert not master.supervisor.latched and np.abs(master.feedback().position - q2).max() > 5e-4


def test_drive_reboot_latches_and_recover_reconfigures_it(rig):
    """A drive that reboots (NMT reset node) loses its configuration and homing: fault at
    the boot-up message; recover re-configures it and starts it; homing is required again."""
    sim, master = rig
    master.network.send_message(0, bytes([0x81, 2]))          # NMT reset node 2
    wait_for(_latched(master, FaultKind.NMT_STATE, 'a2'), 0.1 + SLACK, 'reboot fault')
    states = lambda: master.feedback().states   # noqa: E731 - a2 sends no TPDO in PRE-OPERATIONAL
    wait_for(lambda: states()[0] is State402.QUICK_STOP_ACTIVE is states()[2], 0.1, 'protective stop')
    assert sim.drive(2).state.name == 'SWITCH_ON_DISABLED'
    _recover_ok(master)
    assert sim.drive(2).read_od(0x1017) == 50 and sim.drive(2).read_od(0x6060) == 8
    assert master.status().drives[1].nmt == 'OPERATIONAL'
    with pytest.raises(DriverOperationError, match='not homed'):
        master.enable()
    master.home()
    master.enable()


def test_drives_stop_on_their_own_when_the_master_dies(rig):
    """docs/safety.md §2: the drives consume the master's heartbeat (1016h = 200 ms) and apply
    6007h = 3 (quick stop) when it stops. Bound: 200 ms + one heartbeat period + twice
    the slack (the simulator's own timer thread notices the silence)."""
    sim, master = rig
    stalled = sim.stalled_seconds
    master.cycle.stop_event.set()           # the SYNC thread (and the heartbeat) stops dead
    t = wait_for(lambda: all(sim.drive(i).state.name == 'QUICK_STOP_ACTIVE' for i in (1, 2, 3)),
                 0.3 + 2 * SLACK + 2.0, 'drives in QUICK STOP ACTIVE')
    # on the drives' own clock: minus the time this process stood still (a loaded host; the
    # simulated drives live in it, their clock stood still too), which a real drive would not
    assert t - (sim.stalled_seconds - stalled) <= 0.3 + 2 * SLACK, (t, sim.stalled_seconds - stalled)


def test_boot_finds_drives_that_booted_earlier_without_heartbeat():
    """A drive powered before the master listened, with heartbeat production off (1017h =
    0, the CiA 301 default): after listening LISTEN_S for a boot-up or heartbeat, boot sends
    NMT reset communication and gets its boot-up (not at half the boot time-out)."""
    channel = f'cantest-{os.getpid()}-{next(_ids)}'
    cfg = dict(CFG)
    # a 4 s boot time-out: half of it (what a boot that waited would take) stays well
    # apart from LISTEN_S plus the reset's boot-up on a busy host
    cfg['can'] = dict(CFG['can'], boot_timeout=4.0)
    sim = SimulatedBrace(CFG, channel=channel)
    master = BraceMaster.from_device_config(cfg, channel=channel)
    try:
        for node_id in (1, 2, 3):
            sim.drive(node_id).set_data(0x1017, 0, (0).to_bytes(2, 'little'))
        t0 = time.perf_counter()
        master.boot()
        assert LISTEN_S < time.perf_counter() - t0 < 0.5 * 4.0
        assert [d.nmt for d in master.status().drives] == ['OPERATIONAL'] * 3
        assert sim.drive(2).read_od(0x1017) == 50
    finally:
        master.shutdown()
        sim.shutdown()


# ---------------------------------------------------------------------------- stamped streams

class _RpdoTargets(can.Listener):
    """Target positions (counts) of one drive's RPDO1 frames: controlword U16 + target I32."""

    def __init__(self, node_id):
        self.cob_id = 0x200 + node_id
        self.targets = []

    def on_message_received(self, msg):
        if msg.arbitration_id == self.cob_id and len(msg.data) >= 6:
            self.targets.append(int.from_bytes(msg.data[2:6], 'little', signed=True))


def test_bunched_stamped_setpoints_pass_the_step_limit(rig):
    """A 200 Hz stream at 30 mm/s whose messages arrive bunched (two at once after a
    10 ms pause, the way a loaded executor delivers them): judged over the smaller of the
    stamp and arrival intervals plus one period (0 + 2 ms: 0.63 mm allowed), a 0.15 mm step
    passes. No protective stop; the drives follow."""
    sim, master = rig
    q0 = master.feedback().position.copy()
    direction = pose_delta([0.0, 0.001, 0.0]) / np.linalg.norm(pose_delta([0.0, 0.001, 0.0]))
    speed = 0.03                                    # m/s along the combined direction
    t_stamp = 100.0                                  # the sender's clock: any origin
    for k in range(1, 41):
        q = q0 + direction * speed * 0.005 * k
        master.set_targets(q, stamp=t_stamp + 0.005 * k)
        if k % 2 == 0:
            time.sleep(0.010)                        # two per 10 ms, back to back (paces the sender)
    assert not master.supervisor.latched, master.supervisor.summary()
    assert np.linalg.norm(master.feedback().position - q0) > 0.5 * np.linalg.norm(q - q0)


def test_a_senders_clock_cannot_license_a_jump(rig):
    """A setpoint 20 mm ahead, sent 5 ms after the previous one but stamped 1 s later
    (20 mm/s by its stamps): judged by its arrival, it is a jump. Step-limit stop; the
    drives do not move 20 mm (issue: the direct actuator stream)."""
    sim, master = rig
    q0 = master.feedback().position.copy()
    master.set_targets(q0, stamp=10.0)
    time.sleep(0.005)                   # the arrival interval under test (5 ms), not a wait
    master.set_targets(q0 + pose_delta([0.0, 0.02, 0.0]), stamp=11.0)
    wait_for(_latched(master, FaultKind.STEP_LIMIT), 0.002 + SLACK, 'step limit')
    wait_for(lambda: stopped(master), 0.5, 'protective stop')
    assert np.abs(master.feedback().position - q0).max() < 1e-4


def test_setpoints_whose_stamps_do_not_increase_are_counted_and_reported(rig):
    sim, master = rig
    q0 = master.feedback().position.copy()
    master.set_targets(q0, stamp=20.0)
    for _ in range(10):                               # frozen stamps: not newer commands
        time.sleep(0.003)                             # paces the sender, not a wait
        master.set_targets(q0 + pose_delta([0.0, 0.0005, 0.0]), stamp=20.0)
    # each refused as it arrives, whichever the cycle looked at (run 1002)
    wait_for(lambda: master.status().rejected_setpoints >= 10, 0.2, 'rejections counted')
    assert master.status().rejected_setpoints == 10
    assert any('stamps not increasing' in w for w in master.status().warnings)
    assert not master.supervisor.latched
    assert master.feedback().position == pytest.approx(q0, abs=1e-6)      # nothing moved


@pytest.mark.parametrize('stamp', [math.nan, math.inf, '20.0', True])
def test_a_setpoint_stamp_that_is_not_a_finite_number_is_refused_naming_it(rig, stamp):
    """A NaN stamp compares false with every stamp: taken, it would pass the stream's order
    check and switch it off for every setpoint after it (a frozen-stamp stream then moves
    the brace, run 1002). Refused with a ValueError naming the stamp; nothing moves, and
    the stream's order check still holds for the setpoints that follow."""
    sim, master = rig
    q0 = master.feedback().position.copy()
    master.set_targets(q0, stamp=30.0)
    with pytest.raises(ValueError, match='stamp'):
        master.set_targets(q0 + pose_delta([0.0, 0.0005, 0.0]), stamp=stamp)
    master.set_targets(q0 + pose_delta([0.0, 0.0005, 0.0]), stamp=30.0)      # not newer
    wait_for(lambda: master.status().rejected_setpoints >= 1, 0.2, 'the old stamp refused')
    assert master.feedback().position == pytest.approx(q0, abs=1e-6)


def test_stamped_stream_faster_than_v_max_latches_a_step_limit(rig):
    """Stamps 5 ms apart, steps of 1 mm: 200 mm/s > v_max = 65 mm/s (+ 0.5 mm margin)."""
    sim, master = rig
    q0 = master.feedback().position.copy()
    step = np.array([0.0, 0.001, 0.0])
    n = master.status().accepted_setpoints
    master.set_targets(q0, stamp=10.0)
    wait_for(lambda: master.status().accepted_setpoints > n, 0.002 + SLACK, 'first setpoint applied')
    master.set_targets(q0 + step, stamp=10.005)
    wait_for(_latched(master, FaultKind.STEP_LIMIT, 'a2'), 0.002 + SLACK, 'step limit')


def test_after_a_hold_the_resumed_stream_ramps_without_a_jump(rig):
    """The stream stops (hold), then resumes 2 mm further on 0.12 s later (by stamps and by
    arrival: 17 mm/s, allowed). The drives must not see a 2 mm target jump in one SYNC: on
    the bus, RPDO1 targets change by at most v_max·period = 0.13 mm (1065 counts)."""
    sim, master = rig
    tap = can.Bus(interface='virtual', channel=sim.channel)
    rpdo = _RpdoTargets(2)
    notifier = can.Notifier(tap, [rpdo])
    try:
        q0 = master.feedback().position.copy()
        master.set_targets(q0, stamp=50.0)
        sent = time.perf_counter()
        wait_for(lambda: master.status().stale_setpoint_holds >= 1, 0.5, 'hold')
        # the resumed setpoint arrives 0.12 s after the last one, as its stamp says: the
        # arrival time is the test's input (paces the sender), not a wait
        time.sleep(max(0.0, sent + 0.12 - time.perf_counter()))
        q1 = q0 + pose_delta([0.0, 0.002, 0.0])
        master.set_targets(q1, stamp=50.12)
        # keep the stream fresh at the new place until the drives got there
        goal = round(q1[1] * CPM)
        stream_until(master, q1,
                     lambda: (np.allclose(master.feedback().position, q1, rtol=0, atol=2e-6)
                              and rpdo.targets and abs(rpdo.targets[-1] - goal) <= 1),
                     2.0, 'drives at the resumed target', stamp=50.12)
    finally:
        notifier.stop()
        tap.shutdown()
    assert not master.supervisor.latched, master.supervisor.summary()
    steps = np.abs(np.diff(rpdo.targets))
    v_max_counts = 0.065 * 0.002 * CPM               # YAML: 65 mm/s, 500 Hz, 8192 counts/mm
    assert steps.max() <= math.ceil(v_max_counts)
    assert abs(rpdo.targets[-1] - goal) <= 1


def test_late_answers_in_a_burst_are_attributed_to_consecutive_syncs():
    """Three TPDO1s answering SYNCs 11, 12, 13, all sent (by a late simulator or a late
    receive thread) after SYNC 13 went out: by timestamp alone each would answer SYNC 13
    and positions 4 ms apart would look simultaneous. Counted from the answer to SYNC 10
    they are 11, 12, 13; a drive silent for longer than the attribution window is placed
    by its timestamp again."""
    from brace_control.can.sync import SyncClock
    clock = SyncClock(attribution_window=25)         # the master's record of the SYNCs it sent
    now = time.time()
    for k in range(1, 14):                           # SYNC k sent at now - (13 - k) * 2 ms
        clock.log.append((now - (13 - k) * 0.002, 100.0 + k * 0.002, k))
    clock.index, clock.time = 13, 100.0 + 13 * 0.002
    stamp = now + 0.0005                             # after SYNC 13
    got = []
    previous = 10
    for _ in range(3):
        index, t = clock.answered(stamp, previous)
        got.append((index, round(t, 6)))
        previous = index
    assert got == [(11, 100.022), (12, 100.024), (13, 100.026)]
    assert clock.answered(stamp, 13)[0] == 13        # never past the timestamp's SYNC
    assert clock.answered(stamp, None)[0] == 13      # first answer: by timestamp
    clock.attribution_window = 1
    assert clock.answered(stamp, 10)[0] == 13        # silent 2 SYNCs > window: by timestamp


# ---------------------------------------------------------------------------- planned motions
# The executor's tests on the bus: a planned pose motion of the lumbar brace, its actuator
# knots from the paper's eq. 3 (rpr_oracles.lumbar_eq3, independent of the mechanism code),
# sampled by the master at every SYNC. Each SYNC's three targets must be the IK of ONE pose
# of the plan (one time base for all axes), also while braking (time scaling).

import sys  # noqa: E402
sys.path.insert(0, os.path.dirname(__file__))
from rpr_oracles import lumbar_eq3  # noqa: E402

from brace_control.can import ActuatorTrajectory  # noqa: E402



def _min_jerk_pose(p0, p1, T):
    """Thesis 002 eq. (2.2): pose, rate, acceleration at times t (arrays)."""
    def f(t):
        s = np.clip(np.asarray(t, float) / T, 0.0, 1.0)[:, None]
        d = np.asarray(p1) - np.asarray(p0)
        return (np.asarray(p0) + d * (10 * s**3 - 15 * s**4 + 6 * s**5),
                d * (30 * s**2 - 60 * s**3 + 30 * s**4) / T, d * (60 * s - 180 * s**2 + 120 * s**3) / T**2)
    return f


def _actuator_knots(plan, T, n=61):
    """Knots of IK(plan) from eq. 3: positions, rates (central differences of eq. 3 along the
    plan's rate) and accelerations (second differences along the path)."""
    t = np.linspace(0.0, T, n)
    P, V, A = plan(t)
    h = 1e-4
    Q = np.array([lumbar_eq3(p) for p in P])
    Qp = np.array([lumbar_eq3(p + v * h + 0.5 * a * h * h) for p, v, a in zip(P, V, A)])
    Qm = np.array([lumbar_eq3(p - v * h + 0.5 * a * h * h) for p, v, a in zip(P, V, A)])
    QD = (Qp - Qm) / (2 * h)
    QDD = (Qp - 2 * Q + Qm) / (h * h)
    QD[-1] = 0.0
    QDD[-1] = 0.0
    return ActuatorTrajectory(t, Q, QD, QDD)


class _Targets(can.Listener):
    """Every drive's RPDO1 target (counts), grouped per SYNC (the SYNC closes a group)."""

    def __init__(self):
        self.current = {}
        self.groups = []
        self.times = []                 # the SYNC's bus timestamp, one per group

    def on_message_received(self, msg):
        if msg.arbitration_id == 0x80:
            if len(self.current) == 3:
                self.groups.append([self.current[i] for i in (1, 2, 3)])
                self.times.append(msg.timestamp)
            self.current = {}
        elif 0x201 <= msg.arbitration_id <= 0x203 and len(msg.data) >= 6:
            self.current[msg.arbitration_id - 0x200] = int.from_bytes(msg.data[2:6], 'little',
                                                                      signed=True)

    def stop(self):
        pass


def _on_path(groups, plan, T, samples=2001):
    """For each SYNC's targets (counts): the largest distance (counts) of any axis from the
    IK of the single plan pose nearest to them (least squares over the plan's time, on a
    grid then refined continuously). One time base: every axis at one tau."""
    from scipy.optimize import minimize_scalar
    taus = np.linspace(0.0, T, samples)
    Q = np.array([lumbar_eq3(p) for p in plan(taus)[0]]) * CPM
    step = taus[1] - taus[0]
    worst = []
    for g in np.asarray(groups, float):
        k = int(np.argmin(np.sum((Q - g) ** 2, axis=1)))

        def cost(tau, g=g):
            return float(np.sum((lumbar_eq3(plan(np.array([tau]))[0][0]) * CPM - g) ** 2))
        res = minimize_scalar(cost, bounds=(max(0.0, taus[k] - step), min(T, taus[k] + step)),
                              method='bounded', options={'xatol': 1e-9})
        worst.append(np.abs(lumbar_eq3(plan(np.array([res.x]))[0][0]) * CPM - g).max())
    return np.asarray(worst)


def _fraction_done(master, q_from, q_to):
    """How far the drives are from ``q_from`` towards ``q_to`` (0 .. 1), on the axis that
    travels most."""
    q_from, q_to = np.asarray(q_from), np.asarray(q_to)
    i = int(np.argmax(np.abs(q_to - q_from)))
    return (master.feedback().position[i] - q_from[i]) / (q_to[i] - q_from[i])


def _accelerations(rec):
    """Second differences of the targets (m/s^2), SYNC by SYNC: the executor advances a
    motion one period per SYNC (a late SYNC delays the motion, it never stretches a step)."""
    q = np.asarray(rec.groups, float) / CPM
    return np.diff(q, 2, axis=0) / 0.002 ** 2


def _run(master, sim, trajectory, *, until, tag=1):
    tap = can.Bus(interface='virtual', channel=sim.channel)
    rec = _Targets()
    notifier = can.Notifier(tap, [rec])
    forces = []
    try:
        assert master.execute(trajectory, start=time.perf_counter() + 0.02, tag=tag) is None
        t0 = time.perf_counter()

        def ended():
            forces.append(sim.truth().forces)      # the true leg forces, one sample per poll
            return until(master, time.perf_counter() - t0)
        wait_for(ended, 10.0, 'the end of the motion', poll=0.002)
    finally:
        notifier.stop()
        tap.shutdown()
    return rec, np.asarray(forces)


def test_a_trajectory_runs_on_one_time_base_for_all_axes(rig):
    """Sampled at every SYNC: each SYNC's three targets are IK of one pose of the plan
    within a count or two (the plan's own grid here is 0.3 ms), and the drives end at the
    goal's lengths; the executor reports accepted, started, finished."""
    sim, master = rig
    goal = HOME + [0.0, 0.012, 0.04]
    T = 1.5
    plan = _min_jerk_pose(HOME, goal, T)
    rec, _ = _run(master, sim, _actuator_knots(plan, T),
                  until=lambda m, t: t > 0.1 and not m.moving)
    groups = rec.groups
    moving = [g for g, h in zip(groups[1:], groups[:-1]) if g != h]
    assert len(moving) > 0.8 * T / 0.002
    assert _on_path(moving, plan, T).max() <= 3.0
    wait_for(lambda: np.allclose(master.feedback().position, lumbar_eq3(goal), rtol=0, atol=3e-7), 0.5,
             'drives at the goal lengths')
    assert [e.kind for e in master.execution_events()] == ['accepted', 'started', 'finished']
    assert not master.supervisor.latched


def test_a_cancel_brakes_along_the_path_within_a_max_and_never_passes_the_goal(rig):
    """Time scaling: while braking every SYNC's targets are still IK of one plan pose
    (the same path, slower), the command decelerates within a_max, and it stops short of
    the goal it cancels."""
    sim, master = rig
    goal = HOME + [0.0, 0.02, 0.06]
    T = 1.6
    plan = _min_jerk_pose(HOME, goal, T)
    state = {'sent': False}

    def until(m, t):
        if t > 0.7 and not state['sent']:
            m.stop_motion('cancel requested', tag=1)
            state['sent'] = True
        return state['sent'] and not m.moving
    rec, _ = _run(master, sim, _actuator_knots(plan, T), until=until)
    moving = [g for g, h in zip(rec.groups[1:], rec.groups[:-1]) if g != h]
    assert _on_path(moving, plan, T).max() <= 3.0
    assert np.abs(_accelerations(rec)).max() <= 0.5 * 1.05 + 2 / CPM / 0.002 ** 2   # a_max + counts
    final = master.feedback().position
    assert np.all(np.abs(final - lumbar_eq3(HOME)) < np.abs(lumbar_eq3(goal) - lumbar_eq3(HOME)))
    kinds = [(e.kind, e.reason) for e in master.execution_events()]
    assert kinds[-1] == ('stopped', 'cancel requested')


def test_a_new_trajectory_replaces_the_running_one_continuously(rig):
    """JTC semantics: B starts where A is at B's start time (planned from A's state there):
    no step in the targets' velocity or acceleration at the splice."""
    sim, master = rig
    T = 1.5
    a_goal = HOME + [0.0, 0.015, 0.05]
    plan_a = _min_jerk_pose(HOME, a_goal, T)
    knots_a = _actuator_knots(plan_a, T)
    tap = can.Bus(interface='virtual', channel=sim.channel)
    rec = _Targets()
    notifier = can.Notifier(tap, [rec])
    try:
        t_a = time.perf_counter() + 0.02
        assert master.execute(knots_a, start=t_a, tag=1) is None
        wait_for(lambda: any(e.tag == 1 and e.kind == 'started' for e in master.execution_events()),
                 0.5, 'A started')
        # B, sent while A runs: from A's state (in actuator space) 0.7 s into A (near its
        # highest speed), to rest at A's start lengths
        t_b = t_a + 0.7
        q0, v0, a0 = knots_a.sample(t_b - t_a)
        q1 = lumbar_eq3(HOME)
        tb = np.linspace(0.0, 1.2, 61)
        from brace_control.trajectory.base import quintic_coefficients
        b = quintic_coefficients(q0, v0, a0, q1, 0 * q1, 0 * q1, 1.2)
        s = (tb / 1.2)[:, None]
        Qb = sum(b[j] * s ** j for j in range(6))
        Vb = sum(j * b[j] * s ** (j - 1) for j in range(1, 6)) / 1.2
        Ab = sum(j * (j - 1) * b[j] * s ** (j - 2) for j in range(2, 6)) / 1.2 ** 2
        assert master.execute(ActuatorTrajectory(tb, Qb, Vb, Ab), start=t_b, tag=2) is None
        wait_for(lambda: time.perf_counter() > t_b + 0.3 and not master.moving, 3.0, 'B done')
    finally:
        notifier.stop()
        tap.shutdown()
    assert np.abs(_accelerations(rec)).max() <= 0.5 + 3 / CPM / 0.002 ** 2
    kinds = [(e.tag, e.kind) for e in master.execution_events()]
    assert (1, 'preempted') in kinds and kinds[-1] == (2, 'finished')


def test_halt_brakes_along_the_path_then_holds_in_quick_stop(rig):
    sim, master = rig
    goal = HOME + [0.0, 0.02, 0.06]
    T = 1.6
    plan = _min_jerk_pose(HOME, goal, T)
    assert master.execute(_actuator_knots(plan, T), start=time.perf_counter() + 0.02, tag=1) is None
    wait_for(lambda: _fraction_done(master, lumbar_eq3(HOME), lumbar_eq3(goal)) >= 0.25, T,
             'the motion a quarter of its way')
    master.halt()
    assert all(s is State402.QUICK_STOP_ACTIVE for s in master.feedback().states)
    assert np.all(np.abs(sim.truth().velocities) < 1e-9)
    # where it stopped is on the path: eq. 3 of one plan pose
    counts = master.feedback().position * CPM
    assert _on_path([counts], plan, T).max() <= 3.0
    assert [e.kind for e in master.execution_events()][-1] == 'stopped'


def test_trajectories_that_must_not_run_are_rejected_and_nothing_moves(rig):
    sim, master = rig
    q0 = master.feedback().position.copy()
    t = np.linspace(0.0, 1.0, 11)
    far = ActuatorTrajectory(t, q0 + np.outer(t, [0.0, 0.2, 0.0]))            # beyond the stroke
    fast = ActuatorTrajectory([0.0, 0.05], np.array([q0, q0 + [0.0, 0.02, 0.0]]))
    moving_end = ActuatorTrajectory([0.0, 1.0], np.array([q0, q0 + [0.0, 0.001, 0.0]]),
                                    np.array([[0, 0, 0], [0, 0.001, 0]]), np.zeros((2, 3)))
    away = ActuatorTrajectory([0.0, 1.0], np.array([q0 + [0.0, 0.01, 0.0]] * 2))   # 10 mm away
    reasons = [master.execute(tr, start=time.perf_counter(), tag=k)
               for k, tr in enumerate((far, fast, moving_end), start=1)]
    assert 'outside its range' in reasons[0]
    assert 'speed limit' in reasons[1]
    assert 'not at rest' in reasons[2]
    assert master.execute(away, start=time.perf_counter(), tag=4) is None   # rejected at the splice
    wait_for(lambda: any(e.tag == 4 and e.kind == 'rejected' for e in master.execution_events()),
             0.5, 'splice rejection')
    master.disable()
    assert 'not enabled' in master.execute(fast, start=time.perf_counter(), tag=5)
    assert master.feedback().position == pytest.approx(q0, abs=1e-6)


def test_the_legs_carry_only_the_static_load_while_moving(rig):
    """Self-stress (the brace's legs nearly parallel: 1 um of inconsistency ~ 1 N): during a
    lift and a rotation, the true leg forces stay within 10 N of the static forces along
    the path (the ring's equilibrium with the body for the commanded lengths, an oracle of
    its own: test_e2e.Device.ring_pose, written from the paper and the YAML)."""
    from test_e2e import Device
    from pathlib import Path
    device = Device(Path('config/lumbar_brace.yaml'))
    sim, master = rig
    goal = HOME + [0.0, 0.015, 0.06]
    T = 1.8
    plan = _min_jerk_pose(HOME, goal, T)
    truths = []

    def until(m, t):
        truths.append(sim.truth())
        return t > 0.1 and not m.moving
    _run(master, sim, _actuator_knots(plan, T), until=until)
    worst = 0.0
    pose = HOME.copy()
    for tr in truths[::5]:
        pose = device.ring_pose(tr.lengths, pose)
        static = device.k_leg * (tr.lengths - device.lengths(pose))
        worst = max(worst, float(np.abs(tr.forces - static).max()))
    assert worst < 10.0, worst
    assert not master.supervisor.latched, master.supervisor.summary()


# ---------------------------------------------------------------------------- soft limit, relief
def _rig_with(safety, cfg=CFG):
    """A rig whose safety limits are overridden (the YAML's body and geometry; the lumbar
    brace's unless ``cfg`` is another device's)."""
    import copy
    cfg = copy.deepcopy(cfg)
    cfg['safety'].update(safety)
    channel = f'cantest-{os.getpid()}-{next(_ids)}'
    sim = SimulatedBrace(cfg, channel=channel)
    master = BraceMaster.from_device_config(cfg, channel=channel)
    master.boot()
    master.home()
    master.enable()
    return sim, master


def test_the_soft_force_limit_brakes_a_pressing_motion_and_nothing_latches():
    """docs/safety.md §14: a lift against the body (4000 N/m) loads every leg ~27 N; with the soft
    limit at 15 N the motion decelerates along its path (still on it) and holds, its
    trajectory reported stopped naming the leg and the force; nothing latches and the next
    motion (down, unloading) runs."""
    sim, master = _rig_with({'force_limit': 60.0, 'soft_force_limit': 15.0, 'release_force': 5.0})
    try:
        goal = HOME + [0.0, 0.02, 0.0]
        T = 1.5
        plan = _min_jerk_pose(HOME, goal, T)
        rec, forces = _run(master, sim, _actuator_knots(plan, T),
                           until=lambda m, t: t > 0.1 and not m.moving)
        events = master.execution_events()
        assert events[-1].kind == 'stopped' and 'soft force limit' in events[-1].reason, events
        assert not master.supervisor.latched and master.state is MasterState.ENABLED
        moving = [g for g, h in zip(rec.groups[1:], rec.groups[:-1]) if g != h]
        assert _on_path(moving, plan, T).max() <= 3.0               # braked along the path
        assert np.abs(forces).max() < 25.0                           # never near the full 27 N
        assert np.abs(sim.truth().lengths - lumbar_eq3(goal)).max() > 1e-3   # stopped short
        back = _min_jerk_pose(plan(np.array([0.0]))[0][0] * 0 + _pose_of(master), HOME, 1.2)
        assert master.execute(_actuator_knots(back, 1.2), start=time.perf_counter() + 0.02, tag=2) is None
        wait_for(lambda: any(e.kind == 'finished' for e in master.execution_events()), 3.0, 'back home')
        assert not master.supervisor.latched
    finally:
        master.shutdown()
        sim.shutdown()


def _pose_of(master):
    """The pose whose eq. 3 lengths are the drives' positions (Newton on eq. 3)."""
    q = master.feedback().position
    p = HOME.copy()
    for _ in range(30):
        J = np.column_stack([(lumbar_eq3(p + h) - lumbar_eq3(p - h)) / 2e-7
                             for h in np.eye(3) * 1e-7])
        p = p - np.linalg.solve(J, lumbar_eq3(p) - q)
    return p


def test_a_loaded_stop_is_relieved_then_recovered():
    """docs/safety.md §15: the patient slumps (the body's rest pose 26 mm lower: ~100 N on the
    ring) while the brace holds: the legs pass the force limit (30 N here) and a protective
    stop latches; recover is refused while loaded. relieve backs every leg off slowly until
    all forces are below the release force; recover then succeeds and the drives enable."""
    sim, master = _rig_with({'force_limit': 30.0, 'soft_force_limit': 24.0, 'release_force': 6.0})
    try:
        sim.set_rest_pose(HOME + [0.0, -0.026, 0.0])
        wait_for(_latched(master, FaultKind.FORCE_LIMIT), 0.5, 'force limit')
        wait_for(lambda: stopped(master), 0.5, 'protective stop')
        _recover_refused(master, FaultKind.FORCE_LIMIT)
        before = np.abs(sim.truth().forces).max()
        assert before > 30.0
        # the soft body unloads slowly (its force decays with a time constant of ~7 s: the
        # relief's gain is set by a leg against its own stiffness): 13 s on a quiet machine,
        # and the simulated world slows with the SYNCs a busy host misses. The check is what
        # the relief ends with, not how long it takes: a longer deadline than the default 20 s
        message = master.relieve(timeout=60.0)
        assert 'relieved' in message
        truth = sim.truth()
        assert np.abs(truth.forces).max() < 6.0          # the true forces, not one noisy reading
        speed = np.abs(truth.velocities).max()
        assert speed < 1e-9                                                # holding
        _recover_and_enable(master)
    finally:
        master.shutdown()
        sim.shutdown()


def test_relieve_refuses_a_fault_it_cannot_back_off_from(rig):
    sim, master = rig
    with pytest.raises(DriverOperationError, match='nothing to relieve'):
        master.relieve()
    sim.drive(2).heartbeat_silenced = True
    wait_for(_latched(master, FaultKind.HEARTBEAT_LOST, 'a2'), 0.15 + SLACK, 'heartbeat fault')
    with pytest.raises(DriverOperationError, match='cannot relieve'):
        master.relieve()
    sim.drive(2).heartbeat_silenced = False


def test_a_loaded_stop_on_rigid_rotary_joints_is_relieved():
    """docs/safety.md §15 on the 2R neck brace: its joints are modelled rigid (actuator.stiffness
    1e7 N·m/rad), so a relief paced by the legs' stiffness alone crawled at micro-radians per
    second and timed out with the head still pushed. The head's rest moves 40 mm (800 N/m:
    ~32 N at the support point) while the brace holds: the joint torques pass the force
    limit (2 N·m here), a protective stop latches, recover is refused; relieve swings the
    joints back until the TRUE torques (the simulator's) are below the release force, and
    recover then succeeds."""
    cfg = load_device_config('config/neck_brace_2r.yaml')
    sim, master = _rig_with({'force_limit': 2.0, 'soft_force_limit': 1.6, 'release_force': 0.4}, cfg)
    try:
        rest = np.asarray(cfg['sim']['rest_pose'], float)
        sim.set_rest_pose(rest + np.array([0.0, 0.04]))
        wait_for(_latched(master, FaultKind.FORCE_LIMIT), 2.0, 'force limit')
        wait_for(lambda: stopped(master), 1.0, 'protective stop')
        _recover_refused(master, FaultKind.FORCE_LIMIT)
        assert np.abs(sim.truth().forces).max() > 2.0
        message = master.relieve()
        assert 'relieved' in message and 'mrad' in message, message
        assert np.abs(sim.truth().forces).max() < 0.4, (sim.truth().forces, message)
        _recover_and_enable(master)
    finally:
        master.shutdown()
        sim.shutdown()


def test_a_cable_brace_takes_up_its_slack_after_a_relief():
    """4-RPR neck brace (cables pull only): the head's rest moves 22 mm (1500 N/m: 33 N) and
    a protective stop latches on the cables' force limit (15 N here: 13 mm of slack to take
    up, at the take-up's ~1 mm/s; 40 mm and 25 N took 27 mm and 31 s); the relief pays the
    cables out until every tension is below the release force, and some go slack: their
    commanded lengths then fit no pose. take_up shortens every slack cable until it holds
    tension_min (5 N) again: afterwards each commanded length is the length of that cable at
    the simulator's TRUE head pose (geometry written out here) within its stretch under
    load (shorter by tension / 2e5 N/m) and two counts, and every TRUE tension is at least tension_min
    less the load cell's noise."""
    cfg = load_device_config('config/neck_brace_4rpr.yaml')
    sim, master = _rig_with({'force_limit': 15.0, 'soft_force_limit': 12.0, 'release_force': 5.0}, cfg)
    try:
        rest = np.asarray(cfg['sim']['rest_pose'], float)
        sim.set_rest_pose(rest + np.array([0.022, 0.0, 0.0]))
        wait_for(_latched(master, FaultKind.FORCE_LIMIT), 2.0, 'force limit')
        wait_for(lambda: stopped(master), 1.0, 'protective stop')
        assert 'relieved' in master.relieve()
        _recover_ok(master)
        master.enable()
        truth = sim.truth()
        off = np.abs(master.feedback().position - cable_lengths_4rpr(cfg, truth.pose))
        assert off.max() > 0.002, f'premise: slack cables after the relief, {off} m'
        message = master.take_up(below=5.0)
        assert 'slack taken up' in message, message
        wait_for(lambda: not master.moving, 1.0, 'rest after the take-up')
        truth = sim.truth()
        tension = -truth.forces
        stretch = np.maximum(tension, 0.0) / float(cfg['sim']['leg_stiffness'])
        geometric = cable_lengths_4rpr(cfg, truth.pose)
        count = float(cfg['actuator']['screw_lead']) / float(cfg['actuator']['encoder_counts_per_rev'])
        np.testing.assert_allclose(master.feedback().position + stretch, geometric, atol=2 * count + 1e-5)
        assert np.all(tension >= 5.0 - 4 * float(cfg['sim']['load_cell_noise'])), tension
        assert master.state is MasterState.ENABLED and not master.supervisor.latched
        assert 'nothing to take up' in master.take_up(below=5.0)
    finally:
        master.shutdown()
        sim.shutdown()


def test_a_drive_under_local_control_is_named_when_enable_times_out():
    """A drive left under local control from its start (its panel, the vendor's setup tool)
    keeps statusword bit 9 (remote) clear and ignores the controlword: homing, then enable,
    time out, and the message names that drive and the remote bit, not only the states. (A
    drive taken under local control later is a protective stop at once: below.)"""
    from brace_control.can import DriverTimeoutError
    channel = f'cantest-{os.getpid()}-{next(_ids)}'
    sim = SimulatedBrace(CFG, channel=channel)
    master = BraceMaster.from_device_config(CFG, channel=channel)
    try:
        sim.faults.local_control(2)
        master.boot()
        with pytest.raises(DriverTimeoutError) as err:
            master.home(timeout=1.0)
        text = str(err.value)
        assert 'bit 9 (remote) is clear on a2' in text and 'a1' not in text.split('clear on')[1], text
        assert sim.drive(2).statusword & 0x200 == 0 and sim.drive(1).statusword & 0x200
        assert not master.supervisor.latched, master.supervisor.summary()   # never remote: no stop
        sim.faults.local_control(2, False)
        master.home()
        master.enable()
    finally:
        master.shutdown()
        sim.shutdown()


# ------------------------------------------------------------------ from a fault sweep (session 14)

def _relieving_a_slumped_patient(timeout: float):
    """The lumbar rig (force limit 30 N) with the patient slumped 26 mm: the force stop
    latched, then ``relieve(timeout)`` running in a thread. Returns ``sim, master, worker,
    result``: ``result`` gets ``message`` or ``error`` and ``at`` (monotonic) when it returns."""
    import threading
    sim, master = _rig_with({'force_limit': 30.0, 'soft_force_limit': 24.0, 'release_force': 6.0})
    try:
        sim.set_rest_pose(HOME + [0.0, -0.026, 0.0])
        wait_for(_latched(master, FaultKind.FORCE_LIMIT), 0.5, 'force limit')
        wait_for(lambda: stopped(master), 0.5, 'protective stop')
        time.sleep(0.3)
    except BaseException:
        master.shutdown()
        sim.shutdown()
        raise
    result: dict = {'start': float(np.abs(sim.truth().forces).max())}

    def relieve() -> None:
        try:
            result['message'] = master.relieve(timeout=timeout)
        except DriverOperationError as exc:
            result['error'] = str(exc)
        result['at'] = time.monotonic()
    worker = threading.Thread(target=relieve)
    worker.start()
    wait_for(lambda: np.abs(sim.truth().velocities).max() > 1e-5, 5.0, 'the relief moving')
    return sim, master, worker, result


def test_a_relief_that_a_new_fault_ends_returns_at_once():
    """docs/safety.md §15: a relief under way when a fault it cannot back off from latches (a
    drive's heartbeat lost): the drives stop, and relieve() answers at once with the fault,
    not after its own time-out (it waited 60 s + 2 s here, holding the API: a disable
    meanwhile waited as long)."""
    sim, master, worker, result = _relieving_a_slumped_patient(60.0)
    try:
        t0 = time.monotonic()
        sim.faults.silence_heartbeat(2)
        worker.join(10.0)
        assert not worker.is_alive(), 'relieve() still waiting 10 s after the fault'
        assert result['at'] - t0 < 1.0, result['at'] - t0
        assert 'relief stopped' in result.get('error', '') and 'heartbeat' in result['error'], result
        wait_for(lambda: np.abs(sim.truth().velocities).max() < 1e-6, 1.0, 'the brace still')
    finally:
        sim.faults.silence_heartbeat(2, False)
        worker.join(70.0)
        master.shutdown()
        sim.shutdown()


def test_a_drive_that_left_operational_must_be_homed_again(rig):
    """docs/safety.md §2: a drive that restarts without a boot-up message (an NMT reset the
    drive answers silently) comes back with its position counter anew: the truth and its
    reading no longer agree. recover re-configures it but the master is no longer homed, and
    enable is refused until it is."""
    sim, master = rig
    sim.faults.silent_boot(2, 'always')
    master.network.send_message(0, bytes([0x81, 2]))          # NMT reset node 2
    wait_for(lambda: master.supervisor.latched, 1.0, 'the restart seen')
    deadline = time.monotonic() + 5.0
    while master.recover() and time.monotonic() < deadline:
        time.sleep(0.2)                                       # its heartbeat still to come
    assert not master.supervisor.latched, master.supervisor.summary()
    off = np.abs(master.feedback().position - sim.truth().lengths)
    assert off[1] > 0.01, off                                 # why: a2's reading restarted
    assert not master.homed
    with pytest.raises(DriverOperationError, match='hom'):
        master.enable()
    master.home()
    master.enable()
    np.testing.assert_allclose(master.feedback().position, sim.truth().lengths, atol=2e-6)


def test_a_homing_cut_short_leaves_the_master_not_homed_and_the_drives_in_csp(rig):
    """A homing that fails midway (drive 2's EMCY with a drive fault once the homing runs)
    leaves the reference unknown: not homed, and every drive back in cyclic synchronous
    position (6061h, read back from the drives), not left in homing mode."""
    import threading
    sim, master = rig
    master.disable()
    failed: list = []

    def home() -> None:
        try:
            master.home()
        except Exception as exc:  # noqa: BLE001 - the failure this test causes
            failed.append(exc)
    worker = threading.Thread(target=home)
    worker.start()
    wait_for(lambda: master.state is MasterState.HOMING, 5.0, 'the homing running')
    sim.faults.send_emcy(2, 0x7305, fault=True)
    worker.join(30.0)
    assert failed, 'the homing succeeded despite the drive fault'
    assert not master.homed
    sim.faults.clear_emcy_fault(2)
    for d in master.life.drives:
        assert d.node.sdo[0x6061].raw == 8, d.name            # cyclic synchronous position


def test_a_relief_steered_by_a_load_cell_that_misreads_stops_before_it_presses_harder():
    """docs/safety.md §15 "under force supervision": during a relief, a2's load cell sticks at
    -31.5 N (beyond the 30 N limit, the other way from its leg's load). The relief ends at
    once, naming a2, and no true leg force rises above what the relief started with (it
    steered every leg to a stroke's end, all three pressing 31 N the other way: the hard
    limit, latched already, said nothing more). Oracle: the simulator's true forces, sampled
    throughout."""
    sim, master, worker, result = _relieving_a_slumped_patient(20.0)
    try:
        time.sleep(0.3)
        sim.faults.set_load_cell(2, -31.5)
        peak = 0.0
        while worker.is_alive():
            peak = max(peak, float(np.abs(sim.truth().forces).max()))
            time.sleep(0.002)
        assert 'relief stopped' in result.get('error', '') and 'a2' in result['error'], result
        assert peak <= max(30.0, result['start']) + 2.0, (peak, result['start'])
    finally:
        sim.faults.set_load_cell(2, None)
        worker.join(30.0)
        master.shutdown()
        sim.shutdown()


def test_a_drive_taken_under_local_control_is_a_protective_stop_naming_it(rig):
    """docs/safety.md §4: a drive put under local control (statusword bit 9, remote, clear:
    its panel or a setup tool) ignores the controlword from the bus, so the master cannot stop
    it. Latched and named at once; the other drives stop; recover is refused until the drive
    is back under the bus's control."""
    sim, master = rig
    sim.faults.local_control(2)
    try:
        wait_for(_latched(master, FaultKind.DRIVE_FAULT, 'a2'), OBSERVE_S, 'local control seen')
        assert 'remote' in master.supervisor.summary() and 'local control' in master.supervisor.summary()
        wait_for(lambda: all(sim.drive(n).state in (State402.QUICK_STOP_ACTIVE, State402.SWITCH_ON_DISABLED)
                             for n in (1, 3)), 0.5, 'the other drives stopped')
        assert master.recover(), 'recover accepted with a2 still under local control'
    finally:
        sim.faults.local_control(2, False)
    _recover_ok(master)
    master.enable()


def test_an_encoder_that_jumps_while_the_brace_is_disabled_is_caught(rig):
    """docs/safety.md §9: a reading that jumps faster than the actuator can move is a fault
    whether or not the drive is commanded: drive 2's encoder jumps 3 mm while the brace is
    disabled. It latches (the reference is suspect: not homed), so the next enable cannot
    start from a reading 3 mm off the truth (it did)."""
    sim, master = rig
    master.disable()
    sim.faults.jump_encoder(2, 0.003)
    wait_for(_latched(master, FaultKind.POSITION_JUMP, 'a2'), OBSERVE_S, 'the jump caught')
    assert not master.homed
    off = master.feedback().position - sim.truth().lengths
    assert abs(off[1]) > 0.002, off                          # the reading is off the truth
    with pytest.raises(Exception):
        master.enable()
