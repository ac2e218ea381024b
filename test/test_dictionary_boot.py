"""The boot planned against drives' own dictionaries, and the simulated drives answering as them.

Issue 23: the vendors' EDS files in ``test/data/eds/`` (provenance in its README). The
oracle is the dictionary file as ``canopen.import_od`` reads it, looked up here by hand
(never through our planner or :class:`~brace_control.can.dictionary.Dictionary`), the CiA
301 abort codes, and the simulator's ground truth; never the plan itself.
"""
from __future__ import annotations

import configparser
import contextlib
import copy
import itertools
import re
import os
import struct
import time
from pathlib import Path

import can
import canopen
import numpy as np
import pytest
from canopen import objectdictionary as od

from brace_control.can import (ActuatorTrajectory, BraceMaster, DriverInitializationError,
                               MasterConfig)
from brace_control.can.plan import DictionaryError
from brace_control.config import ConfigError, DeviceConfig, load_device_config
from brace_control.mechanisms import mechanism_from_config
from brace_control.sim import SimulatedBrace
from brace_control.sim.drive import DriveLimits, SimulatedDrive
from brace_control.sim.host import SimBus

ROOT = Path(__file__).resolve().parents[1]
EDS = ROOT / 'test' / 'data' / 'eds'
NANOTEC = EDS / 'CL3-E-2-0F.eds'
SLAVE = EDS / 'cia402_slave.eds'
FAULHABER = EDS / '605.3150.69-B-EK-2-60.eds'
MODULE = ROOT / 'config' / 'analog_input_module.eds'
EPOS4 = EDS / 'maxon_epos4_node4.dcf'
EPOS2 = EDS / 'maxon_epos2_347717.eds'
ELMO = EDS / 'elmo_cob.dcf'
ROBOTEQ = EDS / 'roboteq_v80_21a.eds'
BASE = load_device_config(ROOT / 'config' / 'lumbar_brace.yaml')
MECH = mechanism_from_config(BASE)
_ids = itertools.count()

# the abort codes of CiA 301 table 22
NO_OBJECT, READ_ONLY, NOT_MAPPABLE, PDO_LENGTH = 0x06020000, 0x06010002, 0x06040041, 0x06040042
VALUE_RANGE, VALUE_HIGH = 0x06090030, 0x06090031
_STRUCT_BITS = {'B': 8, 'b': 8, 'H': 16, 'h': 16, 'I': 32, 'i': 32, 'f': 32, 'q': 64, 'Q': 64, 'd': 64}


def config(**can_params) -> DeviceConfig:
    """The lumbar brace with ``can.*`` replaced (the YAML's own directory kept)."""
    params = copy.deepcopy(dict(BASE))
    params['can'].update(can_params)
    return DeviceConfig(params, BASE.path)


def master_for(cfg: DeviceConfig, channel: str = 'unused') -> BraceMaster:
    return BraceMaster(MasterConfig.from_device_config(cfg, channel=channel))


def raw_var(dictionary: canopen.ObjectDictionary, index: int, sub: int):
    """The file's variable, looked up by hand (an array lists only the sub-indices it has)."""
    if index not in dictionary:
        return None
    obj = dictionary[index]
    if isinstance(obj, od.ODVariable):
        return obj if sub == 0 else None
    return obj.subindices.get(sub)


def edited_eds(tmp_path: Path, src: Path, *, drop: tuple[str, ...] = (),
               set_: dict[tuple[str, str], str] | None = None, add: dict[str, dict] | None = None) -> Path:
    """A copy of ``src`` with sections dropped (by name prefix), values set, sections added."""
    cp = configparser.RawConfigParser()
    cp.optionxform = str
    cp.read(src, encoding='latin-1')
    for section in list(cp.sections()):
        if any(section.upper().startswith(d.upper()) for d in drop):
            cp.remove_section(section)
    for (section, key), value in (set_ or {}).items():
        cp.set(section, key, value)
    for section, values in (add or {}).items():
        cp.add_section(section)
        for k, v in values.items():
            cp.set(section, k, v)
    out = tmp_path / f'edited{next(_ids)}_{src.name}'
    with open(out, 'w', encoding='latin-1') as f:
        cp.write(f)
    return out


# ------------------------------------------------------------------ the plan against the file

PLANNED = {
    'nanotec': dict(eds=str(NANOTEC), load_cell_object='0x3220:1'),
    'cia402_slave + CiA 401 module': dict(eds=str(SLAVE), load_cell_node={'node_id': 10, 'eds': str(MODULE)}),
    'our own drive': dict(eds='lumbar_drive.eds'),
    'maxon EPOS4 (a DCF)': dict(eds=str(EPOS4), load_cell_object='0x3160:1'),
    'maxon EPOS2': dict(eds=str(EPOS2), load_cell_object='0x207C:1'),
    'Elmo Gold (a DCF)': dict(eds=str(ELMO), load_cell_object='0x2205:1'),
}


@pytest.mark.parametrize('case', sorted(PLANNED))
def test_every_write_of_the_plan_is_one_the_dictionary_file_accepts(case):
    """Replay every SDO write of the boot against the file (the issue's own check): the object
    exists, is writable, has the size written; a mapping entry names an object with
    ``PDOMapping=1`` of the entry's size; no PDO longer than 64 bits."""
    cfg = config(**PLANNED[case])
    master = master_for(cfg)
    plans = master.plan()
    targets = [(p.node_id, p.dictionary.path, p.writes + p.mapping) for p in plans]
    if master.module_plan is not None:
        mp = master.module_plan
        targets.append((mp.node_id, mp.dictionary.path, mp.writes + mp.mapping))
    for node_id, path, writes in targets:
        dictionary = canopen.import_od(str(path), node_id)
        counts: dict[int, list[int]] = {}
        for w in writes:
            var = raw_var(dictionary, w.index, w.subindex)
            assert var is not None, f'{path.name}: {w.index:04X}h:{w.subindex} ({w.what}) is not in the file'
            assert 'w' in var.access_type, f'{path.name}: {w.index:04X}h:{w.subindex} is {var.access_type}'
            assert _STRUCT_BITS[w.fmt] == len(var), (w, len(var))
            if (0x1600 <= w.index <= 0x17FF or 0x1A00 <= w.index <= 0x1BFF) and w.subindex and w.value:
                mapped = raw_var(dictionary, w.value >> 16, (w.value >> 8) & 0xFF)
                assert mapped is not None and mapped.pdo_mappable, f'{path.name}: {w.value:08X}h not mappable'
                assert len(mapped) == w.value & 0xFF
                counts.setdefault(w.index, []).append(w.value & 0xFF)
        for index, bits in counts.items():
            assert sum(bits) <= 64, (index, bits)


def test_nanotec_boots_with_the_load_cell_on_analog_input_3220h_1():
    master = master_for(config(**PLANNED['nanotec']))
    plan = master.plan()[0]
    raw = canopen.import_od(str(NANOTEC), 1)
    analog = raw_var(raw, 0x3220, 1)
    assert analog.data_type == od.INTEGER16 and analog.pdo_mappable
    tpdo1 = [w.value for w in plan.mapping if w.index == 0x1A00 and w.subindex > 0]
    assert tpdo1 == [0x60410010, 0x60640020, 0x32200110]
    assert plan.feedforward and plan.home_offset_on_drive
    assert raw_var(raw, 0x2401, 0) is None


def test_ros2_canopen_slave_boots_without_feed_forward_and_says_so():
    master = master_for(config(**PLANNED['cia402_slave + CiA 401 module']))
    plans = master.plan()
    raw = canopen.import_od(str(SLAVE), 1)
    assert not raw_var(raw, 0x60B1, 0).pdo_mappable               # the file's own word
    assert all(not p.feedforward for p in plans)
    assert not any(w.index == 0x1601 and w.subindex and w.value >> 16 == 0x60B1
                   for p in plans for w in p.mapping)
    report = '\n'.join(master.boot_report)
    for absent in ('6007h', '1006h', '607Fh'):
        assert raw_var(raw, int(absent[:4], 16), 0) is None
        assert absent in report, report
    assert '60B1h' in report and 'feed-forward' in report, report
    # the module carries the load cells: its TPDO1 maps 6401h:1..3
    module_tpdo = [w.value for w in master.module_plan.mapping if w.index == 0x1A00 and w.subindex > 0]
    assert module_tpdo == [0x64010110, 0x64010210, 0x64010310]


def test_the_ros2_canopen_slave_alone_is_refused_naming_its_missing_load_cell():
    with pytest.raises(DictionaryError) as err:
        master_for(config(eds=str(SLAVE))).plan()
    text = str(err.value)
    assert '2401h:0' in text and 'can.load_cell_node' in text and 'cia402_slave.eds' in text, text


def test_faulhaber_is_refused_naming_csp_and_every_missing_object():
    raw = canopen.import_od(str(FAULHABER), 1)
    modes = raw_var(raw, 0x6502, 0).default
    assert not modes >> 7 & 1                                      # no CSP, by the file
    missing = [i for i in (0x60B1, 0x60C2, 0x6007, 0x605A, 0x6065, 0x1006) if i not in raw]
    assert len(missing) == 6
    with pytest.raises(DictionaryError) as err:
        master_for(config(eds=str(FAULHABER))).plan()
    text = str(err.value)
    assert 'cyclic synchronous position' in text and '6502h' in text, text
    assert '605.3150.69-B-EK-2-60.eds' in text and 'a1 (node 1), a2 (node 2), a3 (node 3)' in text
    for index in missing:
        assert f'{index:04X}h' in text, (f'{index:04X}h', text)
    assert text.count('cannot drive the brace') == 1              # one message, not one per drive


def test_a_drive_of_two_axes_listing_its_objects_per_axis_is_refused_naming_the_entries(tmp_path):
    """A dual-axis drive's file that lists 6064h and 607Ah as arrays, one entry per axis (the
    layout of ZLTECH's ZLAC8015D file, NamPER221/base-canopen): the refusal says what the
    file has there, not that sub-index 0 is read-only or not mappable."""
    per_axis = {}
    for index, name, access in (('6064', 'Position actual value', 'ro'), ('607A', 'Target position', 'rw')):
        per_axis[index] = {'ParameterName': name, 'ObjectType': '0x8', 'SubNumber': '3'}
        per_axis[f'{index}sub0'] = {'ParameterName': 'Highest sub-index', 'ObjectType': '0x7',
                                    'DataType': '0x0005', 'AccessType': 'ro', 'DefaultValue': '2',
                                    'PDOMapping': '0'}
        for sub, axis in ((1, 'Left'), (2, 'Right')):
            per_axis[f'{index}sub{sub}'] = {'ParameterName': f'{axis} motor {name}', 'ObjectType': '0x7',
                                            'DataType': '0x0004', 'AccessType': access,
                                            'DefaultValue': '0', 'PDOMapping': '1'}
    eds = edited_eds(tmp_path, NANOTEC, drop=('6064', '607A'), add=per_axis)
    with pytest.raises(DictionaryError) as err:
        master_for(config(eds=str(eds), load_cell_object='0x3220:1')).plan()
    text = str(err.value)
    for index, name in (('6064h', 'Position actual value'), ('607Ah', 'Target position')):
        assert f'{index}:0 ({name.lower()}) is an array of 2 entries' in text, text
        assert f"{index}:1 'Left motor {name}'" in text and f"{index}:2 'Right motor {name}'" in text
    assert 'not writable' not in text and 'several axes' in text


class _Frames(can.Listener):
    def __init__(self) -> None:
        self.frames: list[can.Message] = []

    def on_message_received(self, msg: can.Message) -> None:
        self.frames.append(msg)


def test_faulhaber_configure_fails_within_5_s_and_nothing_is_sent_nothing_moves():
    channel = f'dict-{os.getpid()}-{next(_ids)}'
    cfg = config(eds=str(FAULHABER))
    sim = SimulatedBrace(cfg, channel=channel)
    spy_bus = can.Bus(interface='virtual', channel=channel)
    spy = _Frames()
    notifier = can.Notifier(spy_bus, [spy])
    before = sim.truth().lengths.copy()
    master = master_for(cfg, channel)
    try:
        t0 = time.perf_counter()
        with pytest.raises(DictionaryError):
            master.boot()
        assert time.perf_counter() - t0 <= 5.0
        time.sleep(0.05)
        master_frames = [m for m in spy.frames if m.arbitration_id == 0 or 0x600 <= m.arbitration_id <= 0x67F
                         or m.arbitration_id in (0x80, 0x77F) or 0x200 <= m.arbitration_id <= 0x57F]
        assert master_frames == [], master_frames[:5]
        np.testing.assert_array_equal(sim.truth().lengths, before)
    finally:
        master.shutdown()
        notifier.stop()
        spy_bus.shutdown()
        sim.shutdown()


def test_a_drive_without_1016h_boots_with_a_warning_that_a_hardware_stop_is_needed(tmp_path):
    eds = edited_eds(tmp_path, NANOTEC, drop=('1016',))
    master = master_for(config(eds=str(eds), load_cell_object='0x3220:1'))
    plans = master.plan()
    assert all(any('1016h' in w and 'hardware stop' in w for w in p.warnings) for p in plans)
    assert any(line.startswith('warning: a1, a2, a3') and '1016h' in line for line in master.boot_report)
    assert all(w.index != 0x1016 for p in plans for w in p.writes)


def test_homing_method_is_checked_against_what_the_dictionary_offers(tmp_path):
    # 60E3h (supported homing methods) listing 1, 2 and 37: method 35 is refused, 37 suggested
    add = {'60E3': {'ParameterName': 'Supported homing methods', 'ObjectType': '0x8', 'SubNumber': '4'},
           '60E3sub0': {'ParameterName': 'n', 'ObjectType': '0x7', 'DataType': '0x0005', 'AccessType': 'ro',
                        'DefaultValue': '3', 'PDOMapping': '0'}}
    for sub, method in ((1, 1), (2, 2), (3, 37)):
        add[f'60E3sub{sub}'] = {'ParameterName': f'm{sub}', 'ObjectType': '0x7', 'DataType': '0x0002',
                                'AccessType': 'ro', 'DefaultValue': str(method), 'PDOMapping': '0'}
    eds = edited_eds(tmp_path, NANOTEC, add=add)
    with pytest.raises(DictionaryError, match=r'homing method 35.*60E3h lists \[1, 2, 37\].*method 37'):
        master_for(config(eds=str(eds), load_cell_object='0x3220:1')).plan()
    plan = master_for(config(eds=str(eds), load_cell_object='0x3220:1', homing_method=37)).plan()[0]
    assert any(w.index == 0x6098 and w.value == 37 for w in plan.writes)


# ------------------------------------------------------------------ PDO mapping from the YAML

def test_a_yaml_mapping_is_planned_on_the_pdo_it_names():
    cfg = config(eds=str(NANOTEC), load_cell_object='0x3220:1',
                 tpdo={'2': {'mapping': ['0x6041:0', '0x6064:0', '0x3220:1'], 'transmission': 1}})
    plan = master_for(cfg).plan()[0]
    assert plan.feedback.number == 2 and plan.feedback.cob_id == 0x281
    seq = [(w.index, w.subindex, w.value) for w in plan.mapping]
    # CiA 301 order on TPDO2, and TPDO1 disabled (the drive has 8 TPDOs: all others disabled)
    tpdo2 = [s for s in seq if s[0] in (0x1801, 0x1A01)]
    assert tpdo2[:2] == [(0x1801, 1, 0x80000281), (0x1A01, 0, 0)]
    assert tpdo2[-1] == (0x1801, 1, 0x281)
    assert (0x1800, 1, 0x80000181) in seq
    raw = canopen.import_od(str(NANOTEC), 1)
    tpdos = {0x1800 + n for n in range(512) if 0x1800 + n in raw}
    assert len(tpdos) == 8
    # every TPDO the drive has is written invalid (TPDO2 first, for its mapping), none beyond
    disabled = {s[0] for s in seq if s[1] == 1 and s[2] & 0x80000000 and s[0] >= 0x1800}
    assert disabled == tpdos


@pytest.mark.parametrize('mapping, expected', [
    ({'rpdo': {'2': {'mapping': ['0x60B1:0']}}}, r'60B1h:0 \(can.rpdo.2.mapping\): not PDO-mappable'),
    ({'rpdo': {'5': {'mapping': ['0x607A:0']}}}, r'RPDO5 \(can.rpdo.5\): the drive has RPDOs 1, 2, 3, 4'),
    ({'tpdo': {'1': {'mapping': ['0x6064:0', '0x6064:0', '0x6064:0']}}}, r'96 bits mapped, a PDO holds at most 64'),
    ({'tpdo': {'1': {'mapping': ['0x6041:0', '0x6062:0']}}}, r'carries the statusword but not the position'),
    ({'rpdo': {'1': {'mapping': ['0x6040:0', '0x607A:0', '0x6071:0']}}}, r'6071h:0.*absent'),
])
def test_a_yaml_mapping_the_dictionary_refuses_is_named(mapping, expected):
    cfg = config(eds=str(SLAVE), load_cell_node={'node_id': 10, 'eds': str(MODULE)}, **mapping)
    with pytest.raises(DictionaryError, match=expected):
        master_for(cfg).plan()


def test_object_references_in_the_yaml_are_read_or_named():
    with pytest.raises(ConfigError, match=r'can.load_cell_object.*"0xIIII:SS"'):
        MasterConfig.from_device_config(config(load_cell_object='analog one'), channel='x')
    with pytest.raises(ConfigError, match=r'can.eds .*no such file'):
        MasterConfig.from_device_config(config(eds='no_such_drive.eds'), channel='x')


# ------------------------------------------------------------------ the simulated drive answers as the file says

@pytest.fixture
def bus_drive():
    """One simulated drive from a given EDS on a bus, and a canopen client node for it."""
    made = []

    def make(eds: Path, node_id: int = 1):
        channel = f'dict-{os.getpid()}-{next(_ids)}'
        host = SimBus(channel)
        drive = SimulatedDrive(node_id, eds, limits=DriveLimits(), initial_length_m=0.39)
        host.add(drive)
        host.start()
        net = canopen.Network()
        net.connect(interface='virtual', channel=channel)
        node = canopen.RemoteNode(node_id, canopen.ObjectDictionary())
        net.add_node(node)
        made.append((host, net))
        return drive, node
    yield make
    for host, net in made:
        net.disconnect()
        host.shutdown()


def _abort(node, index, sub, data=None):
    try:
        if data is None:
            node.sdo.upload(index, sub)
        else:
            node.sdo.download(index, sub, data)
    except canopen.SdoAbortedError as exc:
        return exc.code
    return None


def test_simulated_drives_abort_as_cia_301_says_for_their_own_dictionary(bus_drive):
    raw = canopen.import_od(str(NANOTEC), 1)
    drive, node = bus_drive(NANOTEC)
    assert raw_var(raw, 0x2401, 0) is None and raw_var(raw, 0x6007, 0).pdo_mappable is False
    assert _abort(node, 0x2401, 0) == NO_OBJECT                           # absent
    assert _abort(node, 0x6041, 0, struct.pack('<H', 0)) == READ_ONLY     # ro
    assert _abort(node, 0x1A00, 1, struct.pack('<I', 0x60070010)) == NOT_MAPPABLE
    for sub in (1, 2, 3):                                                  # 3 x 32 bit
        assert _abort(node, 0x1A00, sub, struct.pack('<I', 0x60640020)) is None
    assert _abort(node, 0x1A00, 0, struct.pack('<B', 3)) == PDO_LENGTH
    assert _abort(node, 0x3220, 1) is None                                 # its analog input exists
    raw_slave = canopen.import_od(str(SLAVE), 1)
    slave, snode = bus_drive(SLAVE)
    assert 0x1404 not in raw_slave and 0x1A04 not in raw_slave
    assert _abort(snode, 0x1404, 1, struct.pack('<I', 0x80000000)) == NO_OBJECT   # no RPDO5
    assert _abort(snode, 0x1601, 1, struct.pack('<I', 0x60B10020)) == NOT_MAPPABLE
    # modes of operation from 6502h (A5h: PP, PV, homing, CSP)
    assert raw_var(raw_slave, 0x6502, 0).default == 0xA5
    assert _abort(snode, 0x6060, 0, struct.pack('<b', 9)) == VALUE_RANGE          # CSV: not offered
    assert _abort(snode, 0x6060, 0, struct.pack('<b', 8)) is None


def test_faulhaber_simulated_refuses_csp(bus_drive):
    raw = canopen.import_od(str(FAULHABER), 1)
    assert raw_var(raw, 0x6060, 0).max == 6
    drive, node = bus_drive(FAULHABER)
    assert _abort(node, 0x6060, 0, struct.pack('<b', 8)) == VALUE_HIGH          # the file's HighLimit


# ------------------------------------------------------------------ boot robustness on the simulated bus

def _rig(cfg: DeviceConfig, *, before_start=None):
    channel = f'dict-{os.getpid()}-{next(_ids)}'
    sim = SimulatedBrace(cfg, channel=channel, start=before_start is None)
    if before_start is not None:
        before_start(sim)
        sim.start()
    return sim, master_for(cfg, channel), channel


@contextlib.contextmanager
def _rigged(cfg: DeviceConfig, *, before_start=None):
    """``(sim, master)`` of :func:`_rig`, both shut down on leaving."""
    sim, master, _ = _rig(cfg, before_start=before_start)
    try:
        yield sim, master
    finally:
        master.shutdown()
        sim.shutdown()


def _move_and_check(sim, master):
    """Home, enable, a 6 mm lift: the simulator's true lengths end at the IK of the goal."""
    master.home()
    master.enable()
    q0 = MECH.inverse(MECH.home_pose)
    q1 = MECH.inverse(MECH.home_pose + np.array([0.0, 0.006, 0.01]))
    t = np.linspace(0.0, 0.8, 33)
    s = t / 0.8
    p, v = 10 * s ** 3 - 15 * s ** 4 + 6 * s ** 5, (30 * s ** 2 - 60 * s ** 3 + 30 * s ** 4) / 0.8
    a = (60 * s - 180 * s ** 2 + 120 * s ** 3) / 0.64
    assert master.execute(ActuatorTrajectory(t, q0 + np.outer(p, q1 - q0), np.outer(v, q1 - q0),
                                             np.outer(a, q1 - q0)), start=time.perf_counter() + 0.05,
                          tag=3) is None
    end = time.monotonic() + 5
    while (master.moving or np.max(np.abs(sim.truth().lengths - q1)) > 2e-6) and time.monotonic() < end:
        time.sleep(0.01)
    assert np.max(np.abs(sim.truth().lengths - q1)) <= 2e-6, sim.truth().lengths - q1
    assert not master.supervisor.latched, master.supervisor.summary()


def test_a_drive_answering_sdo_20_ms_late_boots_with_can_sdo_timeout_raised():
    def slow(sim):
        for node_id in (1, 2, 3):
            sim.faults.delay_sdo(node_id, 0.02)
    impatient = config(**PLANNED['nanotec'], sdo_timeout=0.01, sdo_retries=0)
    with _rigged(impatient, before_start=slow) as (sim, master):
        with pytest.raises(DriverInitializationError, match=r'did not answer the SDO write.*can.sdo_timeout = 0.01'):
            master.boot()
    # raised to ten times the delay: at 0.05 s a loaded host (three test workers) stretched a
    # 20 ms answer past it, and the retry's answer arriving after the next request was taken
    # for that request's (canopen: "Unexpected response 0x60")
    with _rigged(config(**PLANNED['nanotec'], sdo_timeout=0.2), before_start=slow) as (sim, master):
        master.boot()
        _move_and_check(sim, master)


@pytest.mark.parametrize('when', ['power_on', 'always'])
def test_a_drive_that_sends_no_boot_up_is_brought_up(when):
    """'power_on': no boot-up until the master's NMT reset-communication, which it answers with
    one (seen on the bus after the reset). 'always': none at all; the SDO probe finds it."""
    spy = _Frames()

    def quiet(sim):
        for node_id in (1, 2, 3):
            sim.faults.silent_boot(node_id, when)
        spy_bus = can.Bus(interface='virtual', channel=sim.channel)
        quiet.notifier = can.Notifier(spy_bus, [spy])
        quiet.bus = spy_bus
    sim, master, _ = _rig(config(**PLANNED['nanotec']), before_start=quiet)   # 1017h = 0 on the CL3-E
    try:
        master.boot()
        frames = [(m.arbitration_id, bytes(m.data)) for m in spy.frames]
        resets = [i for i, f in enumerate(frames) if f[0] == 0 and f[1][:1] == b'\x82']
        bootups = [i for i, f in enumerate(frames) if 0x701 <= f[0] <= 0x703 and f[1] == b'\x00']
        assert {frames[i][1][1] for i in resets} == {1, 2, 3}
        if when == 'power_on':
            assert len(bootups) == 3 and min(bootups) > min(resets)
        else:
            assert bootups == []
        _move_and_check(sim, master)
    finally:
        master.shutdown()
        quiet.notifier.stop()
        quiet.bus.shutdown()
        sim.shutdown()


def test_a_drive_without_607ch_homes_with_the_offset_kept_by_the_master(tmp_path):
    eds = edited_eds(tmp_path, NANOTEC, drop=('607C',))
    cfg = config(eds=str(eds), load_cell_object='0x3220:1')
    with _rigged(cfg) as (sim, master):
        master.boot()
        assert not master.plans[0].home_offset_on_drive
        assert any('607Ch' in line and 'keeps the home offset' in line for line in master.boot_report)
        _move_and_check(sim, master)
        # the drive's own counts are its homing result (no 607Ch: 0 at home), not the length
        q = sim.truth().lengths
        assert abs(sim.drive(2).position_counts - round(q[1] * 8192000)) > 1000
        np.testing.assert_allclose(master.feedback().position, q, atol=2e-7)


def test_an_unsigned_analog_input_reads_zero_force_at_mid_scale(tmp_path):
    """A 16-bit unsigned ADC input of a bipolar load-cell amplifier: 0 N at 32768 counts."""
    eds = edited_eds(tmp_path, NANOTEC, set_={('3220sub1', 'DataType'): '0x0006'})
    cfg = config(eds=str(eds), load_cell_object='0x3220:1')
    with _rigged(cfg) as (sim, master):
        master.boot()
        _move_and_check(sim, master)
        true = sim.truth().forces
        assert np.all(np.abs(true) > 2.0)
        counts = [sim.drive(n).read_od(0x3220, 1) for n in (1, 2, 3)]
        assert all(0 <= c <= 0xFFFF for c in counts)
        np.testing.assert_allclose(np.array(counts) - 32768, true / 0.01, atol=4 * 0.05 / 0.01 + 1)
        np.testing.assert_allclose(master.feedback().force, true, atol=4 * 0.05 + 0.01)


# ------------------------------------------------------------------ files that are not ASCII

FAULHABER_CC = EDS / '605.3150.51-V-EK-2-60.eds'


def test_a_vendor_file_that_is_not_utf8_is_read_and_refused_for_what_it_lacks():
    """Faulhaber's 605.3150.51 (test/data/eds/README.md) has byte 94h in its comments: read
    with UTF-8, as ``canopen`` opens a path here, it is no dictionary at all. It is read, and
    refused for what the file says (its 6060h range, looked up here by hand)."""
    raw = FAULHABER_CC.read_bytes()
    with pytest.raises(UnicodeDecodeError):
        raw.decode('utf-8')
    cp = configparser.RawConfigParser()
    cp.optionxform = str
    cp.read_string(raw.decode('latin-1'))
    low, high = int(cp.get('6060', 'LowLimit'), 0), int(cp.get('6060', 'HighLimit'), 0)
    assert high < 8                                                # no CSP, by the file
    with pytest.raises(DictionaryError) as err:
        master_for(config(eds=str(FAULHABER_CC))).plan()
    text = str(err.value)
    assert 'not a readable' not in text, text
    assert f'6060h allows {low}..{high}, not 8' in text and 'cyclic synchronous position' in text, text
    assert "CC / Faulhaber" in text, text


@pytest.mark.parametrize('encoding', ['utf-8-sig', 'cp1252'])
def test_the_same_dictionary_in_another_encoding_plans_the_same_boot(tmp_path, encoding):
    """The Nanotec file (UTF-8: its '‰' units) saved by another tool: UTF-8 with a byte-order
    mark, or Windows-1252 (the '‰' is byte 89h, not UTF-8). The plan's writes are the
    original file's."""
    text = NANOTEC.read_bytes().decode('utf-8')
    assert not text.isascii()
    copy_ = tmp_path / NANOTEC.name
    copy_.write_bytes(text.encode(encoding))
    assert copy_.read_bytes() != NANOTEC.read_bytes()

    def writes(path):
        plan = master_for(config(eds=str(path), load_cell_object='0x3220:1')).plan()
        return [[(w.index, w.subindex, w.value) for w in p.writes + p.mapping] for p in plan]
    assert writes(copy_) == writes(NANOTEC)


# ------------------------------------------------------------------ the drive's own units (60A8h, 60A9h)

def _file_value(path: Path, section: str, key: str = 'DefaultValue') -> int:
    cp = configparser.RawConfigParser()
    cp.optionxform = str
    cp.read_string(path.read_bytes().decode('latin-1'))
    return int(cp.get(section, key), 0)


def test_a_velocity_unit_per_minute_is_set_to_the_position_unit_per_second_before_any_velocity():
    """The CL3-E starts in 0.1 degree (60A8h) and rpm (60A9h), by its file: the boot writes
    60A9h = the position unit per second before 607Fh and 6083h..6085h, which it writes in
    position units per second, and says that 8192 counts per revolution is not the drive's
    3600; with 3600 it says they agree."""
    pos, vel = _file_value(NANOTEC, '60A8'), _file_value(NANOTEC, '60A9')
    assert (pos >> 16) & 0xFF == 0x41 and (pos >> 24) == 0xFF            # 10^-1 degree
    assert (vel >> 8) & 0xFF == 0x47                                      # per minute
    master = master_for(config(**PLANNED['nanotec']))                     # 8192 counts/rev
    plan = master.plan()[0]
    order = [w.index for w in plan.writes]
    unit = next(w for w in plan.writes if w.index == 0x60A9)
    assert unit.value == (pos & 0xFFFF0000) | 0x0300, hex(unit.value)
    assert all(order.index(0x60A9) < order.index(i) for i in (0x607F, 0x6083, 0x6084, 0x6085))
    assert plan.feedforward
    warnings = [w for w in plan.warnings if '60A8h' in w]
    assert len(warnings) == 1 and '3600' in warnings[0] and 'encoder_counts_per_rev' in warnings[0], plan.warnings
    agreeing = copy.deepcopy(dict(BASE))
    agreeing['can'].update(PLANNED['nanotec'])
    agreeing['actuator']['encoder_counts_per_rev'] = 3600
    plan = master_for(DeviceConfig(agreeing, BASE.path)).plan()[0]
    assert not [w for w in plan.warnings if '60A8h' in w], plan.warnings
    assert any('60A8h' in n and '3600' in n for n in plan.notes), plan.notes


def test_a_velocity_unit_that_cannot_be_set_means_no_feed_forward_and_a_yaml_feed_forward_is_refused(tmp_path):
    """60A9h read-only at rpm: a velocity offset in counts/s would be read as rpm (a runaway),
    so the default mapping carries no 60B1h, a warning names 60A9h, and a YAML that maps 60B1h
    is refused before anything is sent."""
    eds = edited_eds(tmp_path, NANOTEC, set_={('60A9', 'AccessType'): 'ro'})
    plan = master_for(config(eds=str(eds), load_cell_object='0x3220:1')).plan()[0]
    assert not plan.feedforward
    assert not any(w.index == 0x60A9 for w in plan.writes)
    assert not any(w.index == 0x1601 and w.subindex and w.value >> 16 == 0x60B1 for w in plan.mapping)
    assert any('60A9h' in w and '00B44700h' in w for w in plan.warnings), plan.warnings
    rpdo = {1: {'mapping': ['0x6040:0', '0x607A:0'], 'transmission': 1},
            2: {'mapping': ['0x60B1:0'], 'transmission': 1}}
    with pytest.raises(DictionaryError, match=r'60B1h velocity offset in can\.rpdo: 60A9h'):
        master_for(config(eds=str(eds), load_cell_object='0x3220:1', rpdo=rpdo)).plan()


def test_a_drive_in_increments_per_second_is_left_as_it_is():
    """The ros2_canopen slave has no 60A8h / 60A9h: nothing written, nothing said of units."""
    raw = canopen.import_od(str(SLAVE), 1)
    assert raw_var(raw, 0x60A8, 0) is None and raw_var(raw, 0x60A9, 0) is None
    master = master_for(config(**PLANNED['cia402_slave + CiA 401 module']))
    for plan in master.plan():
        assert not any(w.index in (0x60A8, 0x60A9) for w in plan.writes)
        assert not any('60A8h' in t or '60A9h' in t for t in plan.notes + plan.warnings)


def test_a_max_profile_velocity_the_file_will_not_raise_is_a_warning_naming_both_speeds(tmp_path):
    """607Fh capped at 25000 by the file (maxon's EPOS2 EDS does so, in rpm) and starting
    there: the master's 0.065 m/s x 8192000 counts/m cannot be written, and the drive's own
    value is below it; the boot plan warns with both numbers, rather than a note that "the
    drive's own value applies"."""
    eds = edited_eds(tmp_path, NANOTEC, set_={('607F', 'HighLimit'): '25000', ('607F', 'DefaultValue'): '25000'})
    plan = master_for(config(eds=str(eds), load_cell_object='0x3220:1')).plan()[0]
    wanted = round(float(BASE['actuator']['max_velocity']) * 8192 / float(BASE['actuator']['screw_lead']))
    assert not any(w.index == 0x607F for w in plan.writes)
    warning = [w for w in plan.warnings if w.startswith('607Fh')]
    assert len(warning) == 1 and '25000' in warning[0] and str(wanted) in warning[0], plan.warnings


# ------------------------------------------------------------------ PDOs the dictionary fixes

def _read_only(values: dict[str, str | None]) -> dict[tuple[str, str], str]:
    """``edited_eds`` settings: each section read-only, at the value given (``None``: as it is)."""
    out = {}
    for section, value in values.items():
        out[(section, 'AccessType')] = 'ro'
        if value is not None:
            out[(section, 'DefaultValue')] = value
    return out


def test_fixed_pdos_that_carry_what_the_master_needs_are_used_as_the_drive_has_them(tmp_path):
    """TPDO1 fixed (1A00h read-only) with the position, the load cell and the statusword in its
    own order, RPDO1 fixed, both COB-IDs read-only: nothing of them is written (the simulated
    drives abort a write to a read-only object, as CiA 301 says), the feedback is decoded in
    the drive's order, and the brace moves to the IK of the goal on the simulator's truth."""
    eds = edited_eds(tmp_path, NANOTEC, set_=_read_only({
        '1A00sub0': '3', '1A00sub1': '0x60640020', '1A00sub2': '0x32200110', '1A00sub3': '0x60410010',
        '1600sub0': '2', '1600sub1': '0x60400010', '1600sub2': '0x607A0020',
        '1800sub1': '$NODEID+0x180', '1400sub1': '$NODEID+0x200'}))
    cfg = config(eds=str(eds), load_cell_object='0x3220:1')
    plan = master_for(cfg).plan()[0]
    written = {(w.index, w.subindex) for w in plan.writes + plan.mapping}
    for index in (0x1A00, 0x1600):
        assert not any(i == index for i, _ in written), sorted(written)
    assert (0x1800, 1) not in written and (0x1400, 1) not in written
    assert plan.feedback.roles == ('position', 'load', 'statusword')
    with _rigged(cfg) as (sim, master):
        master.boot()
        _move_and_check(sim, master)
        np.testing.assert_allclose(master.feedback().force, sim.truth().forces, atol=4 * 0.05 + 0.01)


@pytest.mark.parametrize('fixed, named', [
    ({'1A00sub0': '2', '1A00sub1': '0x60410010', '1A00sub2': '0x60610008'},
     ['1A00h read-only', '60410010h, 60610008h']),
    ({'1800sub2': '0xFF'}, ['1800h:2 is read-only at 255', 'can.tpdo.1.transmission = 1']),
    ({'1800sub1': '0x80000181'}, ['1800h:1 is read-only', 'invalid (80000181h)']),
])
def test_a_fixed_pdo_that_cannot_serve_is_refused_before_anything_is_sent(tmp_path, fixed, named):
    """A fixed TPDO1 without the position and the load cell, a fixed event-driven transmission
    type, a fixed invalid COB-ID: the configure step refuses, naming the object and what the
    file fixes it at."""
    eds = edited_eds(tmp_path, NANOTEC, set_=_read_only(fixed))
    with pytest.raises(DictionaryError) as err:
        master_for(config(eds=str(eds), load_cell_object='0x3220:1')).plan()
    text = str(err.value)
    for part in named:
        assert part in text, (part, text)
    assert 'Nothing was sent' in text


def test_pdo_mappings_in_compact_storage_are_planned_to_their_declared_size(tmp_path):
    """CiA 306 compact storage: the RPDO1 and TPDO1 mapping arrays as ``CompactSubObj=8`` with
    no sub-index sections (a tool's way of writing them). The plan maps RPDO1 with two entries
    and TPDO1 with three, as with the sections written out, and the brace moves on the
    simulated drives built from the same file."""
    cp = configparser.RawConfigParser()
    cp.optionxform = str
    cp.read_string(NANOTEC.read_bytes().decode('utf-8'))
    for index in ('1600', '1A00'):
        subs = [s for s in cp.sections() if s.upper().startswith(f'{index}SUB')]
        assert len(subs) - 1 == 8, subs                          # the file's 8 entries
        for section in subs:
            cp.remove_section(section)
        cp.remove_option(index, 'SubNumber')
        for key, value in (('ObjectType', '0x8'), ('CompactSubObj', '8'), ('DataType', '0x0007'),
                           ('AccessType', 'rw'), ('PDOMapping', '0')):
            cp.set(index, key, value)
    eds = tmp_path / 'compact_CL3-E-2-0F.eds'
    with open(eds, 'w', encoding='utf-8') as f:
        cp.write(f)
    cfg = config(eds=str(eds), load_cell_object='0x3220:1')
    plan = master_for(cfg).plan()[0]
    entries = {index: [w.value for w in plan.mapping if w.index == index and w.subindex > 0 and w.value]
               for index in (0x1600, 0x1A00)}
    assert entries[0x1600] == [0x60400010, 0x607A0020], entries
    assert entries[0x1A00] == [0x60410010, 0x60640020, 0x32200110], entries
    with _rigged(cfg) as (sim, master):
        master.boot()
        _move_and_check(sim, master)


# ------------------------------------------------------------------ a load-cell module nobody here wrote

IOX4 = EDS / 'IoX4_8AI.eds'


def _iox4_inputs() -> list[str]:
    """The file's own analog inputs (7130h, CiA 404's process value), read by hand."""
    cp = configparser.RawConfigParser()
    cp.optionxform = str
    cp.read_string(IOX4.read_bytes().decode('latin-1'))
    subs = [s for s in cp.sections() if s.upper().startswith('7130SUB') and s.upper() != '7130SUB0']
    assert all(cp.get(s, 'PDOMapping') == '1' and int(cp.get(s, 'DataType'), 0) == 0x0003 for s in subs)
    return [cp.get(s, 'ParameterName') for s in subs]


def test_a_vendor_analog_module_without_6401h_is_refused_naming_the_inputs_it_has():
    """SYS TEC's IO-X4 has no CiA 401 6401h: the refusal names the module and lists the analog
    inputs its file has (7100h / 7130h, AI0..), so a lab knows what to put in
    can.load_cell_node.objects."""
    names = _iox4_inputs()
    with pytest.raises(DictionaryError) as err:
        master_for(config(eds=str(SLAVE), load_cell_node={'node_id': 10, 'eds': str(IOX4)})).plan()
    text = str(err.value)
    assert 'sysWORXX CANopen IO-X4' in text and '6401h:1' in text, text
    assert 'can.load_cell_node.objects' in text and 'AI0_Input' in text, text
    assert names[0] == 'AI0_Input_PV'


def test_the_brace_moves_with_its_load_cells_on_a_vendor_analog_module():
    """The ros2_canopen slaves with the load cells on the IO-X4's 7130h:1..3 (INTEGER16): the
    module boots from its own file, and the forces the master reads follow the simulator's
    true leg forces within the noise (4 sigma) and one count."""
    cfg = config(eds=str(SLAVE), load_cell_node={'node_id': 10, 'eds': str(IOX4),
                                                 'objects': ['0x7130:1', '0x7130:2', '0x7130:3']})
    with _rigged(cfg) as (sim, master):
        master.boot()
        module_tpdo = [w.value for w in master.module_plan.mapping if w.index == 0x1A00 and w.subindex > 0]
        assert module_tpdo == [0x71300110, 0x71300210, 0x71300310]
        _move_and_check(sim, master)
        noise = float(BASE['sim']['load_cell_noise'])
        count = float(BASE['actuator']['load_cell_n_per_count'])
        # the drives are on target; the body behind the legs may still be settling, and the
        # master's feedback is a SYNC or more older than the truth read now (a burner run saw
        # 0.21 N between them): compare once the true forces hold still within a count
        seen = [sim.truth().forces.copy()]

        def settled() -> bool:
            seen.append(sim.truth().forces.copy())
            return len(seen) > 5 and np.ptp(np.array(seen[-5:]), axis=0).max() < count
        deadline = time.monotonic() + 10
        while not settled():
            assert time.monotonic() < deadline, f'the true forces did not settle: {seen[-5:]}'
            time.sleep(0.02)                 # paces the samples (50 Hz), not a wait
        np.testing.assert_allclose(master.feedback().force, sim.truth().forces, atol=4 * noise + count)


def test_a_drive_that_keeps_only_part_of_the_velocity_unit_stops_the_boot_naming_it():
    """Firmware that accepts the 60A9h write but keeps its own unit (a drive whose velocity unit
    is always rpm, only the power of ten settable): read back, the boot stops before the
    drives are enabled, naming what the drive kept; the simulator's true lengths never move."""
    def rpm_only(sim):
        for node_id in (1, 2, 3):
            drive = sim.drive(node_id)
            put = drive._put

            def keep_rpm(index, sub, value, put=put):
                if index == 0x60A9:
                    value = (value & 0xFF000000) | 0x00B44700
                put(index, sub, value)
            drive._put = keep_rpm
    with _rigged(config(**PLANNED['nanotec']), before_start=rpm_only) as (sim, master):
        before = sim.truth().lengths.copy()
        with pytest.raises(DriverInitializationError) as err:
            master.boot()
        text = str(err.value)
        assert 'kept 60A9h:0 = FFB44700h after FF410300h was written' in text, text
        assert 'a1 (node 1)' in text
        np.testing.assert_array_equal(sim.truth().lengths, before)


# ------------------------------------------------------------------ absolute encoders

def test_a_drive_that_cannot_home_is_refused_with_the_way_out_and_runs_with_absolute_encoders(tmp_path):
    """The CL3-E without 6098h (homing method), as some drives with absolute encoders are:
    with can.homing_method 35 the plan is refused, saying to set it to 0; with 0, nothing of
    homing is written or sent (home() is a no-op), enable needs no homing, the simulated
    drives read the installed length from power-up (absolute encoders), and the brace moves
    to the goal's inverse kinematics on the simulator's truth."""
    eds = edited_eds(tmp_path, NANOTEC, drop=('6098',))
    assert raw_var(canopen.import_od(str(eds), 1), 0x6098, 0) is None
    with pytest.raises(DictionaryError) as err:
        master_for(config(eds=str(eds), load_cell_object='0x3220:1')).plan()
    assert '6098h' in str(err.value) and 'can.homing_method: 0' in str(err.value), str(err.value)
    cfg = config(eds=str(eds), load_cell_object='0x3220:1', homing_method=0)
    plan = master_for(cfg).plan()[0]
    assert not any(w.index == 0x6098 for w in plan.writes)
    with _rigged(cfg) as (sim, master):
        master.boot()
        np.testing.assert_allclose(master.feedback().position, sim.truth().lengths, atol=2e-7)
        _move_and_check(sim, master)          # home() first: nothing to do
        assert master.homed


def test_a_drive_whose_file_leaves_its_device_type_at_0_answers_as_a_cia_402_servo_drive(tmp_path, bus_drive, caplog):
    """maxon's EPOS2 EDS and CiA's sample 402 device leave 1000h unset or 0; a real drive
    answers its own device type. The simulated drive answers 00020192h (CiA 301: profile 402,
    a servo drive), so the boot does not warn "not a CiA 402 drive" about a file's silence;
    a file that gives a value is answered with it."""
    eds = edited_eds(tmp_path, NANOTEC, set_={('1000', 'DefaultValue'): '0x00000000'})
    drive, node = bus_drive(eds)
    assert struct.unpack('<I', node.sdo.upload(0x1000, 0))[0] == 0x00020192
    raw = canopen.import_od(str(NANOTEC), 1)
    given = raw_var(raw, 0x1000, 0).default
    assert given                                           # the file's own value ...
    drive2, node2 = bus_drive(NANOTEC, node_id=2)
    assert struct.unpack('<I', node2.sdo.upload(0x1000, 0))[0] == given    # ... answered as is
    cfg = config(eds=str(eds), load_cell_object='0x3220:1')
    with caplog.at_level('WARNING'), _rigged(cfg) as (sim, master):
        master.boot()
    assert 'not a CiA 402 drive' not in caplog.text, caplog.text


# ------------------------------------------------------------------ drives of a sweep (session 14)

def _file_entry(path: Path, index: int, sub: int) -> dict[str, str]:
    """The keys of ``index``:``sub`` as the file writes them (read here with configparser, not by
    the code under test): its ``[60C2sub1]`` section (any case), for sub-index 0 of a variable
    its ``[6060]`` section; lower-cased keys."""
    cp = configparser.RawConfigParser(inline_comment_prefixes=(';',), strict=False)
    cp.read_string(path.read_bytes().decode('utf-8-sig', errors='replace'))
    sections = {name.lower(): name for name in cp.sections()}
    for name in [f'{index:04x}sub{sub:x}'] + ([f'{index:04x}'] if sub == 0 else []):
        if name in sections:
            return {k.lower(): v.strip() for k, v in cp.items(sections[name])}
    return {}


def _number(text: str) -> int:
    return int(text, 0) if text else 0


@pytest.mark.parametrize('case', sorted(PLANNED))
def test_a_unit_code_is_written_only_as_the_files_limits_encode_it(case):
    """60A8h / 60A9h (CiA 402 SI unit codes): where the file's LowLimit and HighLimit agree in
    bits 8..23 (the unit and its time base; maxon's EPOS4: 60A9h 00B44700h..FFB44700h, rpm with
    a prefix), a written code keeps those bits; a numeric range check alone let 00B50300h
    (increments per second) through, which the drive aborts and its boot with it."""
    cfg = config(**PLANNED[case])
    for plan in master_for(cfg).plan():
        for w in plan.writes:
            if w.index not in (0x60A8, 0x60A9):
                continue
            entry = _file_entry(Path(plan.dictionary.path), w.index, 0)
            low, high = _number(entry.get('lowlimit', '')), _number(entry.get('highlimit', ''))
            if entry.get('lowlimit') and entry.get('highlimit') and (low & 0xFFFF00) == (high & 0xFFFF00):
                assert w.value & 0xFFFF00 == low & 0xFFFF00, (case, f'{w.index:04X}h', f'{w.value:08X}h')


def test_maxon_epos4_keeps_its_rpm_and_boots_without_feed_forward_saying_why():
    """The EPOS4's 60A9h can only change its prefix: the plan leaves it (no write), drops the
    velocity feed-forward (an offset in counts/s read as rpm would run away), and its warning
    names the file's limits."""
    plan = master_for(config(**PLANNED['maxon EPOS4 (a DCF)'])).plan()[0]
    assert not any(w.index == 0x60A9 for w in plan.writes)
    assert not plan.feedforward
    assert not any(w.subindex and w.value >> 16 == 0x60B1 for w in plan.mapping)
    assert any('60A9h' in w and '00B44700h..FFB44700h' in w for w in plan.warnings), plan.warnings


@pytest.mark.parametrize('case', sorted(PLANNED))
def test_the_interpolation_period_is_written_whole_or_not_at_all(case):
    """60C2h:1 (value) and :2 (10^index s) are one period: a plan writes both, or one whose
    other sub-index the file has read-only at the value wanted, or neither. maxon's EPOS2
    allows only 1 in 60C2h:1; its 60C2h:2 = -3 alone told the drive 1 ms against a 2 ms SYNC."""
    for plan in master_for(config(**PLANNED[case])).plan():
        subs = {w.subindex: w.value for w in plan.writes if w.index == 0x60C2}
        if len(subs) == 1:
            (written, _), = subs.items()
            other = _file_entry(Path(plan.dictionary.path), 0x60C2, 3 - written)
            assert other.get('accesstype', '').lower() in ('ro', 'const'), (case, subs, other)
        if subs:
            period = subs.get(1, 0) * 10.0 ** subs.get(2, 0) if len(subs) == 2 else None
            assert period is None or period == pytest.approx(1.0 / BASE['can']['sync_rate_hz']), (case, subs)


def test_epos2_leaves_its_interpolation_period_and_says_so():
    plan = master_for(config(**PLANNED['maxon EPOS2'])).plan()[0]
    assert not any(w.index == 0x60C2 for w in plan.writes)
    assert any('60C2h' in n and 'not written' in n for n in plan.notes), plan.notes


def test_a_load_cell_named_by_its_record_is_refused_naming_the_inputs_in_it():
    """``can.load_cell_object: "0x2205"`` on an Elmo Gold: 2205h is a record whose sub-index 0
    counts its entries. The refusal names the key the user set and the inputs to choose from
    (2205h:1, 2205h:2 as the file names them), not a PDO mapping the YAML never set."""
    with pytest.raises(DictionaryError) as err:
        master_for(config(eds=str(ELMO), load_cell_object='0x2205')).plan()
    text = str(err.value)
    assert 'can.load_cell_object' in text and '"0x2205:1"' in text, text
    names = [_file_entry(ELMO, 0x2205, sub).get('parametername') for sub in (1, 2)]
    assert all(n and n in text for n in names), (names, text)
    assert 'can.tpdo' not in text, text


def test_a_mapping_longer_than_the_drive_s_pdo_is_refused_as_too_long_not_as_read_only():
    """Roboteq's RoboMC (v8.0): each TPDO mapping lists 2 entries, all read-write. The refusal
    says the drive maps at most 2; it does not call the mapping fixed or read-only (which the
    file, read here, does not say)."""
    assert all(_file_entry(ROBOTEQ, 0x1A00, sub).get('accesstype', '').lower() == 'rw' for sub in (0, 1, 2))
    with pytest.raises(DictionaryError) as err:
        master_for(config(eds=str(ROBOTEQ), load_cell_object='0x2146:1', homing_method=0)).plan()
    text = str(err.value)
    assert 'maps at most 2' in text, text
    assert 'read-only' not in text and 'fixed' not in text, text


@pytest.mark.parametrize('flaw', ['comments lines', 'empty revision number', 'a key twice'])
def test_a_file_with_a_format_flaw_that_describes_no_object_plans_as_the_clean_file_does(tmp_path, flaw):
    """Vendors' files that canopen's strict reader refuses whole, for flaws outside every
    object: a [Comments] section whose Lines is not its LineN count, an empty RevisionNumber,
    a key given twice. Read leniently, the boot is planned as the clean file's is (the
    oracle: the clean file's plan, read strictly), with a warning naming the flaw."""
    text = SLAVE.read_text(encoding='utf-8')
    if flaw == 'comments lines':
        text = text.replace('[Comments]\nLines=0\n', '[Comments]\nLines=2\nLine1=made by a tool\n', 1)
    elif flaw == 'empty revision number':
        text = re.sub(r'(?m)^(VendorNumber=.*\n)', r'\1RevisionNumber=\n', text, count=1)
    else:
        text = re.sub(r'(?m)^(\[1018\]\s*\n)', r'\1ParameterName=Identity\n', text, count=1)
    flawed = tmp_path / 'flawed_cia402_slave.eds'
    flawed.write_text(text, encoding='utf-8')
    with pytest.raises(Exception):                              # the strict reader refuses it
        canopen.import_od(str(flawed), 1)
    cell = {'load_cell_node': {'node_id': 10, 'eds': str(MODULE)}}
    clean = master_for(config(eds=str(SLAVE), **cell)).plan()[0]
    plan = master_for(config(eds=str(flawed), **cell)).plan()[0]
    assert plan.writes == clean.writes and plan.mapping == clean.mapping
    assert any('not a well-formed EDS/DCF' in w for w in plan.warnings), plan.warnings


def test_a_file_in_compact_pdo_storage_is_refused_saying_so(tmp_path):
    """CiA 306 compact PDO storage (``CompactPDO`` in [DeviceInfo], the PDOs' communication and
    mapping objects left out): the refusal says the file declares its PDOs that way and how to
    expand them, not that the drive has none."""
    eds = edited_eds(tmp_path, NANOTEC, drop=('14', '15', '16', '17', '18', '19', '1A', '1B'),
                     set_={('DeviceInfo', 'CompactPDO'): '0x3F'})
    with pytest.raises(DictionaryError) as err:
        master_for(config(eds=str(eds), load_cell_object='0x3220:1')).plan()
    assert 'CompactPDO' in str(err.value), str(err.value)
