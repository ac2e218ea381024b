"""Check a planned motion against the mechanism before anything moves (SAFETY.md 5, 10).

Along the sampled path every pose must be reachable (inverse kinematics within the
stroke: the mechanism's :class:`~brace_control.mechanisms.base.UnreachablePose`),
inside the workspace, away from singularities (cond(J) below the limit, and no sign
change of det(J) between samples: a singularity crossed between two samples); the
actuator speeds ``q_dot = J x_dot`` and accelerations (``q_ddot``, by central
differences of ``q_dot`` along the samples) must stay within the actuator limits.
Stroke, workspace and singularity violations reject the goal; speed and acceleration
violations tell the planner how much to slow down.
"""
from __future__ import annotations

import enum
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from .base import Trajectory

if TYPE_CHECKING:  # pragma: no cover
    from ..mechanisms.base import Mechanism

__all__ = ['Limits', 'Violation', 'PathCheck', 'check_path', 'check_pose']


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
    """

    max_velocity: np.ndarray
    max_acceleration: np.ndarray
    max_jerk: np.ndarray
    actuator_max_velocity: np.ndarray | float
    actuator_max_acceleration: np.ndarray | float | None = None
    singularity_condition_max: float = 1e4
    samples: int = 200

    @classmethod
    def from_config(cls, cfg: dict, *, dof: int | None = None) -> 'Limits':
        """From a device config (:class:`~brace_control.config.DeviceConfig` or nested dict).

        :raises ValueError: a platform limit with the wrong length for ``dof`` or not > 0.
        """
        traj, act = cfg.get('trajectory', {}), cfg.get('actuator', {})
        mech = cfg.get('mechanism', {})

        def arr(name: str, default: list[float]) -> np.ndarray:
            a = np.asarray(traj.get(name, default), dtype=float).reshape(-1)
            if dof is not None and a.size == 1:
                a = np.full(dof, a[0])
            if dof is not None and a.size != dof:
                raise ValueError(f'trajectory.{name} needs {dof} values (one per pose '
                                 f'coordinate), got {a.size}')
            if not np.all(np.isfinite(a) & (a > 0.0)):
                raise ValueError(f'trajectory.{name} must be finite and > 0, got {a.tolist()}')
            return a
        return cls(max_velocity=arr('max_velocity', [0.03, 0.03, 0.3]),
                   max_acceleration=arr('max_acceleration', [0.1, 0.1, 1.0]),
                   max_jerk=arr('max_jerk', [1.0, 1.0, 10.0]),
                   actuator_max_velocity=float(act.get('max_velocity', 0.065)),
                   actuator_max_acceleration=(None if act.get('max_acceleration') is None
                                              else float(act['max_acceleration'])),
                   singularity_condition_max=float(mech.get('singularity_condition_max', 1e4)),
                   samples=int(traj.get('path_check_samples', 200)))


class Violation(enum.Enum):
    """What a path check found (``NONE``: the path is fine)."""

    NONE = 'none'
    NON_FINITE = 'non_finite'
    STROKE = 'stroke'                  # inverse kinematics: actuator outside its range
    WORKSPACE = 'workspace'            # mechanism.in_workspace is False
    SINGULARITY = 'singularity'        # cond(J) too high, or det(J) changes sign
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
        kind = Violation.SINGULARITY if type(exc).__name__ == 'SingularPose' else Violation.STROKE
        return PathCheck(kind, f'pose {_fmt(pose)} is unreachable: {exc}')
    J = np.asarray(mech.jacobian(pose), dtype=float)
    cond = float(np.linalg.cond(J)) if np.all(np.isfinite(J)) else np.inf
    if not cond <= condition_max:
        return PathCheck(Violation.SINGULARITY,
                         f'pose {_fmt(pose)} is singular: cond(J) = {cond:.3g} > {condition_max:.3g}')
    if not mech.in_workspace(pose):
        return PathCheck(Violation.WORKSPACE, f'pose {_fmt(pose)} is outside the workspace')
    return PathCheck(q=q, jacobian=J)


def check_path(mech: 'Mechanism', trajectory: Trajectory, limits: Limits, *,
               samples: int | None = None) -> PathCheck:
    """Check ``trajectory`` against ``mech`` on ``samples`` (default ``limits.samples``) instants.

    The first geometric violation (stroke, workspace, singularity) found in time order is
    returned with its reason and time; otherwise the speed and acceleration ratios are
    filled in and the violation is ``ACTUATOR_SPEED`` / ``ACTUATOR_ACCELERATION`` if a
    ratio exceeds 1 (speed reported first).
    """
    n = max(int(samples or limits.samples), 2)
    T = trajectory.duration
    ts = np.linspace(0.0, T, n)
    P, V, _ = trajectory.sample_many(ts)
    names = tuple(getattr(mech, 'actuator_names', ()))
    qs, jacs = [], []
    first: PathCheck | None = None          # first stroke / workspace / non-finite failure
    for t, pose in zip(ts, P):
        if not np.all(np.isfinite(pose)):
            first = PathCheck(Violation.NON_FINITE, f'pose {pose.tolist()} is not finite')
        else:
            try:
                q = np.asarray(mech.inverse(pose), dtype=float)
            except ValueError as exc:   # UnreachablePose (and SingularPose) are ValueErrors
                kind = (Violation.SINGULARITY if type(exc).__name__ == 'SingularPose'
                        else Violation.STROKE)
                first = PathCheck(kind, f'pose {_fmt(pose)} is unreachable: {exc}')
            else:
                if not mech.in_workspace(pose):
                    first = PathCheck(Violation.WORKSPACE, f'pose {_fmt(pose)} is outside the workspace')
                    # a pose out of the workspace because it is singular is reported as such
                    jacs.append(np.asarray(mech.jacobian(pose), dtype=float))
        if first is not None:
            first.time = float(t)
            first.reason = f'at t = {t:.3f} s: {first.reason}'
            break
        qs.append(q)
        jacs.append(np.asarray(mech.jacobian(pose), dtype=float))
    k = len(jacs)
    # singularities among the poses checked so far (batched: one SVD / det call)
    if k:
        J = np.asarray(jacs)
        cond = np.linalg.cond(J) if np.all(np.isfinite(J)) else np.full(k, np.inf)
        bad = np.flatnonzero(~(cond <= limits.singularity_condition_max))
        crossing = np.array([], dtype=int)
        if J.shape[1] == J.shape[2]:
            det = np.linalg.det(J)
            crossing = np.flatnonzero(det[1:] * det[:-1] < 0.0) + 1
        i_bad = int(bad[0]) if bad.size else k
        i_cross = int(crossing[0]) if crossing.size else k
        if min(i_bad, i_cross) < k:             # at or before the first other failure
            i = min(i_bad, i_cross)
            if i == i_bad:
                reason = (f'pose {_fmt(P[i])} is singular: cond(J) = {cond[i]:.3g} > '
                          f'{limits.singularity_condition_max:.3g}')
            else:
                reason = f'the path crosses a singularity (det J changes sign before pose {_fmt(P[i])})'
            return PathCheck(Violation.SINGULARITY, f'at t = {ts[i]:.3f} s: {reason}', time=float(ts[i]))
    if first is not None:
        return first
    qdots = [Ji @ vel for Ji, vel in zip(jacs, V)]
    qdot = np.asarray(qdots)
    vmax = np.broadcast_to(np.asarray(limits.actuator_max_velocity, dtype=float), qdot.shape[1:])
    speed = np.abs(qdot) / vmax
    check = PathCheck(q=np.asarray(qs))
    check.speed_ratio = float(speed.max()) if speed.size else 0.0
    if limits.actuator_max_acceleration is not None and n >= 3 and T > 0:
        qddot = np.gradient(qdot, ts, axis=0)
        amax = np.broadcast_to(np.asarray(limits.actuator_max_acceleration, dtype=float),
                               qdot.shape[1:])
        acc = np.abs(qddot) / amax
        check.acceleration_ratio = float(acc.max()) if acc.size else 0.0
    if check.speed_ratio > 1.0 + 1e-9:
        i, j = np.unravel_index(int(np.argmax(speed)), speed.shape)
        name = names[j] if j < len(names) else f'#{j}'
        check.violation = Violation.ACTUATOR_SPEED
        check.time = float(ts[i])
        check.reason = (f'actuator {name} would move at {abs(qdot[i, j]):.4f}/s at t = {ts[i]:.3f} s, '
                        f'limit {vmax[j]:.4f}/s')
    elif check.acceleration_ratio > 1.0 + 1e-9:
        check.violation = Violation.ACTUATOR_ACCELERATION
        check.reason = (f'actuator acceleration {check.acceleration_ratio:.3f} x the limit '
                        f'{np.max(np.asarray(limits.actuator_max_acceleration)):.4f}/s^2')
    return check
