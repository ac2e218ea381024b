"""A new target inside the stroke (docs/safety.md §5) and within the step limit (§7), with the
velocity ramp near the stroke end being approached (§5). Plain logic on numbers: the CAN
master checks every setpoint of a stream with it before anything of it is sent
(:func:`brace_control.can.supervision.check_step`, run by :mod:`brace_control.can.cycle`).

Positions are in the actuator's unit: m on a linear actuator, rad on a rotary joint
(``unit``, which only names things in the reasons). A target the functions refuse is a
protective stop: the setpoint is rejected and a step-limit stop latches (§7).
"""
from __future__ import annotations

import math

from .verdict import OK, Action, Verdict

__all__ = ['max_step', 'stroke', 'step_limit']


def max_step(current: float, new: float, dt: float, *, lo: float, hi: float, v_max: float,
             a_max: float, margin: float) -> float:
    """Largest allowed ``|new − current|`` over ``dt``: ``v·dt + margin`` (docs/safety.md §7).

    :param lo: the low end of the actuator's range (m or rad).
    :param hi: its high end.
    :param v_max: the actuator's maximum speed (m/s or rad/s).
    :param a_max: its maximum acceleration (m/s² or rad/s²).
    :param margin: ``safety.step_margin`` (m or rad).

    ``v`` is ``v_max``, ramped down near the stroke end being approached (``v ≤ √(2·a_max·d)``,
    ``d`` the distance from ``new`` to the end ``new`` lies towards from ``current``, none
    past it; docs/safety.md §5)."""
    d = (hi - new) if new > current else (new - lo)
    v = min(v_max, math.sqrt(2.0 * a_max * max(d, 0.0)))
    return v * dt + margin


def stroke(new: float, lo: float, hi: float, unit: str = 'm') -> Verdict:
    """docs/safety.md §5: a target outside ``[lo, hi]`` (or not a number) is a protective stop.

    ``unit``: ``'m'`` names the range "the stroke", anything else (``'rad'``) "the joint
    range"."""
    if not lo <= new <= hi:
        what = 'stroke' if unit == 'm' else 'joint range'
        return Verdict(Action.PROTECTIVE_STOP,
                       f'target {new:.5f} {unit} is outside the {what} {lo:.3f}–{hi:.3f} {unit}')
    return OK


def step_limit(current: float, new: float, dt: float, *, lo: float, hi: float, v_max: float,
               a_max: float, margin: float, unit: str = 'm') -> Verdict:
    """docs/safety.md §7: a target further than :func:`max_step` from the current one is a
    protective stop (the ramp of §5 included). The reason gives the step and the bound in mm
    (``unit`` ``'m'``) or mrad."""
    allowed = max_step(current, new, dt, lo=lo, hi=hi, v_max=v_max, a_max=a_max, margin=margin)
    if abs(new - current) > allowed:
        mu = 'mm' if unit == 'm' else 'mrad'
        return Verdict(Action.PROTECTIVE_STOP,
                       f'target step {abs(new - current) * 1e3:.3f} {mu} in {dt * 1e3:.1f} ms exceeds '
                       f'{allowed * 1e3:.3f} {mu} (v_max·dt + margin)')
    return OK
