"""Knots of a motion: where to sample it so that quintic Hermite interpolation rebuilds it.

A planned motion travels between the nodes as knots (:class:`~.hermite.KnotTrajectory`):
the trajectory node samples its pose trajectory, the IK node converts the knots to
actuator space. Each side must rebuild the motion the other meant within a tolerance
(ARCHITECTURE.md: "interpolation error below 1 um of actuator length"). :func:`refine`
starts from a grid and halves every segment whose midpoint, rebuilt from its two knots,
misses the true motion by more than the tolerance, until none does.

Pure numpy: no ROS.
"""
from __future__ import annotations

from collections.abc import Callable

import numpy as np

from .base import Trajectory, TrajectoryError
from .hermite import KnotTrajectory

__all__ = ['refine', 'knots_of', 'DEFAULT_KNOT_PERIOD', 'MAX_KNOTS']

#: the first grid's spacing (s); refinement adds knots where the motion needs them
DEFAULT_KNOT_PERIOD = 0.05
#: a motion is never sent as more knots than this
MAX_KNOTS = 20000

Evaluate = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]


def refine(evaluate: Evaluate, times: np.ndarray, *, tol: float | np.ndarray,
           max_knots: int = MAX_KNOTS, rounds: int = 12) -> KnotTrajectory:
    """Knots at ``times`` and wherever needed so the rebuilt motion is within ``tol``.

    :param evaluate: ``evaluate(ts) -> (P, V, A)``, the true motion at the times ``ts``
        (arrays of shape (len(ts), n)).
    :param times: the first knots (sorted, distinct), e.g. a grid plus the motion's own
        segment breaks.
    :param tol: largest |rebuilt - true| at a segment's midpoint, per coordinate (scalar or (n,)).
    :raises TrajectoryError: the tolerance is not met within ``max_knots`` knots.
    """
    ts = np.unique(np.asarray(times, dtype=float))
    P, V, A = evaluate(ts)
    tol = np.asarray(tol, dtype=float)
    for _ in range(rounds):
        knots = KnotTrajectory(ts, P, V, A)
        if ts.size < 2:
            return knots
        mid = 0.5 * (ts[:-1] + ts[1:])
        Pm, Vm, Am = evaluate(mid)
        err = np.abs(knots.sample_many(mid)[0] - Pm)
        bad = np.flatnonzero(np.any(err > tol, axis=1))
        if bad.size == 0:
            return knots
        if ts.size + bad.size > max_knots:
            raise TrajectoryError(f'the motion needs more than {max_knots} knots to be rebuilt '
                                  f'within {np.max(tol):.3g}')
        order = np.argsort(np.concatenate([ts, mid[bad]]), kind='stable')
        ts = np.concatenate([ts, mid[bad]])[order]
        P = np.concatenate([P, Pm[bad]])[order]
        V = np.concatenate([V, Vm[bad]])[order]
        A = np.concatenate([A, Am[bad]])[order]
    raise TrajectoryError(f'the motion could not be rebuilt within {np.max(tol):.3g} from its knots')


def knots_of(trajectory: Trajectory, *, tol: float | np.ndarray = 1e-7,
             period: float = DEFAULT_KNOT_PERIOD, breaks: np.ndarray | None = None,
             max_knots: int = MAX_KNOTS) -> KnotTrajectory:
    """Knots that rebuild ``trajectory`` within ``tol`` (m or rad per coordinate).

    The first grid spaces knots ``period`` apart and adds ``breaks`` (segment boundaries
    such as via-point times: the motion is only C2 there).
    """
    T = float(trajectory.duration)
    n = max(2, int(np.ceil(T / period)) + 1)
    grid = np.linspace(0.0, T, n)
    if breaks is not None:
        grid = np.concatenate([grid, np.clip(np.asarray(breaks, dtype=float), 0.0, T)])
    return refine(trajectory.sample_many, grid, tol=tol, max_knots=max_knots)
