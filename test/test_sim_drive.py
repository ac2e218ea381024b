"""The simulated CiA 402 drive as any master sees it: canopen's own master side on the bus.

Virtual bus, a unique channel per test, no fixed sleeps: SYNCs are sent one at a time by
the test (the simulated time step is 1006h, 2 ms by default) and every wait is on a
condition with a timeout. Oracles: CiA 301/402 and docs/can.md, not the simulator.
"""
from __future__ import annotations

import copy

import itertools
import os
import struct
import threading
import time
from collections.abc import Callable
from pathlib import Path

import can
import canopen
import pytest

from brace_control.config import DeviceConfig, load_device_config
from brace_control.sim import SimulatedBrace

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

    def __init__(self, name: str) -> None:
        self.channel = f'simtest-{os.getpid()}-{next(_ids)}-{name}'
        self.net = canopen.Network()
        self.net.connect(interface='virtual', channel=self.channel)
        self.rec = Recorder()
        self.net.notifier.add_listener(self.rec)
        # the drive exactly as the YAML's actuator rates it: these tests check the drive's
        # own acceleration limit (the simulator's default motors are 10x faster)
        params = copy.deepcopy(dict(load_device_config(CFG)))
        params['sim']['drive_acceleration_factor'] = 1.0
        self.sim = SimulatedBrace(DeviceConfig(params, CFG.resolve()), channel=self.channel)
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
    rig.net.send_message(0, b'\x82\x01')
    assert bytes(rig.rec.wait(cob(0x701), since=since)[0].data) == b'\x00'
    assert node.sdo[0x1800][2].raw == 1
    # reset node: the application restarts, the incremental encoder reads 0 again
    since = rig.rec.mark()
    rig.net.send_message(0, b'\x81\x00')         # all nodes
    for nid in (1, 2, 3):
        assert bytes(rig.rec.wait(cob(0x700 + nid), since=since)[0].data) == b'\x00'
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
    t2 = [m for m in rig.rec.frames[since:] if m.arbitration_id == 0x282]
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
    for _ in range(250):
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
