"""Motion along the path of a one-mobility mechanism: the upper-limb trainer's coupler curve.

The Hoeken four-bar has one crank: its handle ``P`` moves on the coupler curve only, so a
straight line between two of its points (what a pose-space profile interpolates) leaves the
curve wherever the curve bends — everywhere but the straight stroke. Here the profile runs
in the curve's arc length ``s`` instead (minimum jerk in ``s``: the hand's speed along its
path is the bell of Flash and Hogan; on the straight stroke ``s`` is the distance in x, the
thesis's prescription), and :class:`PathTrajectory` maps it back to poses, every sample on
the curve:

* ``s(theta)`` is the arc length from the lower end of the crank range,
  ``s' = |dP/dtheta|``, integrated on a fine grid (composite Simpson per cell) and held as a
  cubic spline; ``theta(s)`` by Newton on it from the inverse spline's guess;
* ``theta_dot = s_dot / s'``, ``theta_ddot = (s_ddot - s'' theta_dot^2) / s'`` (the chain rule
  on ``s(theta(t))``), then ``P_dot = P' theta_dot``, ``P_ddot = P'' theta_dot^2 + P' theta_ddot``;
* a start that moves (a goal preempting a running motion) gives ``s_dot = s' J v`` and the
  tangential part of its acceleration.

The crank range is one turn at most, so the path between two poses is the crank's own way
between their angles (never across the range's end): unique, within the actuator limits.

Pure numpy/scipy: no ROS.
"""
from __future__ import annotations

import weakref
from typing import Any

import numpy as np

from .base import Trajectory, TrajectoryError

__all__ = ['CurvePath', 'PathTrajectory', 'curve_path']

#: grid cells over the crank range (Simpson's rule per cell)
_CELLS = 4096
#: Newton steps on s(theta) = s for theta(s)
_NEWTON_STEPS = 3
#: the smallest |dP/dtheta| (m/rad) a path may have: below it the crank turns while the
#: handle stands still (a dead point of the path) and s cannot parametrise it
_MIN_SPEED = 1e-6

_CACHE: 'weakref.WeakKeyDictionary[Any, CurvePath]' = weakref.WeakKeyDictionary()


def curve_path(mech: Any) -> 'CurvePath | None':
    """The :class:`CurvePath` of a one-mobility mechanism (one per mechanism object), else
    ``None``: a mechanism whose pose coordinates are its degrees of freedom moves freely
    between poses."""
    if int(getattr(mech, 'mobility', getattr(mech, 'dof', 0))) != 1 or \
            not callable(getattr(mech, 'path_point', None)):
        return None
    try:
        return _CACHE[mech]
    except KeyError:
        path = _CACHE[mech] = CurvePath(mech)
        return path


class CurvePath:
    """A mechanism's path by arc length (see the module docstring).

    :param mech: a mechanism with ``mobility = 1``, ``path_point(theta) -> (P, P', P'')``
        (arrays (N, dof)), ``inverse(pose) -> [theta]`` and ``actuator_limits``.
    :raises TrajectoryError: the path has a dead point in the crank range.
    """

    def __init__(self, mech: Any) -> None:
        self.mech = mech
        lo, hi = (float(np.ravel(v)[0]) for v in mech.actuator_limits)
        self.theta_range = (lo, hi)
        n = _CELLS
        th = np.linspace(lo, hi, 2 * n + 1)                    # cell ends and midpoints
        speed = np.linalg.norm(mech.path_point(th)[1], axis=1)
        if np.min(speed) < _MIN_SPEED:
            k = int(np.argmin(speed))
            raise TrajectoryError(f'the path stands still at crank angle {th[k]:.4f} rad '
                                  f'(|dP/dtheta| = {speed[k]:.2e} m/rad): arc length cannot '
                                  'parametrise it')
        h = (hi - lo) / n
        cells = h / 6.0 * (speed[0:-1:2] + 4.0 * speed[1::2] + speed[2::2])
        knots = th[::2]
        s = np.concatenate([[0.0], np.cumsum(cells)])
        from scipy.interpolate import CubicSpline     # scipy on first use (every node's start)
        # s(theta) interpolates the integral; its derivative is clamped to the true speed at
        # both ends (s' = |P'|), so s_dot / s' and the curve's tangent agree to the grid's accuracy
        self._s = CubicSpline(knots, s, bc_type=((1, speed[0]), (1, speed[-1])))
        self._ds = self._s.derivative()
        self._dds = self._s.derivative(2)
        self._theta = CubicSpline(s, knots)
        self.length = float(s[-1])

    # ------------------------------------------------------------------ coordinates
    def theta_of_pose(self, pose: np.ndarray) -> float:
        """The crank angle of a pose on the path (the mechanism's inverse kinematics)."""
        return float(np.ravel(self.mech.inverse(pose))[0])

    def s_of_theta(self, theta: float | np.ndarray) -> np.ndarray:
        return np.asarray(self._s(theta), dtype=float)

    def coordinate(self, pose: np.ndarray) -> float:
        """Arc length ``s`` (m) of a pose on the path."""
        return float(self.s_of_theta(self.theta_of_pose(pose)))

    def rates(self, pose: np.ndarray, velocity: np.ndarray, acceleration: np.ndarray
              ) -> tuple[float, float]:
        """``(s_dot, s_ddot)`` of a motion through ``pose`` with this pose velocity and
        acceleration (their components along the path)."""
        th = self.theta_of_pose(pose)
        _, dp, ddp = (a[0] for a in self.mech.path_point(th))
        tt = float(dp @ dp)
        th_d = float(dp @ velocity) / tt
        th_dd = float(dp @ (np.asarray(acceleration, float) - ddp * th_d ** 2)) / tt
        ds, dds = float(self._ds(th)), float(self._dds(th))
        return ds * th_d, ds * th_dd + dds * th_d ** 2

    def theta_of_s(self, s: np.ndarray) -> np.ndarray:
        """Crank angles of arc lengths ``s`` (Newton on the spline ``s(theta)``). Beyond the
        path's ends the splines extrapolate: the angle leaves the crank range, and the path
        check reports the stroke (a crank that turns fully would read the same pose there)."""
        s = np.asarray(s, dtype=float)
        th = self._theta(s)
        for _ in range(_NEWTON_STEPS):
            th = th - (self._s(th) - s) / self._ds(th)
        return th

    def crank(self, s: np.ndarray, s_d: np.ndarray, s_dd: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The actuator's angle, rate and acceleration (each (N,)) of ``s(t)`` and its rates."""
        th = self.theta_of_s(s)
        ds, dds = self._ds(th), self._dds(th)
        th_d = s_d / ds
        return th, th_d, (s_dd - dds * th_d ** 2) / ds

    def states(self, s: np.ndarray, s_d: np.ndarray, s_dd: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Poses, velocities and accelerations (each (N, dof)) of ``s(t)`` and its rates."""
        th, th_d, th_dd = self.crank(s, s_d, s_dd)
        p, dp, ddp = self.mech.path_point(th)
        return p, dp * th_d[:, None], ddp * (th_d ** 2)[:, None] + dp * th_dd[:, None]


class PathTrajectory(Trajectory):
    """A pose trajectory along a :class:`CurvePath`: the scalar profile ``inner`` (of the arc
    length) mapped onto the curve. Jerk (order 3) by central differences of the acceleration."""

    _JERK_H = 1e-5

    def __init__(self, path: CurvePath, inner: Trajectory) -> None:
        if inner.dim != 1:
            raise TrajectoryError(f'a path profile has one coordinate, got {inner.dim}')
        self.path = path
        self.inner = inner
        self.duration = float(inner.duration)
        self.dim = int(np.asarray(path.mech.home_pose).size)

    def actuator_motion(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The crank's exact angle, rate and acceleration at times ``t`` (each (N, 1)): what
        the path check holds against the actuator limits (no numerical differentiation)."""
        s, s_d, s_dd = (x[:, 0] for x in self.inner._evaluate(self._clamp(t), 2)[:3])
        return tuple(x[:, None] for x in self.path.crank(s, s_d, s_dd))

    def _evaluate(self, t: np.ndarray, order: int) -> list[np.ndarray]:
        s, s_d, s_dd = (x[:, 0] for x in self.inner._evaluate(t, 2)[:3])
        out = list(self.path.states(s, s_d, s_dd))
        if order >= 3:
            h = self._JERK_H
            ap = self._evaluate(np.clip(t + h, 0.0, self.duration), 2)[2]
            am = self._evaluate(np.clip(t - h, 0.0, self.duration), 2)[2]
            span = np.clip(t + h, 0.0, self.duration) - np.clip(t - h, 0.0, self.duration)
            out.append((ap - am) / np.where(span > 0.0, span, 1.0)[:, None])
        return out
