"""ik_node: pose setpoints -> actuator setpoints (inverse kinematics of the device).

Subscribes ``/brace/pose_setpoint`` (``geometry_msgs/PoseStamped``, in ``base_frame``),
publishes ``/brace/actuator_setpoint`` (``sensor_msgs/JointState``: one entry per
actuator of the YAML, ``position`` = IK, ``velocity`` = J · pose rate from the previous
accepted setpoint, 0 for the first one or after a gap).

A setpoint that is malformed (NaN/inf, wrong frame, a non-planar quaternion for a planar
device) or unreachable (outside the stroke, singular) is rejected: a throttled warning,
a ``/diagnostics`` status with the reason, nothing published; the last valid setpoint
stays in force downstream (SAFETY.md 6, 10). The output keeps the setpoint's stamp, so
the driver's staleness check and the latency bench see when the pose was commanded.
"""
from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from geometry_msgs.msg import PoseStamped
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState

from ..mechanisms import UnreachablePose, mechanism_from_config
from .diagnostics import ERROR, OK, WARN, NodeDiagnostics
from .msgs import MalformedMessage, joint_state, pose_from_msg, pose_kind, stamp_to_ns
from .params import declare_device_parameters
from .runner import run_node

__all__ = ['IkNode', 'main', 'SETPOINT_QOS', 'POSE_SETPOINT_TOPIC', 'ACTUATOR_SETPOINT_TOPIC']

POSE_SETPOINT_TOPIC = '/brace/pose_setpoint'
ACTUATOR_SETPOINT_TOPIC = '/brace/actuator_setpoint'

#: Setpoint streams: reliable, depth 10. At 200 Hz a best-effort depth-1 stream would
#: let DDS drop a setpoint whenever a callback runs late; the driver's per-cycle step
#: check (SAFETY.md 7) would then see a double step. Reliable with a few samples of
#: history absorbs scheduling jitter (10 samples = 50 ms at 200 Hz) without building a
#: backlog the staleness check would not catch (stale setpoints are held, SAFETY.md 1).
SETPOINT_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                          reliability=ReliabilityPolicy.RELIABLE,
                          durability=DurabilityPolicy.VOLATILE)

#: Rejection warnings are throttled to one per this many seconds (the stream is 200 Hz).
REJECT_LOG_PERIOD = 1.0


def angle_aware_difference(a: np.ndarray, b: np.ndarray, angular: Sequence[int]) -> np.ndarray:
    """``a - b`` with the ``angular`` coordinates wrapped to (-pi, pi]."""
    d = np.asarray(a, float) - np.asarray(b, float)
    for i in angular:
        d[i] = math.atan2(math.sin(d[i]), math.cos(d[i]))
    return d


class IkNode(Node):
    """Inverse kinematics of the configured mechanism on the setpoint stream."""

    def __init__(self, *, node_name: str = 'ik_node', **kwargs) -> None:
        super().__init__(node_name, **kwargs)
        self.cfg = declare_device_parameters(self, ('mechanism', 'actuator', 'trajectory'))
        self.mechanism = mechanism_from_config(self.cfg)
        self.base_frame: str = self.cfg['base_frame']
        self.actuator_names = tuple(self.mechanism.actuator_names)
        self._kind = pose_kind(self.mechanism)
        self._angular = [2] if self._kind == 'planar' else []
        # Successive setpoints further apart than this are a new stream: velocity 0.
        self._max_gap_ns = int(5e9 / float(self.cfg['trajectory']['rate_hz']))
        self._last_pose: np.ndarray | None = None
        self._last_stamp_ns: int | None = None
        self.accepted = 0
        self.rejected = 0
        self.last_rejection = ''
        self._pub = self.create_publisher(JointState, ACTUATOR_SETPOINT_TOPIC, SETPOINT_QOS)
        self._sub = self.create_subscription(
            PoseStamped, POSE_SETPOINT_TOPIC, self._on_setpoint, SETPOINT_QOS)
        self.diagnostics = NodeDiagnostics(self, f'brace_control/{node_name}')
        self.diagnostics.set(OK, 'waiting for setpoints', accepted=0, rejected=0)
        self.get_logger().info(
            f'{type(self.mechanism).__name__} ({", ".join(self.actuator_names)}): '
            f'{POSE_SETPOINT_TOPIC} -> {ACTUATOR_SETPOINT_TOPIC} in {self.base_frame!r}')

    # ------------------------------------------------------------------ callbacks
    def _on_setpoint(self, msg: PoseStamped) -> None:
        try:
            pose = pose_from_msg(msg, frame_id=self.base_frame, mechanism=self.mechanism)
            q = self.mechanism.inverse(pose)
            check = getattr(self.mechanism, 'check_singularity', None)
            if callable(check):
                check(pose)
            jac = self.mechanism.jacobian(pose)
        except (MalformedMessage, UnreachablePose, ValueError) as exc:
            self._reject(exc)
            return
        stamp_ns = stamp_to_ns(msg.header.stamp)
        qdot = np.zeros(len(q))
        if self._last_pose is not None and self._last_stamp_ns is not None:
            dt_ns = stamp_ns - self._last_stamp_ns
            if 0 < dt_ns <= self._max_gap_ns:
                xdot = angle_aware_difference(pose, self._last_pose, self._angular) / (dt_ns * 1e-9)
                qdot = jac @ xdot
        self._last_pose, self._last_stamp_ns = pose, stamp_ns
        self._pub.publish(joint_state(self.actuator_names, position=q, velocity=qdot,
                                      stamp=msg.header.stamp, frame_id=self.base_frame))
        self.accepted += 1
        if self.diagnostics.level != OK or self.accepted == 1:
            self.diagnostics.set(OK, 'tracking setpoints', accepted=self.accepted)
        else:
            self.diagnostics.values['accepted'] = self.accepted

    def _reject(self, exc: Exception) -> None:
        self.rejected += 1
        kind = 'unreachable' if isinstance(exc, UnreachablePose) else 'malformed'
        reason = getattr(exc, 'reason', None) or ('singular' if type(exc).__name__ == 'SingularPose'
                                                   else kind)
        self.last_rejection = f'{kind} setpoint rejected ({reason}): {exc}'
        self.get_logger().warning(self.last_rejection + '; holding the last valid setpoint',
                               throttle_duration_sec=REJECT_LOG_PERIOD)
        self.diagnostics.set(ERROR if kind == 'malformed' else WARN, self.last_rejection,
                             rejected=self.rejected, last_rejection_reason=reason)


def main(args: Sequence[str] | None = None) -> int:
    return run_node(IkNode, executable='ik_node', args=args,
                    summary='inverse kinematics: /brace/pose_setpoint -> /brace/actuator_setpoint')


if __name__ == '__main__':
    raise SystemExit(main())
