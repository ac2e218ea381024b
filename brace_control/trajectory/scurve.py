"""Jerk-limited, time-optimal, synchronised S-curve motion (Ruckig, community version).

Ruckig plans every coordinate within its velocity, acceleration and jerk limits and
time-synchronises them so all finish together. Two things are handled here:

* Ruckig raises :class:`ruckig.RuckigError` (or returns an error code; for codes its
  Python enum lacks, such as -101 "trajectory duration exceeds its numerical limits",
  the binding raises ``ValueError``) for some valid inputs that sit exactly on a
  boundary between its profile types. :class:`SCurve`
  retries with the limits relaxed downward by a few parts in 10^9..10^5 and positions
  nudged by ~1e-12, then with phase synchronisation off, and finally falls back to
  a straight minimum-jerk motion stretched in time until it respects the same limits:
  it never raises for finite inputs with positive limits, and stays within the limits.
* The community version ignores position limits: the caller checks the path
  (:func:`brace_control.trajectory.limits.check_path`).
"""
from __future__ import annotations

import numpy as np
from ruckig import InputParameter, Result, Ruckig, RuckigError, Synchronization
from ruckig import Trajectory as RuckigTrajectory

from .base import ArrayLike, Trajectory, TrajectoryError, as_points
from .minimum_jerk import MinimumJerk

__all__ = ['SCurve', 'minimum_jerk_within']

# relative shrink of the limits on each retry (1 = as given)
_RETRY_SHRINK = (1.0, 1.0 - 1e-9, 1.0 - 1e-7, 1.0 - 1e-5, 1.0 - 1e-3)


class SCurve(Trajectory):
    """Time-optimal jerk-limited motion from ``start`` to ``goal`` at rest (Ruckig).

    :param start: start position (dim,).
    :param goal: goal position (dim,).
    :param max_velocity: per-coordinate velocity limit (> 0).
    :param max_acceleration: per-coordinate acceleration limit (> 0).
    :param max_jerk: per-coordinate jerk limit (> 0).
    :param v0: initial velocity (moving start), default at rest.
    :param a0: initial acceleration, default 0.
    :param min_duration: the motion lasts at least this long (s), e.g. an arrival time.
    :ivar fallback: ``None``, or why the minimum-jerk fallback replaced Ruckig's plan.
    :ivar attempts: Ruckig calls made.
    :ivar retries: Ruckig's error messages of the attempts that failed (empty if none).
    :raises TrajectoryError: non-finite inputs or non-positive limits.
    """

    def __init__(self, start: ArrayLike, goal: ArrayLike, max_velocity: ArrayLike,
                 max_acceleration: ArrayLike, max_jerk: ArrayLike, *,
                 v0: ArrayLike | None = None, a0: ArrayLike | None = None,
                 min_duration: float | None = None) -> None:
        p0 = as_points(start, 'start')
        n = p0.size
        pf = as_points(goal, 'goal', n=n)
        vmax = as_points(max_velocity, 'max_velocity', n=n, broadcast=True)
        amax = as_points(max_acceleration, 'max_acceleration', n=n, broadcast=True)
        jmax = as_points(max_jerk, 'max_jerk', n=n, broadcast=True)
        for name, arr in (('max_velocity', vmax), ('max_acceleration', amax), ('max_jerk', jmax)):
            if np.any(arr <= 0.0):
                raise TrajectoryError(f'{name} must be > 0 on every axis, got {arr.tolist()}')
        v = as_points(v0, 'v0', n=n, default=0.0)
        a = as_points(a0, 'a0', n=n, default=0.0)
        if min_duration is not None and not (np.isfinite(min_duration) and min_duration >= 0):
            raise TrajectoryError(f'min_duration must be finite and >= 0, got {min_duration}')
        self.dim = n
        self.start_position, self.goal_position = p0, pf
        self.v0, self.a0 = v, a
        self.max_velocity, self.max_acceleration, self.max_jerk = vmax, amax, jmax
        self.fallback: str | None = None
        self.attempts = 0
        self._ruckig: RuckigTrajectory | None = None
        self._mj: MinimumJerk | None = None
        errors: list[str] = []
        rng = np.random.default_rng(0)
        for sync in (Synchronization.Time, Synchronization.No):
            for i, shrink in enumerate(_RETRY_SHRINK):
                nudge = 0.0 if i == 0 else 1e-12 * (1 + i)
                goal_try = pf + nudge * rng.standard_normal(n)
                traj = self._calculate(p0, v, a, goal_try, vmax * shrink, amax * shrink,
                                       jmax * shrink, min_duration, sync, errors)
                if traj is not None:
                    self._ruckig = traj
                    self.duration = float(traj.duration)
                    self._final = goal_try
                    self.retries = errors
                    return
        self.retries = errors
        self.fallback = '; '.join(dict.fromkeys(errors)) or 'Ruckig found no trajectory'
        self._mj = minimum_jerk_within(p0, pf, vmax, amax, jmax, v0=v, a0=a,
                                       min_duration=min_duration or 0.0)
        self.duration = self._mj.duration

    def _calculate(self, p0, v0, a0, goal, vmax, amax, jmax, min_duration, sync,
                   errors: list[str]) -> RuckigTrajectory | None:
        n = p0.size
        inp = InputParameter(n)
        inp.current_position = p0.tolist()
        inp.current_velocity = v0.tolist()
        inp.current_acceleration = a0.tolist()
        inp.target_position = goal.tolist()
        inp.target_velocity = [0.0] * n
        inp.target_acceleration = [0.0] * n
        inp.max_velocity = vmax.tolist()
        inp.max_acceleration = amax.tolist()
        inp.max_jerk = jmax.tolist()
        inp.synchronization = sync
        if min_duration:
            inp.minimum_duration = float(min_duration)
        traj = RuckigTrajectory(n)
        self.attempts += 1
        try:
            result = Ruckig(n).calculate(inp, traj)
        except RuckigError as exc:
            errors.append(str(exc).strip().splitlines()[0] if str(exc).strip() else 'RuckigError')
            return None
        except ValueError as exc:
            # ruckig 0.19 returns codes its Python enum lacks (e.g. -101, trajectory
            # duration beyond its maximum): the binding raises "-101 is not a valid Result"
            errors.append(f'Ruckig: {exc}')
            return None
        if result not in (Result.Working, Result.Finished):
            errors.append(f'Ruckig result {result}')
            return None
        if not np.isfinite(traj.duration) or traj.duration < 0.0:
            errors.append(f'Ruckig duration {traj.duration}')
            return None
        return traj

    @property
    def uses_ruckig(self) -> bool:
        """``True`` when Ruckig planned the motion (not the minimum-jerk fallback)."""
        return self._ruckig is not None

    def _evaluate(self, t: np.ndarray, order: int) -> list[np.ndarray]:
        if self._mj is not None:
            return self._mj._evaluate(np.clip(t, 0.0, self._mj.duration), order)
        n = self.dim
        out = [np.empty((t.size, n)) for _ in range(order + 1)]
        at = self._ruckig.at_time
        for i, ti in enumerate(t):
            p, v, a = at(float(ti))
            vals = (p, v, a)
            for k in range(min(order, 2) + 1):
                out[k][i] = vals[k]
            if order >= 3:
                out[3][i] = self._jerk_at(float(ti))
        if t.size and self.duration > 0.0:
            # the end is exactly the goal, at rest (Ruckig ends within ~1e-12 of it)
            end = t >= self.duration
            out[0][end] = self.goal_position
            for k in range(1, order + 1):
                out[k][end] = 0.0
        return out

    def _jerk_at(self, t: float) -> np.ndarray:
        # piecewise-constant jerk: central difference of the acceleration
        h = 1e-7
        lo, hi = max(t - h, 0.0), min(t + h, self.duration)
        if hi <= lo:
            return np.zeros(self.dim)
        return (np.asarray(self._ruckig.at_time(hi)[2]) - np.asarray(self._ruckig.at_time(lo)[2])) / (hi - lo)


def minimum_jerk_within(start: np.ndarray, goal: np.ndarray, max_velocity: np.ndarray,
                        max_acceleration: np.ndarray, max_jerk: np.ndarray, *,
                        v0: np.ndarray | None = None, a0: np.ndarray | None = None,
                        min_duration: float = 0.0) -> MinimumJerk:
    """The straight minimum-jerk motion (2.2) stretched until it respects per-axis limits.

    At rest at both ends the peaks are ``1.875 A/T``, ``5.7735 A/T^2`` and ``60 A/T^3``
    (``A`` the per-axis distance); a moving start is stretched numerically (peaks checked
    on 257 samples) until within the limits, or until 1e4 s (a start already above a limit
    cannot be helped: the initial values are left as they are).
    """
    A = np.abs(goal - start)
    with np.errstate(divide='ignore', invalid='ignore'):
        T = max(float(np.max(1.875 * A / max_velocity)),
                float(np.max(np.sqrt(5.773502691896258 * A / max_acceleration))),
                float(np.max(np.cbrt(60.0 * A / max_jerk))), float(min_duration), 1e-3)
    v0 = np.zeros_like(start) if v0 is None else v0
    a0 = np.zeros_like(start) if a0 is None else a0
    moving = np.any(v0 != 0.0) or np.any(a0 != 0.0)
    traj = MinimumJerk(start, goal, T * (1.0 + 1e-9), v0=v0, a0=a0)
    if not moving:
        return traj
    allowed = [np.maximum(lim, np.abs(x0)) for lim, x0 in
               ((max_velocity, v0), (max_acceleration, a0), (max_jerk, np.zeros_like(v0)))]
    while T < 1e4:
        traj = MinimumJerk(start, goal, T, v0=v0, a0=a0)
        ts = np.linspace(0.0, T, 257)
        p, v, a = traj.sample_many(ts)
        j = traj._evaluate(ts, 3)[3]
        if all(np.all(np.abs(x) <= lim * (1 + 1e-9)) for x, lim in zip((v, a, j), allowed)):
            return traj
        T *= 1.2
    return traj
