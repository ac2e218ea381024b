"""interaction_node: the lumbar paper's zero-torque mode and wrench goals, the user-facing side.

``ros2 run brace_control interaction_node --ros-args --params-file config/lumbar_brace.yaml``

The admittance itself (:class:`~brace_control.interaction.AdmittanceController`, equations
(1), (2) there) runs **inside the CAN driver's SYNC cycle**
(:mod:`brace_control.interaction.inloop`): the load cells of one SYNC move the command of
the next, a loop delay of two SYNC periods instead of the 16-47 ms through ROS
(docs/interaction.md, "Delay"). This node has one job: the mode and its policy.

* services ``~/start`` and ``~/stop`` (``std_srvs/Trigger``). ``~/start`` needs the drives
  enabled and at rest; the driver's admittance starts from its command with zero velocity
  and zero goal (zero-torque mode) through ``/can_driver_node/interaction_start``.
  ``~/stop`` (and any limit) decelerates the virtual motion to rest at
  ``interaction.stop_deceleration`` along its direction; then the driver holds;
* subscribes ``/brace/wrench_goal`` (``WrenchStamped`` in ``base_frame`` or
  ``platform_frame``): the wrench the brace shall apply on the body, while the mode runs.
  Hybrid control: only the pose axes marked in ``interaction.force_axes`` follow a
  wrench; the others hold (a goal with a nonzero component on a held axis is rejected),
  as is a goal above ``interaction.max_goal_wrench`` or the wrench capacity at the
  estimated pose (``/brace/pose``); the previous goal stays. An accepted goal goes to the
  driver on ``/brace/interaction/goal`` in the pose axes' components (the driver checks
  it again at its own pose: a rejection there is reported too);
* subscribes ``/brace/execution_status``: the driver's in-cycle events
  (``can_driver_node/interaction/<n>``: started, stopping, stopped, aborted, preempted,
  goal_applied, goal_rejected) become this node's goal statuses;
* publishes ``/brace/goal_status`` (``DiagnosticStatus``, one message per event, like
  trajectory_node's goals): ``name`` = ``interaction_node/interaction/<n>`` with ``message``
  ``started`` | ``rejected`` | ``stopping`` | ``stopped`` | ``aborted`` (a limit, a halt, a
  fault, the drives disabled, or a position goal that took over: the reason);
  ``name`` = ``interaction_node/wrench_goal/<n>`` with ``accepted`` (this node checked it
  and sent it), then ``applied`` (the driver's cycle has it; ``applied_ns``: the wall clock
  then, what a step response is timed from) or ``rejected`` (here, or by the driver at its
  own pose: "the driver: ..."). ``values``: ``state``, ``reason``, ``goal``;
* position goals and interaction do not fight: trajectory_node, given a goal while the
  mode runs, has the driver end it (an empty trajectory: the virtual motion brakes to
  rest, ``aborted``: "a position goal arrived") and plans the goal from the positions the
  driver reports then (docs/interaction.md, "Conventions"). A motion that reaches the
  driver during interaction anyway replaces it continuously (``aborted``: "a position goal
  took over"). An operator's position goal always wins.
"""
from __future__ import annotations

import itertools
import math
import threading
from collections.abc import Sequence

import numpy as np
from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import PoseStamped, WrenchStamped
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.node import Node
from rclpy.serialization import deserialize_message
from std_srvs.srv import Trigger

from ..interaction import AdmittanceController, AdmittanceParams, GoalRejected
from ..mechanisms import mechanism_from_config
from . import topics
from .diagnostics import OK, WARN, NodeDiagnostics
from .msgs import (MalformedMessage, now_stamp, pose_from_msg, pose_kind, stamp_to_ns, status_msg,
                   status_values)
from .params import declare_device_parameters
from .runner import run_node

__all__ = ['InteractionNode', 'main', 'wrench_in_pose_axes']

#: the wrench goals whose driver events this node still names (the newest; a goal's
#: ``applied`` or driver ``rejected`` comes within one executor pass of the driver's)
GOALS_KEPT = 64


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
    """The mode, its goals and its events; the admittance runs in the driver's cycle."""

    def __init__(self, *, node_name: str = 'interaction_node', driver: str = 'can_driver_node',
                 **kwargs) -> None:
        super().__init__(node_name, **kwargs)
        self.cfg = declare_device_parameters(
            self, ('mechanism', 'actuator', 'trajectory', 'safety', 'interaction'), cli_args=kwargs.get('cli_args'))
        self.mechanism = self.cfg.model or mechanism_from_config(self.cfg)
        self.params = AdmittanceParams.from_config(self.cfg, self.mechanism)
        #: the goal checks (held axes, max_goal_wrench, capacity at the estimated pose)
        self.checker = AdmittanceController(self.mechanism, self.params)
        self.base_frame: str = self.cfg['base_frame']
        self.platform_frame: str = self.cfg['platform_frame']
        self._kind = pose_kind(self.mechanism)
        self._driver = driver
        self._lock = threading.Lock()
        #: the latest /brace/pose as CDR bytes: converted only when a goal needs it (a 100 Hz
        #: stream deserialised and checked on every message cost ~5 % of a core at rest)
        self._pose_cdr: bytes | None = None
        self._enabled = False
        self._active = False
        self._session = 0
        self._goal_ids = itertools.count(1)
        self._last_goal_name = ''
        #: the goals sent to the driver, by the stamp of the message sent (the driver's events
        #: name a goal by it), the newest GOALS_KEPT
        self._goal_names: dict[int, str] = {}
        self._status_pub = self.create_publisher(DiagnosticStatus, topics.GOAL_STATUS, topics.GOAL_STATUS_QOS)
        self._goal_pub = self.create_publisher(WrenchStamped, topics.INTERACTION_GOAL, topics.GOAL_QOS)
        self.create_subscription(PoseStamped, topics.POSE, self._on_pose, topics.MEASURED_QOS, raw=True)
        self.create_subscription(WrenchStamped, topics.WRENCH_GOAL, self._on_goal, topics.GOAL_QOS)
        self.create_subscription(DiagnosticStatus, topics.DRIVER_STATE, self._on_driver_state,
                                 topics.LATCHED_QOS)
        self.create_subscription(DiagnosticStatus, topics.EXECUTION_STATUS, self._on_execution,
                                 topics.STATUS_QOS)
        clients = ReentrantCallbackGroup()
        self._start_client = self.create_client(Trigger, f'/{driver}/interaction_start', callback_group=clients)
        self._stop_client = self.create_client(Trigger, f'/{driver}/interaction_stop', callback_group=clients)
        services = MutuallyExclusiveCallbackGroup()
        self.create_service(Trigger, '~/start', self._on_start, callback_group=services)
        self.create_service(Trigger, '~/stop', self._on_stop, callback_group=services)
        self.diagnostics = NodeDiagnostics(self, f'brace_control/{node_name}')
        self.diagnostics.set(OK, 'position mode (interaction idle)', mode='idle')
        axes = ''.join('F' if a else 'P' for a in self.params.force_axes)
        self.get_logger().info(
            f'admittance M={self.params.mass.tolist()} D={self.params.damping.tolist()} '
            f'axes {axes} (F force, P position), in {driver}\'s SYNC cycle; call ~/start')

    # ------------------------------------------------------------------ inputs
    def _on_pose(self, cdr: bytes) -> None:
        self._pose_cdr = cdr

    def _estimated_pose(self) -> np.ndarray:
        """The latest pose estimate, in the mechanism's pose coordinates; GoalRejected
        naming what is wrong when there is none or it is malformed."""
        if self._pose_cdr is None:
            raise GoalRejected(f'no pose estimate on {topics.POSE}: the capacity cannot be checked')
        msg = deserialize_message(self._pose_cdr, PoseStamped)
        try:
            return pose_from_msg(msg, frame_id=self.base_frame, mechanism=self.mechanism)
        except MalformedMessage as exc:
            raise GoalRejected(f'the pose estimate on {topics.POSE} is unusable: {exc}') from exc

    def _on_driver_state(self, msg: DiagnosticStatus) -> None:
        self._enabled = status_values(msg).get('enabled') == 'true'

    def _on_goal(self, msg: WrenchStamped) -> None:
        gid = next(self._goal_ids)
        name = f'{self.get_name()}/wrench_goal/{gid}'
        with self._lock:
            try:
                if not self._active:
                    raise GoalRejected('interaction is not running: call ~/start first')
                pose = self._estimated_pose()
                theta = float(pose[2]) if self._kind == 'planar' else 0.0
                w = wrench_in_pose_axes(msg, kind=self._kind, theta=theta, base_frame=self.base_frame,
                                        platform_frame=self.platform_frame)
                self.checker.x = np.asarray(pose, dtype=float)
                self.checker.set_goal(w)
            except (MalformedMessage, GoalRejected) as exc:
                self._status_pub.publish(status_msg(name, 'rejected', level=DiagnosticStatus.WARN,
                                                    state='rejected', reason=str(exc)))
                self.get_logger().warning(f'wrench goal {gid} rejected: {exc}')
                return
            self._last_goal_name = name
            out = WrenchStamped()
            out.header.stamp = now_stamp(self)
            self._goal_names[stamp_to_ns(out.header.stamp)] = name
            if len(self._goal_names) > GOALS_KEPT:
                del self._goal_names[next(iter(self._goal_names))]
        out.header.frame_id = self.base_frame
        comp = [float(c) for c in w]
        if self._kind == 'spherical':
            out.wrench.torque.x, out.wrench.torque.y, out.wrench.torque.z = comp
        elif self._kind == 'planar':
            out.wrench.force.x, out.wrench.force.y, out.wrench.torque.z = comp
        elif self._kind == 'xy':
            out.wrench.force.x, out.wrench.force.y = comp
        else:
            out.wrench.force.x = comp[0]
        # 'accepted' first: the driver's answer ('applied', 'rejected') may come back in another
        # thread as soon as the goal is out
        self._status_pub.publish(status_msg(name, 'accepted', state='accepted', reason='',
                                            goal=list(comp), mode='active'))
        self._goal_pub.publish(out)

    def _on_execution(self, msg: DiagnosticStatus) -> None:
        """The driver's in-cycle interaction events -> this node's goal statuses."""
        if not msg.name.startswith(f'{self._driver}/interaction/'):
            return
        values = status_values(msg)
        reason = values.get('reason', '')
        kind = msg.message
        with self._lock:
            if kind in ('goal_applied', 'goal_rejected'):
                try:
                    name = self._goal_names.get(int(values.get('goal_stamp', '')), self._last_goal_name)
                except ValueError:                  # a driver that does not say which goal
                    name = self._last_goal_name
                if not name:
                    return
                if kind == 'goal_rejected':
                    self._status_pub.publish(status_msg(name, 'rejected', level=DiagnosticStatus.WARN,
                                                        state='rejected', reason=f'the driver: {reason}'))
                else:
                    self._status_pub.publish(status_msg(name, 'applied', state='applied', reason='',
                                                        goal=values.get('goal', ''),
                                                        applied_ns=values.get('applied_ns', '')))
                return
            if kind == 'stopping':
                self._publish('stopping', reason)
                return
            if kind not in ('stopped', 'aborted', 'preempted') or not self._active:
                return
            self._active = False
            if kind == 'preempted':
                kind, reason = 'aborted', f'a position goal took over: {reason}'
            self._publish(kind, reason)
            self.diagnostics.set(WARN if kind == 'aborted' else OK,
                                 f'position mode (interaction {kind}: {reason})', mode='idle')
            if kind == 'aborted':
                self.get_logger().warning(f'interaction {self._session} {kind}: {reason}')

    def _publish(self, event: str, reason: str, **values: object) -> None:
        name = f'{self.get_name()}/interaction/{self._session}'
        level = DiagnosticStatus.ERROR if event == 'aborted' else (
            DiagnosticStatus.WARN if event == 'rejected' else DiagnosticStatus.OK)
        self._status_pub.publish(status_msg(name, event, level=level, state=event, reason=reason, **values))

    # ------------------------------------------------------------------ services
    async def _on_start(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        with self._lock:
            self._session += 1
            why = ''
            if self._active:
                why = 'interaction is already running'
            elif not self._enabled:
                why = 'the drives are not enabled (call /can_driver_node/enable)'
            elif not np.any(self.params.force_axes):
                why = 'interaction.force_axes selects no axis'
            elif not self._start_client.service_is_ready():
                why = f'the driver\'s /{self._driver}/interaction_start is not available'
        if not why:
            result = await self._start_client.call_async(Trigger.Request())
            if not result.success:
                why = f'the driver: {result.message}'
        with self._lock:
            if why:
                self._publish('rejected', why)
                response.success, response.message = False, why
                return response
            self._active = True
            self._publish('started', '', detail=result.message)
            self.diagnostics.set(OK, 'interaction active', mode='active')
        response.success, response.message = True, f'interaction {self._session} started ({result.message})'
        return response

    async def _on_stop(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        if not self._active:
            response.success, response.message = True, 'interaction is idle'
            return response
        result = await self._stop_client.call_async(Trigger.Request())
        response.success, response.message = result.success, result.message
        return response


def main(args: Sequence[str] | None = None) -> int:
    return run_node(InteractionNode, executable='interaction_node', args=args,
                    summary='zero-torque mode and wrench goals: the admittance in the CAN driver\'s cycle')


if __name__ == '__main__':
    raise SystemExit(main())
