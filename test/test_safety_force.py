"""docs/safety.md §8, §9 and §14: a load cell at its saturation (§9), a force above the hard
limit (§8), a motion pressing past the soft limit (§14), as plain logic
(brace_control.safety.force), and the CAN layer's per-sample check
(brace_control.can.supervision.check_sample) built on it.

Oracles: the document's rules on hand-picked numbers of the lumbar brace (a load cell
saturated at 28500 counts from its zero, 95 % of its full scale; ``safety.force_limit`` =
250 N) and of the shoulder (25 N·m), each threshold from both sides; the reasons are
compared with literal texts (users and tests grep them). The bus-level behaviour is in
test_can_master.py (load-cell saturation, the fault matrix).
"""
from __future__ import annotations

import math

import pytest

from brace_control.can.supervision import FaultKind, Limits, Sample, check_sample
from brace_control.safety import OK, Action, force_limit, pressing_past_soft_limit, saturation

SATURATED = 28500        # counts from the zero: floor(0.95 x full scale / N per count)
LIMIT = 250.0            # N


def limits(**over) -> Limits:
    kw = dict(period=0.002, v_max=0.065, a_max=0.5, stroke=(0.34, 0.44), step_margin=0.0005,
              path_tolerance=0.005, force_limit=LIMIT, saturation_counts=SATURATED,
              stale_periods=5, heartbeat_timeout=0.15, boot_timeout=5.0, command_timeout=0.015)
    kw.update(over)
    return Limits(**kw)


def sample(counts: int, force: float, *, position: float = 0.39, k: int = 1) -> Sample:
    return Sample(0x1637, position, force, counts, k, k * 0.002)


# ---------------------------------------------------------------------- saturation (§9)

@pytest.mark.parametrize('counts', [0, 1000, SATURATED - 1, -(SATURATED - 1)])
def test_a_reading_below_saturation_is_ok(counts):
    assert saturation(counts, counts * 0.01, SATURATED) is OK


@pytest.mark.parametrize('counts, force, text', [
    (28500, 285.0, 'load cell reads 28500 counts (285.0 N), saturation at ±28500'),
    (-28500, -285.0, 'load cell reads -28500 counts (-285.0 N), saturation at ±28500'),
    (32767, 327.67, 'load cell reads 32767 counts (327.7 N), saturation at ±28500'),
])
def test_a_reading_at_or_above_saturation_either_way_is_a_protective_stop(counts, force, text):
    verdict = saturation(counts, force, SATURATED)
    assert verdict.action is Action.PROTECTIVE_STOP and verdict.reason == text


def test_a_real_valued_input_saturates_on_its_value():
    """A REAL32 load-cell input reads unrounded counts: 28499.9 is below, 28500.0 at it."""
    assert saturation(28499.9, 284.999, 28500) is OK
    assert saturation(28500.0, 285.0, 28500).reason == (
        'load cell reads 28500.0 counts (285.0 N), saturation at ±28500')


# ---------------------------------------------------------------------- the hard force limit (§8)

@pytest.mark.parametrize('force', [0.0, 249.9, LIMIT, -LIMIT, math.nextafter(LIMIT, 0.0)])
def test_a_force_up_to_the_limit_is_ok(force):
    assert force_limit(force, LIMIT) is OK


@pytest.mark.parametrize('force, text', [
    (250.1, 'load-cell force 250.1 N exceeds 250.0 N'),
    (-250.1, 'load-cell force -250.1 N exceeds 250.0 N'),
    (math.nextafter(LIMIT, math.inf), 'load-cell force 250.0 N exceeds 250.0 N'),
    (1e4, 'load-cell force 10000.0 N exceeds 250.0 N'),
])
def test_a_force_above_the_limit_either_way_is_a_protective_stop(force, text):
    verdict = force_limit(force, LIMIT)
    assert verdict.action is Action.PROTECTIVE_STOP and verdict.reason == text


def test_a_rotary_joints_torque_is_judged_on_the_same_rule_and_named_in_newton_metres():
    """The shoulder's limit is 25 N·m; the reason says N·m (it said N before)."""
    assert force_limit(24.99, 25.0, 'N·m') is OK
    assert force_limit(-25.0, 25.0, 'N·m') is OK
    verdict = force_limit(-25.04, 25.0, 'N·m')
    assert verdict.action is Action.PROTECTIVE_STOP
    assert verdict.reason == 'load-cell force -25.0 N·m exceeds 25.0 N·m'


# ---------------------------------------------------------------------- the CAN layer's check

def test_check_sample_reports_saturation_and_force_as_it_always_did():
    lim = limits()
    assert check_sample(None, sample(SATURATED - 1, 249.9), lim, commanded=None) == []
    assert check_sample(None, sample(28500, 285.0), lim, commanded=None) == [
        (FaultKind.LOAD_CELL_SATURATED, 'load cell reads 28500 counts (285.0 N), saturation at ±28500')]
    assert check_sample(None, sample(25001, 250.01), lim, commanded=None) == [
        (FaultKind.FORCE_LIMIT, 'load-cell force 250.0 N exceeds 250.0 N')]
    assert check_sample(None, sample(-25100, -251.0), lim, commanded=None) == [
        (FaultKind.FORCE_LIMIT, 'load-cell force -251.0 N exceeds 250.0 N')]
    assert check_sample(None, sample(25000, 250.0), lim, commanded=None) == []


def test_a_saturated_reading_is_not_judged_as_a_force():
    """Saturation wins: a saturated cell's force is not a measurement, so no FORCE_LIMIT
    beside it."""
    found = check_sample(None, sample(-30000, -300.0), limits(), commanded=None)
    assert found == [(FaultKind.LOAD_CELL_SATURATED,
                      'load cell reads -30000 counts (-300.0 N), saturation at ±28500')]


def test_the_load_cell_is_judged_whether_or_not_the_drive_tracks():
    """Force and saturation hold with or without a target; the tracking checks come after
    (docs/safety.md §8, §9, §11)."""
    found = check_sample(None, sample(26000, 260.0), limits(), commanded=0.39)
    assert found == [(FaultKind.FORCE_LIMIT, 'load-cell force 260.0 N exceeds 250.0 N')]
    found = check_sample(None, sample(26000, 260.0), limits(), commanded=0.4)
    assert [kind for kind, _ in found] == [FaultKind.FORCE_LIMIT, FaultKind.FOLLOWING_ERROR]


def test_a_rotary_joints_check_names_newton_metres():
    lim = limits(unit='rad', force_limit=25.0, stroke=(-1.5708, 1.5708), v_max=6.0, a_max=30.0,
                 step_margin=0.005, path_tolerance=0.08)
    assert check_sample(None, sample(2000, 24.9, position=0.1), lim, commanded=None) == []
    assert check_sample(None, sample(2600, 26.0, position=0.1), lim, commanded=None) == [
        (FaultKind.FORCE_LIMIT, 'load-cell force 26.0 N·m exceeds 25.0 N·m')]


# ---------------------------------------------------------------------- the soft tier (§14)

SOFT = 200.0      # the lumbar brace's soft limit: 0.8 x 250 N (docs/safety.md §14)


def test_a_leg_above_the_soft_limit_that_keeps_rising_is_to_brake():
    """Above the soft limit, a rise of more than 0.5 N since the oldest of at least five
    recent samples: the motion still presses."""
    recent = [200.0, 200.2, 200.4, 200.5, 200.5]
    assert pressing_past_soft_limit(200.51, recent, SOFT)
    assert pressing_past_soft_limit(-200.51, recent, SOFT)          # either direction
    assert not pressing_past_soft_limit(200.5, recent, SOFT)        # a rise of 0.5 N exactly


def test_a_leg_above_the_soft_limit_that_unloads_goes_on():
    """A motion that unloads the leg (its force falling) is not braked, however high."""
    assert not pressing_past_soft_limit(240.0, [245.0, 244.0, 243.0, 242.0, 241.0], SOFT)


def test_nothing_is_judged_at_or_below_the_soft_limit_or_on_too_few_samples():
    assert not pressing_past_soft_limit(SOFT, [150.0] * 5, SOFT)
    assert not pressing_past_soft_limit(210.0, [150.0] * 4, SOFT)
    assert pressing_past_soft_limit(210.0, [150.0] * 5, SOFT)
