"""The platform wrench and the load tiers built on it (docs/safety.md §8, §14).

:class:`PlatformWrench` turns measured actuator positions and load-cell forces into the
wrench the brace puts on the body: the pose by ``forward_nearest`` from the last one, then
the mechanism's statics there. At a fixed pose the statics are affine in the forces
(``J^T f`` for the rigid mechanisms, ``J^T (f − f0)`` for the continuum robot), so the
forward kinematics and the map are refreshed at most every ``pose_period`` (and only when
the positions changed), while the wrench itself is evaluated for every sample. In the SYNC
cycle (500 Hz) a wrench step is then seen in the cycle its load-cell reading arrives; the
pose used is at most ``pose_period`` old (10 ms by default: at the brace's 30 mm/s, 0.3 mm,
whose effect on ``J`` is far below the load cells' noise). A mechanism whose forward
solution is slow refreshes less often, so that it takes at most :data:`FK_SHARE` of the
cycle's time (bench/RESULTS.md, "Load tiers in the cycle").

:class:`WrenchTiers` is the platform wrench's pair of tiers: above ``safety.max_wrench`` on
any axis a protective stop; a motion whose wrench would pass it by the motion's end a soft
stop (:class:`LoadPrediction`). :class:`ForcePrediction` applies the same prediction to each
actuator's load cell against ``safety.force_limit``: the fixed soft limit (0.8 of the hard
one, :mod:`brace_control.can.monitors`) brakes only once it is passed, and a stiff load (the
trainer's crank against the arm) can overshoot from there into the hard limit.
"""
from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from .verdict import OK, Action, Verdict

__all__ = ['PlatformWrench', 'LoadPrediction', 'WrenchTiers', 'ForcePrediction', 'wrench_axis',
           'POSE_PERIOD_S', 'SOFT_FLOOR', 'SOFT_WINDOW_S', 'SOFT_RISE', 'SOFT_STREAM_S',
           'SOFT_AHEAD']

#: s: the longest the pose behind the wrench map may be old while the positions change
POSE_PERIOD_S = 0.01
#: the forward kinematics may take at most this share of the time: a mechanism whose
#: solution takes longer (the shoulder's, the continuum robot's: ~1.5 ms here) refreshes
#: its pose less often than POSE_PERIOD_S
FK_SHARE = 0.1
#: the soft tiers look from this share of the hard limit up (the extrapolation at most
#: doubles the load, so a motion heading past the limit stops with room to brake)
SOFT_FLOOR = 0.5
#: s of motion over which a load's rise is measured
SOFT_WINDOW_S = 0.05
#: a rise below this share of the limit is the load cells' noise, not a rise
SOFT_RISE = 0.01
#: s of a setpoint stream's future counted as "the motion's end" (a stream has no end)
SOFT_STREAM_S = 0.25
#: a rise is carried at most this many times the stroke it was seen over (ten windows of travel
#: at the present speed, 0.5 s). At a motion's start the stroke of a window is microns while
#: the load cells see the drives' acceleration: 0.42 N in 0.01 mm carried over the 34 mm home
#: made 1452 N of a load that was falling (a neck brace's way back from a soft stop)
SOFT_AHEAD = 10.0


def wrench_axis(mechanism: Any, j: int) -> tuple[str, str]:
    """Name and unit of axis ``j`` of ``safety.max_wrench`` for the mechanism's pose kind."""
    axes = {'planar': (('Fx', 'N'), ('Fy', 'N'), ('Mz', 'N·m')), 'xy': (('Fx', 'N'), ('Fy', 'N')),
            'spherical': (('Mx', 'N·m'), ('My', 'N·m'), ('Mz', 'N·m'))}.get(mechanism.pose_kind, ())
    return axes[j] if j < len(axes) else (f'axis {j}', 'N or N·m')


class PlatformWrench:
    """The platform wrench of measured positions and forces (see the module docstring).

    :param mechanism: the device's model (``forward_nearest``, ``wrench``, ``home_pose``).
    :param pose_period: s; 0 solves the forward kinematics for every new ``q``.
    :param legs: a planar RPR's legs in plain floats
        (:class:`~brace_control.mechanisms.planar_floats.PlanarRprFloats`), its ``J^T f``
        without numpy; ``None``: the mechanism's own ``wrench``.

    The per-sample path is plain Python floats (a cached pose: ~10 us); numpy only when the
    pose is solved again. Not thread-safe: one caller (the SYNC thread); :meth:`once` may be
    called from any thread.
    """

    def __init__(self, mechanism: Any, *, pose_period: float = POSE_PERIOD_S, legs: Any = None) -> None:
        self.mechanism = mechanism
        self.pose_period = float(pose_period)
        self.legs = legs
        #: the last pose found (the next forward solution's starting guess)
        self.pose = np.asarray(mechanism.home_pose, dtype=float)
        self._key: tuple[float, ...] | None = None    # q of the last forward solution
        self._t = -math.inf                     # its time
        self._period = self.pose_period         # POSE_PERIOD_S, longer for a slow solution
        self._rows: Any = None                  # legs' rows there (fast path)
        #: the statics at that pose, w = W f + w0: W's rows and w0, plain floats
        self._map: tuple[list[list[float]], list[float]] | None = None
        #: the last solution failed (no pose fits ``q``: a slack cable, a sensor fault):
        #: nothing to judge by until the next one, tried no sooner than a period later
        self._failed = False

    def __call__(self, q: Sequence[float], forces: Sequence[float], now: float) -> list[float] | None:
        """The wrench (a list, one value per wrench axis), or ``None`` when no pose fits
        ``q`` or a value is not finite (nothing to judge by)."""
        key = tuple(map(float, q))
        f = [float(x) for x in forces]
        if not all(map(math.isfinite, key)) or not all(map(math.isfinite, f)):
            return None
        if key != self._key and (now - self._t >= self._period or
                                 (self._rows is None and self._map is None and not self._failed)):
            if not self._refresh(key, now):
                return None
        if self._failed:
            return None
        rows = self._rows
        if rows is not None and len(f) == len(rows):
            return self.legs.wrench(rows, f)
        if self._map is None:
            self._map = self._affine_map(self.pose, len(f))
        W, w0 = self._map
        return [sum(w * x for w, x in zip(row, f)) + c for row, c in zip(W, w0)]

    def once(self, q: Sequence[float], forces: Sequence[float]) -> np.ndarray | None:
        """The wrench of ``(q, forces)`` solved afresh from the last pose, by the mechanism's
        own statics; no cache is read or written (safe beside :meth:`__call__`)."""
        hint = self.pose.copy()
        try:
            pose = np.asarray(self.mechanism.forward_nearest(np.asarray(q, dtype=float), hint), dtype=float)
            return np.asarray(self.mechanism.wrench(pose, np.asarray(forces, dtype=float)), dtype=float)
        except ValueError:
            return None

    def _refresh(self, key: tuple[float, ...], now: float) -> bool:
        """Solve the pose of ``key`` afresh. A failed solution (no pose fits) is paced like
        a good one: the global search it falls back on (every branch, least squares: a cable
        brace's slack cables during a take-up) took ~4 ms, and retried at every SYNC it
        overran the cycle and once held the heartbeat back past the drives' consumer time."""
        t0 = time.perf_counter()
        try:
            pose = np.asarray(self.mechanism.forward_nearest(np.array(key), self.pose), dtype=float)
        except ValueError:
            pose = None
        if self.pose_period > 0.0:
            self._period = max(self.pose_period, (time.perf_counter() - t0) / FK_SHARE)
        self._key, self._t = key, now
        self._rows, self._map = None, None
        self._failed = pose is None or not np.isfinite(pose).all()
        if self._failed:
            return False
        self.pose = pose
        if self.legs is not None and pose.shape == (3,):
            try:
                lengths, rows = self.legs.lengths_and_rows(*pose.tolist())
            except ZeroDivisionError:               # a leg of zero length: the model raises
                return True
            if min(lengths) > 1e-12:
                self._rows = rows
        return True

    def _affine_map(self, pose: np.ndarray, n: int) -> tuple[list[list[float]], list[float]]:
        """``(W, w0)`` with ``wrench(pose, f) = W f + w0`` (exact: the statics are affine in
        ``f`` at a fixed pose; ``test/test_safety_tiers.py`` checks it per device)."""
        w0 = np.asarray(self.mechanism.wrench(pose, np.zeros(n)), dtype=float)
        cols = [np.asarray(self.mechanism.wrench(pose, np.eye(n)[i]), dtype=float) - w0 for i in range(n)]
        return np.column_stack(cols).tolist(), w0.tolist()


class LoadPrediction:
    """The soft tiers' prediction (docs/safety.md §14): a load (per wrench axis or per
    actuator) whose rise per actuator displacement over the last :data:`SOFT_WINDOW_S`,
    carried over the distance the motion has still to go (at most :data:`SOFT_AHEAD` times the
    stroke the rise was seen over), would pass its limit by the motion's end. Looked at from
    :data:`SOFT_FLOOR` of the limit up; a rise within :data:`SOFT_RISE` of the limit is noise. A
    load that stays below its limit is left alone: the prediction is the load at the motion's
    end, not a fixed share of the limit."""

    def __init__(self, *, floor: float = SOFT_FLOOR, window_s: float = SOFT_WINDOW_S,
                 rise: float = SOFT_RISE, ahead: float = SOFT_AHEAD) -> None:
        self.floor, self.window_s, self.rise = float(floor), float(window_s), float(rise)
        self.ahead = float(ahead)
        self._trend: deque[tuple[float, Sequence[float], Sequence[float]]] = deque()

    def clear(self) -> None:
        self._trend.clear()

    def __call__(self, now: float, load: Sequence[float], limit: Sequence[float], q: Sequence[float],
                 distance_to_go: Callable[[], float | None]) -> tuple[int, float, float, float, float, float] | None:
        """``(j, load_j, rise_j, moved, ahead_j, further)`` of the first load predicted past its
        limit, else ``None``; ``ahead_j = load_j + rise_j / moved · further``, ``further = min(to
        go, SOFT_AHEAD · moved)``. ``distance_to_go()``: the actuator-space distance (m or rad) left of
        the running motion, ``None`` when none runs (called only from the floor up)."""
        trend = self._trend
        trend.append((now, load, q))
        while len(trend) > 2 and now - trend[1][0] >= self.window_s:
            trend.popleft()                 # keep one sample at least a window old
        floor = self.floor
        if not any(x > floor * m for x, m in zip(load, limit)):
            return None
        t_old, load_old, q_old = trend[0]
        if now - t_old < self.window_s:
            return None
        moved = math.dist(q, q_old)
        if moved <= 0.0:
            return None
        togo = distance_to_go()
        if togo is None:
            return None
        togo = min(togo, self.ahead * moved)
        for j, (x, x_old, m) in enumerate(zip(load, load_old, limit)):
            rise = x - x_old
            ahead = x + max(rise, 0.0) / moved * togo
            if x > floor * m and rise > self.rise * m and ahead > m:
                return j, float(x), float(rise), moved, float(ahead), float(togo)
        return None


def _soft_reason(tier: str, what: str, unit: str, limit_name: str, limit: float,
                 hit: tuple[int, float, float, float, float, float]) -> str:
    _, load, rise, moved, ahead, further = hit
    return (f'{tier}: {what} at {load:.1f} {unit}, rising {rise:.2f} {unit} in the last '
            f'{moved * 1e3:.2f} mm (or mrad) of the motion, would reach {ahead:.1f} {unit} '
            f'{further * 1e3:.2f} mm (or mrad) further on, above {limit_name} = {limit:g} {unit}; '
            f'decelerated along the path, holding')


class WrenchTiers:
    """``safety.max_wrench``'s two tiers on the platform wrench (docs/safety.md §8, §14)."""

    def __init__(self, platform: PlatformWrench, max_wrench: Sequence[float],
                 prediction: LoadPrediction | None = None) -> None:
        self.platform = platform
        self.limit = [float(x) for x in max_wrench]
        self.prediction = prediction or LoadPrediction()

    def check(self, now: float, q: Sequence[float], forces: Sequence[float],
              distance_to_go: Callable[[], float | None]) -> Verdict:
        w = self.platform(q, forces, now)
        if w is None:
            return OK
        limit = self.limit[:len(w)]
        load = [abs(x) for x in w[:len(limit)]]
        over = [i for i, (x, m) in enumerate(zip(load, limit)) if x > m]
        if over:
            return Verdict(Action.PROTECTIVE_STOP,
                           f'platform wrench {[round(x, 1) for x in w]} exceeds safety.max_wrench '
                           f'{self.limit} on axis {over}')
        hit = self.prediction(now, load, limit, q, distance_to_go)
        if hit is None:
            return OK
        self.prediction.clear()
        axis, unit = wrench_axis(self.platform.mechanism, hit[0])
        return Verdict(Action.SOFT_STOP, _soft_reason('soft wrench limit', f'the platform {axis}', unit,
                                                      'safety.max_wrench', limit[hit[0]], hit))

    def exceeds(self, q: Sequence[float], forces: Sequence[float]) -> bool:
        """The hard tier's "cause still present": the wrench of ``(q, forces)`` above the
        limit. Solved afresh, touching no state of :meth:`check` (another thread may ask)."""
        w = self.platform.once(q, forces)
        if w is None:
            return False
        return any(abs(float(x)) > m for x, m in zip(w, self.limit))


class ForcePrediction:
    """The prediction of :class:`LoadPrediction` on each actuator's load cell against
    ``safety.force_limit`` (the predictive soft force tier): a motion whose force would pass
    the hard limit by its end is braked from :data:`SOFT_FLOOR` of it up."""

    def __init__(self, names: Sequence[str], force_limit: float, unit: str,
                 prediction: LoadPrediction | None = None) -> None:
        self.names = tuple(names)
        self.limit = [float(force_limit)] * len(self.names)
        self.unit = unit
        self.prediction = prediction or LoadPrediction()

    def check(self, now: float, q: Sequence[float], forces: Sequence[float],
              distance_to_go: Callable[[], float | None]) -> Verdict:
        f = [abs(float(x)) for x in forces]
        if len(f) != len(self.limit) or not all(map(math.isfinite, f)):
            return OK
        hit = self.prediction(now, f, self.limit, q, distance_to_go)
        if hit is None:
            return OK
        self.prediction.clear()
        return Verdict(Action.SOFT_STOP, _soft_reason('soft force limit', f"{self.names[hit[0]]}'s load cell",
                                                      self.unit, 'safety.force_limit', self.limit[hit[0]], hit))
