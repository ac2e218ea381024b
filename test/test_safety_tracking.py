"""docs/safety.md §9 and §11: a position jump no actuator can make (§9), the following error
(§11), as plain logic (brace_control.safety.tracking), and the CAN layer's per-sample check
(brace_control.can.supervision.check_sample) built on it.

Oracles: the document's bounds written out here (a jump above ``4·v_max·Δt + margin``;
``|target − actual|`` above ``safety.path_tolerance``) on the lumbar brace's numbers (65 mm/s,
0.5 mm margin, 5 mm tolerance, 500 Hz) and the shoulder's (6 rad/s, 5 mrad, 80 mrad), each
threshold from both sides; the reasons are compared with literal texts (users and tests grep
them). The bus-level behaviour is in test_can_master.py (encoder jump, a stalled actuator).
"""
from __future__ import annotations

import pytest

from brace_control.can.supervision import FaultKind, Limits, Sample, check_sample
from brace_control.safety import OK, Action, following_error, position_jump

PERIOD = 0.002
LUMBAR = dict(v_max=0.065, jump_factor=4.0, margin=0.0005)
ROTARY = dict(v_max=6.0, jump_factor=4.0, margin=0.005)


def jump_bound(dt: float, *, v_max: float, jump_factor: float, margin: float) -> float:
    """docs/safety.md §9: the most an actuator can move in ``dt``."""
    return jump_factor * v_max * dt + margin


def limits(**over) -> Limits:
    kw = dict(period=PERIOD, v_max=0.065, a_max=0.5, stroke=(0.34, 0.44), step_margin=0.0005,
              path_tolerance=0.005, force_limit=250.0, saturation_counts=28500, stale_periods=5,
              heartbeat_timeout=0.15, boot_timeout=5.0, command_timeout=0.015)
    kw.update(over)
    return Limits(**kw)


def sample(position: float, k: int) -> Sample:
    return Sample(0x1637, position, 0.0, 0, k, k * PERIOD)


# ---------------------------------------------------------------------- position jump (§9)

def test_one_period_allows_four_times_v_max_plus_the_margin():
    # 4 x 65 mm/s x 2 ms + 0.5 mm = 1.02 mm
    assert jump_bound(PERIOD, **LUMBAR) == pytest.approx(0.00102)
    assert position_jump(0.39, 0.39 + 0.001019, PERIOD, **LUMBAR) is OK
    assert position_jump(0.39, 0.39 - 0.001019, PERIOD, **LUMBAR) is OK
    verdict = position_jump(0.39, 0.391021, PERIOD, **LUMBAR)
    assert verdict.action is Action.PROTECTIVE_STOP
    assert verdict.reason == 'position changed 1.021 mm in 2.0 ms (physically at most 1.020 mm)'
    verdict = position_jump(0.39, 0.388979, PERIOD, **LUMBAR)
    assert verdict.reason == 'position changed 1.021 mm in 2.0 ms (physically at most 1.020 mm)'


@pytest.mark.parametrize('periods', [1, 2, 3, 10])
@pytest.mark.parametrize('sign', [1.0, -1.0])
def test_the_bound_grows_with_the_time_between_the_samples(periods, sign):
    dt = periods * PERIOD
    bound = jump_bound(dt, **LUMBAR)
    assert position_jump(0.39, 0.39 + sign * bound * (1 - 1e-6), dt, **LUMBAR) is OK
    verdict = position_jump(0.39, 0.39 + sign * bound * (1 + 1e-6), dt, **LUMBAR)
    assert verdict.action is Action.PROTECTIVE_STOP
    assert verdict.reason.startswith('position changed ')
    assert verdict.reason.endswith(f' in {dt * 1e3:.1f} ms (physically at most {bound * 1e3:.3f} mm)')


def test_three_periods_worked_by_hand():
    # 4 x 65 mm/s x 6 ms + 0.5 mm = 2.06 mm
    assert position_jump(0.39, 0.39205, 3 * PERIOD, **LUMBAR) is OK
    assert position_jump(0.39, 0.3921, 3 * PERIOD, **LUMBAR).reason == (
        'position changed 2.100 mm in 6.0 ms (physically at most 2.060 mm)')


def test_a_rotary_jump_is_judged_on_its_own_v_max_and_named_in_mrad():
    """6 rad/s: 4 x 6 x 0.002 + 0.005 = 0.053 rad. The reason says mrad (it said mm before)."""
    assert position_jump(0.0, 0.0529, PERIOD, **ROTARY, unit='rad') is OK
    verdict = position_jump(0.0, 0.0531, PERIOD, **ROTARY, unit='rad')
    assert verdict.action is Action.PROTECTIVE_STOP
    assert verdict.reason == 'position changed 53.100 mrad in 2.0 ms (physically at most 53.000 mrad)'


# ---------------------------------------------------------------------- following error (§11)

@pytest.mark.parametrize('actual', [0.39, 0.39499, 0.38501])
def test_an_error_within_the_tolerance_is_ok(actual):
    assert following_error(actual, 0.39, 0.005) is OK


def test_an_error_beyond_the_tolerance_either_way_is_a_protective_stop():
    verdict = following_error(0.39, 0.3951, 0.005)
    assert verdict.action is Action.PROTECTIVE_STOP
    assert verdict.reason == 'actual 0.39000 m is 5.10 mm from the target 0.39510 m (path tolerance 5.00 mm)'
    verdict = following_error(0.3951, 0.39, 0.005)
    assert verdict.reason == 'actual 0.39510 m is 5.10 mm from the target 0.39000 m (path tolerance 5.00 mm)'


@pytest.mark.parametrize('sign', [1.0, -1.0])
def test_the_tolerance_from_both_sides(sign):
    assert following_error(0.39 + sign * 0.005 * (1 - 1e-6), 0.39, 0.005) is OK
    verdict = following_error(0.39 + sign * 0.005 * (1 + 1e-6), 0.39, 0.005)
    assert verdict.action is Action.PROTECTIVE_STOP and ' from the target ' in verdict.reason


def test_a_rotary_following_error_uses_its_tolerance_in_rad_and_names_rad():
    assert following_error(0.5, 0.579, 0.08, 'rad') is OK
    verdict = following_error(0.5, 0.581, 0.08, 'rad')
    assert verdict.action is Action.PROTECTIVE_STOP
    assert verdict.reason == (
        'actual 0.50000 rad is 81.00 mrad from the target 0.58100 rad (path tolerance 80.00 mrad)')


# ---------------------------------------------------------------------- the CAN layer's check

def test_check_sample_reports_jump_and_following_error_as_it_always_did():
    lim = limits()
    prev = sample(0.39, 1)
    assert check_sample(prev, sample(0.391019, 2), lim, commanded=0.391) == []
    assert check_sample(prev, sample(0.392, 2), lim, commanded=0.392) == [
        (FaultKind.POSITION_JUMP, 'position changed 2.000 mm in 2.0 ms (physically at most 1.020 mm)')]
    assert check_sample(None, sample(0.39, 1), lim, commanded=0.3951) == [
        (FaultKind.FOLLOWING_ERROR,
         'actual 0.39000 m is 5.10 mm from the target 0.39510 m (path tolerance 5.00 mm)')]
    # both, in that order
    assert check_sample(prev, sample(0.392, 2), lim, commanded=0.3980) == [
        (FaultKind.POSITION_JUMP, 'position changed 2.000 mm in 2.0 ms (physically at most 1.020 mm)'),
        (FaultKind.FOLLOWING_ERROR,
         'actual 0.39200 m is 6.00 mm from the target 0.39800 m (path tolerance 5.00 mm)')]


def test_the_jump_is_judged_over_the_syncs_between_the_two_samples():
    lim = limits()
    # two SYNCs apart: 4 x 65 mm/s x 4 ms + 0.5 mm = 1.54 mm
    assert check_sample(sample(0.39, 1), sample(0.3915, 3), lim, commanded=0.392) == []
    assert check_sample(sample(0.39, 1), sample(0.3922, 3), lim, commanded=0.392) == [
        (FaultKind.POSITION_JUMP, 'position changed 2.200 mm in 4.0 ms (physically at most 1.540 mm)')]


def test_no_tracking_check_without_a_target_or_a_newer_sample():
    lim = limits()
    # not tracking (disabled, homing): neither jump nor following error
    assert check_sample(sample(0.39, 1), sample(0.40, 2), lim, commanded=None) == []
    # the same sample again, or an older one: no jump judged; the following error still is
    assert check_sample(sample(0.39, 2), sample(0.40, 2), lim, commanded=0.40) == []
    assert check_sample(sample(0.39, 3), sample(0.40, 2), lim, commanded=0.40) == []
    assert check_sample(None, sample(0.40, 2), lim, commanded=0.406) == [
        (FaultKind.FOLLOWING_ERROR,
         'actual 0.40000 m is 6.00 mm from the target 0.40600 m (path tolerance 5.00 mm)')]
