"""interaction_node: admittance control, the lumbar paper's zero-torque mode and wrench goals.

``ros2 run brace_control interaction_node --ros-args --params-file config/lumbar_brace.yaml``

The math is :class:`~brace_control.interaction.AdmittanceController` (equations (1), (2)
there); docs/interaction.md explains the choice of ``interaction.mass`` / ``damping``.

* subscribes ``/brace/wrench`` (``WrenchStamped``, kinetics_node's load-aware estimate of
  the wrench the brace applies on the body, ``platform_frame``): the measured ``W``;
* subscribes ``/brace/pose`` (the estimated pose: where the mode starts) and
  ``/brace/joint_states`` (the actuator forces: the soft force limit);
* subscribes ``/brace/wrench_goal`` (``WrenchStamped`` in ``base_frame`` or ``platform_frame``):
  the wrench the brace shall apply on the body. Hybrid control: only the pose axes marked
  in ``interaction.force_axes`` follow a wrench; the others hold the pose they had when the
  mode started (a goal with a nonzero component on a held axis is rejected). Without a goal
  (and after ``~/start``) the goal is zero: the zero-torque mode. A goal is rejected when it
  exceeds the mechanism's wrench capacity at the current pose or
  ``interaction.max_goal_wrench``; the previous goal stays;
* publishes ``/brace/pose_setpoint`` (``PoseStamped``, ``base_frame``) at
  ``interaction.rate_hz`` while the mode runs: the stream ik_node turns into actuator
  setpoints, which the driver tracks path-synchronously (one scale for all axes);
* services ``~/start`` and ``~/stop`` (``std_srvs/Trigger``). ``~/start`` needs the drives
  enabled and a fresh pose and wrench estimate; it starts from the estimated pose with zero
  velocity (the driver's stream takes over from its command continuously). ``~/stop`` (and
  any limit) decelerates the virtual motion to rest at ``interaction.stop_deceleration``
  along its direction; the stream then ends and the driver holds;
* publishes ``/brace/goal_status`` (``DiagnosticStatus``, one message per event, like
  trajectory_node's goals): ``name`` = ``interaction_node/interaction/<n>`` with ``message``
  ``started`` | ``rejected`` | ``stopping`` | ``stopped`` | ``aborted`` (a limit: the reason);
  ``name`` = ``interaction_node/wrench_goal/<n>`` with ``accepted`` | ``rejected``.
  ``values``: ``state``, ``reason``, ``pose``, ``goal``;
* position goals and interaction do not fight: a ``/brace/pose_goal`` or ``/brace/pose_path``
  arriving while the mode runs stops the mode first (``aborted``: "a position goal
  arrived"): its stream ends, and the driver splices the goal's planned motion onto the
  command as it is (continuous position, velocity, acceleration). No edit of
  trajectory_node is needed, and an operator's position goal always wins;
* the mode also stops when the drives leave the enabled state, when ``/brace/wrench`` is
  older than ``interaction.wrench_timeout`` (a lost estimate must not drive the brace), or
  at a limit (:mod:`brace_control.interaction.admittance`).
"""
from __future__ import annotations

import itertools
import math
import threading
import time
from collections.abc import Sequence

import numpy as np
from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import PoseStamped, WrenchStamped
from nav_msgs.msg import Path
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger

from ..interaction import AdmittanceController, AdmittanceParams, GoalRejected, LimitStop, Mode
from ..mechanisms import UnreachablePose, mechanism_from_config
from . import topics
from .diagnostics import OK, WARN, NodeDiagnostics
from .msgs import (MalformedMessage, now_stamp, pose_from_msg, pose_kind, pose_msg,
                   status_msg, status_values)
from .params import declare_device_parameters
from .runner import run_node
from .timers import timer_callback

__all__ = ['InteractionNode', 'main', 'wrench_in_pose_axes']

#: s: a pose estimate older than this cannot start the mode
FRESH_S = 0.2


def wrench_in_pose_axes(msg: WrenchStamped, *, kind: str, theta: float, base_frame: str,
                        platform_frame: str) -> np.ndarray:
    """A ``WrenchStamped`` -> the components conjugate to the pose coordinates.

    ``planar``: ``(Fx, Fy, Mz)`` with the force in the base frame (a platform-frame force is
    rotated by ``R(theta)``); ``xy``: ``(Fx, Fy)``; ``path``: ``(Fx,)``; ``spherical``:
    ``(Mx, My, Mz)``.

    :raises MalformedMessage: another frame, or a non-finite component.
    """
    frame = msg.header.frame_id
    if frame not in (base_frame, platform_frame):
        raise MalformedMessage(f'wrench in frame {frame!r}; expected {base_frame!r} or '
                               f'{platform_frame!r}', reason='wrong frame')
    f, t = msg.wrench.force, msg.wrench.torque
    if kind == 'spherical':
        w = np.array([t.x, t.y, t.z], dtype=float)
    elif kind == 'planar':
        w = np.array([f.x, f.y, t.z], dtype=float)
        if frame == platform_frame:
            c, s = math.cos(theta), math.sin(theta)
            w[0], w[1] = c * f.x - s * f.y, s * f.x + c * f.y
    elif kind == 'xy':
        w = np.array([f.x, f.y], dtype=float)
    else:
        w = np.array([f.x], dtype=float)
    if not np.all(np.isfinite(w)):
        raise MalformedMessage(f'wrench not finite: {w.tolist()}', reason='not finite')
    return w


class InteractionNode(Node):
    """Admittance control between ``/brace/wrench`` and ``/brace/pose_setpoint``."""

    def __init__(self, *, node_name: str = 'interaction_node', **kwargs) -> None:
        super().__init__(node_name, **kwargs)
        self.cfg = declare_device_parameters(
            self, ('mechanism', 'actuator', 'trajectory', 'safety', 'interaction'))
        self.mechanism = mechanism_from_config(self.cfg)
        self.params = AdmittanceParams.from_config(self.cfg, self.mechanism)
        self.controller = AdmittanceController(self.mechanism, self.params)
        self.base_frame: str = self.cfg['base_frame']
        self.platform_frame: str = self.cfg['platform_frame']
        self._kind = pose_kind(self.mechanism)
        self._wrench_timeout = float(self.cfg['interaction']['wrench_timeout'])
        # every callback of this node in one mutually exclusive group (the default): the
        # controller's state is touched by one callback at a time; the lock guards it
        # against the services of an in-process caller's executor as well
        self._lock = threading.Lock()
        self._pose: tuple[np.ndarray, float] | None = None
        self._wrench: tuple[np.ndarray, float] | None = None
        self._forces: np.ndarray | None = None
        self._enabled = False
        self._session = 0
        self._goal_ids = itertools.count(1)
        self._setpoint_pub = self.create_publisher(PoseStamped, topics.POSE_SETPOINT, topics.SETPOINT_QOS)
        self._status_pub = self.create_publisher(DiagnosticStatus, topics.GOAL_STATUS, topics.STATUS_QOS)
        self.create_subscription(WrenchStamped, topics.WRENCH, self._on_wrench, topics.MEASURED_QOS)
        self.create_subscription(PoseStamped, topics.POSE, self._on_pose, topics.MEASURED_QOS)
        self.create_subscription(JointState, topics.JOINT_STATES, self._on_joint_states,
                                 topics.MEASURED_QOS)
        self.create_subscription(WrenchStamped, topics.WRENCH_GOAL, self._on_goal, topics.GOAL_QOS)
        self.create_subscription(DiagnosticStatus, topics.DRIVER_STATE, self._on_driver_state,
                                 topics.LATCHED_QOS)
        self.create_subscription(PoseStamped, topics.POSE_GOAL, self._on_position_goal, topics.GOAL_QOS)
        self.create_subscription(Path, topics.POSE_PATH, self._on_position_goal, topics.GOAL_QOS)
        self.create_service(Trigger, '~/start', self._on_start)
        self.create_service(Trigger, '~/stop', self._on_stop)
        self._timer = self.create_timer(self.params.dt, timer_callback(self._on_timer))
        self._timer.cancel()                       # runs only while the mode runs
        self.diagnostics = NodeDiagnostics(self, f'brace_control/{node_name}')
        self.diagnostics.set(OK, 'position mode (interaction idle)', mode='idle')
        axes = ''.join('F' if a else 'P' for a in self.params.force_axes)
        self.get_logger().info(
            f'admittance M={self.params.mass.tolist()} D={self.params.damping.tolist()} '
            f'axes {axes} (F force, P position) at {1.0 / self.params.dt:g} Hz: '
            f'{topics.WRENCH} -> {topics.POSE_SETPOINT}; call ~/start')

    # ------------------------------------------------------------------ inputs
    def _on_wrench(self, msg: WrenchStamped) -> None:
        theta = float(self._pose[0][2]) if (self._pose is not None and self._kind == 'planar') else 0.0
        try:
            w = wrench_in_pose_axes(msg, kind=self._kind, theta=theta, base_frame=self.base_frame,
                                    platform_frame=self.platform_frame)
        except MalformedMessage as exc:
            self.get_logger().warning(f'measured wrench ignored: {exc}', throttle_duration_sec=1.0)
            return
        self._wrench = (w, time.monotonic())

    def _on_pose(self, msg: PoseStamped) -> None:
        try:
            self._pose = (pose_from_msg(msg, frame_id=self.base_frame, mechanism=self.mechanism),
                          time.monotonic())
        except MalformedMessage as exc:
            self.get_logger().warning(f'pose estimate ignored: {exc}', throttle_duration_sec=1.0)

    def _on_joint_states(self, msg: JointState) -> None:
        if len(msg.effort) == self.mechanism.n_actuators:
            self._forces = np.asarray(msg.effort, dtype=float)

    def _on_driver_state(self, msg: DiagnosticStatus) -> None:
        self._enabled = status_values(msg).get('enabled') == 'true'
        if not self._enabled:
            with self._lock:
                if self.controller.mode is Mode.ACTIVE:
                    # the driver stopped: nothing to decelerate, the drives hold or are off
                    self.controller.mode = Mode.IDLE
                    self._end('aborted', f'the drives left the enabled state: {msg.message}')

    def _on_position_goal(self, msg: object) -> None:
        with self._lock:
            if self.controller.mode is not Mode.IDLE:
                # the goal's motion replaces the stream in the driver, continuously from the
                # command as it is: the stream ends now
                self.controller.mode = Mode.IDLE
                self._timer.cancel()
                self._end('aborted', 'a position goal arrived: interaction stops, the goal takes over')

    def _on_goal(self, msg: WrenchStamped) -> None:
        gid = next(self._goal_ids)
        name = f'{self.get_name()}/wrench_goal/{gid}'
        with self._lock:
            theta = float(self.controller.x[2]) if self._kind == 'planar' else 0.0
            try:
                w = wrench_in_pose_axes(msg, kind=self._kind, theta=theta, base_frame=self.base_frame,
                                        platform_frame=self.platform_frame)
                self.controller.set_goal(w)
            except (MalformedMessage, GoalRejected) as exc:
                self._status_pub.publish(status_msg(name, 'rejected', level=DiagnosticStatus.WARN,
                                                    state='rejected', reason=str(exc)))
                self.get_logger().warning(f'wrench goal {gid} rejected: {exc}')
                return
        self._status_pub.publish(status_msg(name, 'accepted', state='accepted', reason='',
                                            goal=w.tolist(), mode=self.controller.mode.value))

    # ------------------------------------------------------------------ services
    def _on_start(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        now = time.monotonic()
        with self._lock:
            why = ''
            if self.controller.mode is not Mode.IDLE:
                why = f'interaction is already {self.controller.mode.value}'
            elif not self._enabled:
                why = 'the drives are not enabled (call /can_driver_node/enable)'
            elif self._pose is None or now - self._pose[1] > FRESH_S:
                why = f'no pose estimate on {topics.POSE} within {FRESH_S} s'
            elif self._wrench is None or now - self._wrench[1] > self._wrench_timeout:
                why = f'no wrench estimate on {topics.WRENCH} within {self._wrench_timeout} s'
            elif not np.any(self.params.force_axes):
                why = 'interaction.force_axes selects no axis'
            if not why:
                try:
                    self.controller.start(self._pose[0])
                except (UnreachablePose, ValueError) as exc:
                    why = f'the estimated pose cannot start the mode: {exc}'
            self._session += 1
            name = f'{self.get_name()}/interaction/{self._session}'
            if why:
                self._status_pub.publish(status_msg(name, 'rejected', level=DiagnosticStatus.WARN,
                                                    state='rejected', reason=why))
                response.success, response.message = False, why
                return response
            self._status_pub.publish(status_msg(name, 'started', state='started', reason='',
                                                pose=self.controller.x.tolist(),
                                                goal=self.controller.goal.tolist()))
            self.diagnostics.set(OK, 'interaction active', mode='active')
            self._timer.reset()
        response.success, response.message = True, f'interaction {self._session} started'
        return response

    def _on_stop(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        with self._lock:
            if self.controller.mode is not Mode.ACTIVE:
                response.success = True
                response.message = f'interaction is {self.controller.mode.value}'
                return response
            self._begin_stop('stopped', 'stop requested')
        response.success, response.message = True, 'decelerating to rest'
        return response

    # ------------------------------------------------------------------ the period
    def _on_timer(self) -> None:
        with self._lock:
            mode = self.controller.mode
            if mode is Mode.IDLE:
                self._timer.cancel()
                return
            now = time.monotonic()
            if mode is Mode.ACTIVE and (self._wrench is None or now - self._wrench[1] > self._wrench_timeout):
                self._begin_stop('aborted', f'no wrench estimate on {topics.WRENCH} for '
                                 f'{self._wrench_timeout} s')
            try:
                x, v = self.controller.step(self._wrench[0] if self._wrench else np.zeros(self.controller.dof),
                                            self._forces)
            except LimitStop as exc:
                self._announce_stop('aborted', exc.reason)
                x, v = self.controller.x.copy(), self.controller.v.copy()
            self._setpoint_pub.publish(pose_msg(x, frame_id=self.base_frame, stamp=now_stamp(self),
                                                mechanism=self.mechanism))
            if self.controller.velocity_limited:
                self.diagnostics.set(WARN, 'interaction: virtual velocity limited by the actuator '
                                     'speed', velocity_limited=self.controller.velocity_limited)
            if self.controller.mode is Mode.IDLE:
                self._timer.cancel()
                self._end(self._stop_kind, self.controller.stop_reason)

    def _begin_stop(self, kind: str, reason: str) -> None:
        self.controller.stop(reason)
        self._announce_stop(kind, reason)

    def _announce_stop(self, kind: str, reason: str) -> None:
        self._stop_kind = kind
        name = f'{self.get_name()}/interaction/{self._session}'
        self._status_pub.publish(status_msg(name, 'stopping', level=DiagnosticStatus.OK,
                                            state='stopping', reason=reason, kind=kind,
                                            pose=self.controller.x.tolist()))
        if kind == 'aborted':
            self.get_logger().warning(f'interaction {self._session} stops: {reason}')

    def _end(self, kind: str, reason: str) -> None:
        name = f'{self.get_name()}/interaction/{self._session}'
        level = DiagnosticStatus.ERROR if kind == 'aborted' else DiagnosticStatus.OK
        self._status_pub.publish(status_msg(name, kind, level=level, state=kind, reason=reason,
                                            pose=self.controller.x.tolist()))
        self.diagnostics.set(WARN if kind == 'aborted' else OK,
                             f'position mode (interaction {kind}: {reason})', mode='idle')

    _stop_kind = 'stopped'


def main(args: Sequence[str] | None = None) -> int:
    return run_node(InteractionNode, executable='interaction_node', args=args,
                    summary='admittance control: /brace/wrench, /brace/wrench_goal -> /brace/pose_setpoint')


if __name__ == '__main__':
    raise SystemExit(main())
