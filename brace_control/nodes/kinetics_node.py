"""kinetics_node: measured joint states -> the estimated pose, its covariance, the wrench on the body.

Subscribes ``/brace/joint_states`` (``sensor_msgs/JointState``: ``position`` = encoder
lengths/angles, ``effort`` = load-cell force N / joint torque N·m, along ``+q``).

The pose is the load-aware estimate of :class:`~brace_control.mechanisms.pose_estimate.PoseEstimator`:
each leg is the actuator in series with ``actuator.stiffness``, so the platform sits on the
leg lengths ``L = q - effort / stiffness``, not on the encoder lengths; weighted least
squares on the inverse-kinematics residual, continuous with the last estimate (the first
one from ``forward_nearest`` at the home pose); a least-squares pose when the lengths do not
close (never silence, never a jump to another assembly mode). Covariance from the encoder
quantum, ``kinetics.load_cell_noise`` and ``kinetics.stiffness_rel_std``.

* ``/brace/pose`` (``PoseStamped`` in ``base_frame``): the estimate.
* ``/brace/pose_with_covariance`` (``PoseWithCovarianceStamped``, ``base_frame``): the same
  pose, covariance 6x6 row-major in (x, y, z, rot x, rot y, rot z); a planar device's
  (x, y, theta) in the x, y, rot z entries; what the device does not measure gets
  ``kinetics.unobserved_variance`` (see :func:`~brace_control.nodes.msgs.pose_covariance_6x6`).
* ``/brace/wrench`` (``WrenchStamped`` in ``platform_frame``): the wrench the actuators
  apply to the platform (and so to the body) at the *estimated* pose with the measured
  efforts, W = Jᵀ f, force components rotated into the platform frame, moment about the
  platform origin. SI.

All three carry the joint state's stamp. While anything moves they follow every joint state.
At rest (every reading within ``kinetics.rest_band_sigmas`` of its own noise of the readings of
the last estimate, and that estimate exact) they are renewed every ``kinetics.rest_period``
(0.05 s) from the newest joint state: a 100 Hz stream at rest is 20 Hz of the same pose,
not 100 Hz of the load cells' noise (:class:`RestGate`). Each topic is made and published
only while something subscribes it (volatile topics: a reader that matches gets the next
sample either way); the estimate itself is kept up to date regardless.
``/diagnostics``: the residual (largest, in m or rad and in standard deviations), exact or
least squares, cond(J), the pose's standard deviations; WARN for a least-squares pose, a step
limited by ``kinetics.max_step``, a pose near a singularity (cond(J) above
``singularity_warn_fraction`` × ``singularity_condition_max``), another assembly mode within
``ambiguity_distance`` or a slack cable; ERROR for a malformed joint state.
"""
from __future__ import annotations

import math
import time
from collections.abc import Sequence

import numpy as np
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped, WrenchStamped
from rclpy.node import Node
from sensor_msgs.msg import JointState

from ..can.units import actuator_kind, scaling_from_config
from ..mechanisms import mechanism_from_config
from ..mechanisms.pose_estimate import MeasurementModel, PoseEstimate, PoseEstimator
from ..schema import mechanism_default
from . import topics
from .diagnostics import ERROR, OK, WARN, NodeDiagnostics
from .msgs import (MalformedMessage, joint_state_arrays, pose_kind, pose_msg,
                   pose_with_covariance_msg, stamp_to_sec, wrench_msg)
from .params import declare_device_parameters
from .runner import run_node

__all__ = ['KineticsNode', 'main', 'platform_frame_wrench']


def platform_frame_wrench(pose: np.ndarray, wrench: np.ndarray, kind: str) -> np.ndarray:
    """A planar wrench ``(Fx, Fy, Mz)`` in base coordinates -> the platform frame.

    The moment about the platform origin is frame independent in the plane; the force
    is rotated by R(theta)ᵀ. Other pose kinds are returned unchanged.
    """
    if kind != 'planar':
        return wrench
    out = np.array(wrench, dtype=float)
    # R(theta)^T (Fx, Fy) in plain floats (numpy's 2x2 product costs more than the rest)
    theta = float(pose[2])
    c, s = math.cos(theta), math.sin(theta)
    fx, fy = float(out[0]), float(out[1])
    out[0], out[1] = c * fx + s * fy, c * fy - s * fx
    return out


class RestGate:
    """When a joint state is worth a new estimate: a reading moved beyond its noise since the
    last estimate, or ``period`` has passed since it (s, on the joint states' stamps).

    :param position_band: per actuator (m or rad): larger encoder changes are motion.
    :param effort_band: per actuator (N or N·m): larger load-cell changes are a new load.
    :param period: the longest gap between estimates at rest; 0: every joint state is due.

    The caller says which estimates count as a reference (:meth:`took`) and when the next
    one must be computed whatever the readings say (:meth:`reset`: an estimate that has not
    converged yet, a failure). A stamp that goes backwards (a replayed bag started again) is due.
    """

    def __init__(self, position_band: np.ndarray, effort_band: np.ndarray, period: float) -> None:
        self.position_band = np.asarray(position_band, float)
        self.effort_band = np.asarray(effort_band, float)
        self.period = float(period)
        self._q: np.ndarray | None = None
        self._effort: np.ndarray | None = None
        self._at = -math.inf
        #: joint states not turned into an estimate (at rest, within ``period``)
        self.skipped = 0

    def due(self, q: np.ndarray, effort: np.ndarray | None, t: float) -> bool:
        if self.period <= 0.0 or self._q is None or not self._at <= t < self._at + self.period:
            return True
        if (np.abs(q - self._q) > self.position_band).any():
            return True
        if (effort is None) != (self._effort is None):
            return True
        if effort is not None and (np.abs(effort - self._effort) > self.effort_band).any():
            return True
        self.skipped += 1
        return False

    def took(self, q: np.ndarray, effort: np.ndarray | None, t: float) -> None:
        """The estimate of these readings at ``t`` is the reference of the next ones."""
        self._q, self._effort, self._at = q, effort, t

    def reset(self) -> None:
        self._q = self._effort = None


class KineticsNode(Node):
    """The load-aware pose estimate and the statics of the configured mechanism."""

    def __init__(self, *, node_name: str = 'kinetics_node', **kwargs) -> None:
        super().__init__(node_name, **kwargs)
        self.cfg = declare_device_parameters(self, ('mechanism', 'actuator', 'kinetics'), cli_args=kwargs.get('cli_args'))
        self.mechanism = self.cfg.model or mechanism_from_config(self.cfg)
        kin, act = self.cfg['kinetics'], self.cfg['actuator']
        scaling = scaling_from_config(self.cfg)
        self.rotary = actuator_kind(self.cfg) == 'rotary'
        self.estimator = PoseEstimator(
            self.mechanism,
            MeasurementModel(stiffness=float(act['stiffness']), resolution=1.0 / scaling.counts_per_unit,
                             force_noise=float(kin['load_cell_noise']),
                             stiffness_rel_std=float(kin['stiffness_rel_std']),
                             force_resolution=scaling.newton_per_count,
                             force_limit=float(act['max_force'])),
            rotary=self.rotary, max_step=float(kin['max_step']),
            max_iterations=int(kin['max_iterations']), residual_sigmas=float(kin['residual_sigmas']))
        self.base_frame: str = self.cfg['base_frame']
        self.platform_frame: str = self.cfg['platform_frame']
        self.actuator_names = tuple(self.mechanism.actuator_names)
        # a joint state outside the actuator range by more than 5 % of it is no pose
        lo, hi = self.mechanism.actuator_limits
        margin = 0.05 * (hi - lo)
        self._q_low, self._q_high = lo - margin, hi + margin
        self._kind = pose_kind(self.mechanism)
        # the model's (from the YAML); a model without a singularity test: the schema's default
        self._cond_max = float(getattr(self.mechanism, 'singularity_condition_max', None)
                               or mechanism_default(None, 'singularity_condition_max'))
        self.ambiguity_distance = float(kin['ambiguity_distance'])
        self.singularity_warn_fraction = float(kin['singularity_warn_fraction'])
        self.ambiguity_check_period = float(kin['ambiguity_check_period'])
        self.unobserved_variance = float(kin['unobserved_variance'])
        model = self.estimator.model
        _, resolution = model.arrays(len(self.actuator_names))
        sigmas = float(kin['rest_band_sigmas'])
        self.rest_gate = RestGate(sigmas * resolution / math.sqrt(12.0),
                                  np.full(len(self.actuator_names), sigmas * math.sqrt(model.force_variance)),
                                  float(kin['rest_period']))
        #: the last estimate (pose, covariance, residual, ...), ``None`` before the first
        self.estimate: PoseEstimate | None = None
        self.pose: np.ndarray = np.asarray(self.mechanism.home_pose, dtype=float)
        self.wrench: np.ndarray | None = None
        self.condition = float('nan')
        self.ambiguous = False
        self._last_ambiguity_check = -math.inf
        self.received = 0
        self.failed = 0
        self._pose_pub = self.create_publisher(PoseStamped, topics.POSE, topics.STATE_QOS)
        self._pose_cov_pub = self.create_publisher(PoseWithCovarianceStamped, topics.POSE_WITH_COVARIANCE,
                                                   topics.STATE_QOS)
        self._wrench_pub = self.create_publisher(WrenchStamped, topics.WRENCH, topics.STATE_QOS)
        self._sub = self.create_subscription(
            JointState, topics.JOINT_STATES, self._on_joint_states, topics.STATE_QOS)
        self.diagnostics = NodeDiagnostics(self, f'brace_control/{node_name}')
        self.diagnostics.set(OK, 'waiting for joint states')

    @property
    def residual(self) -> np.ndarray | None:
        """The last estimate's leg-length residual ``L - l(pose)`` (m or rad), ``None`` before one."""
        return None if self.estimate is None else self.estimate.residual.copy()

    # ------------------------------------------------------------------ callbacks
    def _on_joint_states(self, msg: JointState) -> None:
        self.received += 1
        try:
            arrays = joint_state_arrays(msg, self.actuator_names, ('position', 'effort'),
                                        optional=('effort',))
        except MalformedMessage as exc:
            self._fail(f'joint state rejected: {exc}')
            return
        q, effort = arrays['position'], arrays['effort']
        if (q < self._q_low).any() or (q > self._q_high).any():
            # e.g. incremental encoders before homing read 0: not a pose, not a fault here
            self.failed += 1
            self.rest_gate.reset()
            text = (f'joint positions {np.round(q, 4).tolist()} are outside the actuator range '
                    f'(drives not homed?): no pose published')
            self.get_logger().warning(text, throttle_duration_sec=5.0)
            self.diagnostics.set(WARN, text, failed=self.failed)
            return
        stamp = msg.header.stamp
        t = stamp_to_sec(stamp) or time.monotonic()
        if not self.rest_gate.due(q, effort, t):
            return
        try:
            est = self.estimator.update(q, effort)
            wrench = None if effort is None else self.estimator.wrench(est.pose, effort)
        except ValueError as exc:
            self._fail(f'no pose estimate for q = {np.round(q, 6).tolist()}: {exc}')
            return
        if est.exact and not est.step_limited:
            self.rest_gate.took(q, effort, t)
        else:                                   # not converged: the next reading is due
            self.rest_gate.reset()
        self.estimate, self.pose, self.condition = est, est.pose, est.condition
        # volatile topics: a message nobody reads is not made (a reader that matches gets the
        # next one, as it would anyway)
        if self._pose_pub.get_subscription_count():
            self._pose_pub.publish(pose_msg(est.pose, frame_id=self.base_frame, stamp=stamp,
                                            mechanism=self.mechanism))
        if self._pose_cov_pub.get_subscription_count():
            self._pose_cov_pub.publish(pose_with_covariance_msg(
                est.pose, est.covariance, frame_id=self.base_frame, stamp=stamp,
                mechanism=self.mechanism, unobserved_variance=self.unobserved_variance))
        if wrench is not None:
            self.wrench = platform_frame_wrench(est.pose, wrench, self._kind)
            if self._wrench_pub.get_subscription_count():
                self._wrench_pub.publish(wrench_msg(self.wrench, frame_id=self.platform_frame,
                                                    stamp=stamp, kind=self._kind))
        self._supervise(est)

    def _supervise(self, est: PoseEstimate) -> None:
        now = time.monotonic()
        values = self.diagnostics.values
        if now - self._last_ambiguity_check >= self.ambiguity_check_period:
            self._last_ambiguity_check = now
            try:
                others = [np.asarray(p, float) for p in self.mechanism.forward(est.leg_lengths)]
            except ValueError:
                others = []
            dists = sorted(float(np.linalg.norm(p - est.pose)) for p in others)
            # the tracked solution itself is one of them (distance ~0) when the legs close
            nearest_other = dists[1] if len(dists) > 1 else math.inf
            self.ambiguous = nearest_other < self.ambiguity_distance
            values['assembly_modes'] = len(others)
            values['nearest_other_mode'] = f'{nearest_other:.4g}'
        unit = 'rad' if self.rotary else 'm'
        worst = int((np.abs(est.residual) / est.leg_sigma).argmax())
        values['solution'] = 'exact' if est.exact else 'least squares'
        values['residual_max'] = f'{est.residual_max:.3g} {unit}'
        values['residual_sigmas'] = f'{est.residual_sigmas:.3g}'
        values['condition'] = f'{est.condition:.4g}'
        values['iterations'] = est.iterations
        values['pose'] = est.pose.round(6).tolist()
        values['pose_sigma'] = [float(f'{s:.3g}') for s in np.sqrt(est.covariance.diagonal())]
        values['slack'] = list(est.slack)
        values['skipped_at_rest'] = self.rest_gate.skipped
        if not est.exact:
            self.diagnostics.set(WARN, (
                f'least squares: the leg lengths do not close (actuator {self.actuator_names[worst]} '
                f'off by {est.residual[worst]:.3g} {unit} = {est.residual_sigmas:.3g} sigma); the pose '
                'is the least-squares fit continuous with the last estimate'))
        elif est.step_limited:
            self.diagnostics.set(WARN, (
                f'the lengths point farther than kinetics.max_step = {self.estimator.max_step} from the '
                'last estimate (another assembly mode, or a jump in the readings): '
                + ('the estimate took the assembly nearest the last exact one' if est.reacquired else
                   'the estimate moved continuously, at most max_step per iteration')))
        elif est.condition > self.singularity_warn_fraction * self._cond_max:
            self.diagnostics.set(WARN, f'near a singularity: cond(J) = {est.condition:.3g}')
        elif self.ambiguous:
            self.diagnostics.set(WARN, 'forward solution ambiguous: another assembly mode '
                                       f'within {self.ambiguity_distance} of the tracked one')
        elif est.slack:
            self.diagnostics.set(WARN, f'cables {", ".join(est.slack)} read no tension (slack?): '
                                       'their lengths are not weighed')
        elif self.diagnostics.level != OK or self.received == 1 or self.diagnostics.message != 'tracking':
            self.diagnostics.set(OK, 'tracking')

    def _fail(self, message: str) -> None:
        self.failed += 1
        self.rest_gate.reset()
        self.get_logger().error(message, throttle_duration_sec=1.0)
        self.diagnostics.set(ERROR, message, failed=self.failed)


def main(args: Sequence[str] | None = None) -> int:
    return run_node(KineticsNode, executable='kinetics_node', args=args,
                    summary='load-aware pose estimate + wrench: /brace/joint_states -> '
                            '/brace/pose, /brace/pose_with_covariance, /brace/wrench')


if __name__ == '__main__':
    raise SystemExit(main())
