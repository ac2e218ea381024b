"""kinetics_node: measured joint states -> measured pose and the wrench on the body.

Subscribes ``/brace/joint_states`` (``sensor_msgs/JointState``: ``position`` = actuator
lengths/angles, ``effort`` = load-cell force N / motor torque N·m).

* ``/brace/pose`` (``PoseStamped`` in ``base_frame``): forward kinematics with branch
  tracking, ``forward_nearest(q, hint)``; the hint is the configured home pose at start,
  then the last measured pose, so the solution stays on the assembly mode the device
  is in.
* ``/brace/wrench`` (``WrenchStamped`` in ``platform_frame``): the wrench the actuators
  apply to the platform (and so to the body), W = Jᵀ f, force components rotated into
  the platform frame, moment about the platform origin. SI.
* ``/diagnostics``: WARN when another assembly mode is within ``ambiguity_distance`` of
  the tracked one (the forward solution is ambiguous) or cond(J) is above
  ``singularity_warn_fraction`` × ``mechanism.singularity_condition_max``; ERROR when the
  forward kinematics has no solution for the measured lengths.
"""
from __future__ import annotations

import math
import time
from collections.abc import Sequence

import numpy as np
from geometry_msgs.msg import PoseStamped, WrenchStamped
from rcl_interfaces.msg import FloatingPointRange, ParameterDescriptor
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState

from ..mechanisms import mechanism_from_config
from ..mechanisms.base import rot2
from .diagnostics import ERROR, OK, WARN, NodeDiagnostics
from .msgs import MalformedMessage, joint_state_arrays, pose_kind, pose_msg, wrench_msg
from .params import declare_device_parameters
from .runner import run_node

__all__ = ['KineticsNode', 'main', 'STATE_QOS', 'platform_frame_wrench']

JOINT_STATES_TOPIC = '/brace/joint_states'
POSE_TOPIC = '/brace/pose'
WRENCH_TOPIC = '/brace/wrench'

#: Measured state: reliable, depth 10 (a late subscriber or a slow callback loses no
#: sample of the 100 Hz stream; recorded bags are complete).
STATE_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)


def platform_frame_wrench(pose: np.ndarray, wrench: np.ndarray, kind: str) -> np.ndarray:
    """A planar wrench ``(Fx, Fy, Mz)`` in base coordinates -> the platform frame.

    The moment about the platform origin is frame independent in the plane; the force
    is rotated by R(theta)ᵀ. Other pose kinds are returned unchanged.
    """
    if kind != 'planar':
        return wrench
    out = np.array(wrench, dtype=float)
    out[:2] = rot2(float(pose[2])).T @ out[:2]
    return out


class KineticsNode(Node):
    """Forward kinematics and statics of the configured mechanism on the measured state."""

    def __init__(self, *, node_name: str = 'kinetics_node', **kwargs) -> None:
        super().__init__(node_name, **kwargs)
        self.cfg = declare_device_parameters(self, ('mechanism', 'actuator'))
        self.mechanism = mechanism_from_config(self.cfg)
        self.base_frame: str = self.cfg['base_frame']
        self.platform_frame: str = self.cfg['platform_frame']
        self.actuator_names = tuple(self.mechanism.actuator_names)
        self._kind = pose_kind(self.mechanism)
        self._cond_max = float(self.cfg['mechanism'].get('singularity_condition_max', 1e4))
        self.ambiguity_distance = self.declare_parameter(
            'kinetics.ambiguity_distance', 0.02, ParameterDescriptor(
                description='another assembly mode closer than this (pose norm, m/rad) '
                            '-> ambiguous forward solution',
                floating_point_range=[FloatingPointRange(from_value=0.0, to_value=10.0)])).value
        self.singularity_warn_fraction = self.declare_parameter(
            'kinetics.singularity_warn_fraction', 0.5, ParameterDescriptor(
                description='cond(J) above this fraction of singularity_condition_max -> warn',
                floating_point_range=[FloatingPointRange(from_value=1e-6, to_value=1.0)])).value
        self.ambiguity_check_period = self.declare_parameter(
            'kinetics.ambiguity_check_period', 0.05, ParameterDescriptor(
                description='seconds between full forward solutions (all assembly modes)',
                floating_point_range=[FloatingPointRange(from_value=0.0, to_value=10.0)])).value
        self.pose: np.ndarray = np.asarray(self.mechanism.home_pose, dtype=float)
        self.wrench: np.ndarray | None = None
        self.condition = float('nan')
        self.ambiguous = False
        self._last_ambiguity_check = -math.inf
        self.received = 0
        self.failed = 0
        self._pose_pub = self.create_publisher(PoseStamped, POSE_TOPIC, STATE_QOS)
        self._wrench_pub = self.create_publisher(WrenchStamped, WRENCH_TOPIC, STATE_QOS)
        self._sub = self.create_subscription(
            JointState, JOINT_STATES_TOPIC, self._on_joint_states, STATE_QOS)
        self.diagnostics = NodeDiagnostics(self, f'brace_control/{node_name}')
        self.diagnostics.set(OK, 'waiting for joint states')

    # ------------------------------------------------------------------ callbacks
    def _on_joint_states(self, msg: JointState) -> None:
        self.received += 1
        try:
            arrays = joint_state_arrays(msg, self.actuator_names, ('position', 'effort'),
                                        optional=('effort',))
        except MalformedMessage as exc:
            self._fail(f'joint state rejected: {exc}')
            return
        q = arrays['position']
        lo, hi = self.mechanism.actuator_limits
        margin = 0.05 * (hi - lo)
        if np.any(q < lo - margin) or np.any(q > hi + margin):
            # e.g. incremental encoders before homing read 0: not a pose, not a fault here
            self.failed += 1
            msg = (f'joint positions {np.round(q, 4).tolist()} are outside the actuator range '
                   f'(drives not homed?): no pose published')
            self.get_logger().warning(msg, throttle_duration_sec=5.0)
            self.diagnostics.set(WARN, msg, failed=self.failed)
            return
        try:
            pose = np.asarray(self.mechanism.forward_nearest(q, self.pose), dtype=float)
        except ValueError as exc:
            self._fail(f'no forward solution for q = {np.round(q, 5).tolist()}: {exc}')
            return
        self.pose = pose
        stamp = msg.header.stamp
        self._pose_pub.publish(pose_msg(pose, frame_id=self.base_frame, stamp=stamp,
                                        mechanism=self.mechanism))
        jac = self.mechanism.jacobian(pose)
        if arrays['effort'] is not None:
            w = np.asarray(self.mechanism.wrench(pose, arrays['effort']), dtype=float)
            self.wrench = platform_frame_wrench(pose, w, self._kind)
            self._wrench_pub.publish(wrench_msg(self.wrench, frame_id=self.platform_frame,
                                                stamp=stamp, kind=self._kind))
        self._supervise(q, pose, jac)

    def _supervise(self, q: np.ndarray, pose: np.ndarray, jac: np.ndarray) -> None:
        s = np.linalg.svd(jac, compute_uv=False)
        self.condition = float(s[0] / s[-1]) if s[-1] > 0 else math.inf
        now = time.monotonic()
        if now - self._last_ambiguity_check >= self.ambiguity_check_period:
            self._last_ambiguity_check = now
            others = [np.asarray(p, float) for p in self.mechanism.forward(q)]
            dists = sorted(float(np.linalg.norm(p - pose)) for p in others)
            # the tracked solution itself is one of them (distance ~0)
            nearest_other = dists[1] if len(dists) > 1 else math.inf
            self.ambiguous = nearest_other < self.ambiguity_distance
            self.diagnostics.values['assembly_modes'] = len(others)
            self.diagnostics.values['nearest_other_mode'] = f'{nearest_other:.4g}'
        self.diagnostics.values['condition'] = f'{self.condition:.4g}'
        self.diagnostics.values['pose'] = np.round(pose, 5).tolist()
        if self.condition > self.singularity_warn_fraction * self._cond_max:
            self.diagnostics.set(WARN, f'near a singularity: cond(J) = {self.condition:.3g}')
        elif self.ambiguous:
            self.diagnostics.set(WARN, 'forward solution ambiguous: another assembly mode '
                                       f'within {self.ambiguity_distance} of the tracked one')
        elif self.diagnostics.level != OK or self.received == 1:
            self.diagnostics.set(OK, 'tracking')

    def _fail(self, message: str) -> None:
        self.failed += 1
        self.get_logger().error(message, throttle_duration_sec=1.0)
        self.diagnostics.set(ERROR, message, failed=self.failed)


def main(args: Sequence[str] | None = None) -> int:
    return run_node(KineticsNode, executable='kinetics_node', args=args,
                    summary='forward kinematics + wrench: /brace/joint_states -> '
                            '/brace/pose, /brace/wrench')


if __name__ == '__main__':
    raise SystemExit(main())
