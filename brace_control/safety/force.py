"""An actuator's load cell, sample by sample: a reading at its saturation (docs/safety.md §9)
and a force above the hard limit (§8). Plain logic on numbers: the CAN master evaluates it
in its SYNC cycle for each drive's newest sample
(:func:`brace_control.can.supervision.check_sample`, run by :mod:`brace_control.can.monitors`).

A saturated reading says nothing about the force, so the force limit is judged only on a
reading below saturation (the caller checks :func:`saturation` first). Above the soft limit a
motion that keeps pressing brakes (:func:`pressing_past_soft_limit`, §14, judged by
:class:`brace_control.can.monitors.Monitors`). The platform wrench and the predictive soft
tiers on the same load cells are in :mod:`.wrench` (§8, §14).

The reasons name the reading in its unit: N on a linear actuator, N·m on a rotary joint.
"""
from __future__ import annotations

from collections.abc import Sequence

from .verdict import OK, Action, Verdict

__all__ = ['saturation', 'force_limit', 'pressing_past_soft_limit', 'SOFT_RISE', 'SOFT_TREND']


def saturation(counts: float, force: float, saturation_counts: float, unit: str = 'N') -> Verdict:
    """docs/safety.md §9: a reading at or above ``saturation_counts`` from the load cell's
    zero (``safety.saturation_fraction`` of its full scale) is a protective stop.

    :param counts: the raw reading, counts from its zero.
    :param force: the same reading in ``unit`` (only named in the reason).
    :param unit: 'N' (linear actuator) or 'N·m' (rotary joint).
    :param saturation_counts: ``|counts|`` at or above which the cell is saturated."""
    if abs(counts) >= saturation_counts:
        return Verdict(Action.PROTECTIVE_STOP,
                       f'load cell reads {counts} counts ({force:.1f} {unit}), '
                       f'saturation at ±{saturation_counts}')
    return OK


def force_limit(force: float, limit: float, unit: str = 'N') -> Verdict:
    """docs/safety.md §8: a load-cell force above ``limit`` (``safety.force_limit``) in either
    direction is a protective stop; ``unit`` 'N' or 'N·m' (a rotary joint's torque)."""
    if abs(force) > limit:
        return Verdict(Action.PROTECTIVE_STOP,
                       f'load-cell force {force:.1f} {unit} exceeds {limit:.1f} {unit}')
    return OK


#: the rise of ``|force|`` over the recent samples (N or N·m) that says a motion still presses
SOFT_RISE = 0.5
#: samples of ``|force|`` the rise is judged over, at least
SOFT_TREND = 5


def pressing_past_soft_limit(force: float, recent: Sequence[float], soft_limit: float,
                             rise: float = SOFT_RISE) -> bool:
    """docs/safety.md §14, the soft tier on one load cell: above ``soft_limit``
    (``safety.soft_force_limit``) a motion that keeps pressing is to brake along its path and
    hold (a soft stop, nothing latched); a motion that unloads the leg goes on.

    :param force: the newest reading (N or N·m).
    :param recent: ``|force|`` of the samples before it, oldest first (at least
        :data:`SOFT_TREND` of them, else nothing is judged).
    :param rise: how much ``|force|`` must have risen since the oldest of ``recent``.
    """
    f = abs(force)
    return f > soft_limit and len(recent) >= SOFT_TREND and f - recent[0] > rise
