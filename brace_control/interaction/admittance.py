"""Admittance control of a parallel brace: the pose motion that makes the brace's wrench on
the body track a goal (the lumbar paper's "zero-torque mode", seed 001, "Wearing effect").

Per pose axis ``i`` that is force controlled (``interaction.force_axes``), a virtual
mass-damper driven by the wrench error::

    M_i a_i + D_i v_i = e_i,    e_i = W_goal,i - W_meas,i                         (1)

``W`` is the wrench the brace applies on the body, in the pose coordinates' conjugate
components (planar: Fx, Fy in the base frame and Mz about the platform origin). A body that
pushes the ring up (``W_meas,y < 0``: the brace pushes back down) gives ``e_y > 0``: the ring
moves up, with the body. Zero-torque mode is ``W_goal = 0``. The other axes hold the pose
they had when the mode started (hybrid control).

(1) is integrated exactly over one period ``dt`` with ``e`` held (zero-order hold)::

    v[k+1] = v[k] p + (1 - p) e[k] / D,            p = exp(-D dt / M)             (2)
    x[k+1] = x[k] + e[k] dt / D + (v[k] - e[k] / D) (M / D) (1 - p)

Limits (docs/safety.md §5, §10, §14, §17), never a silent clamp:

* the actuator speed: ``|J v|`` within ``limit_margin x actuator.max_velocity``: the velocity
  vector is scaled as a whole (the virtual model saturates; :attr:`AdmittanceController.
  velocity_limited` counts the periods, the node reports it);
* the workspace, the stroke (with :data:`STROKE_MARGIN` clear at both ends), a
  singularity, the wrench capacity: the pose the ring would reach when braking now at
  ``interaction.stop_deceleration`` is checked at every period;
  one that fails starts a stop (:class:`LimitStop` with the reason), so the ring comes to
  rest before the limit;
* the soft force limit: a measured actuator force above it starts a stop;
* a wrench goal beyond the capacity at the current pose (or ``interaction.max_goal_wrench``)
  is rejected (:class:`GoalRejected`), the previous goal stays.

Pure numpy: no ROS. The stability of (1) in the loop with the delay and the body's
stiffness: :mod:`brace_control.interaction.stability` and docs/interaction.md.
"""
from __future__ import annotations

import enum
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..mechanisms import UnreachablePose
from ..schema import default, soft_force_limit

#: share of each actuator's range kept clear at both ends: the ring must come to rest (on its
#: braking pose) this far from a stroke end, so the drives' own limits (607Dh) never trip
STROKE_MARGIN = 0.02

__all__ = ['AdmittanceController', 'AdmittanceParams', 'GoalRejected', 'LimitStop', 'Mode']


class Mode(enum.Enum):
    """What the controller does."""

    IDLE = 'idle'              # position mode: the controller publishes nothing
    ACTIVE = 'active'          # interaction: (1) runs
    STOPPING = 'stopping'      # decelerating to rest, then IDLE


class GoalRejected(ValueError):
    """A wrench goal the brace cannot (or may not) hold; the message says which axis and why."""


class LimitStop(Exception):
    """A limit ends the interaction: the controller is decelerating; ``reason`` says which."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


@dataclass(frozen=True)
class AdmittanceParams:
    """The virtual model and its limits (SI, per pose axis).

    :param mass: ``M`` (kg or kg·m² per pose axis), > 0.
    :param damping: ``D`` (N·s/m or N·m·s/rad), > 0.
    :param force_axes: which pose axes follow (1); the others hold.
    :param dt: period (s).
    :param stop_deceleration: braking deceleration per pose axis (m/s², rad/s²), > 0.
    :param actuator_max_velocity: actuator speed limit (m/s or rad/s) per actuator.
    :param limit_margin: share of it the motion may use.
    :param soft_force_limit: actuator force (N, N·m) above which the mode stops.
    :param actuator_max_force: force per actuator for the wrench capacity.
    :param min_wrench_capacity: the smallest capacity per wrench axis the ring may pass
        (``trajectory.min_wrench_capacity``), or None.
    :param max_goal_wrench: the largest |goal| per pose axis (inf = capacity alone).
    :param actuator_max_acceleration: the actuators' acceleration limit (m/s² or rad/s², per
        actuator): braking also keeps every actuator's deceleration ``|J Δv| / dt`` within
        ``limit_margin`` of it (``None``: the pose axes' ``stop_deceleration`` alone). Per
        pose axis alone, y and θ braking together asked a lumbar leg for 0.64 m/s² on its
        0.5 m/s² limit.
    :param goal_rate: how fast the wrench the controller tracks moves to a new goal, per
        pose axis (N/s, N·m/s; inf = a step): a step goal is followed as a ramp
        (reference shaping), so that the ring never runs into the legs' deceleration limit
        with the wrench still rising (docs/interaction.md, "Wrench goals"). The ramp is
        one vector: the slowest axis sets its pace, the goal's direction is kept.
    """

    mass: np.ndarray
    damping: np.ndarray
    force_axes: np.ndarray
    dt: float
    stop_deceleration: np.ndarray
    actuator_max_velocity: np.ndarray
    limit_margin: float
    soft_force_limit: float
    actuator_max_force: float
    min_wrench_capacity: np.ndarray | None = None
    max_goal_wrench: np.ndarray | None = None
    goal_rate: np.ndarray | None = None
    actuator_max_acceleration: np.ndarray | None = None

    @classmethod
    def from_config(cls, cfg: Any, mechanism: Any) -> 'AdmittanceParams':
        """From the device config (``interaction.*``, ``actuator.*``, ``safety.*``,
        ``trajectory.limit_margin`` / ``min_wrench_capacity``).

        :raises ValueError: a per-axis list of the wrong length, a non-positive mass,
            damping or deceleration; the message names the key.
        """
        dof = int(mechanism.dof)
        inter = cfg['interaction']

        def per_axis(key: str, *, positive: bool = True) -> np.ndarray:
            raw = np.atleast_1d(np.asarray(inter[key], dtype=float)).ravel()
            if raw.size == 1:
                raw = np.full(dof, float(raw[0]))
            if raw.shape != (dof,) or not np.all(np.isfinite(raw)):
                raise ValueError(f'interaction.{key}: expected {dof} finite numbers (one per pose '
                                 f'axis) or one for all, got {list(inter[key])!r}')
            if positive and np.any(raw <= 0.0):
                raise ValueError(f'interaction.{key}: expected numbers > 0, got {raw.tolist()!r}')
            return raw

        axes = np.atleast_1d(np.asarray(inter['force_axes'], dtype=bool)).ravel()
        if axes.size == 1:
            axes = np.full(dof, bool(axes[0]))
        if axes.shape != (dof,):
            raise ValueError(f'interaction.force_axes: expected {dof} booleans (one per pose axis), '
                             f'got {list(inter["force_axes"])!r}')
        max_goal = per_axis('max_goal_wrench', positive=False)
        rate = per_axis('goal_rate', positive=False)
        if np.any(rate < 0.0):
            raise ValueError(f'interaction.goal_rate: expected numbers >= 0 (0: a step), got {rate.tolist()!r}')
        if np.any(max_goal < 0.0):
            raise ValueError(f'interaction.max_goal_wrench: expected numbers >= 0, got {max_goal.tolist()!r}')
        act, traj = cfg['actuator'], cfg['trajectory']
        soft = soft_force_limit(cfg)
        n = int(mechanism.n_actuators)
        cap = traj.get('min_wrench_capacity')
        cap_arr = None if cap is None else np.asarray(cap, dtype=float)
        if cap_arr is not None and (cap_arr.size <= 1 and not np.any(cap_arr)):
            cap_arr = None
        return cls(mass=per_axis('mass'), damping=per_axis('damping'), force_axes=axes,
                   dt=1.0 / float(inter['rate_hz']), stop_deceleration=per_axis('stop_deceleration'),
                   actuator_max_velocity=np.full(n, float(act['max_velocity'])),
                   actuator_max_acceleration=np.full(n, float(act['max_acceleration'])),
                   limit_margin=float(traj.get('limit_margin', default('trajectory.limit_margin'))), soft_force_limit=soft,
                   actuator_max_force=float(act['max_force']), min_wrench_capacity=cap_arr,
                   max_goal_wrench=np.where(max_goal > 0.0, max_goal, np.inf),
                   goal_rate=np.where(rate > 0.0, rate, np.inf))


class AdmittanceController:
    """Equations (1), (2) for one mechanism, with its limits (module docstring).

    :param mechanism: any mechanism of the protocol (``inverse``, ``jacobian``,
        ``wrench_capacity``, ``dof``).
    :param params: :class:`AdmittanceParams`.
    """

    def __init__(self, mechanism: Any, params: AdmittanceParams) -> None:
        self.mechanism = mechanism
        self.p = params
        self.dof = int(mechanism.dof)
        self.mode = Mode.IDLE
        self.x = np.zeros(self.dof)
        self.v = np.zeros(self.dof)
        self.goal = np.zeros(self.dof)
        #: the wrench tracked now: moves to :attr:`goal` at ``goal_rate``
        self.goal_now = np.zeros(self.dof)
        self.velocity_limited = 0
        self.stop_reason = ''
        self._decay = np.exp(-params.damping * params.dt / params.mass)
        #: a mechanism whose mobility is below its pose's length (the four-bar: one crank,
        #: a point on a curve) keeps the virtual motion on what it can reach
        self._constrain = getattr(mechanism, 'constrain_motion', None)
        #: the Jacobians of the last two poses asked (:meth:`jacobian`)
        self._jacobians: dict[bytes, np.ndarray] = {}

    # ------------------------------------------------------------------ mode
    def start(self, pose: Sequence[float]) -> None:
        """Enter interaction at the measured ``pose`` with zero velocity, zero goal."""
        x = np.asarray(pose, dtype=float)
        if x.shape != (self.dof,) or not np.all(np.isfinite(x)):
            raise ValueError(f'start pose: expected {self.dof} finite numbers, got {pose!r}')
        self.mechanism.inverse(x)                    # raises UnreachablePose: not a start pose
        self.x, self.v = x.copy(), np.zeros(self.dof)
        self.goal = np.zeros(self.dof)
        self.goal_now = np.zeros(self.dof)
        self.velocity_limited = 0
        self.stop_reason = ''
        self.mode = Mode.ACTIVE

    def stop(self, reason: str) -> None:
        """Decelerate to rest (:attr:`mode` STOPPING, then IDLE)."""
        if self.mode is Mode.ACTIVE:
            self.mode = Mode.STOPPING
            self.stop_reason = reason

    def set_goal(self, wrench: Sequence[float]) -> None:
        """The wrench the brace shall apply on the body (pose axes' conjugate components).

        Components on held axes are ignored (they must be zero or the goal is rejected:
        a held axis cannot produce a chosen wrench).

        :raises GoalRejected: not finite, a nonzero component on a held axis, above
            ``max_goal_wrench`` or above the wrench capacity at the current pose.
        """
        w = np.asarray(wrench, dtype=float).ravel()
        if w.shape != (self.dof,) or not np.all(np.isfinite(w)):
            raise GoalRejected(f'wrench goal: expected {self.dof} finite numbers, got {wrench!r}')
        held = ~self.p.force_axes & (w != 0.0)
        if np.any(held):
            i = int(np.flatnonzero(held)[0])
            raise GoalRejected(f'wrench goal on axis {i} = {w[i]:g}, but axis {i} holds position '
                               f'(interaction.force_axes = {self.p.force_axes.astype(int).tolist()})')
        over = np.abs(w) > self.p.max_goal_wrench
        if np.any(over):
            i = int(np.flatnonzero(over)[0])
            raise GoalRejected(f'wrench goal on axis {i} = {w[i]:g} exceeds interaction.max_goal_wrench '
                               f'{self.p.max_goal_wrench[i]:g}')
        cap = self.capacity(self.x)
        along = self._along_path(self.x, w) if cap is not None and cap.shape != w.shape else None
        if along is not None and cap is not None and along.shape == cap.shape:
            if np.any(np.abs(along) > cap):
                raise GoalRejected(f'wrench goal {w.tolist()}: {float(along[0]):.3g} along the path exceeds '
                                   f'the wrench capacity {float(cap[0]):.3g} at pose {np.round(self.x, 5).tolist()}')
        elif cap is not None and cap.shape == w.shape:
            short = np.abs(w) > cap
            if np.any(short):
                i = int(np.flatnonzero(short)[0])
                raise GoalRejected(f'wrench goal on axis {i} = {w[i]:g} exceeds the wrench capacity '
                                   f'{cap[i]:.3g} at pose {np.round(self.x, 5).tolist()}')
        self.goal = w

    def _along_path(self, pose: np.ndarray, w: np.ndarray) -> np.ndarray | None:
        """The component of ``w`` along the path of a one-mobility mechanism (its
        capacity axis), or None for the others."""
        direction = getattr(self.mechanism, 'path_direction', None)
        if direction is None:
            return None
        return np.array([float(np.asarray(direction(pose), dtype=float) @ w)])

    def constrained(self, x: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(x, v)`` put back on what the mechanism can reach (its pose manifold and the
        velocities tangent to it); unchanged for a mechanism that moves every pose axis."""
        if self._constrain is None:
            return x, v
        try:
            cx, cv = self._constrain(x, v)
        except ValueError:
            return x, v
        return np.asarray(cx, dtype=float), np.asarray(cv, dtype=float)

    def capacity(self, pose: np.ndarray) -> np.ndarray | None:
        """The mechanism's wrench capacity at ``pose`` with ``actuator.max_force`` (per
        wrench axis), or None if the mechanism has none."""
        fn = getattr(self.mechanism, 'wrench_capacity', None)
        if fn is None:
            return None
        try:
            return np.asarray(fn(pose, self.p.actuator_max_force), dtype=float)
        except (ValueError, NotImplementedError):
            return None

    # ------------------------------------------------------------------ the period
    def step(self, w_measured: Sequence[float], forces: Sequence[float] | None = None
             ) -> tuple[np.ndarray, np.ndarray]:
        """One period: ``(x, v)`` of the next setpoint (copies).

        :param w_measured: the measured wrench of the brace on the body (pose axes).
        :param forces: the measured actuator forces (soft force limit), or None.
        :raises LimitStop: a limit started a stop this period (the controller is now
            STOPPING; the returned state is still valid after it: call :meth:`step` again).
        """
        if self.mode is Mode.IDLE:
            return self.x.copy(), self.v.copy()
        if self.mode is Mode.STOPPING:
            self._brake()
            return self.x.copy(), self.v.copy()
        w = np.asarray(w_measured, dtype=float)
        if w.shape != (self.dof,) or not np.all(np.isfinite(w)):
            self.stop(f'measured wrench not finite or of the wrong length: {w_measured!r}')
            self._brake()
            raise LimitStop(self.stop_reason)
        if forces is not None:
            f = np.abs(np.asarray(forces, dtype=float))
            if np.any(f > self.p.soft_force_limit):
                i = int(np.argmax(f))
                self.stop(f'soft force limit: actuator {self._name(i)} at {f[i]:.1f} '
                          f'> {self.p.soft_force_limit:.1f}')
                self._brake()
                raise LimitStop(self.stop_reason)
        self.goal_now = self.goal_now + self._ramp_step(self.goal - self.goal_now)
        e = np.where(self.p.force_axes, self.goal_now - w, 0.0)
        # on a path (one crank): only the error's component along it can move the handle; the
        # normal part is the frame's (integrated, it would drift the handle along a curved path)
        e = self.constrained(self.x, e)[1]
        p = self._decay
        v_inf = e / self.p.damping
        v_new = np.where(self.p.force_axes, self.v * p + (1.0 - p) * v_inf, 0.0)
        dx = np.where(self.p.force_axes, v_inf * self.p.dt
                      + (self.v - v_inf) * (self.p.mass / self.p.damping) * (1.0 - p), 0.0)
        scale = self._speed_scale(v_new)
        if scale < 1.0:
            # the virtual model saturates: the pose moves by the trapezoid of the limited
            # velocity (as braking and the in-cycle acceleration limit do). Scaling the ZOH
            # step ``dx`` instead moved the pose at ~2/3 of the velocity it reported, and the
            # next unsaturated or acceleration-limited period caught up in one step (a
            # 9 m/s^2 spike in the command's second difference)
            v_new = v_new * scale
            x_new = self.x + 0.5 * (self.v + v_new) * self.p.dt
        else:
            x_new = self.x + dx
        x_new, v_new = self.constrained(x_new, v_new)
        reason = self._check_ahead(x_new, v_new)
        if reason:
            self.stop(reason)
            self._brake()
            raise LimitStop(reason)
        self.x, self.v = x_new, v_new
        return self.x.copy(), self.v.copy()

    def _ramp_step(self, diff: np.ndarray) -> np.ndarray:
        """This period's share of the way to the goal: ``diff`` scaled as a whole so that no
        axis moves faster than its ``goal_rate`` (the goal's direction is kept: a ramp per
        axis on its own would turn a goal normal to the trainer's path into a push along it
        while the axes ramp)."""
        if self.p.goal_rate is None or not np.any(diff):
            return diff
        with np.errstate(divide='ignore', invalid='ignore'):
            ratio = float(np.max(np.where(np.isfinite(self.p.goal_rate),
                                          np.abs(diff) / (self.p.goal_rate * self.p.dt), 0.0)))
        return diff / ratio if ratio > 1.0 else diff

    def _name(self, i: int) -> str:
        names = getattr(self.mechanism, 'actuator_names', None)
        return str(names[i]) if names is not None and i < len(names) else str(i)

    def _speed_scale(self, v: np.ndarray) -> float:
        """The factor (<= 1) that scales the velocity vector as a whole so that ``|J v|``
        stays within the margin of the actuator speed."""
        if not np.any(v):
            return 1.0
        try:
            qd = self.jacobian(self.x) @ v
        except ValueError:
            return 1.0
        ratio = float(np.max(np.abs(qd) / (self.p.limit_margin * self.p.actuator_max_velocity)))
        if ratio > 1.0:
            self.velocity_limited += 1
            return 1.0 / ratio
        return 1.0

    def _brake_share(self, x: np.ndarray, v: np.ndarray) -> float:
        """The share of the velocity vector ``v`` one period of braking at ``x`` takes off
        (``inf`` at rest): the velocity shrinks as a whole, the most limited of the pose axes
        (``stop_deceleration``) and the actuators (``limit_margin x actuator_max_acceleration``,
        through ``J(x)``) setting the pace."""
        speed = np.abs(v)
        with np.errstate(divide='ignore'):
            share = float(np.min(np.where(speed > 0.0, self.p.stop_deceleration * self.p.dt / speed,
                                          np.inf)))
        a = self.p.actuator_max_acceleration
        if a is not None and np.any(speed):
            try:
                qd = np.abs(self.jacobian(x) @ v)
            except ValueError:             # no Jacobian here: the pose axes' rates alone
                return share
            with np.errstate(divide='ignore'):
                share = min(share, float(np.min(np.where(
                    qd > 0.0, self.p.limit_margin * a * self.p.dt / qd, np.inf))))
        return share

    def jacobian(self, x: Sequence[float]) -> np.ndarray:
        """The mechanism's ``J(x)`` (read only), kept for the last two poses: one period asks
        for the pose it starts from (the speed and acceleration limits) and the one it ends
        at (the braking prediction, the command's ``J v``), each twice."""
        x = np.asarray(x, dtype=float)
        key = x.tobytes()
        J = self._jacobians.get(key)
        if J is None:
            J = np.array(self.mechanism.jacobian(x), dtype=float)    # a copy: ours to keep
            if len(self._jacobians) >= 2:
                del self._jacobians[next(iter(self._jacobians))]
            self._jacobians[key] = J
        return J

    def braking_pose(self, x: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Where the ring comes to rest braking from ``(x, v)`` as :meth:`_brake` does (the
        velocity vector shrinks as a whole, the most limited pose axis or actuator setting
        the pace, :meth:`_brake_share`): after ``T = dt / share`` (``max_i |v_i| / a_i`` on
        the pose axes alone), at ``x + v T / 2``."""
        t_stop = self.p.dt / self._brake_share(x, v)
        return self.constrained(x + 0.5 * v * t_stop, np.zeros_like(v))[0]

    def _check_ahead(self, x: np.ndarray, v: np.ndarray) -> str:
        """The reason the pose reached when braking from ``(x, v)`` is not allowed, or ''."""
        ahead = self.braking_pose(x, v)
        lo, hi = (np.asarray(a, dtype=float) for a in self.mechanism.actuator_limits)
        margin = STROKE_MARGIN * (hi - lo)
        for pose in (x, ahead):
            try:
                q = np.asarray(self.mechanism.inverse(pose), dtype=float)
                near = (q < lo + margin) | (q > hi - margin)
                if np.any(near):
                    i = int(np.flatnonzero(near)[0])
                    return (f'workspace: actuator {self._name(i)} would reach {q[i]:.4f}, within '
                            f'{margin[i]:.4f} of its range {lo[i]:.4f}–{hi[i]:.4f} '
                            f'(braking pose {np.round(pose, 5).tolist()})')
                check = getattr(self.mechanism, 'check_singularity', None)
                if callable(check):
                    check(pose)
            except UnreachablePose as exc:
                return f'workspace: {exc}'
            except ValueError as exc:
                return f'workspace: {exc}'
        need = self.p.min_wrench_capacity
        if need is not None:
            cap = self.capacity(ahead)
            if cap is not None and cap.shape == need.shape:
                short = cap < need
                if np.any(short):
                    i = int(np.flatnonzero(short)[0])
                    return (f'wrench capacity: axis {i} would fall to {cap[i]:.3g} < '
                            f'{need[i]:g} at pose {np.round(ahead, 5).tolist()}')
        return ''

    def _brake(self) -> None:
        """One period of braking: the velocity vector shrinks as a whole within
        ``stop_deceleration`` on every axis (the direction is kept: the ring stays on its
        path); at zero the mode is IDLE."""
        if not np.any(self.v):
            self.v = np.zeros(self.dof)
            self.mode = Mode.IDLE
            return
        factor = max(0.0, 1.0 - self._brake_share(self.x, self.v))
        v_new = self.v * factor
        self.x, self.v = self.constrained(self.x + 0.5 * (self.v + v_new) * self.p.dt, v_new)
        if factor == 0.0:
            self.v = np.zeros(self.dof)
        if factor == 0.0:
            self.mode = Mode.IDLE
