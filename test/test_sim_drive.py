"""The simulated CiA 402 drive as any master sees it: canopen's own master side on the bus.

Virtual bus, a unique channel per test, no fixed sleeps: SYNCs are sent one at a time by
the test (the simulated time step is 1006h, 2 ms by default) and every wait is on a
condition with a timeout. Oracles: CiA 301/402 and docs/can.md, not the simulator.

The CSP servo model (last section) is driven frame by frame without a bus
(:class:`drive_frames.FrameMaster`); its oracles are the closed-form responses of the
position loop docs/can.md specifies (first-order lag, braking curve), derived in each
test's docstring.
"""
from __future__ import annotations

import itertools
import math
import os
import struct
import threading
import time
from collections.abc import Callable
from pathlib import Path

import can
import canopen
import pytest
import yaml

from brace_control.can.plan import pdo_mapping_writes
from brace_control.sim import SimBus, SimulatedBrace
from brace_control.sim.drive import DriveLimits, SimulatedDrive
from drive_frames import FrameMaster

ROOT = Path(__file__).resolve().parent.parent
CFG = ROOT / 'config' / 'lumbar_brace.yaml'
EDS = str(ROOT / 'config' / 'lumbar_drive.eds')
CPM = 8192 / 0.001          # counts per metre (docs/can.md)
_ids = itertools.count()


class Recorder(can.Listener):
    """Every frame the master's bus receives, with a condition to wait on."""

    def __init__(self) -> None:
        self.frames: list[can.Message] = []
        self.cond = threading.Condition()

    def on_message_received(self, msg: can.Message) -> None:
        with self.cond:
            self.frames.append(msg)
            self.cond.notify_all()

    def mark(self) -> int:
        with self.cond:
            return len(self.frames)

    def wait(self, pred: Callable[[can.Message], bool], *, since: int = 0, count: int = 1,
             timeout: float = 2.0) -> list[can.Message]:
        deadline = time.monotonic() + timeout
        with self.cond:
            while True:
                hits = [m for m in self.frames[since:] if pred(m)]
                if len(hits) >= count:
                    return hits
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError(f'waited {timeout} s for {count} frame(s), got {len(hits)}')
                self.cond.wait(left)


def cob(cob_id: int) -> Callable[[can.Message], bool]:
    return lambda m: not m.is_error_frame and m.arbitration_id == cob_id


def wait_until(cond: Callable[[], bool], timeout: float = 2.0) -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            raise TimeoutError('condition not met in time')
        time.sleep(0.002)


class Rig:
    """canopen master + recorder on a fresh channel, then the simulated brace (boots)."""

    def __init__(self, name: str, *, inline: bool = True) -> None:
        self.channel = f'simtest-{os.getpid()}-{next(_ids)}-{name}'
        self.net = canopen.Network()
        self.net.connect(interface='virtual', channel=self.channel)
        self.rec = Recorder()
        self.net.notifier.add_listener(self.rec)
        self.sim = SimulatedBrace(CFG, channel=self.channel, start=False)
        self.sim.host.inline = inline        # False: a receive thread, as on other interfaces
        self.sim.start()
        self.nodes: dict[int, canopen.BaseNode402] = {}

    def node(self, node_id: int) -> canopen.BaseNode402:
        if node_id not in self.nodes:
            self.nodes[node_id] = self.net.add_node(canopen.BaseNode402(node_id, EDS))
        return self.nodes[node_id]

    def sync(self, n: int = 1, *, tpdo_from: tuple[int, ...] = ()) -> None:
        """Send ``n`` SYNCs, each time waiting for TPDO1 of the given nodes."""
        for _ in range(n):
            since = self.rec.mark()
            self.net.send_message(0x80, b'')
            for nid in tpdo_from:
                self.rec.wait(cob(0x180 + nid), since=since)

    def rpdo1(self, node_id: int, controlword: int, target: int) -> None:
        """RPDO1 per docs/can.md: 6040h U16 + 607Ah I32 (applied on the next SYNC)."""
        self.net.send_message(0x200 + node_id, struct.pack('<Hi', controlword, target))

    def tpdo1(self, node_id: int, since: int = 0) -> tuple[int, int, int]:
        """Last TPDO1: statusword, position actual (counts), load cell (counts)."""
        msg = self.rec.wait(cob(0x180 + node_id), since=since)[-1]
        return struct.unpack('<HiH', bytes(msg.data))[:2] + struct.unpack('<h', bytes(msg.data)[6:8])

    def close(self) -> None:
        for node in self.nodes.values():
            for pdo in node.rpdo.map.values():
                pdo.stop()
        self.net.sync.stop()
        self.net.disconnect()
        self.sim.shutdown()


@pytest.fixture
def rig(request: pytest.FixtureRequest):
    r = Rig(request.node.name)
    yield r
    r.close()


@pytest.fixture
def queued_rig(request: pytest.FixtureRequest):
    """The drives receive from a queue, in a thread of their own (sim/host.py: an interface
    other than ``virtual``, or a second simulator on the channel)."""
    r = Rig(request.node.name, inline=False)
    assert r.sim.host._notifier is not None
    yield r
    r.close()


def enable_csp(rig: Rig, node_id: int, *, home: bool = True) -> int:
    """NMT operational, homing 35 on the current position (607Ch = true length), CSP,
    OPERATION ENABLED by RPDO; returns the position actual (counts)."""
    node = rig.node(node_id)
    length = rig.sim.drive(node_id).length_m
    if home:
        node.sdo[0x607C].raw = round(length * CPM)
    rig.net.send_message(0, bytes((0x01, node_id)))
    rig.sync(1, tpdo_from=(node_id,))
    sw, pos, _ = rig.tpdo1(node_id)
    for cw in (0x06, 0x07, 0x0F):
        rig.rpdo1(node_id, cw, pos)
        rig.sync(2, tpdo_from=(node_id,))
    if home:
        node.sdo[0x6060].raw = 6
        rig.rpdo1(node_id, 0x1F, pos)
        rig.sync(2, tpdo_from=(node_id,))
        sw, pos, _ = rig.tpdo1(node_id)
        assert sw & 0x1400 == 0x1400, f'homing attained + target reached expected, sw={sw:#06x}'
        rig.rpdo1(node_id, 0x0F, pos)
        rig.sync(2, tpdo_from=(node_id,))
        node.sdo[0x6060].raw = 8
    rig.sync(1, tpdo_from=(node_id,))
    sw, pos, _ = rig.tpdo1(node_id)
    assert sw & 0x6F == 0x27, f'OPERATION ENABLED expected, sw={sw:#06x}'
    return pos


# ---------------------------------------------------------------- CiA 301: boot, NMT, SDO

def test_boot_up_then_heartbeats_in_pre_operational(rig: Rig) -> None:
    for nid in (1, 2, 3):
        boot = rig.rec.wait(cob(0x700 + nid))[0]
        assert bytes(boot.data) == b'\x00'
        hbs = rig.rec.wait(cob(0x700 + nid), count=3)      # 1017h = 50 ms by default
        assert all(bytes(m.data) == b'\x7f' for m in hbs[1:])
        gap = hbs[2].timestamp - hbs[1].timestamp
        assert 0.02 < gap < 0.2


def test_sdo_expedited_and_segmented_over_the_eds_dictionary(rig: Rig) -> None:
    node = rig.node(2)
    assert node.sdo[0x1000].raw == 0x00020192
    assert node.sdo[0x1014].raw == 0x82
    assert node.sdo['Manufacturer device name'].raw == 'brace_control simulated lumbar drive'  # segmented
    node.sdo[0x6065].raw = 12345
    assert node.sdo[0x6065].raw == 12345
    node.sdo.download(0x607C, 0, struct.pack('<i', -4242), force_segment=True)    # segmented
    assert node.sdo[0x607C].raw == -4242
    with pytest.raises(canopen.SdoAbortedError) as exc:
        node.sdo[0x6041].raw = 0                 # read-only
    assert exc.value.code == 0x06010002
    with pytest.raises(canopen.SdoAbortedError) as exc:
        node.sdo.upload(0x6123, 0)               # no such object
    assert exc.value.code == 0x06020000
    with pytest.raises(canopen.SdoAbortedError):
        node.sdo[0x6060].raw = 3                 # profile velocity: not supported (6502h)


def test_nmt_stop_start_reset_node_and_reset_communication(rig: Rig) -> None:
    node = rig.node(1)
    enable_csp(rig, 1)
    node.sdo[0x1800][2].raw = 2                  # TPDO1 every 2nd SYNC
    since = rig.rec.mark()
    rig.net.send_message(0, b'\x02\x01')         # stop node 1
    rig.rec.wait(lambda m: m.arbitration_id == 0x701 and bytes(m.data) == b'\x04', since=since)
    since = rig.rec.mark()
    for _ in range(3):
        rig.net.send_message(0x80, b'')
    rig.rec.wait(cob(0x701), since=since)        # the next heartbeat: still stopped
    assert not [m for m in rig.rec.frames[since:] if m.arbitration_id == 0x181]
    rig.net.send_message(0, b'\x01\x01')         # start
    rig.rec.wait(lambda m: m.arbitration_id == 0x701 and bytes(m.data) == b'\x05', since=since)
    rig.net.send_message(0x80, b'')
    rig.sync(1, tpdo_from=(1,))                  # type 2: every 2nd SYNC
    # reset communication: 1800h back to the EDS default (type 1), boot-up again
    since = rig.rec.mark()
    # (a heartbeat already on its way when the reset arrives may come first: the boot-up is
    # waited for, not taken to be the next frame; a run in CI saw node 2's 7Fh first)
    rig.net.send_message(0, b'\x82\x01')
    rig.rec.wait(lambda m: m.arbitration_id == 0x701 and bytes(m.data) == b'\x00', since=since)
    assert node.sdo[0x1800][2].raw == 1
    # reset node: the application restarts, the incremental encoder reads 0 again
    since = rig.rec.mark()
    rig.net.send_message(0, b'\x81\x00')         # all nodes
    for nid in (1, 2, 3):
        rig.rec.wait(lambda m, nid=nid: m.arbitration_id == 0x700 + nid and bytes(m.data) == b'\x00',
                     since=since)
    assert node.sdo[0x6064].raw == 0
    assert node.sdo[0x6041].raw & 0x4F == 0x40                  # SWITCH ON DISABLED


# ---------------------------------------------------------------- CiA 402 with BaseNode402

def test_base_node_402_drives_the_state_machine(rig: Rig) -> None:
    node = rig.node(3)
    node.nmt.wait_for_heartbeat(1.0)         # canopen learns the NMT state
    node.sdo[0x1006].raw = 10000             # the SYNC period below
    node.setup_402_state_machine()
    node.nmt.state = 'OPERATIONAL'
    rig.net.sync.start(0.01)
    node.rpdo[1]['Target position'].raw = 0   # unhomed: position actual is 0
    node.rpdo[1].start(0.01)
    node.tpdo[1].wait_for_reception(1.0)
    assert node.state == 'SWITCH ON DISABLED'
    for state in ('READY TO SWITCH ON', 'SWITCHED ON', 'OPERATION ENABLED',
                  'QUICK STOP ACTIVE', 'OPERATION ENABLED', 'SWITCHED ON',
                  'SWITCH ON DISABLED', 'OPERATION ENABLED'):
        node.state = state
        assert node.state == state
    sw = node.statusword
    assert sw & 0x0200 and sw & 0x0010 and sw & 0x0020      # remote, voltage, no quick stop
    assert node.op_mode == 'CYCLIC SYNCHRONOUS POSITION'
    rig.net.sync.stop()


def test_pdo_remapping_by_sdo_changes_what_the_pdos_carry(rig: Rig) -> None:
    node = rig.node(2)
    node.tpdo.read()
    node.rpdo.read()
    assert [v.index for v in node.tpdo[1]] == [0x6041, 0x6064, 0x2401]   # docs/can.md default
    node.tpdo[1].clear()
    node.tpdo[1].add_variable(0x6041)
    node.tpdo[1].add_variable(0x606C)
    node.tpdo[1].add_variable(0x6061)
    node.tpdo[1].trans_type = 1
    node.tpdo[1].enabled = True
    node.tpdo[2].clear()
    node.tpdo[2].add_variable(0x6077)
    node.tpdo[2].add_variable(0x60F4)
    node.tpdo[2].cob_id = 0x282
    node.tpdo[2].trans_type = 2              # every 2nd SYNC
    node.tpdo[2].enabled = True
    node.tpdo.save()
    node.rpdo[1].clear()
    node.rpdo[1].add_variable(0x6040)
    node.rpdo[1].add_variable(0x6060)
    node.rpdo[1].enabled = True
    node.rpdo.save()
    assert node.sdo[0x1A00][0].raw == 3 and node.sdo[0x1A00][2].raw == 0x606C0020
    rig.net.send_message(0, b'\x01\x02')
    since = rig.rec.mark()
    rig.sync(4, tpdo_from=(2,))
    t1 = rig.rec.wait(cob(0x182), since=since, count=4)
    assert all(len(m.data) == 7 for m in t1)           # U16 + I32 + I8
    assert t1[-1].data[6] == 8                           # 6061h: CSP
    assert node.tpdo[1]['Modes of operation display'].raw == 8
    # every 2nd SYNC: two in four. The 4th SYNC's TPDO2 may be recorded just after its TPDO1
    # (waited for above); had TPDO2 gone out at every SYNC, those of the first three, sent
    # before the 4th TPDO1, would already be here: three or four
    t2 = rig.rec.wait(cob(0x282), since=since, count=2)
    assert len(t2) == 2 and all(len(m.data) == 6 for m in t2)
    # the re-mapped RPDO1 (6040h U16 + 6060h I8) switches the mode on the next SYNC
    rig.net.send_message(0x202, struct.pack('<Hb', 0x06, 6))
    since = rig.rec.mark()
    rig.sync(2, tpdo_from=(2,))
    assert rig.rec.wait(cob(0x182), since=since, count=2)[-1].data[6] == 6
    assert node.sdo[0x6060].raw == 6
    # a mapping naming an object that cannot be mapped is refused (CiA 301 0604 0041h)
    with pytest.raises(canopen.SdoAbortedError) as exc:
        node.sdo[0x1A01][1].raw = 0x60650020
    assert exc.value.code == 0x06040041


# ---------------------------------------------------------------- CSP motion and faults

def test_csp_tracking_respects_max_velocity_and_acceleration(rig: Rig) -> None:
    node = rig.node(1)
    node.sdo[0x6065].raw = round(0.05 * CPM)         # wide window: no following error
    pos0 = enable_csp(rig, 1)
    target = pos0 + round(0.02 * CPM)
    rig.rpdo1(1, 0x0F, target)
    positions = []
    for _ in range(300):
        since = rig.rec.mark()
        rig.sync(1, tpdo_from=(1,))
        positions.append(rig.tpdo1(1, since)[1])
        if positions[-1] == target:
            break
    dt = 0.002                                        # 1006h default (EDS)
    steps = [b - a for a, b in zip(positions, positions[1:])]
    v_max, a_max = 0.065 * CPM * dt, 0.5 * CPM * dt * dt
    assert max(steps) <= v_max + 2, 'faster than 65 mm/s'
    assert max(steps) >= v_max - 2, 'never reaches the nominal speed'
    assert all(abs(b - a) <= a_max + 2 for a, b in zip(steps, steps[1:])), 'acceleration limit'
    assert positions[-1] == target                    # arrives, no overshoot beyond a count
    assert max(positions) <= target + 1


def test_software_limit_and_hard_end_stop(rig: Rig) -> None:
    node = rig.node(1)
    pos = enable_csp(rig, 1)
    # target beyond 607Dh:2 (the stroke max, counts) -> FAULT + EMCY 8612h
    since = rig.rec.mark()
    rig.rpdo1(1, 0x0F, round(0.441 * CPM))
    rig.sync(2, tpdo_from=(1,))
    emcy = rig.rec.wait(cob(0x81), since=since)[0]
    assert struct.unpack_from('<H', bytes(emcy.data))[0] == 0x8612
    sw, _, _ = rig.tpdo1(1)
    assert sw & 0x4F == 0x08
    # fault reset while the cause persists: refused; target back inside: accepted
    rig.rpdo1(1, 0x80, round(0.441 * CPM))
    rig.sync(2, tpdo_from=(1,))
    assert rig.tpdo1(1)[0] & 0x4F == 0x08
    rig.rpdo1(1, 0x00, pos)
    rig.sync(1, tpdo_from=(1,))
    since = rig.rec.mark()
    rig.rpdo1(1, 0x80, pos)
    rig.sync(2, tpdo_from=(1,))
    assert rig.tpdo1(1)[0] & 0x4F == 0x40
    reset = rig.rec.wait(cob(0x81), since=since)[0]
    assert struct.unpack_from('<H', bytes(reset.data))[0] == 0x0000
    # software limits opened beyond the stroke: the hard end stop (440 mm) holds,
    # bit 11 internal limit active, then following error
    node.sdo[0x607D][2].raw = round(0.46 * CPM)
    node.sdo[0x6065].raw = round(0.1 * CPM)
    for cw in (0x06, 0x0F):
        rig.rpdo1(1, cw, pos)
        rig.sync(2, tpdo_from=(1,))
    rig.rpdo1(1, 0x0F, round(0.45 * CPM))
    for _ in range(600):
        rig.sync(1, tpdo_from=(1,))
        if rig.sim.truth().lengths[0] >= 0.440:
            break
    rig.sync(2, tpdo_from=(1,))
    sw, _, _ = rig.tpdo1(1)
    assert rig.sim.truth().lengths[0] == pytest.approx(0.440)
    assert sw & 0x0800, f'internal limit active expected, sw={sw:#06x}'


def test_following_error_emcy_fault_and_reset_only_when_cause_gone(rig: Rig) -> None:
    pos = enable_csp(rig, 2)
    window = rig.node(2).sdo[0x6065].raw
    assert window == round(0.003 * CPM)
    since = rig.rec.mark()
    rig.rpdo1(2, 0x0F, pos + round(0.02 * CPM))      # a 20 mm step: lag > 3 mm
    rig.sync(10, tpdo_from=(2,))
    emcy = rig.rec.wait(cob(0x82), since=since)[0]
    code, reg = struct.unpack_from('<HB', bytes(emcy.data))
    assert code == 0x8611 and reg & 0x01
    sw, actual, _ = rig.tpdo1(2)
    assert sw & 0x4F == 0x08 and sw & 0x2000
    assert rig.node(2).sdo[0x603F].raw == 0x8611
    # reset with the far target still commanded: stays in FAULT
    rig.rpdo1(2, 0x80, pos + round(0.02 * CPM))
    rig.sync(2, tpdo_from=(2,))
    assert rig.tpdo1(2)[0] & 0x4F == 0x08
    # target = actual, then a rising edge of bit 7: SWITCH ON DISABLED
    rig.rpdo1(2, 0x00, actual)
    rig.sync(1, tpdo_from=(2,))
    rig.rpdo1(2, 0x80, actual)
    rig.sync(2, tpdo_from=(2,))
    assert rig.tpdo1(2)[0] & 0x4F == 0x40


def test_quick_stop_option_6_ramps_down_and_stays(rig: Rig) -> None:
    rig.node(1).sdo[0x6065].raw = round(0.05 * CPM)
    pos = enable_csp(rig, 1)
    rig.rpdo1(1, 0x0F, pos + round(0.03 * CPM))
    rig.sync(80, tpdo_from=(1,))                          # 130 ms to full speed
    assert rig.sim.drive(1).velocity_mps == pytest.approx(0.065)
    rig.rpdo1(1, 0x02, pos + round(0.03 * CPM))          # quick stop
    rig.sync(2, tpdo_from=(1,))
    assert rig.tpdo1(1)[0] & 0x6F == 0x07                 # QUICK STOP ACTIVE
    rig.sync(40, tpdo_from=(1,))                          # 6085h = 1 m/s^2: 65 ms
    assert rig.sim.drive(1).velocity_mps == 0.0
    assert rig.tpdo1(1)[0] & 0x6F == 0x07                 # stays (option 6)


def test_master_heartbeat_loss_applies_6007h_quick_stop(rig: Rig) -> None:
    node = rig.node(3)
    node.sdo[0x1016][1].raw = (127 << 16) | 100
    hb = rig.net.send_periodic(0x77F, b'\x05', 0.02)
    enable_csp(rig, 3)
    assert not rig.sim.drive(3).master_heartbeat_lost
    since = rig.rec.mark()
    hb.stop()
    emcy = rig.rec.wait(cob(0x83), since=since, timeout=1.0)[0]
    assert struct.unpack_from('<H', bytes(emcy.data))[0] == 0x8130
    assert node.sdo[0x6041].raw & 0x6F == 0x07            # 6007h = 3: QUICK STOP ACTIVE
    hb = rig.net.send_periodic(0x77F, b'\x05', 0.02)
    wait_until(lambda: not rig.sim.drive(3).master_heartbeat_lost)
    hb.stop()


def test_the_heartbeat_consumer_outlives_an_unreadable_receive_queue(rig: Rig, monkeypatch) -> None:
    """The timer thread judges the consumers; a receive queue it cannot read (another kind
    of queue, a bug) is logged and judged as all heard, and the thread goes on: a lost
    master heartbeat is still a quick stop (in fresh-clone work a queue without python-can's
    mutex ended the thread, and with it every consumer, without a word)."""
    def unreadable(now: float) -> float:
        raise AttributeError("'RxQueue' object has no attribute 'mutex'")
    monkeypatch.setattr(rig.sim.host, '_heard_until', unreadable)
    node = rig.node(3)
    node.sdo[0x1016][1].raw = (127 << 16) | 100
    hb = rig.net.send_periodic(0x77F, b'\x05', 0.02)
    enable_csp(rig, 3)
    since = rig.rec.mark()
    hb.stop()
    emcy = rig.rec.wait(cob(0x83), since=since, timeout=1.0)[0]
    assert struct.unpack_from('<H', bytes(emcy.data))[0] == 0x8130
    assert rig.sim.host._timer.is_alive()


def _hold_the_gil(seconds: float) -> float:
    """Stall every thread of this process for about ``seconds``, as a full garbage-collector
    pass does: ``sum`` over a range runs in C and never hands the GIL over. Returns the
    measured stall (s).

    The rate is the fastest of five calibrations (one preempted by a busy host would
    overestimate the time per item and cut the stall short); a stall that still comes out
    short is redone at the rate it measured, up to three times (a shorter stall trips
    nothing, so a retry changes nothing the test looks at)."""
    n = 200_000
    per_item = float('inf')
    for _ in range(5):
        t0 = time.perf_counter()
        sum(range(n))
        per_item = min(per_item, max((time.perf_counter() - t0) / n, 1e-9))
    stalled = 0.0
    for _ in range(3):
        count = int(seconds / per_item)
        t0 = time.perf_counter()
        sum(range(count))
        stalled = time.perf_counter() - t0
        if stalled > 0.8 * seconds:
            break
        per_item = max(stalled / count, 1e-9)
    return stalled


def test_a_stall_of_the_whole_host_process_does_not_trip_the_heartbeat_consumer(rig: Rig) -> None:
    """The simulated drives live in this process: when it does not run at all (here: the GIL
    held 3x the consumer time), their clock stands still with it (sim/host.py)."""
    node = rig.node(3)
    node.sdo[0x1016][1].raw = (127 << 16) | 100           # consumer time 100 ms
    hb = rig.net.send_periodic(0x77F, b'\x05', 0.02)
    enable_csp(rig, 3)
    since = rig.rec.mark()
    stalled = _hold_the_gil(0.3)
    assert stalled > 0.2, f'the stall lasted {stalled:.3f} s; 0.3 s expected'
    rig.rec.wait(cob(0x703), since=rig.rec.mark(), count=3)   # > 100 ms after it
    hb.stop()
    assert not rig.sim.drive(3).master_heartbeat_lost
    assert not rig.rec.wait(cob(0x83), since=since, count=0), 'EMCY sent'
    assert node.sdo[0x6041].raw & 0x6F == 0x27            # still OPERATION ENABLED


def test_a_stall_in_the_middle_of_the_simulators_timer_work_is_a_stall_too(
        rig: Rig, monkeypatch: pytest.MonkeyPatch) -> None:
    """The host stands still (the GIL held 3x the consumer time) just after the simulator's
    timer thread read the clock, before it judged the deadlines: the drive's clock stood still
    with it, whenever in the timer thread's loop the stall falls (sim/host.py)."""
    node = rig.node(3)
    node.sdo[0x1016][1].raw = (127 << 16) | 100           # consumer time 100 ms
    hb = rig.net.send_periodic(0x77F, b'\x05', 0.02)
    enable_csp(rig, 3)
    drive = rig.sim.drive(3)
    armed = threading.Event()
    stalls: list[float] = []
    tick = drive.tick

    def stalling_tick(now: float, heard_until: float | None = None) -> float:
        if armed.is_set():
            armed.clear()
            stalls.append(_hold_the_gil(0.3))
        return tick(now, heard_until)

    monkeypatch.setattr(drive, 'tick', stalling_tick)
    since = rig.rec.mark()
    armed.set()
    wait_until(lambda: stalls)
    assert stalls[0] > 0.2, f'the stall lasted {stalls[0]:.3f} s; 0.3 s expected'
    rig.rec.wait(cob(0x703), since=rig.rec.mark(), count=3)   # > 100 ms after it
    hb.stop()
    assert not drive.master_heartbeat_lost
    assert not rig.rec.wait(cob(0x83), since=since, count=0), 'EMCY sent'
    assert node.sdo[0x6041].raw & 0x6F == 0x27            # still OPERATION ENABLED


def test_frames_queued_behind_a_busy_simulator_thread_are_not_silence(queued_rig: Rig) -> None:
    """The simulator's receive thread busy for 3x the consumer time (here: its SYNC handler
    sleeps 0.3 s, the GIL free, the timer thread on time) while the master's heartbeats keep
    arriving in its queue: the drive does not call that silence (sim/host.py), and a master
    that really falls silent is still caught (test above)."""
    node = queued_rig.node(3)
    node.sdo[0x1016][1].raw = (127 << 16) | 100           # consumer time 100 ms
    hb = queued_rig.net.send_periodic(0x77F, b'\x05', 0.02)
    enable_csp(queued_rig, 3)
    handler = queued_rig.sim.host.sync_handler
    busy, done = threading.Event(), threading.Event()

    def slow_sync(dt: float) -> None:
        busy.set()
        time.sleep(0.3)
        handler(dt)
        done.set()

    since = queued_rig.rec.mark()
    queued_rig.sim.host.sync_handler = slow_sync
    try:
        queued_rig.net.send_message(0x80, b'')
        assert busy.wait(1.0) and done.wait(2.0)
    finally:
        queued_rig.sim.host.sync_handler = handler
    queued_rig.rec.wait(cob(0x703), since=queued_rig.rec.mark(), count=3)
    hb.stop()
    assert not queued_rig.sim.drive(3).master_heartbeat_lost
    assert not queued_rig.rec.wait(cob(0x83), since=since, count=0), 'EMCY sent'
    assert node.sdo[0x6041].raw & 0x6F == 0x27            # still OPERATION ENABLED


def test_the_drives_answer_a_sync_before_its_send_returns_and_count_their_cpu(rig: Rig) -> None:
    """On the virtual bus the drives take a frame in its sender's thread (sim/host.py): the
    SYNC is handled, its TPDO1 queued for the master, when ``send`` returns, with no thread of
    the simulator to wake; the CPU it took is counted (``cpu_seconds``)."""
    assert rig.sim.host._notifier is None
    enable_csp(rig, 3)
    for _ in range(20):
        count, cpu = rig.sim.host.sync_count, rig.sim.cpu_seconds
        rig.net.send_message(0x80, b'')
        assert rig.sim.host.sync_count == count + 1
        assert rig.sim.cpu_seconds > cpu
    since = rig.rec.mark()
    rig.sync(1, tpdo_from=(3,))
    assert rig.rec.wait(cob(0x183), since=since)


def test_a_second_simulator_on_the_channel_receives_in_a_thread_of_its_own(rig: Rig) -> None:
    """Two simulators taking frames in the sender's thread would call into each other: the
    second one on a channel gets a receive thread, and both answer."""
    other = SimBus(rig.channel)
    other.start()
    try:
        assert rig.sim.host._notifier is None and other._notifier is not None
        count = other.sync_count
        rig.net.send_message(0x80, b'')
        wait_until(lambda: other.sync_count == count + 1)
    finally:
        other.shutdown()


# ---------------------------------------------------------------- fault injection

def test_injected_heartbeat_silence_emcy_and_error_frames(rig: Rig) -> None:
    rig.rec.wait(cob(0x702), count=2)
    rig.sim.faults.silence_heartbeat(2)
    since = rig.rec.mark()
    rig.rec.wait(cob(0x701), since=since, count=4)        # 150 ms of node 1's heartbeats
    assert not [m for m in rig.rec.frames[since + 1:] if m.arbitration_id == 0x702]
    rig.sim.faults.silence_heartbeat(2, False)
    rig.rec.wait(cob(0x702), since=since)
    # EMCY with fault: FAULT until the injected cause is cleared and reset
    since = rig.rec.mark()
    rig.sim.faults.send_emcy(1, 0x5530, b'\x01', fault=True)
    emcy = rig.rec.wait(cob(0x81), since=since)[0]
    assert bytes(emcy.data)[:4] == b'\x30\x55\x01\x01'
    node = rig.node(1)
    assert node.sdo[0x6041].raw & 0x4F == 0x08
    node.sdo[0x6040].raw = 0x80
    assert node.sdo[0x6041].raw & 0x4F == 0x08            # cause still there
    rig.sim.faults.clear_emcy_fault(1)
    node.sdo[0x6040].raw = 0x00
    node.sdo[0x6040].raw = 0x80
    assert node.sdo[0x6041].raw & 0x4F == 0x40
    assert node.sdo[0x1003][1].raw == 0x5530             # error history
    # error frames reach the master's bus (canopen ignores them; a listener sees them)
    since = rig.rec.mark()
    rig.sim.faults.error_frame('passive')
    err = rig.rec.wait(lambda m: m.is_error_frame, since=since)[0]
    assert err.arbitration_id & 0x004 and err.data[1] & 0x30


def test_bus_off_makes_the_master_send_fail_until_bus_on(rig: Rig) -> None:
    node = rig.node(1)
    assert node.sdo[0x1000].raw == 0x00020192
    since = rig.rec.mark()
    rig.sim.faults.bus_off(rig.net.bus)
    err = rig.rec.wait(lambda m: m.is_error_frame, since=since)[0]
    assert err.arbitration_id & 0x040                    # CAN_ERR_BUSOFF
    with pytest.raises(can.CanOperationError):
        rig.net.send_message(0x80, b'')
    mark = rig.rec.mark()
    with pytest.raises(TimeoutError):                    # the drives are silent (no heartbeat)
        rig.rec.wait(cob(0x701), since=mark, timeout=0.15)
    rig.sim.faults.bus_on()
    rig.rec.wait(lambda m: m.is_error_frame and m.arbitration_id & 0x100, since=mark)
    assert node.sdo[0x1000].raw == 0x00020192            # talks again


def test_encoder_freeze_jump_load_cell_saturation_and_stall(rig: Rig) -> None:
    rig.node(1).sdo[0x6065].raw = round(0.05 * CPM)
    pos = enable_csp(rig, 1)
    rig.sim.faults.jump_encoder(1, 0.001)
    rig.sync(1, tpdo_from=(1,))
    assert rig.tpdo1(1)[1] == pos + 8192
    rig.sim.faults.jump_encoder(1, 0.0)
    rig.sim.faults.freeze_encoder(1)
    rig.rpdo1(1, 0x0F, pos + round(0.005 * CPM))
    rig.sync(20, tpdo_from=(1,))
    assert rig.tpdo1(1)[1] == pos                        # frozen report ...
    assert rig.sim.truth().lengths[0] * CPM > pos + 1000   # ... of a real motion
    rig.sim.faults.freeze_encoder(1, False)
    rig.sim.faults.saturate_load_cell(1, -1)
    rig.sync(1, tpdo_from=(1,))
    assert rig.tpdo1(1)[2] == -30000                     # 300 N full scale at 0.01 N/count
    rig.sim.faults.saturate_load_cell(1, None)
    rig.sync(1, tpdo_from=(1,))
    assert abs(rig.tpdo1(1)[2]) < 30000
    # stall: the demand moves on, the actuator does not -> following error
    rig.sync(120, tpdo_from=(1,))                        # 5 mm: arrived after 0.2 s
    _, here, _ = rig.tpdo1(1)
    assert here == pos + round(0.005 * CPM)
    rig.node(1).sdo[0x6065].raw = round(0.003 * CPM)
    rig.sim.faults.stall_actuator(1)
    since = rig.rec.mark()
    rig.rpdo1(1, 0x0F, here + round(0.01 * CPM))
    rig.sync(12, tpdo_from=(1,))
    assert struct.unpack_from('<H', bytes(rig.rec.wait(cob(0x81), since=since)[0].data))[0] == 0x8611
    rig.rpdo1(1, 0x00, here)
    rig.sync(1, tpdo_from=(1,))
    rig.rpdo1(1, 0x80, here)
    rig.sync(2, tpdo_from=(1,))
    assert rig.tpdo1(1)[0] & 0x4F == 0x08                # stalled: the cause is not gone
    rig.sim.faults.stall_actuator(1, False)
    rig.rpdo1(1, 0x00, here)
    rig.sync(1, tpdo_from=(1,))
    rig.rpdo1(1, 0x80, here)
    rig.sync(2, tpdo_from=(1,))
    assert rig.tpdo1(1)[0] & 0x4F == 0x40


# ---------------------------------------------------------------- CSP servo model (frame by frame)

T_SYNC = 0.002                  # SYNC period = 1006h = 60C2h (2 x 10^-3 s), the EDS defaults
L0 = 0.390                      # the actuator's length at power-up (m)


def yaml_params() -> dict:
    return yaml.safe_load(CFG.read_text())['/**']['ros__parameters']


P = yaml_params()
V_MAX = float(P['actuator']['max_velocity'])            # 0.065 m/s
A_MAX = float(P['actuator']['max_acceleration'])        # 0.5 m/s^2
KP = 2 * math.pi * float(P['sim']['drive_bandwidth_hz'])   # 1/s
A_BRAKE = 0.9 * A_MAX                                   # braking curve (docs/can.md)
E_LIN = A_BRAKE / KP ** 2                               # m, end of the linear range


def csp_drive() -> tuple[FrameMaster, SimulatedDrive, int]:
    """One drive rated as the YAML's actuator, mapped as docs/can.md, homed at L0, in CSP."""
    limits = DriveLimits(counts_per_m=CPM, max_velocity=V_MAX, max_acceleration=A_MAX,
                         stroke_min=float(P['mechanism']['stroke_min']),
                         stroke_max=float(P['mechanism']['stroke_max']))
    drive = SimulatedDrive(1, EDS, limits=limits, initial_length_m=L0,
                           bandwidth_hz=float(P['sim']['drive_bandwidth_hz']))
    fm = FrameMaster([drive])
    mapping = lambda nid: [(w.index, w.subindex, w.fmt, w.value) for w in pdo_mapping_writes(nid)]
    pos0 = fm.enable_csp([round(L0 * CPM)], configure=mapping)[0]
    return fm, drive, pos0


def ramp(t: float, v: float, a: float) -> tuple[float, float]:
    """A ramp at ``v`` (m/s) reached at constant acceleration ``a``: position (m) and velocity
    (m/s) at ``t`` from its start (0 before)."""
    if t <= 0.0:
        return 0.0, 0.0
    if t < v / a:
        return 0.5 * a * t * t, a * t
    return v * t - v * v / (2.0 * a), v


def run_ramp(v: float, a: float, duration: float, *, feed_forward: bool, ahead: bool,
             stop_at: float = math.inf) -> list[tuple[float, int, float, float]]:
    """Feed one CSP drive the ramp ``p(t)`` (held from ``stop_at`` on) SYNC by SYNC.

    Before the SYNC at ``t_k`` the target is ``p(t_k + T)`` (``ahead``, as the master does)
    or ``p(t_k)``; with ``feed_forward`` RPDO2 carries ``p'(...)`` in counts/s.

    :returns: per SYNC ``(t_k, 6064h - start (counts), p(t_k) (counts), velocity m/s)``.
    """
    fm, drive, pos0 = csp_drive()
    t0 = fm.t + T_SYNC            # the ramp starts one SYNC after enabling: p(t <= 0) = 0

    def p(t: float) -> tuple[float, float]:
        if t > stop_at:
            return ramp(stop_at, v, a)[0], 0.0
        return ramp(t, v, a)

    out = []
    for _ in range(round(duration / T_SYNC)):
        t_sync = fm.t + T_SYNC - t0
        pk, vk = p(t_sync + (T_SYNC if ahead else 0.0))
        fm.rpdo1(1, 0x0F, pos0 + round(pk * CPM))
        if feed_forward:
            fm.rpdo2(1, round(vk * CPM))
        fm.sync(T_SYNC)
        sw, pos, _ = fm.tpdo1(1)
        assert sw & 0x6F == 0x27 and not sw & 0x2000, f'left OPERATION ENABLED: sw={sw:#06x}'
        out.append((t_sync, pos - pos0, p(t_sync)[0] * CPM, drive.velocity_mps))
    return out


def test_csp_without_feed_forward_lags_by_the_first_order_delay_and_never_stops() -> None:
    """A ramp of targets without 60B1h: lag = v (T + 1/Kp), a smooth motion.

    Derivation. The targets ``p_k = p(t_k)``, ``p(t) = v t`` (constant phase), are sent
    before SYNC ``k``; the drive latches ``p_k`` at SYNC ``k`` and its reference runs
    linearly from ``p_{k-1}`` to ``p_k`` over ``[t_k, t_k + T]`` (``T`` = 60C2h = the SYNC
    period): ``r(t) = p_{k-1} + v (t - t_k) = v (t - T)``, the target delayed by one period.
    Without feed-forward the loop is ``x' = Kp (r - x)``; substituting ``x = v (t - T) - c``
    gives ``v = Kp c``: the particular solution lags ``r`` by ``c = v / Kp``, and the rest
    decays as ``exp(-Kp t)``. So ``p(t) - x(t) -> v (T + 1/Kp)``. (Explicit Euler with
    ``x_{n+1} - x_n = h Kp e = v h`` has the same steady lag.) This holds while the loop
    error ``v / Kp`` stays in the linear range ``e_lin = 0.9 a_max / Kp^2``, i.e.
    ``v < 0.9 a_max / Kp`` = 2.4 mm/s at 30 Hz and 0.5 m/s^2: at 2 mm/s the lag is
    4.0 + 10.6 = 14.6 um = 119.7 counts; the encoder quantum adds +-1 count.

    Smoothness: the reference slope only rises (2 mm/s reached at 0.02 m/s^2), and a
    first-order loop's velocity ``v_{n+1} = v_n + Kp h (r' - v_n)`` (``Kp h < 1``) then
    only rises too; the feedback on a quantised position can lower it by at most
    ``Kp x 1 count`` when the reading steps. No stop-and-go: every SYNC moves ``v T``.
    """
    v, a = 0.002, 0.02
    assert v / KP < E_LIN                                   # the linear regime (see above)
    rows = run_ramp(v, a, 0.5, feed_forward=False, ahead=False)
    lag = v * (T_SYNC + 1.0 / KP) * CPM
    settled = [r for r in rows if r[0] > v / a + 8.0 / KP]  # transient exp(-8) of the lag
    assert len(settled) > 100
    for t, pos, p, _ in settled:
        assert abs((p - pos) - lag) <= 1.5, f't={t:.3f}: lag {p - pos:.1f} counts, expected {lag:.1f}'
    steps = [b[1] - a_[1] for a_, b in zip(settled, settled[1:])]
    assert min(steps) >= v * T_SYNC * CPM - 2 and max(steps) <= v * T_SYNC * CPM + 2
    vel = [r[3] for r in rows]
    assert all(later >= earlier - KP / CPM - 1e-12 for earlier, later in zip(vel, vel[1:]))
    assert all(r[3] > 0.0 for r in rows if r[0] > 2 * T_SYNC)   # moving once targets move


def test_csp_with_velocity_feed_forward_tracks_a_ramp_without_lag() -> None:
    """The same kind of ramp at 30 mm/s with 60B1h = p' and targets one period ahead.

    Before SYNC ``k`` the master sends ``p(t_k + T)`` and ``p'(t_k + T)``; latched at SYNC
    ``k`` the reference over ``[t_k, t_k + T]`` is ``p(t_k) + v (t - t_k) = p(t)`` (exact
    for a ramp) and the feed-forward ``v_ff = v``. The loop ``x' = v_ff + Kp (r - x)`` then
    gives ``(r - x)' = -Kp (r - x)``: the lag decays to zero, up to the encoder's
    quantum (+-1 count). Without the feed-forward the same ramp would lag by the braking
    curve of the next test (1 mm); with it, by nothing.
    """
    v, a = 0.030, 0.25
    rows = run_ramp(v, a, 0.5, feed_forward=True, ahead=True)
    settled = [r for r in rows if r[0] > v / a + 8.0 / KP]
    assert len(settled) > 100
    assert max(abs(p - pos) for _, pos, p, _ in settled) <= 2      # 0.24 um
    assert max(abs(p - pos) for _, pos, p, _ in rows) <= 8         # 1 um, also while accelerating
    assert abs(settled[-1][3] - v) <= KP / CPM


def test_csp_large_lag_follows_the_braking_curve_and_stops_without_overshoot() -> None:
    """Beyond the linear range the feedback is the braking curve: no overshoot at a stop.

    docs/can.md: for ``|e| > e_lin`` the feedback speed is ``sqrt(2 a_b (|e| - e_lin/2))``
    with ``a_b = 0.9 a_max``. A ramp at ``v`` without feed-forward settles where that
    speed equals ``v``: ``e = v^2 / (2 a_b) + e_lin / 2``, plus the period of delay of the
    previous test: at 30 mm/s, 1000 + 6.3 + 60 um. When the targets stop, the drive brakes
    along the curve at ``a_b < a_max`` and arrives at the last target without passing it
    (a pure P loop with the motor's acceleration limit would overshoot by millimetres).
    """
    v, a = 0.030, 0.25
    stop_at = 0.8                 # time constant near the curve: v / a_b = 67 ms
    rows = run_ramp(v, a, 1.2, feed_forward=False, ahead=False, stop_at=stop_at)
    lag = (v * v / (2 * A_BRAKE) + E_LIN / 2 + v * T_SYNC) * CPM
    before = [r for r in rows if stop_at - 0.1 < r[0] < stop_at]
    assert all(abs((p - pos) - lag) <= 5 for _, pos, p, _ in before), \
        [round(p - pos) for _, pos, p, _ in before[:3]] + [round(lag)]
    final = ramp(stop_at, v, a)[0] * CPM
    positions = [pos for _, pos, _, _ in rows]
    assert max(positions) <= final + 1                       # never beyond the last target
    assert abs(positions[-1] - final) <= 1                   # and there
    vel = [r[3] for r in rows if r[0] > 0.01]
    assert min(vel) >= 0.0                                    # no reversal


def test_csp_speed_and_acceleration_stay_within_the_actuator_limits() -> None:
    """A demand faster than the actuator (100 mm/s reached at 2 m/s^2, with feed-forward):
    the motor follows at most ``max_velocity`` and ``max_acceleration`` of the YAML, and
    reaches them (a wide following-error window keeps it enabled)."""
    fm, drive, pos0 = csp_drive()
    fm.sdo_write(1, 0x6065, 0, 'I', round(0.05 * CPM))
    vel = [0.0]
    t0 = fm.t
    for _ in range(150):
        t_next = fm.t + 2 * T_SYNC - t0
        p, v = ramp(t_next, 0.1, 2.0)
        fm.rpdo1(1, 0x0F, pos0 + round(p * CPM))
        fm.rpdo2(1, round(v * CPM))
        fm.sync(T_SYNC)
        vel.append(drive.velocity_mps)
    assert max(abs(x) for x in vel) <= V_MAX + 1e-12
    assert max(vel) == pytest.approx(V_MAX)
    acc = [(b - a) / T_SYNC for a, b in zip(vel, vel[1:])]
    assert max(abs(x) for x in acc) <= A_MAX * (1 + 1e-9)
    assert max(acc) == pytest.approx(A_MAX)


def test_position_demand_interpolates_over_60c2h_and_holds_after_a_late_sync() -> None:
    """6062h (position demand) at SYNC instants: CiA 402 CSP linear interpolation from the
    previous target to the new one over 60C2h; a late SYNC finds it at the new target."""
    fm, drive, pos0 = csp_drive()
    fm.sdo_write(1, 0x6065, 0, 'I', round(0.05 * CPM))
    fm.sdo_write(1, 0x60C2, 1, 'B', 4)                       # 4 x 10^-3 s: two SYNC periods
    fm.rpdo1(1, 0x0F, pos0 + 1000)
    fm.sync(T_SYNC)                                          # latched; segment starts here
    assert drive.read_od(0x6062) == pos0
    fm.sync(T_SYNC)
    assert drive.read_od(0x6062) == pytest.approx(pos0 + 500, abs=1)   # half-way at 2 of 4 ms
    fm.sync(T_SYNC)
    assert drive.read_od(0x6062) == pos0 + 1000
    fm.rpdo1(1, 0x0F, pos0 + 3000)
    fm.sync(T_SYNC)
    fm.sync(4 * T_SYNC)                                      # a late SYNC, 8 ms after
    assert drive.read_od(0x6062) == pos0 + 3000


def test_rpdo2_is_decoded_by_its_mapping_and_acts_at_sync() -> None:
    """RPDO2 (0x300 + id) carries 60B1h by the mapping of docs/can.md; the value latches at
    the next SYNC (CiA 301 synchronous RPDO). Re-mapped to 607Ah it sets the target."""
    fm, drive, pos0 = csp_drive()
    assert drive.read_od(0x1601, 1) == 0x60B10020 and drive.read_od(0x1601, 0) == 1
    assert drive.read_od(0x1401, 1) == 0x301 and drive.read_od(0x1401, 2) == 1
    fm.rpdo2(1, 12345)
    assert drive.read_od(0x60B1) == 0
    fm.sync(T_SYNC)
    assert drive.read_od(0x60B1) == 12345
    fm.rpdo2(1, 0)
    fm.sync(T_SYNC)
    for index, sub, fmt, value in ((0x1401, 1, 'I', 0x80000301), (0x1601, 0, 'B', 0),
                                   (0x1601, 1, 'I', 0x607A0020), (0x1601, 0, 'B', 1),
                                   (0x1401, 1, 'I', 0x301)):
        fm.sdo_write(1, index, sub, fmt, value)
    fm.rpdo2(1, pos0 + 77)
    fm.sync(T_SYNC)
    assert drive.read_od(0x607A) == pos0 + 77 and drive.read_od(0x60B1) == 0


def test_entering_operation_enabled_takes_the_actual_position_not_a_stale_target() -> None:
    """607Ah and 60B1h left far from the actual position while disabled: enabling neither
    jumps nor drifts (the reference starts at the actual position, zero feed-forward)."""
    fm, drive, pos0 = csp_drive()
    fm.sdo_write(1, 0x6040, 0, 'H', 0x07)                    # SWITCHED ON (transition 5)
    fm.sdo_write(1, 0x607A, 0, 'i', pos0 + round(0.01 * CPM))
    fm.sdo_write(1, 0x60B1, 0, 'i', round(0.02 * CPM))
    fm.sdo_write(1, 0x6040, 0, 'H', 0x0F)                    # OPERATION ENABLED (4)
    assert drive.read_od(0x607A) == pos0 and drive.read_od(0x60B1) == 0
    for _ in range(50):
        fm.sync(T_SYNC)
    sw, pos, _ = fm.tpdo1(1)
    assert sw & 0x6F == 0x27 and pos == pos0 and drive.velocity_mps == 0.0
