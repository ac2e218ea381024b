"""An actuator's measured position against physics and against its target: a position jump
no actuator can make (docs/safety.md §9) and a following error beyond the path tolerance
(§11). Plain logic on numbers: the CAN master evaluates it in its SYNC cycle for each
tracking drive's newest sample (:func:`brace_control.can.supervision.check_sample`, run by
:mod:`brace_control.can.monitors`).

The reasons name positions in the axis unit: m and mm on a linear actuator, rad and mrad on a
rotary joint.
"""
from __future__ import annotations

from .verdict import OK, Action, Verdict

__all__ = ['position_jump', 'following_error']


def position_jump(previous: float, current: float, dt: float, *, v_max: float,
                  jump_factor: float, margin: float, unit: str = 'm') -> Verdict:
    """docs/safety.md §9: a position that moved more than ``jump_factor·v_max·dt + margin``
    between two samples ``dt`` apart is a protective stop (an encoder that jumped: the
    axis needs homing again).

    :param previous: the position of the earlier sample (m or rad).
    :param current: the position of the newer one.
    :param dt: the time between the two (s; the SYNCs they answer times the period).
    :param v_max: the actuator's maximum speed.
    :param jump_factor: how many times ``v_max`` is impossible (4 in the master).
    :param margin: ``safety.step_margin``.
    :param unit: 'm' (linear) or 'rad' (rotary), for the reason."""
    jump = abs(current - previous)
    bound = jump_factor * v_max * dt + margin
    if jump > bound:
        return Verdict(Action.PROTECTIVE_STOP,
                       f'position changed {jump * 1e3:.3f} m{unit} in {dt * 1e3:.1f} ms '
                       f'(physically at most {bound * 1e3:.3f} m{unit})')
    return OK


def following_error(actual: float, target: float, tolerance: float, unit: str = 'm') -> Verdict:
    """docs/safety.md §11: ``|target − actual|`` beyond ``tolerance``
    (``safety.path_tolerance``) is a protective stop; ``unit`` 'm' or 'rad', for the reason."""
    err = abs(target - actual)
    if err > tolerance:
        return Verdict(Action.PROTECTIVE_STOP,
                       f'actual {actual:.5f} {unit} is {err * 1e3:.2f} m{unit} from the target '
                       f'{target:.5f} {unit} (path tolerance {tolerance * 1e3:.2f} m{unit})')
    return OK
