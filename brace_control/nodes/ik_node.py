"""ik_node: planned pose motions and pose setpoints -> actuator coordinates (inverse kinematics).

Planned motions (ARCHITECTURE.md, "Data flow"): subscribes ``/brace/pose_trajectory``
(``trajectory_msgs/MultiDOFJointTrajectory``, pose knots, see :mod:`.msgs`), converts the
whole motion at once (:func:`~brace_control.trajectory.actuator.actuator_knots`: batch IK,
``q_dot = J x_dot``, ``q_ddot`` along the path, knots added until the interpolated actuator
motion is within 1 um of the IK of the planned poses) and publishes
``/brace/actuator_trajectory`` (``trajectory_msgs/JointTrajectory``, same stamp). An empty
trajectory (a stop) is passed on as an empty one. A motion it cannot convert (malformed, a
pose without inverse kinematics, a knot outside the mechanism's workspace) is reported on ``/brace/execution_status`` as
``rejected`` with the reason and the trajectory's stamp; nothing is published.

Teleoperation stream: subscribes ``/brace/pose_setpoint`` (``geometry_msgs/PoseStamped``,
in ``base_frame``), publishes ``/brace/actuator_setpoint`` (``sensor_msgs/JointState``: one
entry per actuator of the YAML, ``position`` = IK, ``velocity`` = J · pose rate from the
previous accepted setpoint, 0 for the first one or after a gap).

A setpoint that is malformed (NaN/inf, wrong frame, a non-planar quaternion for a planar
device) or unreachable (outside the stroke, singular, outside the workspace the planner
keeps to: a cable brace's pose its cables cannot hold unloaded) is rejected: a throttled warning,
a ``/diagnostics`` status with the reason, nothing published; the last valid setpoint
stays in force downstream (docs/safety.md §6, §10). The output keeps the setpoint's stamp, so
the driver's staleness check and the latency bench see when the pose was commanded.
"""
from __future__ import annotations

import math
import time
from collections.abc import Sequence

import numpy as np
from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import PoseStamped
from rclpy.node import Node
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory, MultiDOFJointTrajectory

from ..mechanisms import SingularPose, UnreachablePose, mechanism_from_config
from ..mechanisms.base import check_workspace, workspace_mask
from ..trajectory import KnotTrajectory, TrajectoryError, actuator_knots
from . import topics
from .diagnostics import ERROR, OK, WARN, NodeDiagnostics
from .msgs import (MalformedMessage, joint_state, joint_trajectory_msg, pose_from_msg,
                   pose_knots_from_msg, pose_kind, stamp_to_ns, status_msg)
from .params import declare_device_parameters
from .runner import run_node

__all__ = ['IkNode', 'main']

#: Rejection warnings are throttled to one per this many seconds (the stream is 200 Hz).
REJECT_LOG_PERIOD = 1.0


def angle_aware_difference(a: np.ndarray, b: np.ndarray, angular: Sequence[int]) -> np.ndarray:
    """``a - b`` with the ``angular`` coordinates wrapped to (-pi, pi]."""
    d = np.asarray(a, float) - np.asarray(b, float)
    for i in angular:
        d[i] = math.atan2(math.sin(d[i]), math.cos(d[i]))
    return d


class NotConnected(Exception):
    """The node downstream of a converted trajectory is not there (no subscriber)."""


class IkNode(Node):
    """Inverse kinematics of the configured mechanism on the setpoint stream."""

    def __init__(self, *, node_name: str = 'ik_node', **kwargs) -> None:
        super().__init__(node_name, **kwargs)
        self.cfg = declare_device_parameters(self, ('mechanism', 'actuator', 'trajectory'), cli_args=kwargs.get('cli_args'))
        self.mechanism = self.cfg.model or mechanism_from_config(self.cfg)
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
        self.converted = 0
        self.conversion_ms = float('nan')
        self._pub = self.create_publisher(JointState, topics.ACTUATOR_SETPOINT, topics.SETPOINT_QOS)
        self._sub = self.create_subscription(
            PoseStamped, topics.POSE_SETPOINT, self._on_setpoint, topics.SETPOINT_QOS)
        self._traj_pub = self.create_publisher(JointTrajectory, topics.ACTUATOR_TRAJECTORY,
                                               topics.TRAJECTORY_QOS)
        self._status_pub = self.create_publisher(DiagnosticStatus, topics.EXECUTION_STATUS,
                                                 topics.STATUS_QOS)
        self.create_subscription(MultiDOFJointTrajectory, topics.POSE_TRAJECTORY,
                                 self._on_trajectory, topics.TRAJECTORY_QOS)
        self.diagnostics = NodeDiagnostics(self, f'brace_control/{node_name}')
        self.diagnostics.watch(self._traj_pub)
        self.diagnostics.set(OK, 'waiting for trajectories and setpoints', accepted=0, rejected=0)
        self.get_logger().info(
            f'{type(self.mechanism).__name__} ({", ".join(self.actuator_names)}): '
            f'{topics.POSE_TRAJECTORY} -> {topics.ACTUATOR_TRAJECTORY}, '
            f'{topics.POSE_SETPOINT} -> {topics.ACTUATOR_SETPOINT} in {self.base_frame!r}')

    # ------------------------------------------------------------------ planned motions
    def _on_trajectory(self, msg: MultiDOFJointTrajectory) -> None:
        """A whole planned motion -> actuator knots, published once (or a rejection)."""
        tag = stamp_to_ns(msg.header.stamp)
        t0 = time.perf_counter()
        try:
            stamp_ns, times, P, V, A = pose_knots_from_msg(msg, frame_id=self.base_frame,
                                                           mechanism=self.mechanism)
            if times.size == 0:
                out = joint_trajectory_msg(self.actuator_names, times, np.zeros((0, len(self.actuator_names))),
                                           np.zeros((0, len(self.actuator_names))),
                                           np.zeros((0, len(self.actuator_names))),
                                           stamp=msg.header.stamp, frame_id=self.base_frame)
                self._traj_pub.publish(out)
                return
            knots = actuator_knots(self.mechanism, KnotTrajectory(times, P, V, A))
            outside = ~workspace_mask(self.mechanism, P)
            if outside.any():               # what the planner refuses, refused here as well
                i = int(np.argmax(outside))
                check_workspace(self.mechanism, P[i])
                raise UnreachablePose(f'knot {i} is outside the workspace')
        except (MalformedMessage, TrajectoryError, ValueError) as exc:
            self._reject_trajectory(tag, exc)
            return
        if self._traj_pub.get_subscription_count() == 0:
            # the topic keeps no history: published now, the motion would be lost silently
            self._reject_trajectory(tag, NotConnected(
                f'nothing subscribes to {topics.ACTUATOR_TRAJECTORY} (is can_driver_node '
                'running?): the motion would be lost'))
            return
        self._traj_pub.publish(joint_trajectory_msg(
            self.actuator_names, knots.times, knots.positions, knots.velocities,
            knots.accelerations, stamp=msg.header.stamp, frame_id=self.base_frame))
        self.converted += 1
        self.conversion_ms = (time.perf_counter() - t0) * 1e3
        self.diagnostics.set(OK, 'converting trajectories', trajectories=self.converted,
                             last_conversion_ms=f'{self.conversion_ms:.2f}',
                             last_knots=int(knots.times.size))

    def _reject_trajectory(self, tag: int, exc: Exception) -> None:
        self.rejected += 1
        kind = ('malformed' if isinstance(exc, MalformedMessage) else
                'not connected' if isinstance(exc, NotConnected) else 'unreachable')
        self.last_rejection = f'{kind} trajectory {tag} rejected: {exc}'
        self.get_logger().error(self.last_rejection)
        self.diagnostics.set(ERROR if kind == 'malformed' else WARN, self.last_rejection,
                             rejected=self.rejected)
        self._status_pub.publish(status_msg(
            f'{self.get_name()}/trajectory/{tag}', 'rejected', level=DiagnosticStatus.ERROR,
            stamp=tag, kind='rejected', reason=f'{kind}: {exc}'))

    # ------------------------------------------------------------------ callbacks
    def _on_setpoint(self, msg: PoseStamped) -> None:
        try:
            pose = pose_from_msg(msg, frame_id=self.base_frame, mechanism=self.mechanism)
            q = self.mechanism.inverse(pose)
            check = getattr(self.mechanism, 'check_singularity', None)
            if callable(check):
                check(pose)
            # the mechanism's whole workspace, as the planner checks it (a cable brace: the
            # cables must hold the pose; a sweep of random setpoints found half of the
            # 4-RPR's accepted ones needing a cable to push)
            check_workspace(self.mechanism, pose)
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
        reason = getattr(exc, 'reason', None) or ('singular' if isinstance(exc, SingularPose)
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
