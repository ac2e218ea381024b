"""docs/safety.md §5 and §7: the stroke and the velocity ramp near its ends (§5), the step
limit (§7), as plain logic (brace_control.safety.stroke), and the CAN layer's check of a new
target (brace_control.can.supervision.check_step, Limits.max_step) built on it.

Oracles: the document's rule written out here (``v·dt + margin``, ``v = min(v_max,
√(2·a_max·d))``, ``d`` the distance from the new target to the end it heads for) and numbers
worked by hand for the lumbar brace (0.34–0.44 m, 65 mm/s, 0.5 m/s², 0.5 mm margin, 500 Hz)
and a rotary joint (±1.5708 rad, 6 rad/s, 30 rad/s², 5 mrad margin). The reasons are
compared with literal texts (users and tests grep them). The bus-level behaviour is in
test_can_master.py (bad setpoints, a stream that steps).
"""
from __future__ import annotations

import math

import pytest

from brace_control.can.supervision import FaultKind, Limits, check_step
from brace_control.safety import OK, Action, max_step, step_limit, stroke

DT = 0.002                                        # s, one SYNC period at 500 Hz
LUMBAR = dict(lo=0.34, hi=0.44, v_max=0.065, a_max=0.5, margin=0.0005)
ROTARY = dict(lo=-1.5708, hi=1.5708, v_max=6.0, a_max=30.0, margin=0.005)


def doc_bound(current: float, new: float, dt: float, *, lo: float, hi: float, v_max: float,
              a_max: float, margin: float) -> float:
    """docs/safety.md §5, §7, as the document words it: the end approached is the one ``new``
    lies towards from ``current`` (the low one when it does not move), ``d`` the distance
    from ``new`` to it (none left once ``new`` is on it or past it)."""
    d = hi - new if new > current else new - lo
    v = min(v_max, math.sqrt(2.0 * a_max * max(d, 0.0)))
    return v * dt + margin


def limits(unit: str = 'm', **over) -> Limits:
    """The CAN layer's thresholds with the numbers above (no config file read)."""
    base = LUMBAR if unit == 'm' else ROTARY
    kw = dict(period=DT, v_max=base['v_max'], a_max=base['a_max'], stroke=(base['lo'], base['hi']),
              step_margin=base['margin'], path_tolerance=0.005, force_limit=250.0,
              saturation_counts=28500, stale_periods=5, heartbeat_timeout=0.15, boot_timeout=5.0,
              command_timeout=0.015, unit=unit)
    kw.update(over)
    return Limits(**kw)


# ---------------------------------------------------------------------- the stroke (§5)

@pytest.mark.parametrize('new', [0.34, 0.39, 0.44])
def test_a_target_inside_the_stroke_or_on_its_ends_is_ok(new):
    assert stroke(new, 0.34, 0.44) is OK


@pytest.mark.parametrize('new, text', [
    (0.4400001, 'target 0.44000 m is outside the stroke 0.340–0.440 m'),
    (0.441, 'target 0.44100 m is outside the stroke 0.340–0.440 m'),
    (0.3399999, 'target 0.34000 m is outside the stroke 0.340–0.440 m'),
    (-0.2, 'target -0.20000 m is outside the stroke 0.340–0.440 m'),
    (math.nan, 'target nan m is outside the stroke 0.340–0.440 m'),
    (math.inf, 'target inf m is outside the stroke 0.340–0.440 m'),
])
def test_a_target_outside_the_stroke_or_not_a_number_is_a_protective_stop(new, text):
    verdict = stroke(new, 0.34, 0.44)
    assert verdict.action is Action.PROTECTIVE_STOP and verdict.reason == text


def test_a_rotary_joint_names_its_joint_range_in_rad():
    assert stroke(1.5707, -1.5708, 1.5708, 'rad') is OK
    verdict = stroke(1.6, -1.5708, 1.5708, 'rad')
    assert verdict.action is Action.PROTECTIVE_STOP
    assert verdict.reason == 'target 1.60000 rad is outside the joint range -1.571–1.571 rad'


# ---------------------------------------------------------------------- the bound and its ramp (§5, §7)

def test_mid_stroke_the_bound_is_v_max_dt_plus_margin():
    # 65 mm/s x 2 ms + 0.5 mm = 0.63 mm, either direction
    assert max_step(0.39, 0.3905, DT, **LUMBAR) == pytest.approx(0.00063, abs=1e-15)
    assert max_step(0.39, 0.3895, DT, **LUMBAR) == pytest.approx(0.00063, abs=1e-15)


def test_near_the_end_approached_the_speed_ramps_to_sqrt_2_a_d():
    # 0.1 mm from the upper end: v = sqrt(2 x 0.5 x 0.0001) = 10 mm/s -> 0.02 + 0.5 = 0.52 mm
    assert max_step(0.4393, 0.4399, DT, **LUMBAR) == pytest.approx(0.00052, abs=1e-12)
    # the same near the lower end, heading down
    assert max_step(0.3407, 0.3401, DT, **LUMBAR) == pytest.approx(0.00052, abs=1e-12)
    # heading away from the end it is near: the other end is far, v_max
    assert max_step(0.4399, 0.4395, DT, **LUMBAR) == pytest.approx(0.00063, abs=1e-15)
    # on the end itself (or past it) no speed is left: the margin alone
    assert max_step(0.4395, 0.44, DT, **LUMBAR) == pytest.approx(0.0005, abs=1e-15)
    assert max_step(0.44, 0.441, DT, **LUMBAR) == pytest.approx(0.0005, abs=1e-15)


def test_the_ramp_starts_where_sqrt_2_a_d_falls_below_v_max():
    d0 = 0.065 ** 2 / (2 * 0.5)                   # 4.225 mm from the end
    far, near = 0.44 - d0 * 1.01, 0.44 - d0 * 0.99
    assert max_step(far - 0.0003, far, DT, **LUMBAR) == pytest.approx(0.065 * DT + 0.0005)
    assert max_step(near - 0.0003, near, DT, **LUMBAR) < 0.065 * DT + 0.0005


@pytest.mark.parametrize('current, new', [
    (0.39, 0.3905), (0.3905, 0.39), (0.4393, 0.4399), (0.3407, 0.3401), (0.4399, 0.4395),
    (0.4, 0.4), (0.34, 0.34), (0.436, 0.4362), (0.3, 0.35),
])
@pytest.mark.parametrize('dt', [0.0005, DT, 0.015])
def test_the_bound_is_the_documents_rule(current, new, dt):
    assert max_step(current, new, dt, **LUMBAR) == pytest.approx(doc_bound(current, new, dt, **LUMBAR),
                                                                 rel=1e-12, abs=1e-15)


@pytest.mark.parametrize('new', [0.3905, 0.4399, 0.4362, 0.3401])
@pytest.mark.parametrize('up', [True, False])
def test_a_step_just_within_the_bound_is_ok_and_just_beyond_it_a_protective_stop(new, up):
    """The bound depends on the new target and the direction only: ``new`` fixed, the
    current target just within and just beyond it."""
    bound = doc_bound(new - 0.001 if up else new + 0.001, new, DT, **LUMBAR)
    sign = 1.0 if up else -1.0
    within, beyond = new - sign * bound * (1 - 1e-6), new - sign * bound * (1 + 1e-6)
    assert step_limit(within, new, DT, **LUMBAR) is OK
    verdict = step_limit(beyond, new, DT, **LUMBAR)
    assert verdict.action is Action.PROTECTIVE_STOP
    assert verdict.reason.startswith('target step ') and ' exceeds ' in verdict.reason


def test_the_step_reason_gives_step_time_and_bound_in_mm():
    assert step_limit(0.39, 0.3906, DT, **LUMBAR) is OK                  # 0.6 mm < 0.63 mm
    verdict = step_limit(0.4393, 0.4399, DT, **LUMBAR)                   # 0.6 mm > 0.52 mm
    assert verdict.action is Action.PROTECTIVE_STOP
    assert verdict.reason == 'target step 0.600 mm in 2.0 ms exceeds 0.520 mm (v_max·dt + margin)'
    verdict = step_limit(0.4, 0.39, 0.015, **LUMBAR)                     # 10 mm > 1.475 mm
    assert verdict.reason == 'target step 10.000 mm in 15.0 ms exceeds 1.475 mm (v_max·dt + margin)'


def test_a_rotary_step_is_judged_and_named_in_mrad():
    # mid-range: 6 rad/s x 2 ms + 5 mrad = 17 mrad
    assert max_step(0.0, 0.01, DT, **ROTARY) == pytest.approx(0.017)
    assert step_limit(0.0, 0.0169, DT, unit='rad', **ROTARY) is OK
    verdict = step_limit(0.0, 0.0171, DT, unit='rad', **ROTARY)
    assert verdict.action is Action.PROTECTIVE_STOP
    assert verdict.reason == 'target step 17.100 mrad in 2.0 ms exceeds 17.000 mrad (v_max·dt + margin)'
    # 10 mrad from the end: v = sqrt(2 x 30 x 0.01) = 0.7746 rad/s -> 1.549 + 5 = 6.549 mrad
    new = 1.5608
    assert max_step(new - 0.006, new, DT, **ROTARY) == pytest.approx(math.sqrt(0.6) * DT + 0.005)
    assert step_limit(new - 0.0065, new, DT, unit='rad', **ROTARY) is OK
    verdict = step_limit(new - 0.0066, new, DT, unit='rad', **ROTARY)
    assert verdict.reason == 'target step 6.600 mrad in 2.0 ms exceeds 6.549 mrad (v_max·dt + margin)'


# ---------------------------------------------------------------------- the CAN layer's check

def test_check_step_gives_the_texts_it_always_gave():
    lim = limits()
    assert check_step('a1', 0.39, 0.3906, DT, lim) is None
    assert check_step('a1', 0.4393, 0.4399, DT, lim) == (
        'target step 0.600 mm in 2.0 ms exceeds 0.520 mm (v_max·dt + margin)')
    assert check_step('a1', 0.439, 0.441, DT, lim) == 'target 0.44100 m is outside the stroke 0.340–0.440 m'
    # the stroke is judged first: a target outside it names the stroke, not the step
    assert check_step('a1', 0.39, 0.5, DT, lim) == 'target 0.50000 m is outside the stroke 0.340–0.440 m'
    assert check_step('a1', 0.39, math.nan, DT, lim) == 'target nan m is outside the stroke 0.340–0.440 m'
    rot = limits('rad')
    assert check_step('j1', 0.0, 0.0169, DT, rot) is None
    assert check_step('j1', 0.0, 0.0171, DT, rot) == (
        'target step 17.100 mrad in 2.0 ms exceeds 17.000 mrad (v_max·dt + margin)')
    assert check_step('j1', 1.5, 1.6, DT, rot) == (
        'target 1.60000 rad is outside the joint range -1.571–1.571 rad')
    assert FaultKind.STEP_LIMIT.value == 'step limit'           # what the cycle latches it as


def test_check_step_uses_each_actuators_own_range():
    lim = limits(strokes=((0.34, 0.44), (0.30, 0.40)))
    assert check_step('a2', 0.395, 0.399, DT, lim, 1) == (
        'target step 4.000 mm in 2.0 ms exceeds 0.563 mm (v_max·dt + margin)')
    # 1 mm from actuator 2's upper end: sqrt(2 x 0.5 x 0.001) = 31.6 mm/s -> 0.563 mm
    assert check_step('a2', 0.3985, 0.399, DT, lim, 1) is None
    assert check_step('a2', 0.39833, 0.399, DT, lim, 1) == (
        'target step 0.670 mm in 2.0 ms exceeds 0.563 mm (v_max·dt + margin)')
    assert check_step('a2', 0.399, 0.401, DT, lim, 1) == (
        'target 0.40100 m is outside the stroke 0.300–0.400 m')
    # the same target is inside actuator 1's range (0.34–0.44 m): a step, not the stroke
    assert check_step('a1', 0.399, 0.401, DT, lim, 0) == (
        'target step 2.000 mm in 2.0 ms exceeds 0.630 mm (v_max·dt + margin)')


@pytest.mark.parametrize('current, new, index', [
    (0.39, 0.3905, None), (0.4393, 0.4399, None), (0.3407, 0.3401, 0), (0.3985, 0.399, 1),
    (0.301, 0.3005, 1), (0.4399, 0.4395, 0),
])
def test_limits_max_step_is_the_documents_rule_on_the_actuators_range(current, new, index):
    lim = limits(strokes=((0.34, 0.44), (0.30, 0.40)))
    lo, hi = (0.34, 0.44) if index is None else ((0.34, 0.44), (0.30, 0.40))[index]
    want = doc_bound(current, new, DT, lo=lo, hi=hi, v_max=0.065, a_max=0.5, margin=0.0005)
    assert lim.max_step(current, new, DT, index) == pytest.approx(want, rel=1e-12, abs=1e-15)


def test_the_tier_modules_need_neither_ros_nor_the_bus():
    """brace_control.safety's stroke, force and tracking tiers import only the standard
    library and the package's own verdict (read from their source: nothing is imported)."""
    import ast
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1] / 'brace_control' / 'safety'
    for name in ('stroke.py', 'force.py', 'tracking.py'):
        imported = set()
        for node in ast.walk(ast.parse((root / name).read_text(encoding='utf-8'))):
            if isinstance(node, ast.Import):
                imported |= {a.name for a in node.names}
            elif isinstance(node, ast.ImportFrom):
                imported.add('.' * node.level + (node.module or ''))
        outside = {m for m in imported - {'.verdict'}
                   if m.startswith('.') or m.split('.')[0] not in sys.stdlib_module_names}
        assert not outside, (name, outside)
