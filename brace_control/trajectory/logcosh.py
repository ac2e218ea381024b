"""The shoulder-joint thesis's log-cosh S-curve (seed 004, 仿真过程).

The thesis plans each motion as the displacement

    S(t) = Sd/2 + ve^2/(4 ae) ln[cosh(2 ae t/ve - delta) / cosh(2 ae t/ve - delta - 2 Sd ae/ve^2)]

whose velocity ``ve/2 [tanh(u) - tanh(u - k)]`` (``u = 2 ae t/ve - delta``,
``k = 2 Sd ae/ve^2``) rises to at most ``ve`` and whose acceleration
``ae [sech^2 u - sech^2 (u - k)]`` stays within ``ae``. ``S`` is odd about the
mid-time ``tm = (delta + k/2) ve/(2 ae)`` and only tends to 0 and ``Sd`` at
``t -> -inf, +inf``: ``S(0) = eps`` is not exactly 0.

Here the motion lasts ``T = 2 tm = delta ve/ae + Sd/ve`` and is made exact: the odd
cubic ``c1 w + c3 w^3`` (``w = t - tm``) is subtracted so velocity and acceleration are
exactly zero at both ends (it is of order ``e^{-2 delta}``), and the result is scaled so
it starts at 0 and ends at ``Sd`` exactly. These corrections raise the peaks by about
0.1 % (``delta = 5``); a profile built from limits is slowed just enough to absorb that.
All coordinates follow the straight line
``start + s(t) (goal - start)`` with one normalised ``s`` (synchronised).
"""
from __future__ import annotations

import math

import numpy as np

from .base import (ArrayLike, PiecewisePolynomial, Trajectory, TrajectoryError, as_points,
                   quintic_coefficients)

__all__ = ['LogCosh']


def _logcosh(x: np.ndarray) -> np.ndarray:
    """``ln cosh x`` without overflow."""
    ax = np.abs(x)
    return ax + np.log1p(np.exp(-2.0 * ax)) - math.log(2.0)


class LogCosh(Trajectory):
    """Log-cosh S-curve from ``start`` to ``goal``, exact at both ends and at rest there.

    Give either ``duration`` (the shape is then set by ``delta`` and ``cruise_fraction``,
    the share of the time spent near the peak velocity ``Sd/ve``), or the peak velocity
    ``ve`` and acceleration ``ae`` of the normalised path (per unit of the straight-line
    distance, 1/s and 1/s^2) — or per-coordinate limits ``max_velocity`` /
    ``max_acceleration``, from which ``ve``, ``ae`` are the largest the slowest axis allows.

    :param start: start position (dim,).
    :param goal: goal position (dim,).
    :param duration: total time ``T`` (s); ``None`` derives it from ``ve``, ``ae``.
    :param delta: the shift ``delta`` of the thesis formula (>= 2; larger = sharper ends).
    :param cruise_fraction: ``(Sd/ve)/T`` when ``duration`` is given, in (0, 1).
    :param ve: peak velocity of ``s`` (1/s). :param ae: peak acceleration of ``s`` (1/s^2).
    :param max_velocity: per-coordinate limit (units/s), alternative to ``ve``.
    :param max_acceleration: per-coordinate limit (units/s^2), alternative to ``ae``.
    :param v0: initial velocity (moving start). :param a0: initial acceleration.
        A moving start adds the quintic that takes ``(0, v0, a0)`` to rest at ``T``.
    :raises TrajectoryError: non-finite or inconsistent parameters.
    """

    def __init__(self, start: ArrayLike, goal: ArrayLike, duration: float | None = None, *,
                 delta: float = 5.0, cruise_fraction: float = 0.4,
                 ve: float | None = None, ae: float | None = None,
                 max_velocity: ArrayLike | None = None, max_acceleration: ArrayLike | None = None,
                 v0: ArrayLike | None = None, a0: ArrayLike | None = None) -> None:
        p0 = as_points(start, 'start')
        n = p0.size
        pf = as_points(goal, 'goal', n=n)
        if not (math.isfinite(delta) and delta >= 2.0):
            raise TrajectoryError(f'delta must be >= 2, got {delta}')
        self.dim = n
        self.start_position, self.goal_position = p0, pf
        self._d = pf - p0
        self.delta = float(delta)
        Sd = 1.0                                   # normalised distance
        dist = np.abs(pf - p0)
        if duration is not None:
            T = float(duration)
            if not (math.isfinite(T) and T > 0.0):
                raise TrajectoryError(f'duration must be finite and > 0 s, got {duration}')
            if not 0.0 < cruise_fraction < 1.0:
                raise TrajectoryError(f'cruise_fraction must be in (0, 1), got {cruise_fraction}')
            ve_ = Sd / (cruise_fraction * T)
            ae_ = self.delta * ve_ / ((1.0 - cruise_fraction) * T)
        else:
            if ve is None and max_velocity is not None:
                vmax = np.abs(as_points(max_velocity, 'max_velocity', n=n, broadcast=True))
                with np.errstate(divide='ignore'):
                    ve = float(np.min(np.where(dist > 0, vmax / np.maximum(dist, 1e-300), np.inf)))
            if ae is None and max_acceleration is not None:
                amax = np.abs(as_points(max_acceleration, 'max_acceleration', n=n, broadcast=True))
                with np.errstate(divide='ignore'):
                    ae = float(np.min(np.where(dist > 0, amax / np.maximum(dist, 1e-300), np.inf)))
            if ve is None or ae is None:
                raise TrajectoryError('LogCosh needs a duration, or ve and ae (or the per-axis limits)')
            if not math.isfinite(ve) or not math.isfinite(ae):       # zero-length motion
                ve, ae = 1.0, 1.0
            if not (ve > 0.0 and ae > 0.0):
                raise TrajectoryError(f've and ae must be > 0, got ve={ve}, ae={ae}')
            ve_, ae_ = float(ve), float(ae)
            T = self.delta * ve_ / ae_ + Sd / ve_
        self._setup(ve_, ae_, T)
        if duration is None:
            # the end corrections raise the peaks by ~e^{-2 delta}: slow down in time
            # (ve/f, ae/f^2 is the same shape f times longer) so ve, ae are never exceeded
            # peaks: velocity at tm, acceleration near u = 0 (t = delta ve / 2 ae) and u = k
            t_acc = self.delta * ve_ / (2.0 * ae_)
            ts = np.concatenate([np.linspace(0.0, T, 801), [0.5 * T],
                                 t_acc + np.linspace(-0.01, 0.01, 41) * T,
                                 T - t_acc + np.linspace(-0.01, 0.01, 41) * T])
            ts = ts[(ts >= 0.0) & (ts <= T)]
            _, dS, ddS, _ = self._corrected(ts)
            f = max(float(np.max(np.abs(dS))) / ve_, math.sqrt(float(np.max(np.abs(ddS))) / ae_), 1.0)
            if f > 1.0:
                f *= 1.0 + 1e-6
                self._setup(ve_ / f, ae_ / (f * f), T * f)
        v = as_points(v0, 'v0', n=n, default=0.0)
        a = as_points(a0, 'a0', n=n, default=0.0)
        self.v0, self.a0 = v, a
        self._correction: PiecewisePolynomial | None = None
        if np.any(v != 0.0) or np.any(a != 0.0):
            z = np.zeros(n)
            self._correction = PiecewisePolynomial(
                quintic_coefficients(z, v, a, z, z, z, self.duration)[None], np.array([self.duration]))

    def _setup(self, ve_: float, ae_: float, T: float) -> None:
        Sd = 1.0
        self.ve, self.ae, self.duration = ve_, ae_, T
        self._k = 2.0 * Sd * ae_ / ve_ ** 2
        self._tm = 0.5 * T
        # odd cubic correction c1 w + c3 w^3 cancelling S'(0) and S''(0), w = t - tm
        s0, sv0, sa0, _ = self._raw(np.array([0.0]))
        W = -self._tm
        # velocity: S'(0) - c1 - 3 c3 W^2 = 0 ; acceleration: S''(0) - 6 c3 W = 0
        self._c3 = float(sa0[0]) / (6.0 * W)
        self._c1 = float(sv0[0]) - 3.0 * self._c3 * W * W
        lo = float(s0[0]) - (self._c1 * W + self._c3 * W ** 3)
        self._offset = lo
        self._scale = 1.0 / (Sd - 2.0 * lo)       # odd about tm: end value is Sd - lo

    def _raw(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The thesis's ``S(t)`` (Sd = 1) and its first three derivatives."""
        ve, ae, k = self.ve, self.ae, self._k
        u = 2.0 * ae * t / ve - self.delta
        S = 0.5 + ve * ve / (4.0 * ae) * (_logcosh(u) - _logcosh(u - k))
        th1, th2 = np.tanh(u), np.tanh(u - k)
        dS = 0.5 * ve * (th1 - th2)
        sech1, sech2 = 1.0 - th1 * th1, 1.0 - th2 * th2
        ddS = ae * (sech1 - sech2)
        dddS = -4.0 * ae * ae / ve * (sech1 * th1 - sech2 * th2)
        return S, dS, ddS, dddS

    def _corrected(self, t: np.ndarray) -> list[np.ndarray]:
        """Normalised ``s(t)`` in [0, 1] and its first three derivatives."""
        S, dS, ddS, dddS = self._raw(t)
        w = t - self._tm
        c1, c3 = self._c1, self._c3
        return [(S - (c1 * w + c3 * w ** 3) - self._offset) * self._scale,
             (dS - c1 - 3.0 * c3 * w * w) * self._scale,
             (ddS - 6.0 * c3 * w) * self._scale,
             (dddS - 6.0 * c3) * self._scale]

    def sample(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Position, velocity, acceleration at ``t`` (scalar fast path of the setpoint loop)."""
        t = min(max(float(t), 0.0), self.duration)
        ve, ae, k = self.ve, self.ae, self._k
        u = 2.0 * ae * t / ve - self.delta
        w = t - self._tm
        c1, c3, sc = self._c1, self._c3, self._scale

        def lncosh(x: float) -> float:
            ax = abs(x)
            return ax + math.log1p(math.exp(-2.0 * ax)) - math.log(2.0)
        th1, th2 = math.tanh(u), math.tanh(u - k)
        S = 0.5 + ve * ve / (4.0 * ae) * (lncosh(u) - lncosh(u - k))
        s0 = (S - (c1 * w + c3 * w ** 3) - self._offset) * sc
        s1 = (0.5 * ve * (th1 - th2) - c1 - 3.0 * c3 * w * w) * sc
        s2 = (ae * ((1.0 - th1 * th1) - (1.0 - th2 * th2)) - 6.0 * c3 * w) * sc
        d = self._d
        p, v, a = self.start_position + s0 * d, s1 * d, s2 * d
        if self._correction is not None:
            cp, cv, ca = self._correction.sample(t)
            p, v, a = p + cp, v + cv, a + ca
        return p, v, a

    def _evaluate(self, t: np.ndarray, order: int) -> list[np.ndarray]:
        s = self._corrected(t)
        d = self.goal_position - self.start_position
        out = [self.start_position[None, :] + s[0][:, None] * d[None, :]]
        for j in range(1, order + 1):
            out.append(s[j][:, None] * d[None, :])
        if self._correction is not None:
            corr = self._correction._evaluate(t, order)
            out = [o + c for o, c in zip(out, corr)]
        return out[:order + 1]
