"""Fault model without a bus: latching, 'recover only when the cause is gone', monitors."""
import can
import pytest

from brace_control.can.supervision import (FaultKind, Limits, Sample, Supervisor, check_sample,
                                           check_step, decode_error_frame)
from brace_control.can.units import scaling_from_config
from brace_control.config import ConfigError, load_device_config


@pytest.fixture(scope='module')
def cfg():
    return load_device_config('config/lumbar_brace.yaml')


@pytest.fixture(scope='module')
def limits(cfg):
    return Limits.from_config(cfg, scaling_from_config(cfg))


def test_limits_come_from_the_yaml(limits):
    assert limits.period == pytest.approx(0.002)
    assert limits.stroke == (0.34, 0.44)
    assert limits.saturation_counts == 28500
    assert limits.heartbeat_timeout == pytest.approx(0.15)


def test_consumer_time_must_exceed_producer_time(cfg):
    bad = dict(cfg)
    bad['can'] = dict(cfg['can'], heartbeat_consumer_ms=50)
    with pytest.raises(ConfigError, match='heartbeat_consumer_ms'):
        Limits.from_config(bad, scaling_from_config(cfg))


# docs/safety.md §4, §8
def test_a_fault_latches_once_and_calls_the_reaction():
    seen = []
    sup = Supervisor(on_fault=seen.append)
    assert sup.report(FaultKind.EMCY, 'EMCY 8611h', drive='a1') is not None
    assert sup.report(FaultKind.EMCY, 'again', drive='a1') is None
    assert sup.latched and len(seen) == 1 and sup.first.cause == 'EMCY 8611h'


def test_latch_clears_only_when_every_cause_is_gone():
    present = {'hb': True}
    sup = Supervisor()
    sup.report(FaultKind.HEARTBEAT_LOST, 'no heartbeat', drive='a2',
               still_present=lambda: present['hb'])
    sup.report(FaultKind.POSITION_JUMP, 'jump', drive='a1')     # momentary
    blocking = sup.try_clear()
    assert [f.kind for f in blocking] == [FaultKind.HEARTBEAT_LOST] and sup.latched
    present['hb'] = False
    assert sup.try_clear() == [] and not sup.latched


def test_a_predicate_that_fails_keeps_the_latch():
    sup = Supervisor()
    sup.report(FaultKind.EXTERNAL, 'x', still_present=lambda: 1 / 0)
    assert sup.try_clear() and sup.latched


def test_step_limit_is_vmax_dt_plus_margin(limits):
    dt = 0.002
    allowed = 0.065 * dt + 0.0005
    assert check_step('a1', 0.39, 0.39 + 0.99 * allowed, dt, limits) is None
    assert 'exceeds' in check_step('a1', 0.39, 0.39 + 1.01 * allowed, dt, limits)


# docs/safety.md §5, §7
def test_step_limit_ramps_down_near_the_stroke_end(limits):
    # 0.1 mm from the end a 0.6 mm step in 2 ms is allowed mid-stroke but not here
    assert check_step('a1', 0.39, 0.3906, 0.002, limits) is None
    assert check_step('a1', 0.4393, 0.4399, 0.002, limits) is not None
    assert 'outside the stroke' in check_step('a1', 0.439, 0.441, 0.002, limits)


def _sample(pos, *, load=0, k=1, sw=0x1637):
    return Sample(sw, pos, load * 0.01, load, k, k * 0.002)


# docs/safety.md §8, §9, §11
def test_monitors_flag_saturation_force_jump_and_following_error(limits):
    kinds = lambda found: {k for k, _ in found}   # noqa: E731
    assert kinds(check_sample(None, _sample(0.39, load=28500), limits, commanded=None)) == {
        FaultKind.LOAD_CELL_SATURATED}
    assert kinds(check_sample(None, _sample(0.39, load=25001), limits, commanded=None)) == {
        FaultKind.FORCE_LIMIT}
    prev, cur = _sample(0.39, k=1), _sample(0.392, k=2)
    assert FaultKind.POSITION_JUMP in kinds(check_sample(prev, cur, limits, commanded=0.392))
    assert kinds(check_sample(None, _sample(0.39), limits, commanded=0.3951)) == {
        FaultKind.FOLLOWING_ERROR}
    assert check_sample(prev, _sample(0.39012, k=2), limits, commanded=0.3902) == []


# docs/safety.md §3
def test_error_frames_decode_socketcan_layout():
    busoff = can.Message(is_error_frame=True, arbitration_id=0x040, data=bytes(8))
    passive = can.Message(is_error_frame=True, arbitration_id=0x004,
                          data=bytes([0, 0x30, 0, 0, 0, 0, 128, 128]))
    restarted = can.Message(is_error_frame=True, arbitration_id=0x100, data=bytes(8))
    assert decode_error_frame(busoff).bus_off
    p = decode_error_frame(passive)
    assert p.error_passive and not p.bus_off and 'TX error passive' in p.description
    assert decode_error_frame(restarted).restarted
