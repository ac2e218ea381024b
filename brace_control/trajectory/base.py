"""What every motion profile offers, and the piecewise-polynomial machinery they share.

Pure numpy: no ROS. A *trajectory* maps time ``t`` (s, from its own start) to position,
velocity and acceleration of every coordinate (platform pose ``(x, y, theta)`` for the
planar braces, SI units). Times outside ``[0, duration]`` clamp to the ends, so a
finished trajectory holds its goal at rest.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from bisect import bisect_right
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

__all__ = [
    'Trajectory', 'PiecewisePolynomial', 'MotionState', 'TrajectoryError',
    'as_points', 'quintic_coefficients',
]

ArrayLike = Sequence[float] | np.ndarray


class TrajectoryError(ValueError):
    """A trajectory cannot be built from the inputs given (the message says which and why)."""


def as_points(value: ArrayLike | None, name: str, *, n: int | None = None,
              default: float | None = None, broadcast: bool = False) -> np.ndarray:
    """``value`` as a finite 1-D float array (of length ``n`` if given).

    ``None`` gives ``default`` repeated ``n`` times when a default is given; with
    ``broadcast`` (limits) a single value is repeated ``n`` times.

    :raises TrajectoryError: non-numeric, non-finite or wrong length; the message names ``name``.
    """
    if value is None:
        if default is None or n is None:
            raise TrajectoryError(f'{name}: a value is required')
        return np.full(n, float(default))
    try:
        arr = np.array(value, dtype=float).reshape(-1) if np.ndim(value) <= 1 else None
    except (TypeError, ValueError) as exc:
        raise TrajectoryError(f'{name}: expected numbers, got {value!r}') from exc
    if arr is None:
        raise TrajectoryError(f'{name}: expected a 1-D array, got shape {np.shape(value)}')
    if n is not None and arr.shape != (n,):
        if arr.size == 1 and broadcast:
            arr = np.full(n, float(arr[0]))
        else:
            raise TrajectoryError(f'{name}: expected {n} values, got {arr.size}')
    if arr.size == 0:
        raise TrajectoryError(f'{name}: empty')
    if not np.all(np.isfinite(arr)):
        raise TrajectoryError(f'{name}: non-finite value in {arr.tolist()}')
    return arr


@dataclass(frozen=True)
class MotionState:
    """Position, velocity and acceleration of every coordinate at one instant."""

    p: np.ndarray
    v: np.ndarray
    a: np.ndarray


class Trajectory(ABC):
    """A motion from a start state to a goal at rest.

    Subclasses implement :meth:`_evaluate` on an array of times already clamped to
    ``[0, duration]``.
    """

    duration: float
    dim: int

    @abstractmethod
    def _evaluate(self, t: np.ndarray, order: int) -> list[np.ndarray]:
        """Derivatives 0..``order`` at times ``t`` (shape (N,)), each of shape (N, dim)."""

    def _clamp(self, t: float | np.ndarray) -> np.ndarray:
        return np.clip(np.atleast_1d(np.asarray(t, dtype=float)), 0.0, self.duration)

    def sample(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Position, velocity, acceleration at ``t`` (s); ``t`` outside the motion clamps."""
        p, v, a = self._evaluate(self._clamp(t), 2)[:3]
        return p[0], v[0], a[0]

    def sample_many(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`sample` for an array of times: three arrays of shape (N, dim)."""
        p, v, a = self._evaluate(self._clamp(t), 2)[:3]
        return p, v, a

    def jerk(self, t: float) -> np.ndarray:
        """Jerk at ``t`` (zero outside the motion)."""
        if not 0.0 <= t <= self.duration:
            return np.zeros(self.dim)
        return self._evaluate(self._clamp(t), 3)[3][0]

    def state(self, t: float) -> MotionState:
        """:meth:`sample` as a :class:`MotionState`."""
        return MotionState(*self.sample(t))

    @property
    def start(self) -> np.ndarray:
        return self.sample(0.0)[0]

    @property
    def goal(self) -> np.ndarray:
        return self.sample(self.duration)[0]


def quintic_coefficients(p0: np.ndarray, v0: np.ndarray, a0: np.ndarray,
                         p1: np.ndarray, v1: np.ndarray, a1: np.ndarray,
                         duration: float) -> np.ndarray:
    """Coefficients ``b_k`` (shape (6, dim)) of the quintic ``sum b_k sigma^k``, ``sigma = t/T``.

    Meets position, velocity and acceleration at both ends. With ``v = a = 0`` at both
    ends this is the Flash–Hogan straight minimum-jerk motion, eqs. (2.2)–(2.3):
    ``b = (x_f - x_0)(0, 0, 0, 10, -15, 6)``. ``duration`` may be an array that broadcasts
    against the states (one duration per segment, shape (m, 1)).
    """
    T = np.asarray(duration, dtype=float)
    h = p1 - p0
    V0, V1 = v0 * T, v1 * T            # velocities in sigma units
    A0, A1 = a0 * T * T, a1 * T * T
    b = np.empty((6,) + np.shape(p0))
    b[0] = p0
    b[1] = V0
    b[2] = A0 / 2.0
    b[3] = 10.0 * h - 6.0 * V0 - 4.0 * V1 - 1.5 * A0 + 0.5 * A1
    b[4] = -15.0 * h + 8.0 * V0 + 7.0 * V1 + 1.5 * A0 - A1
    b[5] = 6.0 * h - 3.0 * (V0 + V1) - 0.5 * A0 + 0.5 * A1
    return b


# d^k/dsigma^k of sigma^j: factor j!/(j-k)!
_FALLING = np.array([[float(np.prod(range(j - k + 1, j + 1))) if j >= k else 0.0
                      for j in range(6)] for k in range(6)])


class PiecewisePolynomial(Trajectory):
    """Quintic segments in normalised time: segment ``i`` spans ``[T_i, T_i + h_i]``.

    ``coeffs[i]`` (shape (6, dim)) are the coefficients in ``sigma = (t - T_i) / h_i``; the
    ``k``-th time derivative is the ``k``-th ``sigma`` derivative divided by ``h_i^k``.
    """

    def __init__(self, coeffs: np.ndarray, durations: np.ndarray, *,
                 rest_goal: np.ndarray | None = None) -> None:
        self.coeffs = np.asarray(coeffs, dtype=float)           # (m, 6, dim)
        # a motion that ends at rest at a known goal returns it exactly from t = duration on
        # (summing the coefficients at sigma = 1 can lose digits on very long motions)
        self.rest_goal = None if rest_goal is None else np.asarray(rest_goal, dtype=float)
        self.durations = np.asarray(durations, dtype=float)     # (m,)
        self.breaks = np.concatenate([[0.0], np.cumsum(self.durations)])
        self.duration = float(self.breaks[-1])
        self.dim = self.coeffs.shape[2]
        self._break_list = self.breaks.tolist()
        self._h_list = self.durations.tolist()

    def sample(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Position, velocity, acceleration at ``t`` (scalar fast path of the setpoint loop)."""
        t = float(t)
        T = self.duration
        if self.rest_goal is not None and t >= T:
            z = np.zeros(self.dim)
            return self.rest_goal.copy(), z, z.copy()
        t = 0.0 if t < 0.0 else (T if t > T else t)
        seg = min(max(bisect_right(self._break_list, t) - 1, 0), len(self.durations) - 1)
        h = self._h_list[seg]
        s = (t - self._break_list[seg]) / h
        s2 = s * s
        c = self.coeffs[seg]
        p = np.dot((1.0, s, s2, s2 * s, s2 * s2, s2 * s2 * s), c)
        v = np.dot((1.0, 2.0 * s, 3.0 * s2, 4.0 * s2 * s, 5.0 * s2 * s2), c[1:]) / h
        a = np.dot((2.0, 6.0 * s, 12.0 * s2, 20.0 * s2 * s), c[2:]) / (h * h)
        return p, v, a

    def _evaluate(self, t: np.ndarray, order: int) -> list[np.ndarray]:
        m = len(self.durations)
        seg = np.clip(np.searchsorted(self.breaks, t, side='right') - 1, 0, m - 1)
        h = self.durations[seg]
        sigma = (t - self.breaks[seg]) / h
        powers = sigma[:, None] ** np.arange(6)[None, :]         # (N, 6)
        c = self.coeffs[seg]                                      # (N, 6, dim)
        out = []
        for k in range(order + 1):
            # sum_j falling[k, j] b_j sigma^(j-k)
            pk = np.zeros_like(powers)
            pk[:, :6 - k] = powers[:, :6 - k]
            w = _FALLING[k][k:][None, :] * pk[:, :6 - k]         # (N, 6-k)
            val = np.einsum('nj,njd->nd', w, c[:, k:, :])
            out.append(val / (h[:, None] ** k))
        if self.rest_goal is not None:
            end = t >= self.duration
            if np.any(end):
                out[0][end] = self.rest_goal
                for k in range(1, order + 1):
                    out[k][end] = 0.0
        return out

    def segment_jerk_cost(self) -> np.ndarray:
        """``1/2 int |jerk|^2 dt`` of each segment (Flash–Hogan cost, eq. (2.1))."""
        d0 = 6.0 * self.coeffs[:, 3]
        d1 = 24.0 * self.coeffs[:, 4]
        d2 = 60.0 * self.coeffs[:, 5]
        integral = (d0 * d0 + d0 * d1 + (2.0 * d0 * d2 + d1 * d1) / 3.0
                    + d1 * d2 / 2.0 + d2 * d2 / 5.0).sum(axis=1)
        return 0.5 * integral / self.durations ** 5

    def jerk_cost(self) -> float:
        """Flash–Hogan cost ``C = 1/2 int (x'''^2 + y'''^2 + ...) dt``, eq. (2.1)."""
        return float(self.segment_jerk_cost().sum())
