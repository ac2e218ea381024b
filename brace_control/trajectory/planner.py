"""Plan a motion that holds the limits: build the profile, check it, slow it down or reject.

:func:`plan_motion` is what the trajectory node calls for every goal. It never moves
anything; it returns a :class:`Plan` whose whole path has been checked against the
mechanism (:func:`~.limits.check_path`), or raises :class:`PlanRejected` with the reason.
"""
from __future__ import annotations

import dataclasses
import enum
import importlib
import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from .base import ArrayLike, Trajectory, TrajectoryError, as_points
from .limits import Limits, PathCheck, Violation, check_capacity, check_path, check_pose
from .logcosh import LogCosh
from .minimum_jerk import FittsLaw, MinimumJerk, ViaPointMinimumJerk
from .path import PathTrajectory, curve_path
from .scurve import SCurve

if TYPE_CHECKING:  # pragma: no cover
    from ..mechanisms.base import Mechanism

__all__ = ['Profile', 'Plan', 'PlanRejected', 'plan_motion', 'build_profile']

MAX_DURATION_S = 600.0       # a goal that needs a longer motion than this is rejected
_MAX_STRETCHES = 16


class Profile(str, enum.Enum):
    """Motion profile (``trajectory.profile``)."""

    MINIMUM_JERK = 'minimum_jerk'
    SCURVE = 'scurve'
    LOGCOSH = 'logcosh'


class PlanRejected(ValueError):
    """The goal cannot be reached within the limits; ``reason`` says why (for the status)."""

    def __init__(self, reason: str, violation: Violation = Violation.NONE) -> None:
        super().__init__(reason)
        self.reason = reason
        self.violation = violation


@dataclass
class Plan:
    """A checked motion: ``trajectory`` holds every limit along its path.

    :ivar stretch: total time-scaling applied to respect the actuator limits (1 = none).
    :ivar notes: what the planner changed or fell back to (for the log and status).
    """

    trajectory: Trajectory
    profile: Profile
    check: PathCheck
    stretch: float = 1.0
    notes: list[str] = field(default_factory=list)
    #: numbers for the goal's status (e.g. the path's minimum wrench capacity)
    values: dict = field(default_factory=dict)

    @property
    def duration(self) -> float:
        return self.trajectory.duration


def build_profile(profile: Profile, start: np.ndarray, goal: np.ndarray, limits: Limits, *,
                  duration: float | None, via: np.ndarray | None = None,
                  t_via: np.ndarray | None = None, v0: np.ndarray | None = None,
                  a0: np.ndarray | None = None, scale: float = 1.0) -> Trajectory:
    """One profile without checks. ``scale`` slows an S-curve (limits / scale^k)."""
    if via is not None and len(via):
        return ViaPointMinimumJerk(start, via, goal, duration, t_via, v0=v0, a0=a0)
    if profile is Profile.MINIMUM_JERK:
        return MinimumJerk(start, goal, duration, v0=v0, a0=a0)
    if profile is Profile.LOGCOSH:
        return LogCosh(start, goal, duration, v0=v0, a0=a0)
    return SCurve(start, goal, limits.max_velocity / scale, limits.max_acceleration / scale ** 2,
                  limits.max_jerk / scale ** 3, v0=v0, a0=a0, min_duration=duration)


#: what planning imports on first use (the path's splines, the via-time search, the sparse
#: via-point solve, the mechanisms' roots and integrals), not with the package: a node that
#: never plans does not pay for them (361bd45)
PLANNING_MODULES = ('scipy.interpolate', 'scipy.optimize', 'scipy.sparse.linalg', 'scipy.special')


def load_planning_modules() -> None:
    """Import :data:`PLANNING_MODULES` now, so that no goal's planning pays for them.

    The trajectory node's planner does this before its first goal: a goal's planning time
    is held to ``trajectory.planning_budget``, and the first goal on the trainer's curved
    path, whose spline imported ``scipy.interpolate``, took 0.5 s more on a quiet machine
    and over 5 s on a loaded one (rejected: "planning took 5.39 s").
    """
    for name in PLANNING_MODULES:
        importlib.import_module(name)


def plan_motion(mech: 'Mechanism', start: ArrayLike, goal: ArrayLike, profile: Profile | str,
                limits: Limits, *, via: ArrayLike | None = None, t_via: ArrayLike | None = None,
                duration: float | None = None, v0: ArrayLike | None = None,
                a0: ArrayLike | None = None, fitts: FittsLaw | None = None,
                fitts_axes: tuple[int, ...] | None = None) -> Plan:
    """Plan a limit-respecting motion from ``start`` (moving with ``v0``, ``a0``) to ``goal``.

    * ``via`` (k, dof) points are passed in order with the minimum-jerk via-point model,
      eqs. (2.4)–(2.11), whatever the profile (community Ruckig has no waypoints), at
      ``t_via`` or at the optimal times.
    * Without ``duration``, the minimum-jerk and log-cosh profiles take Fitts' law,
      eq. (2.12), on the distance over ``fitts_axes`` (all by default; A, W in m); the
      S-curve is time-optimal within ``limits``.
    * The goal and via points are checked first, then the whole sampled path (stroke,
      workspace, singularity); if an actuator would be too fast the motion is stretched
      in time (S-curve: planned within proportionally lower limits) until it is not.

    :raises PlanRejected: bad input (non-finite, wrong length, times out of order), a
        pose outside the stroke or the workspace or a singularity on the way, or a motion
        that would need more than ``MAX_DURATION_S``; the reason names what and where.
    """
    try:
        profile = Profile(profile)
    except ValueError as exc:
        raise PlanRejected(f'unknown profile {profile!r}; expected one of '
                           f'{[p.value for p in Profile]}') from exc
    dof = int(getattr(mech, 'dof', np.size(start)))
    try:
        p0 = as_points(start, 'start', n=dof)
        pf = as_points(goal, 'goal', n=dof)
        vel0 = as_points(v0, 'v0', n=dof, default=0.0)
        acc0 = as_points(a0, 'a0', n=dof, default=0.0)
        vias = None
        if via is not None:
            vias = np.array(via, dtype=float)
            vias = vias.reshape(1, -1) if vias.ndim == 1 else vias
            if vias.ndim != 2 or vias.shape[1] != dof:
                raise TrajectoryError(f'via points: expected shape (k, {dof}), got {np.shape(via)}')
            if not np.all(np.isfinite(vias)):
                raise TrajectoryError('via points: non-finite value')
            if vias.shape[0] == 0:
                vias = None
        tv = None
        if t_via is not None and vias is not None:
            tv = as_points(t_via, 't_via', n=vias.shape[0])
            if duration is None:
                raise TrajectoryError('via times given without a total duration')
        if duration is not None and not (math.isfinite(duration) and duration > 0.0):
            raise TrajectoryError(f'duration must be finite and > 0 s, got {duration}')
    except (TrajectoryError, TypeError, ValueError) as exc:
        raise PlanRejected(f'bad goal: {exc}', Violation.NON_FINITE) from exc

    cond_max = limits.singularity_condition_max
    targets = ([('via point %d' % (i + 1), vp) for i, vp in enumerate(vias)] if vias is not None
               else []) + [('goal', pf)]
    for label, pose in targets:
        res = check_pose(mech, pose, condition_max=cond_max)
        if not res.ok:
            raise PlanRejected(f'{label} rejected: {res.reason}', res.violation)

    notes: list[str] = []
    if vias is not None and profile is not Profile.MINIMUM_JERK:
        notes.append(f'via points: minimum-jerk via-point model used instead of {profile.value}')
    # a one-mobility mechanism (the four-bar) moves along its path: the profile runs in the
    # path's arc length, every sample on the path (.path)
    path = curve_path(mech)
    profile_limits = limits
    if path is not None:
        try:
            p0, pf = np.array([path.coordinate(p0)]), np.array([path.coordinate(pf)])
            vias = None if vias is None else np.array([[path.coordinate(v)] for v in vias])
            vel0, acc0 = (np.array([r]) for r in path.rates(
                as_points(start, 'start', n=dof), vel0, acc0))
        except ValueError as exc:
            raise PlanRejected(f'start off the path: {exc}', Violation.WORKSPACE) from exc
        profile_limits = dataclasses.replace(
            limits, max_velocity=np.array([np.min(limits.max_velocity)]),
            max_acceleration=np.array([np.min(limits.max_acceleration)]),
            max_jerk=np.array([np.min(limits.max_jerk)]))
        fitts_axes = (0,)
        notes.append('along the path (arc length)')
    T = duration
    if T is None and (profile is not Profile.SCURVE or vias is not None):
        fitts = fitts or FittsLaw()
        axes = list(fitts_axes) if fitts_axes is not None else list(range(dof))
        chain = np.vstack([p0] + ([vias] if vias is not None else []) + [pf])[:, axes]
        amplitude = float(np.sum(np.linalg.norm(np.diff(chain, axis=0), axis=1)))
        T = fitts.duration(amplitude)
        notes.append(f"Fitts' law: A = {amplitude:.4f}, tf = {T:.3f} s")

    stretch = 1.0
    scale = 1.0
    traj: Trajectory | None = None
    for _ in range(_MAX_STRETCHES):
        try:
            inner = build_profile(profile, p0, pf, profile_limits, duration=T, via=vias,
                                  t_via=None if tv is None else tv * stretch, v0=vel0, a0=acc0,
                                  scale=scale)
        except TrajectoryError as exc:
            raise PlanRejected(f'cannot plan: {exc}') from exc
        if isinstance(inner, SCurve) and inner.fallback:
            notes.append(f'Ruckig failed ({inner.fallback}); minimum-jerk fallback within the limits')
        if isinstance(inner, ViaPointMinimumJerk) and tv is None and vias is not None:
            tv = inner.t_via / stretch          # optimised once, then scaled with the duration
        traj = inner if path is None else PathTrajectory(path, inner)
        if traj.duration > MAX_DURATION_S:
            raise PlanRejected(f'the motion would last {traj.duration:.1f} s '
                               f'(more than {MAX_DURATION_S:.0f} s) to respect the limits')
        check = check_path(mech, traj, limits)
        if check.ok:
            capacity, minima = check_capacity(mech, traj, limits)
            if not capacity.ok:
                raise PlanRejected(f'path rejected {capacity.reason}', capacity.violation)
            if stretch > 1.0 or scale > 1.0:
                notes.append(f'slowed down x{max(stretch, scale):.3f} for the actuator limits')
            values = {} if minima is None else {
                'min_wrench_capacity': ' '.join(f'{c:.4g}' for c in minima)}
            return Plan(traj, profile, check, max(stretch, scale), notes, values)
        if not check.violation.fixable_by_slowing:
            raise PlanRejected(f'path rejected {check.reason}', check.violation)
        factor = max(check.speed_ratio, math.sqrt(max(check.acceleration_ratio, 0.0)), 1.0) * 1.02
        if isinstance(inner, SCurve) and vias is None and duration is None:
            scale *= factor
        else:
            T = traj.duration * factor
            stretch *= factor
    raise PlanRejected(f'cannot respect the actuator limits: {check.reason}', check.violation)
