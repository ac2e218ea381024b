"""Pure parts of the CAN layer: unit scaling, CiA 402 decoding, PDO layouts, timing.

Oracles are the numbers of docs/can.md and CiA 402-2 tables, not the code.
"""
import math
import struct
import threading
import time
from pathlib import Path

import canopen
import numpy as np
import pytest
from canopen import objectdictionary as od

from brace_control.can.cia402 import (STATE_STATUSWORD, Controlword, EmcyCode, ErrorRegister,
                                      NmtState, State402, controlword_towards, decode_state,
                                      describe_statusword, emcy_description, error_register_bits)
from brace_control.can.pdo import RPDO1, RPDO2, TPDO1, frame_bits
from brace_control.can.plan import pdo_mapping_writes
from brace_control.can.timing import PeriodStats, run_periodic
from brace_control.can.units import AxisScaling, scaling_from_config
from brace_control.config import ConfigError, load_device_config


@pytest.fixture(scope='module')
def scaling():
    return scaling_from_config(load_device_config('config/lumbar_brace.yaml'))


def test_linear_scaling_is_8192000_counts_per_metre(scaling):
    assert scaling.counts_per_unit == pytest.approx(8192 / 0.001)
    assert scaling.to_counts(0.39) == 3194880
    assert scaling.to_si(3194880) == pytest.approx(0.39)
    assert scaling.velocity_to_counts(0.065) == 532480


def test_load_cell_newtons_per_count_and_int16_saturation(scaling):
    assert scaling.force_to_si(12345) == pytest.approx(123.45)
    assert scaling.force_to_counts(1e6) == 32767
    # 95 % of 300 N at 0.01 N/count
    assert scaling.saturation_counts(0.95) == 28500


def test_rotary_scaling_counts_per_radian():
    s = AxisScaling.rotary(encoder_counts_per_rev=4096, gear_ratio=10.0,
                           newton_metre_per_count=0.001, rated_torque_nm=5.0)
    assert s.to_counts(math.pi) == 4096 * 10 // 2


def test_bad_scaling_names_the_parameter():
    with pytest.raises(ConfigError, match='screw_lead'):
        scaling_from_config({'actuator': {'encoder_counts_per_rev': 8192, 'screw_lead': 0.0,
                                          'load_cell_n_per_count': 0.01,
                                          'load_cell_rated_force': 300.0}})


def test_position_overflow_is_an_error_not_a_wrap(scaling):
    with pytest.raises(OverflowError):
        scaling.to_counts(1000.0)


@pytest.mark.parametrize('sw, state', [
    (0x0250, State402.SWITCH_ON_DISABLED),     # CiA 402-2 table 30: xxxx xxxx x1xx 0000
    (0x0231, State402.READY_TO_SWITCH_ON),
    (0x0233, State402.SWITCHED_ON),
    (0x1637, State402.OPERATION_ENABLED),
    (0x0217, State402.QUICK_STOP_ACTIVE),
    (0x021F, State402.FAULT_REACTION_ACTIVE),
    (0x0218, State402.FAULT),
    (0x0000, State402.NOT_READY_TO_SWITCH_ON),
])
def test_statusword_decodes_to_the_cia402_state(sw, state):
    assert decode_state(sw) is state


def test_statusword_description_lists_warning_and_internal_limit():
    assert describe_statusword(0x08B7) == 'OPERATION ENABLED, warning, internal limit'


def test_enable_path_follows_the_cia402_transitions():
    seq, state = [], State402.SWITCH_ON_DISABLED
    nxt = {0x06: State402.READY_TO_SWITCH_ON, 0x07: State402.SWITCHED_ON,
           0x0F: State402.OPERATION_ENABLED}
    while state is not State402.OPERATION_ENABLED:
        cw = controlword_towards(state, State402.OPERATION_ENABLED)
        seq.append(cw)
        state = nxt[cw]
    assert seq == [0x06, 0x07, 0x0F]
    assert controlword_towards(State402.QUICK_STOP_ACTIVE, State402.OPERATION_ENABLED) == 0x00
    assert controlword_towards(State402.OPERATION_ENABLED, State402.QUICK_STOP_ACTIVE) == 0x02
    assert controlword_towards(State402.OPERATION_ENABLED, State402.OPERATION_ENABLED) == 0x0F


def test_no_command_leaves_fault_but_a_reset():
    assert controlword_towards(State402.FAULT, State402.OPERATION_ENABLED) is None
    assert Controlword.FAULT_RESET == 0x80


def test_emcy_codes_decode_exact_then_by_class():
    assert emcy_description(0x8611) == 'following error'
    assert emcy_description(0x8130) == 'life guard or heartbeat error'
    assert emcy_description(0x2399) == 'current'
    assert emcy_description(0x0000) == 'error reset / no error'


def test_pdo_layouts_match_docs_can_md():
    assert RPDO1.size == 6 and TPDO1.size == 8 and RPDO2.size == 4
    assert RPDO1.pack(0x0F, -2) == struct.pack('<Hi', 0x0F, -2)
    assert RPDO2.pack(-532480) == struct.pack('<i', -532480)     # 60B1h, counts/s
    seq = [(w.index, w.subindex, w.value) for w in pdo_mapping_writes(2)]
    writes = set(seq)
    assert (0x1600, 1, 0x60400010) in writes and (0x1600, 2, 0x607A0020) in writes
    assert (0x1A00, 3, 0x24010010) in writes and (0x1800, 1, 0x182) in writes
    # RPDO2: 60B1h:00, 32 bit, transmission type 1, COB-ID 300h + id; CiA 301 order:
    # invalid COB-ID, count 0, entry, count, type, valid COB-ID
    rpdo2 = [w for w in seq if w[0] in (0x1401, 0x1601)]
    assert rpdo2 == [(0x1401, 1, 0x80000302), (0x1601, 0, 0), (0x1601, 1, 0x60B10020),
                     (0x1601, 0, 1), (0x1401, 2, 1), (0x1401, 1, 0x302)]
    # the rest disabled: RPDO3/4, TPDO2-4
    for index, cob in ((0x1402, 0x402), (0x1403, 0x502), (0x1801, 0x282), (0x1802, 0x382),
                       (0x1803, 0x482)):
        assert [w[2] for w in seq if w[:2] == (index, 1)] == [0x80000000 | cob]


def test_eds_describes_the_velocity_offset_and_rpdo2():
    eds = canopen.import_od(str(Path(__file__).resolve().parent.parent / 'config' / 'lumbar_drive.eds'), 2)
    vo = eds[0x60B1]
    assert vo.data_type == od.INTEGER32 and vo.pdo_mappable and vo.writable and vo.readable
    assert eds[0x1401][1].default == 0x302 and eds[0x1401][2].default == 1
    assert eds[0x1601][0].default == 1 and eds[0x1601][1].default == 0x60B10020
    assert eds[0x6062].data_type == od.INTEGER32 and eds[0x6062].pdo_mappable


def test_cia402_state_bits_error_register_and_nmt_codes():
    # CiA 402-2 table 30: the bits a drive in each state shows (x = 0)
    assert STATE_STATUSWORD[State402.SWITCH_ON_DISABLED] == 0b0100_0000
    assert STATE_STATUSWORD[State402.READY_TO_SWITCH_ON] == 0b0010_0001
    assert STATE_STATUSWORD[State402.OPERATION_ENABLED] == 0b0010_0111
    assert STATE_STATUSWORD[State402.QUICK_STOP_ACTIVE] == 0b0000_0111
    assert STATE_STATUSWORD[State402.FAULT] == 0b0000_1000
    for state, bits in STATE_STATUSWORD.items():
        assert decode_state(bits) is state
    # CiA 301 1001h: generic bit 0 with the class bit (4 communication, 5 device profile)
    assert error_register_bits(EmcyCode.FOLLOWING_ERROR) == ErrorRegister.GENERIC | ErrorRegister.DEVICE_PROFILE == 0x21
    assert error_register_bits(EmcyCode.HEARTBEAT) == 0x11
    assert error_register_bits(0x2310) == 0x03 and error_register_bits(0x5530) == 0x01
    assert error_register_bits(EmcyCode.NO_ERROR) == 0
    assert NmtState.INITIALISING == NmtState.BOOTUP == 0x00 and NmtState.PRE_OPERATIONAL == 0x7F
    assert emcy_description(EmcyCode.REFERENCE_LIMIT).startswith('reference limit')


def test_bus_load_estimate_of_docs_can_md():
    # SYNC + 3 RPDO1 + 3 RPDO2 + 3 TPDO1 per 2 ms, worst-case stuffing: docs/can.md says
    # 1090 bits, 55 % at 1 Mbit/s (805 bits, 40 %, without the three RPDO2)
    bits = frame_bits(0) + 3 * frame_bits(6) + 3 * frame_bits(4) + 3 * frame_bits(8)
    # by hand: 47 + 8 dlc + floor((33 + 8 dlc) / 4) per frame
    assert bits == (47 + 8) + 3 * (47 + 48 + 20) + 3 * (47 + 32 + 16) + 3 * (47 + 64 + 24) == 1090
    assert 0.54 < bits / 0.002 / 1e6 < 0.55


class _ScriptedClock:
    """A ``time`` stand-in for brace_control.can.timing: ``perf_counter`` advances 1 us per read
    (a spin ends), ``sleep`` wakes ``oversleep`` late, the loop's body advances it by the work
    it was scripted to take."""

    def __init__(self, rng):
        self.now = 100.0
        self.rng = rng

    def perf_counter(self):
        self.now += 1e-6
        return self.now

    def sleep(self, s):
        # the kernel's overshoot: mostly under the spin's 0.3 ms, sometimes a preemption of up to
        # 5 periods
        over = self.rng.choice([self.rng.uniform(0.0, 2e-4), self.rng.uniform(0.0, 0.01)],
                               p=[0.9, 0.1])
        self.now += s + over


def test_periodic_loop_keeps_absolute_deadlines(monkeypatch):
    """run_periodic on a scripted clock, judged by the definition of absolute deadlines: the
    grid is start + j·period; each tick wakes at the first grid deadline not yet passed when the
    previous cycle's work ended (the ones passed are skipped and counted as overruns), and no
    later than the sleep's own overshoot beyond it; never early. The scripted work is mostly
    short, sometimes over a period, once a 1.84 s stall (the stalls a loaded host gave)."""
    from brace_control.can import timing
    period, n = 0.002, 400
    rng = np.random.default_rng(11)
    clock = _ScriptedClock(rng)
    monkeypatch.setattr(timing, 'time', clock)
    work = rng.choice([1e-4, 1.5e-3, 3.1e-3, 7.9e-3], size=n, p=[0.7, 0.2, 0.07, 0.03])
    work[150] = 1.84
    ticks, ends = [], []

    def body(k, t):
        ticks.append(t)
        clock.now += work[k]
        ends.append(clock.now)

    stats = PeriodStats(period)
    start = clock.now                   # the grid's origin: run_periodic reads the clock next
    run_periodic(period, body, threading.Event(), stats=stats, max_cycles=n)
    ticks, ends = np.array(ticks), np.array(ends)
    assert len(ticks) == n and stats.cycles == n
    skipped = 0
    for m in range(n):
        if m == 0:
            j = 1
        else:
            j = math.floor((ends[m - 1] - start) / period) + 1      # first grid point after the end
            j = max(j, j_prev + 1)
            skipped += j - j_prev - 1
        deadline = start + j * period
        # the grid point itself (within the clock's reads), or the sleep's overshoot past it
        assert deadline - 1e-5 <= ticks[m] <= deadline + 0.0101, (m, ticks[m] - deadline)
        j_prev = j
    assert stats.overruns == skipped and skipped >= 920        # the stall alone skips 919-920
    # not a relative sleep: 400 ticks plus the skipped deadlines, on the grid to the end
    assert (ticks[-1] - start) / period == pytest.approx(n + skipped, abs=5.1)


def test_periodic_loop_on_the_real_clock_is_never_early_and_keeps_its_grid():
    """The same loop on the machine's clock. What a loaded host cannot change: no tick before its
    deadline; the median tick within half a period of the grid (a relative sleep drifts by its
    latency every tick: tens of periods by the end). How often it wakes late is the scheduler's
    business: measured in bench/bench_can.py's bare floor, not here."""
    stats = PeriodStats(0.002)
    ticks, missed = [], []              # each tick's wake time, and the misses counted before it
    start = time.perf_counter()
    run_periodic(0.002, lambda k, t: (ticks.append(t), missed.append(stats.overruns)),
                 threading.Event(), stats=stats, max_cycles=200)
    # the m-th tick wakes on the grid start + (1 + g)·period, g = m plus the deadlines missed
    # (skipped and counted) before it. The grid's origin is taken before the call, not from the
    # first tick: that one may itself be late
    phase = (np.array(ticks) - start) / 0.002 - 1.0
    grid = np.arange(200) + np.array(missed)
    late = phase - grid
    assert np.all(late >= 0.0), late
    assert np.median(late) < 0.5, late
    assert stats.cycles == 200


def test_the_feedbacks_samples_answer_the_newest_sync_every_drive_answered():
    """Receiver.feedback's pairing (receive._newest_common) against its definition, on random
    histories: each drive's recent samples in SYNC order (non-decreasing SYNC numbers, some
    SYNCs missed, a few answered twice); the samples of the largest SYNC number all of them
    hold, each drive's newest of that number; none when they hold none in common."""
    from brace_control.can.receive import _newest_common
    from brace_control.can.supervision import Sample
    rng = np.random.default_rng(7)
    for trial in range(3000):
        drives = int(rng.integers(1, 5))
        start = int(rng.integers(0, 4))
        recent = []
        for d in range(drives):
            k, r = start, []
            for _ in range(int(rng.integers(1, 17))):
                k += int(rng.choice([0, 1, 1, 1, 1, 2, 3]))     # twice, next, or missed ones
                r.append(Sample(0, float(len(r)), 0.0, 0, k, float(d)))
            recent.append(tuple(r))
        common = set.intersection(*({s.sync_index for s in r} for r in recent))
        got = _newest_common(recent)
        if not common:
            assert got is None, trial
            continue
        k = max(common)
        expected = [[s for s in r if s.sync_index == k][-1] for r in recent]
        assert got is not None and all(a is b for a, b in zip(got, expected)), trial
