"""The admittance inside the CAN driver's SYNC cycle: the executor's interaction source.

Why in the cycle (docs/interaction.md, "Delay"): the loop's stability against a stiff body
needs ``D > 2 K T / pi`` and following a body at ``v`` costs ``~ D v`` of wrench, so the
transparency is set by the loop delay ``T``. Through ROS (joint states at 100 Hz,
kinetics_node, interaction_node, ik_node, the driver's stream) ``T`` measured 16-47 ms
(median 27 ms, bench/bench_interaction_delay.py). In the cycle, the load cells of SYNC
``k`` (TPDOs answering it) form the wrench at cycle ``k + 1``, whose targets go out before
SYNC ``k + 1`` and are reached by the interpolating drives at SYNC ``k + 2``: two periods
(4 ms at 500 Hz), as ros2_control's admittance_controller chained in the controller
manager's loop, or CORC's loop at the drive rate.

Per admittance period (every ``n`` SYNCs, ``n = round(can.sync_rate_hz /
interaction.rate_hz)``, 1 on the lumbar brace) :meth:`InLoopAdmittance.update`:

1. ``W = J(x)^T f``: the wrench the brace applies on the body from the load-cell forces
   ``f`` (push positive along ``A_i -> B_i``), ``J`` at the admittance pose ``x``: the
   mechanism's :meth:`wrench` (kinetics_node's ``/brace/wrench`` convention, in the pose
   axes' components: planar ``Fx, Fy`` base frame, ``Mz``);
2. :meth:`AdmittanceController.step <.admittance.AdmittanceController.step>` (equations
   (1), (2), its limits and braking, unchanged);
3. ``q = IK(x)``, ``q_dot = J(x) x_dot``: every actuator from the one pose, on one time base
   (the path-synchronous rule: the command stays on the inverse-kinematics manifold).

The actuator acceleration is limited as the speed is, the velocity change scaled as a
whole (:meth:`InLoopAdmittance._accel_scale`): the admittance's motion is what the drives
execute, never clipped per axis afterwards.

Cost: the model's ``inverse`` / ``jacobian`` / ``wrench_capacity`` / ``check_singularity``
cost ~0.1-0.9 ms each in numpy (the controller's step ~2.7 ms on a loaded host: over a
500 Hz cycle). :class:`FastPlanarKinematics` gives the planar n-RPR the same functions on
:class:`~brace_control.mechanisms.planar_floats.PlanarRprFloats` (leg lengths and rows in
plain floats, the closed-form capacity ``f_max / max_j |(J^-1)_ij|`` of a square ``J``),
checked against the model at construction (bench/bench_interaction_cycle.py has the cost).
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from ..mechanisms import SingularPose, UnreachablePose
from ..mechanisms.planar_floats import PlanarRprFloats
from .admittance import AdmittanceController, AdmittanceParams, LimitStop, Mode

__all__ = ['FastPlanarKinematics', 'InLoopAdmittance', 'kinematics_for']


class FastPlanarKinematics:
    """A square planar n-RPR (``dof = n = 3``) with the protocol's ``inverse``, ``jacobian``,
    ``wrench``, ``check_singularity``, ``wrench_capacity`` evaluated on plain floats (and one
    3x3 inverse / SVD); every other attribute is the model's.

    :param mechanism: the model (:class:`~brace_control.mechanisms.planar.RprLegs`).
    :param legs: its :class:`PlanarRprFloats` (``PlanarRprFloats.of(mechanism)``).
    """

    def __init__(self, mechanism: Any, legs: PlanarRprFloats) -> None:
        self._m = mechanism
        self._legs = legs
        lo, hi = (np.asarray(a, dtype=float) for a in mechanism.actuator_limits)
        self._lo, self._hi = lo.tolist(), hi.tolist()
        self._cond_max = float(mechanism.singularity_condition_max)
        self._names = list(mechanism.actuator_names)
        # one period evaluates the same few poses several times (the pose, the next one, its
        # braking pose): the last few results, by pose
        self._cache: dict[tuple[float, float, float], tuple[list[float], list[tuple[float, float, float]]]] = {}

    def __getattr__(self, name: str) -> Any:
        if name.startswith('__') or name == '_m':   # e.g. while unpickling: no model yet
            raise AttributeError(name)
        return getattr(self._m, name)

    def _rows(self, pose: Sequence[float]) -> tuple[list[float], list[tuple[float, float, float]]]:
        x, y, th = (float(v) for v in pose)
        key = (x, y, th)
        hit = self._cache.get(key)
        if hit is not None:
            return hit
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(th)):
            raise ValueError(f'pose: non-finite value: {[x, y, th]}')
        out = self._legs.lengths_and_rows(x, y, th)
        if len(self._cache) >= 6:
            self._cache.clear()
        self._cache[key] = out
        return out

    def inverse(self, pose: Sequence[float]) -> np.ndarray:
        """Leg lengths (m); :class:`UnreachablePose` outside the stroke (as the model)."""
        lengths, _ = self._rows(pose)
        for i, q in enumerate(lengths):
            if not self._lo[i] - 1e-12 <= q <= self._hi[i] + 1e-12:
                raise UnreachablePose(f'actuator {self._names[i]} would need {q:.4f} m, its range is '
                                      f'{self._lo[i]:.4f}–{self._hi[i]:.4f} m',
                                      actuator=self._names[i], value=q, limits=(self._lo[i], self._hi[i]))
        return np.array(lengths)

    def jacobian(self, pose: Sequence[float]) -> np.ndarray:
        return np.array(self._rows(pose)[1])

    def wrench(self, pose: Sequence[float], forces: Sequence[float]) -> np.ndarray:
        """``J^T f`` (Fx N, Fy N, Mz N·m about the platform origin, base frame)."""
        return np.array(self._legs.wrench(self._rows(pose)[1], [float(f) for f in forces]))

    def check_singularity(self, pose: Sequence[float]) -> None:
        """:class:`SingularPose` when ``cond(J) > singularity_condition_max`` (the model's rule)."""
        sv = np.linalg.svd(np.array(self._rows(pose)[1]), compute_uv=False)
        c = float(sv[0] / sv[-1]) if sv[-1] > 0.0 else math.inf
        if not c <= self._cond_max:
            raise SingularPose(f'pose {np.round(np.asarray(pose, float), 5).tolist()} is at or near a '
                               f'singularity: cond(J) = {c:.3g} > {self._cond_max:.3g}')

    def wrench_capacity(self, pose: Sequence[float], force_limits: Any) -> np.ndarray:
        """Closed form of the model's square, regular case: ``W = J^T f`` so ``f = J^-T W``
        and axis ``i`` alone holds ``w_i = f_max / max_j |(J^-1)_ij|``; 0 at a singular
        ``J`` (the unsupported direction)."""
        self.inverse(pose)
        J = np.array(self._rows(pose)[1])
        try:
            jinv = np.linalg.inv(J)
        except np.linalg.LinAlgError:
            return np.zeros(3)
        lim = np.broadcast_to(np.asarray(force_limits, dtype=float), (3,))
        # f_j = sum_i (J^-T)_ji W_i = sum_i (J^-1)_ij W_i: W = w e_i needs |w (J^-1)_ij| <= lim_j
        return np.min(lim[None, :] / np.maximum(np.abs(jinv), 1e-300), axis=1)

    def agrees_with_model(self, poses: Sequence[Sequence[float]], force_limit: float) -> bool:
        """Lengths, ``J``, capacity (rel. 1e-9) and the singularity verdict equal the model's."""
        m = self._m
        try:
            for p in poses:
                p = np.asarray(p, dtype=float)
                if not (np.allclose(self.inverse(p), m.inverse(p), rtol=0, atol=1e-12)
                        and np.allclose(self.jacobian(p), m.jacobian(p), rtol=0, atol=1e-12)
                        and np.allclose(self.wrench_capacity(p, force_limit),
                                        m.wrench_capacity(p, force_limit), rtol=1e-9, atol=1e-9)):
                    return False
                try:
                    m.check_singularity(p)
                    model_ok = True
                except SingularPose:
                    model_ok = False
                try:
                    self.check_singularity(p)
                    fast_ok = True
                except SingularPose:
                    fast_ok = False
                if fast_ok != model_ok:
                    return False
        except (ValueError, np.linalg.LinAlgError):
            return False
        return True


def kinematics_for(mechanism: Any, force_limit: float) -> Any:
    """:class:`FastPlanarKinematics` of a square planar RPR when it agrees with the model at
    the home pose and two poses about it; otherwise the model itself."""
    legs = PlanarRprFloats.of(mechanism)
    if legs is None or int(mechanism.n_actuators) != 3:
        return mechanism
    fast = FastPlanarKinematics(mechanism, legs)
    home = np.asarray(mechanism.home_pose, dtype=float)
    poses = []
    for dx, dy, dth in ((0.0, 0.0, 0.0), (0.0, 0.0, 5.0), (0.002, -0.01, 8.0), (-0.003, 0.005, -6.0),
                        (0.001, -0.005, 12.0)):
        p = home + np.array([dx, dy, math.radians(dth)])
        try:
            mechanism.inverse(p)
            mechanism.check_singularity(p)
        except ValueError:             # unreachable or singular: no pose to compare at
            continue
        poses.append(p)
    if len(poses) < 2:
        return mechanism
    return fast if fast.agrees_with_model(poses, force_limit) else mechanism


class InLoopAdmittance:
    """The admittance as the executor's interaction source (module docstring).

    :param mechanism: the device's model.
    :param params: :class:`AdmittanceParams` (``dt`` is replaced by ``n x sync_period``).
    :param sync_period: the SYNC period (s).
    :param a_max: actuator acceleration limit (unit/s², per actuator): the velocity change is
        scaled as a whole to ``params.limit_margin x a_max``; braking keeps to it too
        (``params.actuator_max_acceleration``).
    """

    def __init__(self, mechanism: Any, params: AdmittanceParams, *, sync_period: float,
                 a_max: Sequence[float] | float) -> None:
        rate = 1.0 / params.dt
        self.n_syncs = max(1, round(1.0 / (sync_period * rate)))
        dt = self.n_syncs * sync_period
        self.n = int(mechanism.n_actuators)
        self.a_max = np.broadcast_to(np.asarray(a_max, dtype=float), (self.n,)).copy()
        # braking keeps to the same actuator limit as the active mode's velocity changes
        self.params = AdmittanceParams(**{**params.__dict__, 'dt': dt,
                                          'actuator_max_acceleration': self.a_max})
        self.kin = kinematics_for(mechanism, self.params.actuator_max_force)
        self.mechanism = mechanism
        self.controller = AdmittanceController(self.kin, self.params)
        self.dof = int(mechanism.dof)
        self.accel_limited = 0
        #: the wrench of the last update (pose axes) and the forces it came from
        self.wrench = np.zeros(self.dof)
        self._pose_hint = np.asarray(mechanism.home_pose, dtype=float)

    @property
    def mode(self) -> Mode:
        return self.controller.mode

    @property
    def dt(self) -> float:
        return self.params.dt

    def begin(self, q: Sequence[float], q_dot: Sequence[float]) -> None:
        """Take over from the command ``q`` with ``q_dot`` (must be ~0: interaction starts
        from rest). The pose ``x = forward_nearest(q)``, zero velocity, zero goal.

        :raises ValueError: the command is moving or its pose cannot start the mode (why).
        """
        qd = np.asarray(q_dot, dtype=float)
        if np.any(np.abs(qd) > 1e-9):
            raise ValueError(f'the command is moving (rates {np.round(qd, 5).tolist()}): interaction '
                             'starts from rest; wait for the motion to end')
        x = np.asarray(self.mechanism.forward_nearest(np.asarray(q, dtype=float), self._pose_hint), float)
        self.controller.start(x)           # raises UnreachablePose / ValueError
        self.accel_limited = 0

    def update(self, forces: Sequence[float]) -> tuple[np.ndarray, np.ndarray, str]:
        """One admittance period from the load-cell forces of the latest SYNC.

        :returns: ``(q, q_dot, stop_reason)``: the command ``dt`` ahead (IK of the new pose,
            ``J x_dot``) and, when a limit started a stop in this period, its reason
            (else ''); :attr:`mode` is IDLE once braked to rest.
        """
        c = self.controller
        f = np.asarray(forces, dtype=float)
        x0, v0 = c.x, c.v
        try:
            w = np.asarray(self.kin.wrench(x0, f), dtype=float) if np.all(np.isfinite(f)) else \
                np.full(self.dof, math.nan)
        except ValueError:
            w = np.full(self.dof, math.nan)
        self.wrench = w
        reason = ''
        try:
            x, v = c.step(w, f)
        except LimitStop as exc:
            reason = exc.reason
            x, v = c.x.copy(), c.v.copy()
        if c.mode is Mode.ACTIVE:
            x, v = self._accel_scale(x0, v0, x, v)
        self._pose_hint = x
        lengths = self.kin.inverse(x)
        J = self.controller.jacobian(x)
        return np.asarray(lengths, dtype=float), J @ v, reason

    def _accel_scale(self, x0: np.ndarray, v0: np.ndarray, x: np.ndarray, v: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
        """Scale the velocity change ``v - v0`` as a whole so every actuator's acceleration
        ``|J (v - v0)| / dt`` stays within ``limit_margin x a_max``; the pose then moves by
        the trapezoid of the limited velocity (the controller's state follows)."""
        dv = v - v0
        if not np.any(dv):
            return x, v
        J = self.controller.jacobian(x0)
        ratio = float(np.max(np.abs(J @ dv) / (self.params.limit_margin * self.a_max * self.dt)))
        if ratio <= 1.0:
            return x, v
        self.accel_limited += 1
        v_new = v0 + dv / ratio
        x_new, v_new = self.controller.constrained(x0 + 0.5 * (v0 + v_new) * self.dt, v_new)
        self.controller.x, self.controller.v = x_new.copy(), v_new.copy()
        return x_new, v_new
