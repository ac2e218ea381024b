"""Knot trajectories: quintic Hermite interpolation through (time, position, velocity, acceleration).

What travels between the nodes is a planned motion sampled at knots (ARCHITECTURE.md,
"Data flow": ``/brace/pose_trajectory``, ``/brace/actuator_trajectory``); each side
rebuilds the same continuous motion from them: on every segment the quintic that meets
position, velocity and acceleration at both knots (C2 across knots). A minimum-jerk
segment (a quintic, eqs. (2.2)-(2.3) of thesis 002) is reproduced exactly.

Pure numpy: no ROS.
"""
from __future__ import annotations

import bisect
from collections.abc import Sequence

import numpy as np

from .base import Trajectory, TrajectoryError, quintic_coefficients

__all__ = ['KnotTrajectory', 'segment_coefficients']


def segment_coefficients(h: np.ndarray, p0: np.ndarray, v0: np.ndarray, a0: np.ndarray,
                         p1: np.ndarray, v1: np.ndarray, a1: np.ndarray) -> np.ndarray:
    """Coefficients ``c0..c5`` (shape (6, k, n)) of quintic Hermite segments in their own time.

    ``p(s) = sum_j c_j s^j`` on ``s in [0, h]`` meets ``(p0, v0, a0)`` at 0 and ``(p1, v1, a1)``
    at ``h`` (``h`` shape (k, 1)): :func:`~.base.quintic_coefficients` in ``sigma = s / h``,
    rescaled by ``h^j``.
    """
    b = quintic_coefficients(p0, v0, a0, p1, v1, a1, h)
    return b / h[None] ** np.arange(6).reshape(6, 1, 1)


class KnotTrajectory(Trajectory):
    """Knots ``(t_i, q_i, q_dot_i, q_ddot_i)``, quintic Hermite between them.

    Any coordinates: actuator positions (m or rad) or platform poses. Before the first knot
    the motion holds the first knot, after the last the last.

    :param times: s from the trajectory's start, strictly increasing, ``times[0] >= 0``.
    :param positions: (N, n) positions.
    :param velocities: (N, n), or ``None``: from a clamped cubic spline through the
        positions (zero velocity at both ends).
    :param accelerations: (N, n), or ``None``: the second derivative of the cubic spline
        through the positions and velocities (C2 where the data allows).
    :raises TrajectoryError: wrong shapes, non-finite values, times not increasing.
    """

    def __init__(self, times: Sequence[float] | np.ndarray, positions: np.ndarray,
                 velocities: np.ndarray | None = None,
                 accelerations: np.ndarray | None = None) -> None:
        t = np.asarray(times, dtype=float).reshape(-1)
        q = np.asarray(positions, dtype=float)
        if q.ndim != 2 or q.shape[0] != t.size or t.size == 0:
            raise TrajectoryError(f'expected one row of positions per time: {t.size} times, '
                                  f'positions of shape {q.shape}')
        n = q.shape[1]
        if n == 0:
            raise TrajectoryError('no joints')
        if not np.all(np.isfinite(t)) or not np.all(np.isfinite(q)):
            raise TrajectoryError('non-finite time or position')
        if t[0] < 0.0 or np.any(np.diff(t) <= 0.0):
            raise TrajectoryError(f'times from start must be >= 0 and strictly increasing, '
                                  f'got {np.round(t[:8], 6).tolist()}{" ..." if t.size > 8 else ""}')
        v = None if velocities is None else np.asarray(velocities, dtype=float)
        a = None if accelerations is None else np.asarray(accelerations, dtype=float)
        for name, arr in (('velocities', v), ('accelerations', a)):
            if arr is not None and (arr.shape != q.shape or not np.all(np.isfinite(arr))):
                raise TrajectoryError(f'{name}: expected finite values of shape {q.shape}, '
                                      f'got shape {arr.shape}')
        if v is None or a is None:
            v, a = _spline_derivatives(t, q, v)
        self.times = t
        self.positions = q
        self.velocities = v
        self.accelerations = a
        self.n = self.dim = n
        if t.size > 1:
            h = np.diff(t)[:, None]
            self._coef = segment_coefficients(h, q[:-1], v[:-1], a[:-1], q[1:], v[1:], a[1:])
        else:
            self._coef = np.zeros((6, 0, n))
        self._times_list = t.tolist()

    @property
    def duration(self) -> float:
        """Time from start of the last knot (s)."""
        return float(self.times[-1])

    @property
    def start_time(self) -> float:
        """Time from start of the first knot (s); > 0 means "reach it then" (JTC)."""
        return float(self.times[0])

    def sample(self, tau: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(q, q_dot, q_ddot)`` at ``tau`` s from the start (clamped to the knots' span)."""
        t = self._times_list
        if tau <= t[0] or len(t) == 1:
            return self.positions[0].copy(), self.velocities[0].copy(), self.accelerations[0].copy()
        if tau >= t[-1]:
            return self.positions[-1].copy(), self.velocities[-1].copy(), self.accelerations[-1].copy()
        k = bisect.bisect_right(t, tau) - 1
        s = tau - t[k]
        c = self._coef[:, k]
        p = c[0] + s * (c[1] + s * (c[2] + s * (c[3] + s * (c[4] + s * c[5]))))
        v = c[1] + s * (2.0 * c[2] + s * (3.0 * c[3] + s * (4.0 * c[4] + s * 5.0 * c[5])))
        a = 2.0 * c[2] + s * (6.0 * c[3] + s * (12.0 * c[4] + s * 20.0 * c[5]))
        return p, v, a

    def sample_many(self, taus: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`sample` at each of ``taus`` (vectorised); arrays of shape (len(taus), n)."""
        taus = np.clip(np.asarray(taus, dtype=float), self.times[0], self.times[-1])
        if self.times.size == 1:
            rep = np.ones((taus.size, 1))
            return rep * self.positions[0], rep * self.velocities[0], rep * self.accelerations[0]
        k = np.clip(np.searchsorted(self.times, taus, side='right') - 1, 0, self.times.size - 2)
        s = (taus - self.times[k])[:, None]
        c = self._coef[:, k]
        p = c[0] + s * (c[1] + s * (c[2] + s * (c[3] + s * (c[4] + s * c[5]))))
        v = c[1] + s * (2.0 * c[2] + s * (3.0 * c[3] + s * (4.0 * c[4] + s * 5.0 * c[5])))
        a = 2.0 * c[2] + s * (6.0 * c[3] + s * (12.0 * c[4] + s * 20.0 * c[5]))
        end = taus >= self.times[-1]           # the last knot exactly (a motion ends at rest)
        if np.any(end):
            p[end], v[end], a[end] = self.positions[-1], self.velocities[-1], self.accelerations[-1]
        return p, v, a

    def _evaluate(self, t: np.ndarray, order: int) -> list[np.ndarray]:
        taus = np.clip(np.asarray(t, dtype=float), self.times[0], self.times[-1])
        if self.times.size == 1:
            rep = np.ones((taus.size, 1))
            return [rep * self.positions[0], rep * self.velocities[0],
                    rep * self.accelerations[0], 0.0 * rep * self.positions[0]][:order + 1]
        k = np.clip(np.searchsorted(self.times, taus, side='right') - 1, 0, self.times.size - 2)
        s = (taus - self.times[k])[:, None]
        c = self._coef[:, k]
        out = []
        for d in range(order + 1):
            # d-th derivative of sum_j c_j s^j
            val = np.zeros_like(c[0])
            for j in range(5, d - 1, -1):
                factor = float(np.prod(range(j - d + 1, j + 1)))
                val = val * s + factor * c[j] if j < 5 else factor * c[j]
            out.append(val)
        end = taus >= self.times[-1]           # the last knot exactly
        if np.any(end):
            knot = (self.positions[-1], self.velocities[-1], self.accelerations[-1], 0.0)
            for d in range(order + 1):
                out[d][end] = knot[d]
        return out

    def dense(self, per_segment: int = 4) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(tau, q, q_dot, q_ddot)`` at every knot and ``per_segment - 1`` points between
        (for limit checks of the interpolated motion, not only of its knots)."""
        t = self.times
        if t.size == 1:
            return t.copy(), self.positions.copy(), self.velocities.copy(), self.accelerations.copy()
        u = np.linspace(0.0, 1.0, per_segment, endpoint=False)
        taus = np.concatenate([(t[:-1, None] + np.diff(t)[:, None] * u).reshape(-1), t[-1:]])
        return (taus, *self.sample_many(taus))

    def with_start(self, q: np.ndarray, v: np.ndarray, a: np.ndarray) -> 'KnotTrajectory':
        """The same knots with ``(q, v, a)`` prepended at time 0 (a first knot at ``t > 0``:
        ros2_control's "reach the first point at its time from the current state")."""
        return KnotTrajectory(np.concatenate([[0.0], self.times]),
                              np.vstack([q, self.positions]),
                              np.vstack([v, self.velocities]),
                              np.vstack([a, self.accelerations]))

    def __repr__(self) -> str:
        return f'KnotTrajectory({self.times.size} knots, {self.n} joints, {self.duration:.3f} s)'


def _spline_derivatives(t: np.ndarray, q: np.ndarray,
                        v: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Velocities (clamped cubic spline, zero at the ends) and accelerations for knots that
    lack them. With velocities given, accelerations are those of the cubic Hermite
    segments averaged at each knot."""
    if t.size == 1:
        z = np.zeros_like(q)
        return (z if v is None else v), z
    if v is None:
        from scipy.interpolate import CubicSpline
        spline = CubicSpline(t, q, axis=0, bc_type='clamped')
        return spline(t, 1), spline(t, 2)
    h = np.diff(t)[:, None]
    dp = np.diff(q, axis=0)
    # cubic Hermite segment k: second derivative at its start and end
    a_start = (6.0 * dp - (4.0 * v[:-1] + 2.0 * v[1:]) * h) / h ** 2
    a_end = (-6.0 * dp + (2.0 * v[:-1] + 4.0 * v[1:]) * h) / h ** 2
    a = np.empty_like(q)
    a[0], a[-1] = a_start[0], a_end[-1]
    a[1:-1] = 0.5 * (a_end[:-1] + a_start[1:])
    return v, a


