"""Minimum-jerk motion (Flash & Hogan 1985), straight and through via points; Fitts' law.

Upper-limb trainer thesis (seed 002), §2.3:

* straight line, eqs. (2.2)–(2.3): ``x(t) = x0 + (x0 - xf)(15 tau^4 - 6 tau^5 - 10 tau^3)``,
  ``tau = t / tf``, per coordinate; generalised here to a non-rest start (the quintic
  with the given initial velocity and acceleration, ending at rest), which is the
  minimum-jerk motion for those boundary conditions;
* through via points, eqs. (2.4)–(2.11): a piecewise quintic passing each via point,
  continuous up to the fourth derivative there (the interior-point condition of Flash
  & Hogan, Appendix C); the via times minimise the cost (2.1);
* movement time by Fitts' law, eq. (2.12): ``tf = a + b log2(2A / W)``.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np

from .base import (ArrayLike, PiecewisePolynomial, TrajectoryError, as_points,
                   quintic_coefficients)

__all__ = [
    'MinimumJerk', 'ViaPointMinimumJerk', 'fitts_duration', 'FittsLaw', 'brake',
    'solve_via_quintics',
]


def _duration(duration: float, name: str = 'duration') -> float:
    try:
        T = float(duration)
    except (TypeError, ValueError) as exc:
        raise TrajectoryError(f'{name}: expected seconds, got {duration!r}') from exc
    if not (math.isfinite(T) and T > 0.0):
        raise TrajectoryError(f'{name} must be finite and > 0 s, got {T}')
    return T


class MinimumJerk(PiecewisePolynomial):
    """Straight minimum-jerk motion from ``start`` to ``goal`` in ``duration`` s, eqs. (2.2)–(2.3).

    With ``v0``/``a0`` (a moving start, e.g. when a new goal preempts a running one) it is
    the quintic meeting ``(start, v0, a0)`` at ``t = 0`` and ``(goal, 0, 0)`` at ``duration``:
    position, velocity and acceleration are continuous with the motion it replaces.

    :param start: start position per coordinate.
    :param goal: goal position, same length.
    :param duration: movement time ``tf`` (s), > 0.
    :param v0: initial velocity (default at rest).
    :param a0: initial acceleration (default 0).
    :raises TrajectoryError: non-finite inputs, unequal lengths, non-positive duration.
    """

    def __init__(self, start: ArrayLike, goal: ArrayLike, duration: float, *,
                 v0: ArrayLike | None = None, a0: ArrayLike | None = None) -> None:
        p0 = as_points(start, 'start')
        n = p0.size
        pf = as_points(goal, 'goal', n=n)
        T = _duration(duration)
        v = as_points(v0, 'v0', n=n, default=0.0)
        a = as_points(a0, 'a0', n=n, default=0.0)
        zero = np.zeros(n)
        b = quintic_coefficients(p0, v, a, pf, zero, zero, T)
        super().__init__(b[None], np.array([T]), rest_goal=pf)
        self.start_position, self.goal_position = p0, pf
        self.v0, self.a0 = v, a


def solve_via_quintics(points: np.ndarray, durations: np.ndarray, *,
                       v0: np.ndarray | None = None, a0: np.ndarray | None = None) -> np.ndarray:
    """Piecewise-quintic minimum-jerk coefficients through ``points`` (k+2, dim).

    ``points[0]`` is the start (with ``v0``, ``a0``), ``points[-1]`` the goal (at rest);
    each interior point is reached at the end of its segment, and the pieces join with
    continuous velocity, acceleration, jerk and snap (C4), the Flash–Hogan necessary
    condition for an interior point constraint. Returns (m, 6, dim) normalised-time
    coefficients (see :class:`~.base.PiecewisePolynomial`).
    """
    m = len(durations)
    dim = points.shape[1]
    v0 = np.zeros(dim) if v0 is None else v0
    a0 = np.zeros(dim) if a0 is None else a0
    N = 6 * m
    rows: list[int] = []
    cols: list[int] = []
    vals: list[float] = []
    rhs = np.zeros((N, dim))
    row = 0
    fall = [[math.perm(j, k) for j in range(6)] for k in range(6)]   # d^k sigma^j at sigma=1

    def put(c: int, value: float) -> None:
        rows.append(row)
        cols.append(c)
        vals.append(value)

    # start: p, v, a
    h0 = durations[0]
    for k, val in enumerate((points[0], v0 * h0, a0 * h0 * h0)):
        put(k, math.factorial(k))
        rhs[row] = val
        row += 1
    for i in range(m - 1):
        hi, hn = durations[i], durations[i + 1]
        # end of segment i at the via point, start of segment i+1 at the via point
        for j in range(6):
            put(6 * i + j, 1.0)
        rhs[row] = points[i + 1]
        row += 1
        put(6 * (i + 1), 1.0)
        rhs[row] = points[i + 1]
        row += 1
        # derivatives 1..4 continuous: (d^k seg_i at 1) / hi^k = (k! b_{i+1,k}) / hn^k
        for k in range(1, 5):
            for j in range(k, 6):
                put(6 * i + j, fall[k][j] / hi ** k)
            put(6 * (i + 1) + k, -math.factorial(k) / hn ** k)
            row += 1
    # goal: p, v = a = 0
    last = m - 1
    for k in range(3):
        for j in range(k, 6):
            put(6 * last + j, fall[k][j])
        rhs[row] = points[-1] if k == 0 else 0.0
        row += 1
    # a band matrix (each row touches two neighbouring segments): a sparse LU solves it in
    # O(m), so a path of many poses costs in proportion to their number
    from scipy.sparse import csc_matrix
    from scipy.sparse.linalg import MatrixRankWarning, spsolve
    A = csc_matrix((vals, (rows, cols)), shape=(N, N))
    with warnings.catch_warnings():
        warnings.simplefilter('error', MatrixRankWarning)
        try:
            sol = np.asarray(spsolve(A, rhs)).reshape(N, dim)
        except (MatrixRankWarning, RuntimeError) as exc:
            raise TrajectoryError(f'via-point system is singular for segment durations {durations}') from exc
    if not np.all(np.isfinite(sol)):
        raise TrajectoryError(f'via-point system is singular for segment durations {durations}')
    return sol.reshape(m, 6, dim)


#: via points beyond this many get chord-length times instead of optimised ones
MAX_OPTIMISED_VIA = 8


class ViaPointMinimumJerk(PiecewisePolynomial):
    """Minimum-jerk motion through via points, eqs. (2.4)–(2.11) generalised to ``k`` via points.

    A piecewise quintic through ``start``, each row of ``via`` in order, and ``goal``,
    C4 at every via point (Flash & Hogan, Appendix C). With ``t_via=None`` the via
    times minimise the integrated squared jerk (2.1) over the fixed ``duration``; the
    thesis found ``t1 = 0.243349 s`` (``tf = 0.5 s``, ``t1/tf = 0.4867``) for its curved reach,
    rounded to 0.25 s in App. B — the optimum this class finds for those points.

    :param start: start position (dim,).
    :param via: one via point (dim,) or several (k, dim), in the order they are passed.
    :param goal: goal position (dim,), reached at rest at ``duration``.
    :param duration: total movement time ``tf`` (s).
    :param t_via: via times (s from the start), strictly increasing in ``(0, duration)``,
        or ``None`` to optimise them.
    :param v0: initial velocity (moving start), default at rest.
    :param a0: initial acceleration, default 0.
    :ivar t_via: the via times used (s), shape (k,).
    :raises TrajectoryError: bad shapes, non-finite values, via times out of order.
    """

    def __init__(self, start: ArrayLike, via: ArrayLike, goal: ArrayLike, duration: float,
                 t_via: ArrayLike | float | None = None, *,
                 v0: ArrayLike | None = None, a0: ArrayLike | None = None) -> None:
        p0 = as_points(start, 'start')
        n = p0.size
        pf = as_points(goal, 'goal', n=n)
        T = _duration(duration)
        try:
            vias = np.array(via, dtype=float)
        except (TypeError, ValueError) as exc:
            raise TrajectoryError(f'via: expected numbers, got {via!r}') from exc
        if vias.ndim == 1:
            vias = vias.reshape(1, -1)
        if vias.ndim != 2 or vias.shape[1] != n or vias.shape[0] == 0:
            raise TrajectoryError(f'via: expected shape (k, {n}), got {np.shape(via)}')
        if not np.all(np.isfinite(vias)):
            raise TrajectoryError('via: non-finite value')
        v = as_points(v0, 'v0', n=n, default=0.0)
        a = as_points(a0, 'a0', n=n, default=0.0)
        k = vias.shape[0]
        pts = np.vstack([p0, vias, pf])
        self._pts, self._v0, self._a0 = pts, v, a
        if t_via is None:
            times = self._optimal_via_times(pts, T, v, a)
        else:
            times = as_points(t_via, 't_via', n=k)
            if not (np.all(np.diff(np.concatenate([[0.0], times, [T]])) > 0.0)):
                raise TrajectoryError(
                    f't_via must increase strictly inside (0, {T}) s, got {times.tolist()}')
        durations = np.diff(np.concatenate([[0.0], times, [T]]))
        super().__init__(solve_via_quintics(pts, durations, v0=v, a0=a), durations, rest_goal=pf)
        self.t_via = times
        self.via = vias

    @staticmethod
    def _cost(pts: np.ndarray, durations: np.ndarray, v0: np.ndarray, a0: np.ndarray) -> float:
        return PiecewisePolynomial(solve_via_quintics(pts, durations, v0=v0, a0=a0),
                                   durations).jerk_cost()

    @classmethod
    def _optimal_via_times(cls, pts: np.ndarray, T: float, v0: np.ndarray,
                           a0: np.ndarray) -> np.ndarray:
        """Via times minimising the jerk cost (2.1) for the fixed total time ``T``."""
        from scipy.optimize import minimize, minimize_scalar   # scipy on first use (every node's start)
        k = pts.shape[0] - 2
        eps = 1e-4
        if k == 1:
            def cost1(tau1: float) -> float:
                return cls._cost(pts, np.array([tau1 * T, (1.0 - tau1) * T]), v0, a0)
            grid = np.linspace(0.02, 0.98, 49)
            values = [cost1(g) for g in grid]
            i = int(np.argmin(values))
            lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, len(grid) - 1)]
            lo, hi = max(lo, eps), min(hi, 1.0 - eps)
            res = minimize_scalar(cost1, bounds=(lo, hi), method='bounded',
                                  options={'xatol': 1e-10})
            best = float(res.x) if res.fun <= values[i] else float(grid[i])
            return np.array([best * T])

        # several via points: segment fractions = softmax(z); start from chord lengths
        chords = np.linalg.norm(np.diff(pts, axis=0), axis=1) + 1e-9 * T
        if k > MAX_OPTIMISED_VIA:
            # a long path: times in proportion to the chord lengths (O(k)); optimising k
            # times by simplex search would cost O(k^2) solves
            return np.cumsum(chords / chords.sum() * T)[:-1]
        z0 = np.log(chords / chords.sum())

        def fractions(z: np.ndarray) -> np.ndarray:
            e = np.exp(z - z.max())
            return np.maximum(e / e.sum(), eps)

        scale = 1.0

        def costk(z: np.ndarray) -> float:
            f = fractions(z)
            return cls._cost(pts, f / f.sum() * T, v0, a0) / scale

        scale = max(costk(z0), 1e-300)       # optimise the cost relative to the start's
        res = minimize(costk, z0, method='Nelder-Mead',
                       options={'xatol': 1e-7, 'fatol': 1e-12, 'maxiter': 200 * (k + 1)})
        z = res.x if res.fun <= costk(z0) else z0
        f = fractions(z)
        return np.cumsum(f / f.sum() * T)[:-1]


def brake(p: ArrayLike, v: ArrayLike, a: ArrayLike, *, max_acceleration: ArrayLike,
          min_duration: float = 0.05) -> PiecewisePolynomial:
    """Bring a moving state to rest smoothly, wherever that is (free end point).

    The minimum-jerk motion from ``(p, v, a)`` to zero velocity and acceleration with a
    free final position: the natural boundary condition of (2.1) at a free end makes the
    fifth derivative vanish, so the motion is the quartic meeting ``v(T) = a(T) = 0``.
    ``T`` is the shortest (from ``min_duration`` up) whose peak acceleration stays within
    ``max_acceleration`` per coordinate.
    """
    p0 = as_points(p, 'p')
    n = p0.size
    v0 = as_points(v, 'v', n=n)
    a0 = as_points(a, 'a', n=n)
    amax = np.abs(as_points(max_acceleration, 'max_acceleration', n=n, broadcast=True))
    T = max(float(min_duration), 1e-3)
    with np.errstate(divide='ignore', invalid='ignore'):
        guess = np.where(amax > 0, 1.5 * np.abs(v0) / amax, 0.0)
    T = max(T, float(np.max(guess)))
    for _ in range(60):
        traj = _free_end_quartic(p0, v0, a0, T)
        acc = traj.sample_many(np.linspace(0.0, T, 64))[2]
        peak = np.max(np.abs(acc), axis=0)
        excess = peak[amax > 0] / amax[amax > 0]
        # an initial acceleration above the limit cannot be undone at t = 0
        initial = np.abs(a0[amax > 0]) / amax[amax > 0]
        if excess.size == 0 or np.all(excess <= np.maximum(1.0, initial) + 1e-9):
            return traj
        T *= 1.15
    return traj


def _free_end_quartic(p0: np.ndarray, v0: np.ndarray, a0: np.ndarray, T: float) -> PiecewisePolynomial:
    """Quartic ``p0 + V0 s + A0 s^2/2 + c3 s^3 + c4 s^4`` (s = t/T) with v(T) = a(T) = 0."""
    V0, A0 = v0 * T, a0 * T * T
    # v(T) = 0: V0 + A0 + 3 c3 + 4 c4 = 0 ; a(T) = 0: A0 + 6 c3 + 12 c4 = 0
    M = np.array([[3.0, 4.0], [6.0, 12.0]])
    c3, c4 = np.linalg.solve(M, np.vstack([-(V0 + A0), -A0]))
    b = np.vstack([p0, V0, A0 / 2.0, c3, c4, np.zeros_like(p0)])
    return PiecewisePolynomial(b[None], np.array([T]))


@dataclass(frozen=True)
class FittsLaw:
    """Fitts' law parameters of eq. (2.12): intercept ``a`` (s), slope ``b`` (s/bit), width ``w`` (m)."""

    a: float = 0.2
    b: float = 0.3
    w: float = 0.01
    min_duration: float = 0.05

    def duration(self, amplitude: float) -> float:
        """Movement time for a reach of ``amplitude`` (see :func:`fitts_duration`)."""
        return fitts_duration(amplitude, a=self.a, b=self.b, w=self.w, min_duration=self.min_duration)


def fitts_duration(amplitude: float, *, a: float, b: float, w: float,
                   min_duration: float = 0.05) -> float:
    """Movement time by Fitts' law, eq. (2.12): ``tf = a + b log2(2A / W)``.

    A reach shorter than half the target (``2A/W < 1``, a negative index of difficulty) is
    given the intercept ``a``; the result is at least ``min_duration`` so a zero-length
    goal still has a well-defined motion.

    :param amplitude: target distance ``A`` (m).
    :param a: intercept (s). :param b: slope (s/bit). :param w: target width ``W`` (m).
    :raises TrajectoryError: non-finite or negative amplitude, non-positive width.
    """
    A = float(amplitude)
    if not (math.isfinite(A) and A >= 0.0):
        raise TrajectoryError(f"Fitts' law: amplitude must be finite and >= 0, got {A}")
    if not (math.isfinite(w) and w > 0.0):
        raise TrajectoryError(f"Fitts' law: target width W must be > 0, got {w}")
    index = math.log2(2.0 * A / w) if 2.0 * A > w else 0.0
    return max(float(a) + float(b) * index, float(min_duration))
