"""Check a planned motion against the mechanism before anything moves (docs/safety.md §5, §10).

Along the sampled path every pose must be reachable (inverse kinematics within the
stroke: the mechanism's :class:`~brace_control.mechanisms.base.UnreachablePose`),
inside the workspace, away from singularities (cond(J) below the limit, and no sign
change of det(J) between samples: a singularity crossed between two samples); the
actuator speeds and accelerations must stay within the actuator limits. Those are
checked on the actuator motion the driver will run: the knots ``ik_node`` makes of the
plan (:func:`~.actuator.actuator_knots` of :func:`~.knots.knots_of`), sampled as the
driver's own check samples them (:meth:`~.hermite.KnotTrajectory.dense`). Near the edge of
a leg's reach ``dq/dx`` grows without bound, and a joint's acceleration can peak in the
last 10 ms of a motion: central differences of ``q_dot`` on the 200 path samples read
0.77 of a peak the driver then measured at 1.03 x its limit, and refused the motion the
planner had accepted (3-RRR, a goal 0.1 mm inside leg 2's reach). A one-mobility motion
(:mod:`.path`) gives its actuator motion exactly instead.
Stroke, workspace and singularity violations reject the goal; speed and acceleration
violations tell the planner how much to slow down.
"""
from __future__ import annotations

import enum
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from ..config import as_device_config
from ..schema import mechanism_default
from ..mechanisms.base import SingularPose, UnreachablePose, check_workspace, workspace_mask
from .actuator import UnreachableKnot, actuator_knots
from .base import Trajectory, TrajectoryError
from .knots import knots_of

if TYPE_CHECKING:  # pragma: no cover
    from ..mechanisms.base import Mechanism

__all__ = ['Limits', 'Violation', 'PathCheck', 'check_path', 'check_pose', 'check_capacity',
           'executed_actuator_motion']

#: samples of a trajectory's exact actuator motion (``actuator_motion``) in the path check
EXACT_SAMPLES = 2000

#: a path leaving a start below trajectory.min_wrench_capacity may not dip below the start's
#: capacity by more than this share (the samples' rounding; :func:`check_capacity`)
START_CAPACITY_REL_TOL = 1e-9


@dataclass(frozen=True)
class Limits:
    """Limits a planned motion must respect.

    :param max_velocity: platform velocity limit per coordinate (S-curve planning).
    :param max_acceleration: platform acceleration limit per coordinate (S-curve).
    :param max_jerk: platform jerk limit per coordinate (S-curve).
    :param actuator_max_velocity: actuator speed limit (scalar or per actuator), m/s or rad/s.
    :param actuator_max_acceleration: actuator acceleration limit, or ``None`` to skip.
    :param singularity_condition_max: cond(J) above this counts as singular.
    :param samples: samples of the path checked (``trajectory.path_check_samples``).
    :param limit_margin: share of the actuator speed and acceleration limits a plan may use
        (``trajectory.limit_margin``): the fastest axis never runs at the drives' saturation,
        which leaves room for splicing a new motion and for the drives' position loop.
    :param force_limits: the actuators' effort limits (``actuator.max_force``) for the wrench
        capacity along a path.
    :param min_wrench_capacity: the smallest capacity per wrench axis a path may pass
        (``trajectory.min_wrench_capacity``, in the mechanism's ``wrench_axes``); ``None``
        or all zero: not checked.
    """

    max_velocity: np.ndarray
    max_acceleration: np.ndarray
    max_jerk: np.ndarray
    actuator_max_velocity: np.ndarray | float
    actuator_max_acceleration: np.ndarray | float | None = None
    singularity_condition_max: float = 1e4
    samples: int = 200
    limit_margin: float = 1.0
    force_limits: float | np.ndarray | None = None
    min_wrench_capacity: np.ndarray | None = None

    @classmethod
    def from_config(cls, cfg: dict, *, dof: int | None = None) -> 'Limits':
        """From a device config (:class:`~brace_control.config.DeviceConfig` or nested dict).

        :raises ValueError: a platform limit with the wrong length for ``dof`` or not > 0.
        """
        dc = as_device_config(cfg)     # checked against brace_control.schema, defaults filled
        traj, act, mech = dc.section('trajectory'), dc.section('actuator'), dc.section('mechanism')

        def arr(name: str) -> np.ndarray:
            a = np.asarray(traj[name], dtype=float).reshape(-1)
            if dof is not None and a.size == 1:
                a = np.full(dof, a[0])
            if dof is not None and a.size != dof:
                raise ValueError(f'trajectory.{name} needs {dof} values (one per pose '
                                 f'coordinate), got {a.size}')
            if not np.all(np.isfinite(a) & (a > 0.0)):
                raise ValueError(f'trajectory.{name} must be finite and > 0, got {a.tolist()}')
            return a
        return cls(max_velocity=arr('max_velocity'),
                   max_acceleration=arr('max_acceleration'),
                   max_jerk=arr('max_jerk'),
                   actuator_max_velocity=float(act['max_velocity']),
                   actuator_max_acceleration=float(act['max_acceleration']),
                   # the model's own default when the file has no mechanism (or no type)
                   singularity_condition_max=float(mech.get(
                       'singularity_condition_max',
                       mechanism_default(mech.get('type'), 'singularity_condition_max'))),
                   samples=int(traj['path_check_samples']),
                   limit_margin=float(traj['limit_margin']),
                   force_limits=float(act['max_force']),
                   min_wrench_capacity=_capacity(traj['min_wrench_capacity']))


def _capacity(value) -> np.ndarray | None:
    if value is None:
        return None
    arr = np.asarray(value, dtype=float).reshape(-1)
    if not np.all(np.isfinite(arr)) or np.any(arr < 0.0):
        raise ValueError(f'trajectory.min_wrench_capacity must be finite and >= 0, got {arr.tolist()}')
    return None if not np.any(arr > 0.0) else arr


class Violation(enum.Enum):
    """What a path check found (``NONE``: the path is fine)."""

    NONE = 'none'
    NON_FINITE = 'non_finite'
    STROKE = 'stroke'                  # inverse kinematics: actuator outside its range
    WORKSPACE = 'workspace'            # mechanism.in_workspace is False
    SINGULARITY = 'singularity'        # cond(J) too high, or det(J) changes sign
    CAPACITY = 'capacity'              # the actuators cannot hold the minimum wrench there
    ACTUATOR_SPEED = 'actuator_speed'
    ACTUATOR_ACCELERATION = 'actuator_acceleration'

    @property
    def fixable_by_slowing(self) -> bool:
        return self in (Violation.ACTUATOR_SPEED, Violation.ACTUATOR_ACCELERATION)


@dataclass
class PathCheck:
    """Result of :func:`check_path`.

    ``speed_ratio`` / ``acceleration_ratio``: the path's peak actuator speed (acceleration)
    over the limit, over all actuators (> 1 means too fast).
    """

    violation: Violation = Violation.NONE
    reason: str = ''
    time: float | None = None
    speed_ratio: float = 0.0
    acceleration_ratio: float = 0.0
    q: np.ndarray | None = field(default=None, repr=False)
    jacobian: np.ndarray | None = field(default=None, repr=False)

    @property
    def ok(self) -> bool:
        return self.violation is Violation.NONE


def _fmt(pose: np.ndarray) -> str:
    return '(' + ', '.join(f'{x:.4f}' for x in pose) + ')'


def check_pose(mech: 'Mechanism', pose: np.ndarray, *, condition_max: float) -> PathCheck:
    """One pose: reachable, in the workspace, not singular. Returns the actuator values in ``q``."""
    if not np.all(np.isfinite(pose)):
        return PathCheck(Violation.NON_FINITE, f'pose {pose.tolist()} is not finite')
    try:
        q = np.asarray(mech.inverse(pose), dtype=float)
    except ValueError as exc:       # UnreachablePose (and SingularPose) are ValueErrors
        kind = Violation.SINGULARITY if isinstance(exc, SingularPose) else Violation.STROKE
        return PathCheck(kind, f'pose {_fmt(pose)} is unreachable: {exc}')
    J = np.asarray(mech.jacobian(pose), dtype=float)
    cond = float(np.linalg.cond(J)) if np.all(np.isfinite(J)) else np.inf
    if not cond <= condition_max:
        return PathCheck(Violation.SINGULARITY,
                         f'pose {_fmt(pose)} is singular: cond(J) = {cond:.3g} > {condition_max:.3g}')
    try:
        check_workspace(mech, pose)
    except UnreachablePose as exc:
        return PathCheck(Violation.WORKSPACE, str(exc))
    return PathCheck(q=q, jacobian=J)


def _first_unreachable(mech: 'Mechanism', pose: np.ndarray) -> PathCheck:
    """Why ``pose`` has no inverse kinematics (the mechanism's own message)."""
    try:
        mech.inverse(pose)
    except ValueError as exc:       # UnreachablePose (and SingularPose) are ValueErrors
        kind = Violation.SINGULARITY if isinstance(exc, SingularPose) else Violation.STROKE
        return PathCheck(kind, f'pose {_fmt(pose)} is unreachable: {exc}')
    return PathCheck(Violation.STROKE, f'pose {_fmt(pose)} is unreachable')


def check_path(mech: 'Mechanism', trajectory: Trajectory, limits: Limits, *,
               samples: int | None = None) -> PathCheck:
    """Check ``trajectory`` against ``mech`` on ``samples`` (default ``limits.samples``) instants.

    Vectorised over the samples (``mech.inverse_batch`` / ``jacobian_batch``). The first
    geometric violation (stroke, workspace, singularity) found in time order is returned
    with its reason and time; otherwise the speed and acceleration ratios (against
    ``limit_margin`` times the actuator limits) are filled in and the violation is
    ``ACTUATOR_SPEED`` / ``ACTUATOR_ACCELERATION`` if a ratio exceeds 1 (speed first).
    """
    n = max(int(samples or limits.samples), 2)
    T = trajectory.duration
    ts = np.linspace(0.0, T, n)
    P, _, _ = trajectory.sample_many(ts)
    names = tuple(getattr(mech, 'actuator_names', ()))
    finite = np.all(np.isfinite(P), axis=1)
    Q = np.asarray(mech.inverse_batch(np.where(finite[:, None], P, 0.0)), dtype=float)
    reachable = finite & np.all(np.isfinite(Q), axis=1)
    k = int(np.argmin(reachable)) if not np.all(reachable) else n    # first unreachable
    J = np.asarray(mech.jacobian_batch(P[:k]), dtype=float) if k else np.zeros((0, 1, 1))
    outside = ~workspace_mask(mech, P[:k]) if k else np.zeros(0, dtype=bool)
    k_ws = int(np.argmax(outside)) if np.any(outside) else k         # first outside the workspace
    # singularities up to there (batched: one SVD / det call); a pose outside the
    # workspace because it is singular is reported as singular
    m = min(k_ws + 1, k)
    i_sing = m
    reason = ''
    if m:
        Jm = J[:m]
        cond = np.linalg.cond(Jm) if np.all(np.isfinite(Jm)) else np.full(m, np.inf)
        bad = np.flatnonzero(~(cond <= limits.singularity_condition_max))
        crossing = np.array([], dtype=int)
        if Jm.shape[1] == Jm.shape[2]:
            det = np.linalg.det(Jm)
            crossing = np.flatnonzero(det[1:] * det[:-1] < 0.0) + 1
        i_bad = int(bad[0]) if bad.size else m
        i_cross = int(crossing[0]) if crossing.size else m
        i_sing = min(i_bad, i_cross)
        if i_sing < m:
            reason = (f'pose {_fmt(P[i_sing])} is singular: cond(J) = {cond[i_sing]:.3g} > '
                      f'{limits.singularity_condition_max:.3g}' if i_sing == i_bad else
                      f'the path crosses a singularity (det J changes sign before pose {_fmt(P[i_sing])})')
    if i_sing < m:
        return PathCheck(Violation.SINGULARITY, f'at t = {ts[i_sing]:.3f} s: {reason}',
                         time=float(ts[i_sing]))
    if k_ws < k or k < n:
        i = min(k_ws, k)
        first = (PathCheck(Violation.WORKSPACE, f'pose {_fmt(P[i])} is outside the workspace')
                 if k_ws < k else
                 PathCheck(Violation.NON_FINITE, f'pose {P[i].tolist()} is not finite')
                 if not finite[i] else _first_unreachable(mech, P[i]))
        first.time = float(ts[i])
        first.reason = f'at t = {ts[i]:.3f} s: {first.reason}'
        return first
    qdot = qddot = None
    exact = getattr(trajectory, 'actuator_motion', None)
    if callable(exact):
        # the trajectory knows its actuator motion exactly (a motion along a one-mobility
        # mechanism's path, .path): the range (a crank that turns fully reads the same pose
        # past its end), speed and acceleration on a fine grid, no differencing
        ts = np.linspace(0.0, T, max(n, EXACT_SAMPLES))
        q_exact, qdot, qddot = exact(ts)
        lo, hi = (np.broadcast_to(np.asarray(v, dtype=float), q_exact.shape[1:])
                  for v in mech.actuator_limits)
        out = np.flatnonzero(np.any((q_exact < lo - 1e-9) | (q_exact > hi + 1e-9), axis=1))
        if out.size:
            i = int(out[0])
            j = int(np.argmax((q_exact[i] < lo - 1e-9) | (q_exact[i] > hi + 1e-9)))
            name = names[j] if j < len(names) else f'#{j}'
            return PathCheck(Violation.STROKE, f'at t = {ts[i]:.3f} s: actuator {name} would reach '
                             f'{q_exact[i, j]:.4f}, outside its range {lo[j]:.4f}..{hi[j]:.4f}',
                             time=float(ts[i]))
    else:
        try:
            ts, qdot, qddot = executed_actuator_motion(mech, trajectory)
        except UnreachableKnot as exc:
            return PathCheck(Violation.STROKE, str(exc), time=exc.time)     # names the time
        except TrajectoryError as exc:
            return PathCheck(Violation.NON_FINITE, f'its actuator motion: {exc}')
    margin = float(limits.limit_margin)
    vmax = margin * np.broadcast_to(np.asarray(limits.actuator_max_velocity, dtype=float), qdot.shape[1:])
    speed = np.abs(qdot) / vmax
    check = PathCheck(q=Q)
    check.speed_ratio = float(speed.max()) if speed.size else 0.0
    if limits.actuator_max_acceleration is not None and T > 0:
        amax = margin * np.broadcast_to(np.asarray(limits.actuator_max_acceleration, dtype=float),
                                        qdot.shape[1:])
        acc = np.abs(qddot) / amax
        check.acceleration_ratio = float(acc.max()) if acc.size else 0.0
    if check.speed_ratio > 1.0 + 1e-9:
        i, j = np.unravel_index(int(np.argmax(speed)), speed.shape)
        name = names[j] if j < len(names) else f'#{j}'
        check.violation = Violation.ACTUATOR_SPEED
        check.time = float(ts[i])
        check.reason = (f'actuator {name} would move at {abs(qdot[i, j]):.4f}/s at t = {ts[i]:.3f} s, '
                        f'limit {vmax[j]:.4f}/s ({margin:g} x its speed limit)')
    elif check.acceleration_ratio > 1.0 + 1e-9:
        check.violation = Violation.ACTUATOR_ACCELERATION
        check.reason = (f'actuator acceleration {check.acceleration_ratio:.3f} x the limit '
                        f'{margin * np.max(np.asarray(limits.actuator_max_acceleration)):.4f}/s^2 '
                        f'({margin:g} x the actuators\' limit)')
    return check


def executed_actuator_motion(mech: 'Mechanism', trajectory: Trajectory
                             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(t, q_dot, q_ddot)`` of the actuator motion the driver runs for ``trajectory``: its
    pose knots as trajectory_node sends them, their actuator knots as ik_node makes them,
    at the instants the driver checks (every knot and three points between).

    :raises UnreachableKnot: a pose of the motion has no inverse kinematics (ik_node would
        refuse the motion).
    :raises TrajectoryError: the knots cannot rebuild the motion (ik_node would refuse it).
    """
    poses = knots_of(trajectory, breaks=getattr(trajectory, 'breaks', None))
    ts, _, qdot, qddot = actuator_knots(mech, poses).dense()
    return ts, qdot, qddot


def check_capacity(mech: 'Mechanism', trajectory: Trajectory, limits: Limits, *,
                   samples: int | None = None) -> tuple[PathCheck, np.ndarray | None]:
    """The path's minimum wrench capacity per axis (docs/safety.md §17) against
    ``limits.min_wrench_capacity``: ``(check, minima)``; ``minima`` is ``None`` when the
    mechanism has no capacity model or nothing is checked.

    A path that starts short of the minimum (a capacity stop leaves the ring at the boundary)
    may leave it: samples below the minimum are allowed on an axis only in the stretch from
    the start up to where the capacity first reaches the minimum, and only while it stays at
    or above its value at the start (the path never makes it worse). Otherwise the brace
    would be stuck there: every path from the boundary starts below it.

    A violation names the axis, the capacity, the pose, the time and the limiting actuator.
    """
    batch = getattr(mech, 'wrench_capacity_batch', None)
    if limits.force_limits is None or not callable(batch):
        return PathCheck(), None
    n = max(int(samples or limits.samples), 2)
    ts = np.linspace(0.0, trajectory.duration, n)
    P = trajectory.sample_many(ts)[0]
    caps, limiting = batch(P, limits.force_limits, return_limiting=True)
    caps = np.asarray(caps, dtype=float)
    minima = np.nanmin(caps, axis=0)
    need = limits.min_wrench_capacity
    if need is None:
        return PathCheck(), minima
    axes = tuple(getattr(mech, 'wrench_axes', ())) or tuple(f'#{j}' for j in range(caps.shape[1]))
    need = np.broadcast_to(need, (caps.shape[1],)) if need.size in (1, caps.shape[1]) else need[:caps.shape[1]]
    short = caps < need[None, :]
    for j in np.flatnonzero(short[0]):
        # leaving a short start: the leading stretch below the minimum, never below the start
        reached = np.flatnonzero(~short[:, j])
        if reached.size:
            lead = slice(0, int(reached[0]))
            short[lead, j] &= caps[lead, j] < caps[0, j] * (1.0 - START_CAPACITY_REL_TOL)
    if not np.any(short):
        return PathCheck(), minima
    i, j = np.argwhere(short)[0]
    names = tuple(getattr(mech, 'actuator_names', ()))
    who = int(limiting[i, j])
    by = f', limited by actuator {names[who]}' if 0 <= who < len(names) else ''
    return PathCheck(Violation.CAPACITY,
                     f'at t = {ts[i]:.3f} s the wrench capacity along {axes[j]} is {caps[i, j]:.3g} '
                     f'< trajectory.min_wrench_capacity {need[j]:.3g} at pose {_fmt(P[i])}{by}',
                     time=float(ts[i])), minima
