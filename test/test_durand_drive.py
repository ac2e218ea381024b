"""The durand CiA 402 drive (``test/durand_drive.py``) on its own, driven by canopen's generic
master pieces (``canopen.Network``, ``BaseNode402``, its SDO client, PDO maps and SYNC
producer), not by our BraceMaster.

Oracles come from the standards, not from the drive's code: CiA 301 (boot-up ``0x700+id:
00``, heartbeats at 1017h, mapping entry layout ``index << 16 | sub << 8 | bits``, SDO
abort codes, a synchronous RPDO acts at the next SYNC, EMCY ``0x80+id``, error reset
0000h) and CiA 402-2 (statusword masks of each state, controlword commands, fault reset on
the rising edge of bit 7, quick stop option 605Ah, homing statusword bits 13/12/10,
device type 0x00020192, supported drive modes bits 5 and 7). Each test has its own
virtual channel; waits poll a condition with a time limit.
"""
from __future__ import annotations

import itertools
import os
import statistics
import struct
import threading
import time

import can
import canopen
import pytest
from canopen.objectdictionary.eds import import_from_node
from canopen.sdo import SdoAbortedError

from durand_drive import DurandDrive

_ids = itertools.count()
CPM = 8192 / 0.001                        # counts per metre (the drive's default)

# CiA 402-2 table 30: statusword (mask, value) of each state
SW = {
    'SWITCH ON DISABLED': (0x4F, 0x40),
    'READY TO SWITCH ON': (0x6F, 0x21),
    'SWITCHED ON': (0x6F, 0x23),
    'OPERATION ENABLED': (0x6F, 0x27),
    'QUICK STOP ACTIVE': (0x6F, 0x07),
    'FAULT': (0x4F, 0x08),
}
REMOTE = 1 << 9
TARGET_REACHED = 1 << 10
OP_12 = 1 << 12                          # CSP: drive follows the command; homing: attained
OP_13 = 1 << 13                          # homing: error
HOMING_BITS = 0x3400                     # bits 13, 12, 10


def in_state(sw: int, state: str) -> bool:
    mask, value = SW[state]
    return sw & mask == value


def wait_for(cond, timeout, what='condition', *, poll=0.002):
    """Seconds until ``cond()`` holds; fails the test after ``timeout``."""
    t0 = time.perf_counter()
    while not cond():
        if time.perf_counter() - t0 > timeout:
            pytest.fail(f'{what} not reached within {timeout:.3f} s')
        time.sleep(poll)
    return time.perf_counter() - t0


class Frames(can.Listener):
    """Every frame on the bus (bus timestamp, COB-ID, data), for CiA 301 checks."""

    def __init__(self):
        self.lock = threading.Lock()
        self.frames: list[tuple[float, int, bytes]] = []

    def on_message_received(self, msg):
        with self.lock:
            self.frames.append((msg.timestamp, msg.arbitration_id, bytes(msg.data)))

    def of(self, cob_id):
        with self.lock:
            return [(t, d) for t, c, d in self.frames if c == cob_id]

    def stop(self):
        pass


class Bench:
    """A canopen master network on a fresh virtual channel, and the drives on it."""

    def __init__(self, tmp_path):
        self.channel = f'durand-{os.getpid()}-{next(_ids)}'
        self.tmp_path = tmp_path
        # a passive tap: sees the frames of both the master and the drives
        self.frames = Frames()
        self.tap = can.Bus(interface='virtual', channel=self.channel)
        self.tap_notifier = can.Notifier(self.tap, [self.frames], timeout=0.02)
        self.net = canopen.Network()
        self.net.NOTIFIER_CYCLE = 0.02          # disconnect without waiting a 1 s poll
        self.net.connect(interface='virtual', channel=self.channel)
        self.drives: list[DurandDrive] = []

    def drive(self, node_id=1, *, start=True, **options):
        """A DurandDrive and a canopen BaseNode402 for it, built from the drive's own EDS."""
        drive = DurandDrive(self.channel, node_id, **options)
        self.drives.append(drive)
        eds = drive.write_eds(self.tmp_path / f'drive{node_id}-{next(_ids)}.eds')
        node = canopen.BaseNode402(node_id, str(eds))
        self.net.add_node(node)
        if start:
            drive.start()
            wait_for(lambda: self.frames.of(0x700 + node_id), 2.0, 'boot-up')
        return drive, node

    def close(self):
        for d in self.drives:
            d.stop()
        self.net.sync.stop()
        self.net.disconnect()
        self.tap_notifier.stop()
        self.tap.shutdown()


@pytest.fixture
def bench(tmp_path):
    b = Bench(tmp_path)
    try:
        yield b
    finally:
        b.close()


def emcy_codes(node):
    """EMCY codes received from the node (CiA 301), oldest first."""
    return [e.code for e in list(node.emcy.log)]


def enable_by_sdo(node, *, mode=8):
    node.sdo[0x6060].raw = mode
    for cw in (0x06, 0x07, 0x0F):            # shutdown, switch on, enable operation
        node.sdo[0x6040].raw = cw
    assert in_state(node.sdo[0x6041].raw, 'OPERATION ENABLED')


def map_pdos(node, *, load_cell=(0x2100, 1)):
    """TPDO1 = statusword + position actual + load cell, RPDO1 = controlword + target,
    transmission type 1, through canopen's PDO API (SDO writes of 1400h/1600h/1800h/1A00h)."""
    node.tpdo.read()
    node.rpdo.read()
    tpdo = node.tpdo[1]
    tpdo.clear()
    tpdo.add_variable(0x6041)
    tpdo.add_variable(0x6064)
    tpdo.add_variable(*load_cell)
    tpdo.trans_type = 1
    tpdo.enabled = True
    rpdo = node.rpdo[1]
    rpdo.clear()
    rpdo.add_variable(0x6040)
    rpdo.add_variable(0x607A)
    rpdo.trans_type = 1
    rpdo.enabled = True
    for n in (2, 3, 4):
        node.tpdo[n].enabled = False
        node.rpdo[n].enabled = False
    node.tpdo.save()
    node.rpdo.save()
    return tpdo, rpdo


def sync_and_wait(net, tpdo, timeout=1.0):
    """One SYNC; the TPDO it answers (CiA 301: synchronous TPDOs go out on SYNC)."""
    net.sync.transmit()
    assert tpdo.wait_for_reception(timeout) is not None, 'no TPDO answered the SYNC'


# ---------------------------------------------------------------------------- CiA 301

def test_boot_up_first_then_heartbeats_at_the_producer_time(bench):
    drive, node = bench.drive(5, heartbeat_ms=25)
    wait_for(lambda: len(bench.frames.of(0x705)) >= 6, 2.0, 'five heartbeats')
    frames = bench.frames.of(0x705)
    assert frames[0][1] == b'\x00'                          # boot-up message
    assert {d for _, d in frames[1:]} == {b'\x7f'}          # heartbeats: PRE-OPERATIONAL
    gaps = [b[0] - a[0] for a, b in zip(frames[1:], frames[2:])]
    assert 0.015 < statistics.median(gaps) < 0.060
    # 1017h written by SDO: the producer follows it
    node.sdo[0x1017].raw = 10
    n0 = len(bench.frames.of(0x705))
    wait_for(lambda: len(bench.frames.of(0x705)) >= n0 + 12, 2.0, 'heartbeats at 10 ms')
    later = bench.frames.of(0x705)[n0 + 1:]
    gaps = [b[0] - a[0] for a, b in zip(later, later[1:])]
    assert 0.005 < statistics.median(gaps) < 0.030
    # NMT start: the heartbeat carries OPERATIONAL (05h)
    node.nmt.send_command(0x01)
    wait_for(lambda: bench.frames.of(0x705)[-1][1] == b'\x05', 1.0, 'heartbeat OPERATIONAL')


def test_sdo_reads_the_cia402_identity_and_aborts_per_cia301(bench):
    drive, node = bench.drive(2)
    assert node.sdo.upload(0x1000, 0) == struct.pack('<I', 0x00020192)   # servo drive, profile 402
    modes = node.sdo[0x6502].raw
    assert modes & (1 << 7) and modes & (1 << 5)                          # csp, homing
    assert node.sdo[0x60C2][1].raw == 1 and node.sdo[0x60C2][2].raw == -3
    node.sdo[0x60C2][1].raw = 2
    assert node.sdo[0x60C2][1].raw == 2
    with pytest.raises(SdoAbortedError) as exc:
        node.sdo[0x6041].raw = 0x1234                         # read-only
    assert exc.value.code == 0x06010002
    with pytest.raises(SdoAbortedError) as exc:
        node.sdo.upload(0x6071, 0)                            # not in the dictionary
    assert exc.value.code == 0x06020000
    with pytest.raises(SdoAbortedError) as exc:
        node.sdo.upload(0x607D, 7)                            # no such sub-index
    assert exc.value.code == 0x06090011
    with pytest.raises(SdoAbortedError) as exc:
        node.sdo[0x6060].raw = 3                              # profile velocity: not supported
    assert exc.value.code == 0x06090030
    with pytest.raises(SdoAbortedError) as exc:
        node.sdo.download(0x6040, 0, b'\x06\x00\x00\x00')     # 4 bytes into a U16
    assert exc.value.code == 0x06070010


def test_eds_export_reads_back_in_canopen_with_access_and_mapping(bench, tmp_path):
    drive = DurandDrive(bench.channel, 4)                   # not started: the EDS needs no bus
    od = canopen.import_od(str(drive.write_eds(tmp_path / 'd.eds')), 4)
    expect = {   # index: (access, PDO-mappable) -- CiA 402-2 object descriptions
        0x6040: ('rw', True), 0x6041: ('ro', True), 0x6060: ('rw', True), 0x6061: ('ro', True),
        0x6064: ('ro', True), 0x607A: ('rw', True), 0x60B1: ('rw', True), 0x607C: ('rw', False),
        0x6098: ('rw', False), 0x6502: ('ro', False), 0x6065: ('rw', False),
        0x605A: ('rw', False), 0x6007: ('rw', False), 0x1006: ('rw', False),
        0x607F: ('rw', False), 0x6083: ('rw', False), 0x6084: ('rw', False),
        0x6085: ('rw', False), 0x1017: ('rw', False), 0x1000: ('ro', False),
    }
    for index, (access, mappable) in expect.items():
        var = od[index]
        assert (var.access_type, var.pdo_mappable) == (access, mappable), f'{index:04X}h'
    assert od[0x1000].default == 0x00020192
    assert od[0x6502].default & 0xA0 == 0xA0
    assert od[0x2100][1].access_type == 'ro' and od[0x2100][1].pdo_mappable
    assert od[0x2100][1].data_type == canopen.objectdictionary.INTEGER16
    assert isinstance(od[0x60C2], canopen.objectdictionary.ODRecord)       # RECORD
    assert od[0x60C2][1].data_type == canopen.objectdictionary.UNSIGNED8
    assert od[0x60C2][2].data_type == canopen.objectdictionary.INTEGER8
    assert isinstance(od[0x607D], canopen.objectdictionary.ODRecord)
    assert od[0x607D][1].data_type == od[0x607D][2].data_type == canopen.objectdictionary.INTEGER32
    assert isinstance(od[0x1016], canopen.objectdictionary.ODArray)        # ARRAY
    assert isinstance(od[0x1A00], canopen.objectdictionary.ODRecord)       # CiA 301: RECORD
    assert od[0x1800][1].default == 0x180 + 4                              # $NodeID+0x180
    # options: objects left out, the load cell elsewhere
    other = DurandDrive(bench.channel, 4, without=(0x60B1, 0x1006), load_cell='0x2401:0')
    od2 = canopen.import_od(str(other.write_eds(tmp_path / 'e.eds')), 4)
    assert 0x60B1 not in od2 and 0x1006 not in od2 and 0x2100 not in od2
    assert od2[0x2401].pdo_mappable and od2[0x2401].access_type == 'ro'
    with pytest.raises(ValueError):
        DurandDrive(bench.channel, 4, without=(0x6041,))


def test_the_drive_serves_its_eds_at_1021h(bench):
    """1021h (Store EDS, CiA 301) serves the fixed EDS, not durand's raw export (which calls
    every object from 2000h on mappable and none below)."""
    drive, node = bench.drive(10)
    od = import_from_node(10, bench.net)                      # canopen reads 1021h by SDO
    assert od is not None
    assert od[0x6041].pdo_mappable and od[0x6041].access_type == 'ro'
    assert not od[0x607C].pdo_mappable and not od[0x6502].pdo_mappable
    assert isinstance(od[0x1A00], canopen.objectdictionary.ODRecord)


def test_left_out_objects_are_absent_on_the_bus(bench):
    drive, node = bench.drive(3, without=(0x60B1, 0x1006), load_cell=(0x2401, 0))
    for index in (0x60B1, 0x1006, 0x2100):
        with pytest.raises(SdoAbortedError) as exc:
            node.sdo.upload(index, 0)
        assert exc.value.code == 0x06020000
    drive.set_spring(stiffness=1000.0, rest_position_m=0.0, n_per_count=0.01)
    drive.position_m = 0.002                                # 2 N spring force: 200 counts
    assert struct.unpack('<h', node.sdo.upload(0x2401, 0))[0] == 200


# ---------------------------------------------------------------------------- CiA 402 by SDO

def test_basenode402_walks_the_state_machine_by_sdo(bench):
    drive, node = bench.drive(1)
    assert in_state(node.sdo[0x6041].raw, 'SWITCH ON DISABLED')
    node.sdo[0x6060].raw = 8
    assert node.sdo[0x6061].raw == 8                         # display follows at once
    node.state = 'OPERATION ENABLED'                          # canopen: 06h, 07h, 0Fh
    sw = node.sdo[0x6041].raw
    assert in_state(sw, 'OPERATION ENABLED') and sw & REMOTE and sw & OP_12
    assert node.state == 'OPERATION ENABLED'
    node.state = 'SWITCHED ON'                               # disable operation (5)
    assert in_state(node.sdo[0x6041].raw, 'SWITCHED ON')
    node.state = 'READY TO SWITCH ON'                        # shutdown (6)
    assert in_state(node.sdo[0x6041].raw, 'READY TO SWITCH ON')
    node.sdo[0x6040].raw = 0x0F                              # switch on + enable operation (3+4)
    assert in_state(node.sdo[0x6041].raw, 'OPERATION ENABLED')
    node.sdo[0x6040].raw = 0x06                              # shutdown from OE (8)
    assert in_state(node.sdo[0x6041].raw, 'READY TO SWITCH ON')
    node.sdo[0x6040].raw = 0x00                              # disable voltage (7)
    assert in_state(node.sdo[0x6041].raw, 'SWITCH ON DISABLED')
    node.sdo[0x6040].raw = 0x07                              # switch on from SOD: no transition
    assert in_state(node.sdo[0x6041].raw, 'SWITCH ON DISABLED')


def test_quick_stop_per_option_code(bench):
    drive, node = bench.drive(1)
    # 605Ah = 6: slow down on the quick stop ramp and stay in QUICK STOP ACTIVE
    node.sdo[0x605A].raw = 6
    enable_by_sdo(node)
    node.sdo[0x6040].raw = 0x02                              # quick stop (11)
    assert in_state(node.sdo[0x6041].raw, 'QUICK STOP ACTIVE')
    node.sdo[0x6040].raw = 0x0F                              # enable operation (16)
    assert in_state(node.sdo[0x6041].raw, 'OPERATION ENABLED')
    node.sdo[0x6040].raw = 0x02
    node.sdo[0x6040].raw = 0x00                              # disable voltage (12)
    assert in_state(node.sdo[0x6041].raw, 'SWITCH ON DISABLED')
    # 605Ah = 2: ramp, then SWITCH ON DISABLED on its own
    node.sdo[0x605A].raw = 2
    enable_by_sdo(node)
    node.sdo[0x6040].raw = 0x02
    assert in_state(node.sdo[0x6041].raw, 'SWITCH ON DISABLED')


def test_fault_reset_needs_the_rising_edge_of_bit_7_and_the_cause_gone(bench):
    drive, node = bench.drive(6)
    node.nmt.send_command(0x01)                              # EMCY needs PRE-OP or OPERATIONAL
    enable_by_sdo(node)
    drive.inject_fault(0x2310)                               # continuous over-current
    wait_for(lambda: emcy_codes(node).count(0x2310) == 1, 1.0, 'EMCY 2310h')
    assert node.emcy.active[-1].register & 0x01              # generic error
    assert in_state(node.sdo[0x6041].raw, 'FAULT')
    assert node.sdo[0x603F].raw == 0x2310
    node.sdo[0x6040].raw = 0x80                              # reset while the cause is there
    assert in_state(node.sdo[0x6041].raw, 'FAULT')
    drive.clear_fault()
    node.sdo[0x6040].raw = 0x80                              # bit 7 still high: no edge
    assert in_state(node.sdo[0x6041].raw, 'FAULT')
    node.sdo[0x6040].raw = 0x0F                              # no command leaves FAULT
    assert in_state(node.sdo[0x6041].raw, 'FAULT')
    node.sdo[0x6040].raw = 0x80                              # rising edge (15)
    assert in_state(node.sdo[0x6041].raw, 'SWITCH ON DISABLED')
    wait_for(lambda: emcy_codes(node)[-1:] == [0x0000], 1.0, 'EMCY 0000h (error reset)')
    assert not node.emcy.active


def test_homing_method_35_sets_the_position_to_the_home_offset(bench):
    drive, node = bench.drive(7, position_m=0.25)
    assert node.sdo[0x6064].raw == 0                         # incremental encoder at power-up
    node.sdo[0x6098].raw = 35
    node.sdo[0x607C].raw = 3_000_000
    enable_by_sdo(node, mode=6)
    assert node.sdo[0x6061].raw == 6
    assert node.sdo[0x6041].raw & HOMING_BITS == 0x0400     # not started
    node.sdo[0x6040].raw = 0x1F                              # bit 4 rising edge: start
    sw = node.sdo[0x6041].raw
    assert sw & HOMING_BITS == 0x1400                        # attained, target reached
    assert in_state(sw, 'OPERATION ENABLED')
    assert node.sdo[0x6064].raw == 3_000_000
    assert drive.position_m == pytest.approx(0.25)           # nothing moved
    # an unsupported method: homing error (bit 13)
    node.sdo[0x6040].raw = 0x0F
    node.sdo[0x6060].raw = 8
    node.sdo[0x6098].raw = 1
    node.sdo[0x6060].raw = 6
    node.sdo[0x6040].raw = 0x1F
    assert node.sdo[0x6041].raw & OP_13


def test_master_heartbeat_loss_applies_the_abort_connection_option(bench):
    drive, node = bench.drive(8)
    node.nmt.send_command(0x01)
    node.sdo[0x6007].raw = 3                                  # quick stop
    node.sdo[0x605A].raw = 6
    node.sdo[0x1016][1].raw = (127 << 16) | 150               # master 127, 150 ms
    enable_by_sdo(node)
    beat = can.Message(arbitration_id=0x77F, data=b'\x05', is_extended_id=False)
    task = bench.net.bus.send_periodic(beat, 0.015)
    try:
        time.sleep(0.3)                    # the heartbeat runs: nothing may happen meanwhile
        assert in_state(node.sdo[0x6041].raw, 'OPERATION ENABLED')
    finally:
        task.stop()
    wait_for(lambda: 0x8130 in emcy_codes(node), 1.0, 'EMCY 8130h')   # heartbeat error
    wait_for(lambda: in_state(drive.statusword, 'QUICK STOP ACTIVE'), 1.0, 'QUICK STOP ACTIVE')
    assert node.sdo[0x6041].raw & (1 << 7)                    # warning while the master is gone


# ---------------------------------------------------------------------------- PDOs and SYNC

def test_pdo_mapping_through_canopen_pdo_api(bench):
    drive, node = bench.drive(9)
    tpdo, rpdo = map_pdos(node)
    # CiA 301 mapping entries: index << 16 | sub << 8 | length in bits
    assert [node.sdo[0x1A00][i].raw for i in range(4)] == [3, 0x60410010, 0x60640020, 0x21000110]
    assert [node.sdo[0x1600][i].raw for i in range(3)] == [2, 0x60400010, 0x607A0020]
    assert node.sdo[0x1800][2].raw == 1 and node.sdo[0x1400][2].raw == 1
    assert node.sdo[0x1801][1].raw & 0x80000000                 # TPDO2 invalid
    # pre-operational: no PDOs on SYNC (CiA 301)
    bench.net.sync.transmit()
    assert tpdo.wait_for_reception(0.1) is None
    node.nmt.send_command(0x01)
    sync_and_wait(bench.net, tpdo)
    assert in_state(tpdo['Statusword'].raw, 'SWITCH ON DISABLED')
    assert tpdo[1].raw == 0                                    # position actual
    # canopen's own re-read of the mapping agrees
    node.tpdo.read()
    assert [(v.index, v.subindex) for v in node.tpdo[1]] == [(0x6041, 0), (0x6064, 0), (0x2100, 1)]


def test_synchronous_rpdo_acts_at_the_next_sync(bench):
    drive, node = bench.drive(10)
    tpdo, rpdo = map_pdos(node)
    node.sdo[0x6060].raw = 8
    node.nmt.send_command(0x01)
    sync_and_wait(bench.net, tpdo)
    rpdo['Controlword'].raw = 0x06
    rpdo.transmit()
    wait_for(lambda: bench.frames.of(0x200 + 10), 1.0, 'RPDO1 on the bus')
    time.sleep(0.05)                      # no SYNC yet: the RPDO must wait for one
    assert in_state(node.sdo[0x6041].raw, 'SWITCH ON DISABLED')
    sync_and_wait(bench.net, tpdo)
    assert in_state(node.sdo[0x6041].raw, 'READY TO SWITCH ON')


def test_basenode402_enables_by_pdo_and_sync_moves_toward_the_target(bench):
    k, n_per_count = 2000.0, 0.01                              # N/m, N per count
    drive, node = bench.drive(11, stiffness=k, rest_position_m=0.0, n_per_count=n_per_count)
    tpdo, rpdo = map_pdos(node)
    node.sdo[0x6060].raw = 8
    node.sdo[0x1006].raw = 2000                                # SYNC period 2 ms
    v_max = 100_000                                            # counts/s
    node.sdo[0x607F].raw = v_max
    node.setup_402_state_machine(read_pdos=False)
    node.nmt.send_command(0x01)
    bench.net.sync.start(0.004)
    rpdo.start(0.004)
    try:
        node.state = 'OPERATION ENABLED'                       # canopen drives it by RPDO1
        assert in_state(node.statusword, 'OPERATION ENABLED')
    finally:
        bench.net.sync.stop()
    rpdo.stop()
    assert node.sdo[0x607A].raw == 0                           # target = actual on enable
    # one SYNC at a time: each TPDO answers its SYNC
    target = 6000
    rpdo['Target position'].raw = target
    rpdo['Controlword'].raw = 0x0F
    rpdo.transmit()
    wait_for(lambda: bench.frames.of(0x200 + 11)[-1:] and
             bench.frames.of(0x200 + 11)[-1][1] == struct.pack('<Hi', 0x0F, target), 1.0,
             'RPDO1 with the target')
    positions = []
    for _ in range(80):
        sync_and_wait(bench.net, tpdo)
        positions.append(tpdo[1].raw)
        sw, x, load = tpdo[0].raw, tpdo[1].raw, tpdo[2].raw
        assert in_state(sw, 'OPERATION ENABLED') and sw & OP_12      # CSP: drive follows
        assert load == round(k * (x / CPM) / n_per_count)           # spring force, counts
    steps = [b - a for a, b in zip([0] + positions, positions)]
    assert all(s >= 0 for s in steps)                          # toward the target, no overshoot
    assert max(steps) <= v_max * 0.002 + 1                     # 607Fh: at most 200 counts / SYNC
    assert positions[10] > 1000                                # it moves at once
    assert abs(positions[-1] - target) <= 1
    assert positions[-1] <= target
    assert tpdo[0].raw & TARGET_REACHED                        # within 6065h
    assert drive.position_m == pytest.approx(target / CPM, abs=2 / CPM)
    assert tpdo[2].raw * n_per_count == pytest.approx(k * target / CPM, abs=n_per_count)


# ---------------------------------------------------------------------------- mapping refused

def test_drive_rejecting_a_mapping_its_eds_calls_mappable(bench):
    drive, node = bench.drive(12, reject_mapping=[0x607A])
    assert node.object_dictionary[0x607A].pdo_mappable        # the EDS says: mappable
    assert DurandDrive.REJECT_ABORT_CODE == 0x08000020       # durand: cannot transfer / store
    node.rpdo.read()
    rpdo = node.rpdo[1]
    rpdo.clear()
    rpdo.add_variable(0x6040)
    rpdo.add_variable(0x607A)
    rpdo.trans_type = 1
    rpdo.enabled = True
    with pytest.raises(SdoAbortedError) as exc:
        rpdo.save()
    assert exc.value.code == drive.reject_abort_code == 0x08000020
    assert node.sdo[0x1600][2].raw == 0                        # the entry was not stored
    node.sdo[0x1600][1].raw = 0x60400010                       # other objects still map
    # another code on request: durand sends the SDODomainAbort's own code
    other, node2 = bench.drive(13, reject_mapping=[(0x6064, 0)], reject_abort_code=0x06040041)
    with pytest.raises(SdoAbortedError) as exc:
        node2.sdo[0x1A00][1].raw = 0x60640020
    assert exc.value.code == 0x06040041


def test_strict_mapping_refuses_what_a_drive_cannot_map(bench):
    drive, node = bench.drive(14)
    cases = [
        (0x1A00, 1, 0x607C0020, 0x06040041),                   # home offset: not mappable
        (0x1600, 1, 0x60410010, 0x06040041),                   # statusword into an RPDO (ro)
        (0x1600, 1, 0x60400020, 0x06040041),                   # wrong length
        (0x1A00, 1, 0x60710010, 0x06020000),                   # no such object
    ]
    for index, sub, entry, code in cases:
        with pytest.raises(SdoAbortedError) as exc:
            node.sdo[index][sub].raw = entry
        assert exc.value.code == code, f'{entry:08X}h'
    node.sdo[0x1A00][0].raw = 0
    for sub, entry in enumerate((0x60640020, 0x60640020, 0x60410010), start=1):
        node.sdo[0x1A00][sub].raw = entry
    with pytest.raises(SdoAbortedError) as exc:
        node.sdo[0x1A00][0].raw = 3                           # 80 bits > 64
    assert exc.value.code == 0x06040042


# ---------------------------------------------------------------------------- lifecycle

def test_start_stop_are_idempotent_and_a_restart_boots_again(bench):
    drive, node = bench.drive(15, position_m=0.1)
    drive.start()                                              # again: nothing new
    node.sdo[0x6098].raw = 35
    node.sdo[0x607C].raw = 800_000
    enable_by_sdo(node, mode=6)
    node.sdo[0x6040].raw = 0x1F
    assert node.sdo[0x6064].raw == 800_000
    time.sleep(0.05)
    assert [d for _, d in bench.frames.of(0x70F)].count(b'\x00') == 1
    # NMT reset node: the application restarts (incremental encoder, SWITCH ON DISABLED)
    node.nmt.send_command(0x81)
    wait_for(lambda: [d for _, d in bench.frames.of(0x70F)].count(b'\x00') == 2, 1.0, 'boot-up')
    assert node.sdo[0x6064].raw == 0
    assert in_state(node.sdo[0x6041].raw, 'SWITCH ON DISABLED')
    drive.stop()
    drive.stop()
    assert not drive.running
    n = len(bench.frames.of(0x70F))
    time.sleep(0.15)                                           # three heartbeat periods
    assert len(bench.frames.of(0x70F)) == n                    # silent when off
    drive.start()
    wait_for(lambda: [d for _, d in bench.frames.of(0x70F)].count(b'\x00') == 3, 1.0, 'boot-up')
    assert node.sdo[0x6064].raw == 0 and drive.position_m == pytest.approx(0.1)


def test_two_drives_share_a_bus_and_the_api_is_thread_safe(bench):
    (d1, n1), (d2, n2) = bench.drive(1), bench.drive(2)
    for node in (n1, n2):
        node.sdo[0x1006].raw = 2000
        enable_by_sdo(node)
        node.sdo[0x607A].raw = 4000
    stop = threading.Event()
    errors = []

    def reader():
        while not stop.is_set():
            try:
                for d in (d1, d2):
                    _ = (d.position_m, d.statusword, d.load_cell_counts, d.state)
            except Exception as exc:  # noqa: BLE001
                errors.append(exc)

    t = threading.Thread(target=reader)
    t.start()
    try:
        for _ in range(60):
            bench.net.sync.transmit()
            time.sleep(0.001)                                 # paces the SYNCs
        wait_for(lambda: d1.sync_count >= 60 and d2.sync_count >= 60, 2.0, '60 SYNCs each')
    finally:
        stop.set()
        t.join()
    assert not errors
    assert n1.sdo[0x6064].raw == n2.sdo[0x6064].raw == 4000
