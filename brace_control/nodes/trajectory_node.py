"""trajectory_node: pose goals and paths -> one planned motion each, and each goal's honest outcome.

``ros2 run brace_control trajectory_node --ros-args --params-file config/lumbar_brace.yaml``

Topics and services (all in the device's ``base_frame``):

* ``/brace/pose_goal`` (``geometry_msgs/PoseStamped``): go to this pose. The goal
  carries no duration: Fitts' law (``trajectory.fitts_*``) gives it for the
  minimum-jerk and log-cosh profiles, the S-curve is time-optimal.
* ``/brace/pose_path`` (``nav_msgs/Path``, at most ``trajectory.max_path_poses`` poses):
  pass the intermediate poses (via points) and stop at the last. Each pose's
  ``header.stamp`` is its arrival time counted from the path's ``header.stamp`` (t = 0 is
  the start of the motion; absolute stamps with header = now, or relative ones with
  header = 0, both work). All pose stamps zero: no timing (Fitts' law on the path length,
  optimal via times). Stamps must increase. The path's ``header.frame_id`` must be the
  base frame; a pose's own frame_id must be the base frame too, or empty.
* ``/brace/pose_trajectory`` (``trajectory_msgs/MultiDOFJointTrajectory``): each planned
  motion, once, whole (pose knots, :mod:`.msgs`), ``header.stamp`` = when it takes over
  (``trajectory.plan_lookahead``, 0.15 s by default, after planning began; the driver
  samples it in its SYNC loop).
  ``~/cancel`` publishes an empty one with the running motion's stamp: the driver then
  decelerates along the path and holds. The node runs no periodic timer while idle.
* ``/brace/goal_status`` (``diagnostic_msgs/DiagnosticStatus``, reliable, depth 200): one
  message per goal event. ``name`` = ``trajectory_node/goal/<id>``; ``message`` = the
  state (``accepted``, then exactly one of ``succeeded``, ``rejected``, ``aborted``,
  ``cancelled``; a goal that ends before it was planned gets ``accepted`` first too, so
  every goal's first event is ``accepted`` or ``rejected``); ``level`` OK (accepted,
  succeeded), WARN (rejected, cancelled), ERROR (aborted); ``values``: ``goal_id``,
  ``state``, ``reason``, ``stamp`` (the goal message's header stamp, ns), ``source``
  (``pose_goal`` or ``pose_path``), ``profile``, ``duration`` (s), ``target``, ``time``
  (when the node decided the event, ns of its ROS clock: a reader served late still knows
  when a goal ended), and where known ``final_error`` (per pose coordinate) and
  ``min_wrench_capacity``.
* ``~/cancel`` (``std_srvs/Trigger``): decelerate to rest along the path and hold.

How a goal ends (docs/safety.md §12, §16; :class:`~brace_control.trajectory.TrajectoryRunner`):
it is rejected while the drives are not enabled (``/brace/driver_state``, latched) and when
it cannot be planned within the limits; it succeeds only when the driver reported its
motion finished (``/brace/execution_status``) and the estimated pose (``/brace/pose``,
load aware) came within ``safety.pose_tolerance`` of the goal; it is aborted when the driver
rejected or stopped the motion, when the drives left the enabled state (the driver's
reason), when the platform did not follow (by how much), or when the stack shut down.

Goals arriving faster than they can be planned coalesce: the newest is planned, each one it
superseded is reported ``cancelled: superseded by goal N``. The goal subscriptions keep all
samples (no depth can drop one). A new goal preempts the running one from the state the
running motion has ``trajectory.plan_lookahead`` after the goal arrived (continuous position,
velocity, acceleration). All math is in :mod:`brace_control.trajectory`.

Late splices: a preempting motion that reaches the driver after its takeover time while the
brace moves (a loaded host delays the two DDS hops past the lookahead) no longer starts where
the running command is; the driver refuses it ("more than the splice tolerance; the running
motion continues"). Its goal is then planned again from the motion that goes on (a second
``accepted`` event), up to ``LATE_SPLICE_REPLANS`` times; only then is it aborted with the
driver's reason. When a newer goal waits, the refused goal is cancelled, superseded by it (the
newer goal is planned from the motion that goes on): in a goal flood on a loaded host a refused
goal about to be replaced was reported aborted (run 902).
"""
from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Sequence

import numpy as np
from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.serialization import deserialize_message
from std_srvs.srv import Trigger
from trajectory_msgs.msg import MultiDOFJointTrajectory

from ..can.units import scaling_from_config
from ..control.execution import SPLICE_REFUSED
from ..config import ConfigError
from ..schema import SCHEMA
from ..mechanisms import mechanism_from_config
from ..trajectory import (FittsLaw, GoalEvent, GoalRequest, GoalState, Limits, PlanRejected,
                          PoseError, Profile, TrajectoryError, TrajectoryRunner, arrival_times,
                          knots_of, load_planning_modules)
from . import topics
from .diagnostics import ERROR, OK, WARN, NodeDiagnostics
from .msgs import (MalformedMessage, ns_to_stamp, pose_from_msg, pose_kind, pose_trajectory_msg,
                   stamp_to_ns, stamp_to_sec, status_msg, status_values)
from .params import declare_device_parameters
from .runner import run_node

__all__ = ['TrajectoryNode', 'main']

#: s from the start of planning to the motion taking over (planning, IK and two DDS hops
#: must fit in it for an exact splice; a late motion is blended in by the driver): the
#: default of ``trajectory.plan_lookahead`` (defined in the schema only)
PLAN_LOOKAHEAD_S = float(SCHEMA['trajectory.plan_lookahead'].default)
#: s a goal waits for a cancelled motion to finish braking before it is planned
STOPPING_WAIT_S = 3.0
#: Hz of the timeout checks while a goal is active (none while idle)
CHECK_RATE_HZ = 20.0
#: s the node waits at shutdown until its last goal statuses are acknowledged (at once when
#: every reader has them; 1 s was too short for a recorder a loaded host served late: the
#: interaction demo's bag once lost its last goal's success, run 712)
SHUTDOWN_ACK_S = 3.0
#: times a goal is planned again after the driver refused its motion's splice
LATE_SPLICE_REPLANS = 2

_LEVEL = {GoalState.ACCEPTED: OK, GoalState.SUCCEEDED: OK, GoalState.REJECTED: WARN,
          GoalState.CANCELLED: WARN, GoalState.ABORTED: ERROR}


class TrajectoryNode(Node):
    """Goals in, planned motions out, outcomes reported (see the module docstring)."""

    def __init__(self, *, node_name: str = 'trajectory_node', **kwargs) -> None:
        super().__init__(node_name, **kwargs)
        self.cfg = declare_device_parameters(self, ('mechanism', 'trajectory', 'actuator', 'safety'), cli_args=kwargs.get('cli_args'))
        self.mechanism = self.cfg.model or mechanism_from_config(self.cfg)
        self.base_frame: str = self.cfg['base_frame']
        self.platform_frame: str = self.cfg['platform_frame']
        traj = self.cfg['trajectory']
        safety = self.cfg['safety']
        self.profile = Profile(traj['profile'])
        self.max_path_poses = int(traj['max_path_poses'])
        self.planning_budget = float(traj['planning_budget'])
        self.plan_lookahead = float(traj['plan_lookahead'])
        kind = pose_kind(self.mechanism)
        try:
            limits = Limits.from_config(self.cfg, dof=self.mechanism.dof)
            tolerance = np.asarray(safety['pose_tolerance'], dtype=float).reshape(-1)
            if tolerance.size == 1:
                tolerance = np.full(self.mechanism.dof, tolerance[0])
            if tolerance.size != self.mechanism.dof or not np.all(tolerance > 0):
                raise ValueError(f'safety.pose_tolerance needs {self.mechanism.dof} positive values '
                                 f'(one per pose coordinate), got {tolerance.tolist()}')
        except ValueError as exc:
            raise ConfigError(str(exc)) from exc
        self.runner = TrajectoryRunner(
            self.mechanism, limits, profile=self.profile,
            fitts=FittsLaw(a=traj['fitts_a'], b=traj['fitts_b'], w=traj['fitts_w']),
            fitts_axes=(0, 1) if kind in ('planar', 'xy') else None,
            lookahead=self.plan_lookahead, pose_tolerance=tolerance,
            settle_time=float(safety['settle_time']), report_timeout=float(safety['report_timeout']),
            # the success margin for what the encoders cannot resolve (TrajectoryRunner)
            actuator_resolution=1.0 / scaling_from_config(self.cfg).counts_per_unit)
        # The runner is shared by the executor thread (subscriptions, service, timer) and the
        # planner thread: every runner call holds this lock; planning itself runs outside it.
        self._lock = threading.Lock()
        self._report_lock = threading.Lock()
        self._pending: tuple[GoalRequest, dict] | None = None
        #: the request of the newest goal whose motion went to the driver, and per goal id
        #: how often it was planned again after a refused splice ("Late splices")
        self._committed: GoalRequest | None = None
        self._replans: dict[str, int] = {}
        self._wake = threading.Condition(self._lock)
        self._closing = False
        self._meta: dict[str, dict] = {}          # goal id -> its stamp and source
        self._next_id = 1
        self._last_tag = 0
        self._measured: tuple[np.ndarray, float] | None = None
        self._clock_offset_ns = self.get_clock().now().nanoseconds - round(time.monotonic() * 1e9)
        self.counts = {s.value: 0 for s in GoalState}
        self.last_planning_ms = float('nan')

        self._traj_pub = self.create_publisher(MultiDOFJointTrajectory, topics.POSE_TRAJECTORY,
                                               topics.TRAJECTORY_QOS)
        self._status_pub = self.create_publisher(DiagnosticStatus, topics.GOAL_STATUS, topics.GOAL_STATUS_QOS)
        # raw: a goal whose bytes do not deserialise (a corrupted bag, a foreign publisher)
        # still gets its goal id and a rejected status saying why (rclpy would drop it unseen)
        self.create_subscription(PoseStamped, topics.POSE_GOAL, self._raw(PoseStamped, self._on_goal, 'pose_goal'),
                                 topics.GOAL_QOS, raw=True)
        self.create_subscription(Path, topics.POSE_PATH, self._raw(Path, self._on_path, 'pose_path'),
                                 topics.GOAL_QOS, raw=True)
        self.create_subscription(PoseStamped, topics.POSE, self._on_estimate, topics.MEASURED_QOS)
        self._exec_sub = self.create_subscription(DiagnosticStatus, topics.EXECUTION_STATUS, self._on_execution,
                                 topics.STATUS_QOS)
        self.create_subscription(DiagnosticStatus, topics.DRIVER_STATE, self._on_driver_state,
                                 topics.LATCHED_QOS)
        self.create_service(Trigger, '~/cancel', self._on_cancel)
        self._timer = self.create_timer(1.0 / CHECK_RATE_HZ, self._on_timer)
        self._timer.cancel()                      # runs only while a goal is active
        self._planner = threading.Thread(target=self._planner_loop, name='trajectory_plan',
                                         daemon=True)
        self._planner.start()
        self.diagnostics = NodeDiagnostics(self, f'brace_control/{node_name}')
        self.diagnostics.watch(self._traj_pub)
        # the driver's and the ik node's reports: a 'started' missed while unmatched is a goal
        # aborted as "did not start" (bringup.wait_until_ready waits for both)
        self.diagnostics.watch_subscription(self._exec_sub)
        self.diagnostics.prompt('driver')          # the driver's state, as goals are judged
        self.diagnostics.set(OK, 'idle: waiting for a goal', profile=self.profile.value)
        self.get_logger().info(
            f'{type(self.mechanism).__name__}, profile {self.profile.value}: '
            f'{topics.POSE_GOAL}, {topics.POSE_PATH} -> {topics.POSE_TRAJECTORY} in {self.base_frame!r}')

    # ------------------------------------------------------------------ goals in
    def _new_id(self) -> str:
        gid = str(self._next_id)
        self._next_id += 1
        return gid

    def _raw(self, msg_type: type, handler, source: str):
        """A callback taking the serialised goal: deserialised here, or rejected with why."""
        def on_bytes(data: bytes) -> None:
            try:
                msg = deserialize_message(data, msg_type)
            except Exception as exc:  # noqa: BLE001 - the CDR decoder raises several kinds
                gid = self._new_id()
                self._meta[gid] = {'stamp': 0, 'source': source}
                why = (f'malformed goal: its {len(data)} bytes are not a {msg_type.__name__} '
                       f'(CDR): {exc}')
                self._report([GoalEvent(gid, GoalState.REJECTED, why)])
                return
            handler(msg)
        return on_bytes

    def _on_goal(self, msg: PoseStamped) -> None:
        gid = self._new_id()
        self._meta[gid] = {'stamp': stamp_to_ns(msg.header.stamp), 'source': 'pose_goal'}
        try:
            target = pose_from_msg(msg, frame_id=self.base_frame, mechanism=self.mechanism)
        except MalformedMessage as exc:
            self._report([GoalEvent(gid, GoalState.REJECTED, f'malformed goal: {exc}')])
            return
        self._enqueue(GoalRequest(gid, target))

    def _on_path(self, msg: Path) -> None:
        gid = self._new_id()
        self._meta[gid] = {'stamp': stamp_to_ns(msg.header.stamp), 'source': 'pose_path'}
        try:
            if len(msg.poses) > self.max_path_poses:
                raise PoseError(f'{len(msg.poses)} poses, more than trajectory.max_path_poses = '
                                f'{self.max_path_poses}')
            if msg.header.frame_id != self.base_frame:
                raise MalformedMessage(f'path is in frame {msg.header.frame_id!r}, '
                                       f'expected {self.base_frame!r}', reason='frame')
            if not msg.poses:
                raise PoseError('empty path: no poses')
            # a pose with an empty frame_id is in the path's frame
            poses = [pose_from_msg(p, frame_id=self.base_frame if p.header.frame_id else None,
                                   mechanism=self.mechanism) for p in msg.poses]
            duration, t_via = arrival_times(stamp_to_sec(msg.header.stamp),
                                            [stamp_to_sec(p.header.stamp) for p in msg.poses])
        except (MalformedMessage, PoseError) as exc:
            self._report([GoalEvent(gid, GoalState.REJECTED, f'malformed path: {exc}')])
            return
        via = np.array(poses[:-1]) if len(poses) > 1 else None
        self._enqueue(GoalRequest(gid, poses[-1], via=via, t_via=t_via, duration=duration))

    def _enqueue(self, request: GoalRequest) -> None:
        """Latest goal wins: a goal still waiting to be planned is superseded."""
        with self._lock:
            events = self.runner.admit(request.goal_id)
            superseded = None
            if not events:
                superseded, self._pending = self._pending, (request, {})
                self._wake.notify_all()
        if superseded is not None:
            events = self._supersede(superseded[0].goal_id, request.goal_id) + events
        self._report(events)

    @staticmethod
    def _supersede(old: str, new: str) -> list[GoalEvent]:
        return [GoalEvent(old, GoalState.ACCEPTED, 'queued for planning'),
                GoalEvent(old, GoalState.CANCELLED, f'superseded by goal {new} before it was planned')]

    # ------------------------------------------------------------------ planning (own thread)
    def _planner_loop(self) -> None:
        # before the first goal, not in its planning time (trajectory.planning_budget)
        load_planning_modules()
        while True:
            with self._lock:
                while self._pending is None and not self._closing:
                    self._wake.wait()
                if self._closing:
                    return
                request, _ = self._pending
                self._pending = None
            try:
                events = self._plan_one(request)
                if request.goal_id in self._replans:
                    # planned again after a refused splice: it was accepted before, so a
                    # refusal now ends it as aborted (exactly one terminal state)
                    events = [GoalEvent(ev.goal_id, GoalState.ABORTED, f'planned again after its '
                                        f'splice was refused, then rejected: {ev.reason}', ev.target)
                              if ev.goal_id == request.goal_id and ev.state is GoalState.REJECTED else ev
                              for ev in events]
                self._report(events)
            except Exception as exc:  # noqa: BLE001 - a planner bug must still end the goal
                self.get_logger().error(f'goal {request.goal_id}: planning failed: {exc!r}')
                self._report([GoalEvent(request.goal_id, GoalState.ABORTED,
                                        f'internal error while planning: {exc!r}')])

    def _newer(self, request: GoalRequest) -> list[GoalEvent] | None:
        """If a newer goal is waiting, ``request`` is superseded (caller holds the lock)."""
        if self._pending is None:
            return None
        return self._supersede(request.goal_id, self._pending[0].goal_id)

    def _plan_one(self, request: GoalRequest) -> list[GoalEvent]:
        deadline = time.monotonic() + STOPPING_WAIT_S
        ended_interaction = False
        for _attempt in range(3):
            with self._lock:
                start = None
                while not self._closing:
                    newer = self._newer(request)
                    if newer is not None:
                        return newer
                    rejected = self.runner.admit(request.goal_id)
                    if rejected:
                        return rejected
                    if self._traj_pub.get_subscription_count() == 0:
                        # a plan published now would be lost (the topic keeps no history)
                        return [GoalEvent(request.goal_id, GoalState.REJECTED,
                                          f'nothing subscribes to {topics.POSE_TRAJECTORY} '
                                          '(is ik_node running?): the plan would be lost')]
                    now = time.monotonic()
                    start = self.runner.start_state(now, measured=self._fresh_measured(now))
                    if start is not None or now > deadline:
                        break
                    if self.runner.interacting and not ended_interaction:
                        # a position goal ends interaction: the driver brakes the admittance
                        # to rest and reports where ('aborted' with the positions); the goal
                        # is planned from there (docs/interaction.md, "Position goals")
                        self._traj_pub.publish(self._empty_trajectory(0))
                        ended_interaction = True
                    self._wake.wait(timeout=0.02)      # a cancelled motion is still braking
                if self._closing:
                    return [GoalEvent(request.goal_id, GoalState.ABORTED, 'shutdown')]
                if start is None and ended_interaction:
                    return [GoalEvent(request.goal_id, GoalState.REJECTED,
                                      f'interaction did not end within {STOPPING_WAIT_S:g} s '
                                      '(no report from the driver)')]
                if start is None:
                    return [GoalEvent(request.goal_id, GoalState.REJECTED,
                                      f'the brace is still stopping after a cancel ({STOPPING_WAIT_S:g} s '
                                      'without a report from the driver)')]
            t_plan = time.perf_counter()
            try:
                plan = self.runner.plan(request, start)
                knots = knots_of(plan.trajectory, breaks=getattr(plan.trajectory, 'breaks', None))
            except PlanRejected as exc:
                return [GoalEvent(request.goal_id, GoalState.REJECTED, exc.reason, request.target)]
            except TrajectoryError as exc:
                return [GoalEvent(request.goal_id, GoalState.REJECTED, f'cannot plan: {exc}',
                                  request.target)]
            elapsed = time.perf_counter() - t_plan
            self.last_planning_ms = elapsed * 1e3
            if elapsed > self.planning_budget:
                return [GoalEvent(request.goal_id, GoalState.REJECTED,
                                  f'planning took {elapsed:.2f} s, more than trajectory.planning_budget '
                                  f'= {self.planning_budget:g} s')]
            with self._lock:
                newer = self._newer(request)
                if newer is not None:
                    return newer
                now = time.monotonic()
                if now > start.t0 and start.source == 'motion' and _attempt < 2:
                    continue                  # came late while moving: plan from the new state
                tag = max(self._clock_offset_ns + round(start.t0 * 1e9), self._last_tag + 1)
                self._last_tag = tag
                events = self.runner.commit(request, plan, start, tag=tag, now=now)
                if events and events[-1].state is GoalState.ACCEPTED:
                    self._committed = request
                    self._traj_pub.publish(pose_trajectory_msg(
                        knots.times, knots.positions, knots.velocities, knots.accelerations,
                        frame_id=self.base_frame, joint_name=self.platform_frame,
                        stamp=ns_to_stamp(tag), mechanism=self.mechanism))
                    self._timer.reset()
            return events
        return [GoalEvent(request.goal_id, GoalState.REJECTED, 'could not plan ahead of the '
                          'running motion (planning slower than the lookahead three times)')]

    # ------------------------------------------------------------------ what the stack reports
    def _on_driver_state(self, msg: DiagnosticStatus) -> None:
        values = status_values(msg)
        command = _floats(values.get('command', ''))
        now = time.monotonic()
        with self._lock:
            events = self.runner.on_driver_state(
                values.get('enabled') == 'true', msg.message,
                command if command is not None and command.size == self.mechanism.n_actuators else None,
                executing=values.get('execution', 'hold') != 'hold', now=now)
            self._wake.notify_all()
        self.diagnostics.values['driver'] = msg.message     # what goals are judged against
        self._report(events)

    def _on_execution(self, msg: DiagnosticStatus) -> None:
        values = status_values(msg)
        if '/interaction/' in msg.name:
            # the driver's in-cycle admittance: its tags are sessions, not our stamps
            with self._lock:
                self.runner.on_interaction(values.get('kind', msg.message),
                                           _floats(values.get('positions', '')))
                self._wake.notify_all()
            return
        try:
            tag = int(values.get('stamp', ''))
        except ValueError:
            return
        positions = _floats(values.get('positions', ''))
        now = time.monotonic()
        with self._lock:
            events = self.runner.on_execution(tag, values.get('kind', msg.message),
                                              values.get('reason', ''), positions, now=now,
                                              lag=_float(values.get('lag', '')))
            events = self._plan_late_splices_again(events)
            self._wake.notify_all()
        self._report(events)

    def _plan_late_splices_again(self, events: list[GoalEvent]) -> list[GoalEvent]:
        """Late splices (module docstring): a goal whose motion the driver refused for its
        splice is planned again, from the motion the driver goes on with, instead of being
        aborted; at most :data:`LATE_SPLICE_REPLANS` times. When a newer goal waits, the
        newer one is planned instead and the refused goal is cancelled, superseded by it. The
        caller holds the lock."""
        kept = []
        for ev in events:
            request = self._committed
            replans = self._replans.get(ev.goal_id, 0)
            refused = (ev.state is GoalState.ABORTED and SPLICE_REFUSED in ev.reason and request is not None
                       and request.goal_id == ev.goal_id and not self._closing)
            if refused and self._pending is not None and self._pending[0].goal_id != ev.goal_id:
                kept.append(dataclasses.replace(
                    ev, state=GoalState.CANCELLED,
                    reason=f'superseded by goal {self._pending[0].goal_id}: {ev.reason}'))
                continue
            if refused and self._pending is None and replans < LATE_SPLICE_REPLANS:
                self._replans = {ev.goal_id: replans + 1}
                self._pending = (request, {})
                self.get_logger().warning(f'goal {ev.goal_id}: planned again ({replans + 1} of '
                                          f'{LATE_SPLICE_REPLANS}): {ev.reason}')
                continue
            kept.append(ev)
        return kept

    def _on_estimate(self, msg: PoseStamped) -> None:
        try:
            pose = pose_from_msg(msg, frame_id=self.base_frame, mechanism=self.mechanism)
        except MalformedMessage as exc:
            self.get_logger().warning(f'pose estimate ignored: {exc}', throttle_duration_sec=1.0)
            return
        now = time.monotonic()
        stamp_ns = stamp_to_ns(msg.header.stamp)
        stamp = (stamp_ns - self._clock_offset_ns) * 1e-9 if stamp_ns else now
        self._measured = (pose, now)
        with self._lock:
            events = self.runner.on_estimate(pose, stamp=min(stamp, now), now=now)
        self._report(events)

    def _fresh_measured(self, now: float) -> np.ndarray | None:
        if self._measured is None or now - self._measured[1] > 0.2:
            return None
        return self._measured[0]

    def _on_timer(self) -> None:
        now = time.monotonic()
        with self._lock:
            events = self.runner.check(now)
            idle = self.runner.active_goal is None and self.runner.settled
        self._report(events)
        if idle:
            self._timer.cancel()

    def _on_cancel(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        with self._lock:
            superseded = self._pending
            self._pending = None
            message, tag, events = self.runner.cancel(now=time.monotonic())
        if superseded is not None:
            events = [GoalEvent(superseded[0].goal_id, GoalState.ACCEPTED, 'queued for planning'),
                      GoalEvent(superseded[0].goal_id, GoalState.CANCELLED,
                                'cancel requested before it was planned')] + events
        if tag is not None:
            self._traj_pub.publish(self._empty_trajectory(tag))
            self._timer.reset()
        self._report(events)
        response.success, response.message = True, message
        self.get_logger().info(f'cancel: {message}')
        return response

    def _empty_trajectory(self, tag: int) -> MultiDOFJointTrajectory:
        """A stop for the driver: no points, ``header.stamp`` = the motion it stops (0: any)."""
        stop = MultiDOFJointTrajectory()
        stop.header.frame_id = self.base_frame
        stop.header.stamp = ns_to_stamp(tag)
        stop.joint_names = [self.platform_frame]
        return stop

    # ------------------------------------------------------------------ status out
    def _report(self, events: Sequence[GoalEvent]) -> None:
        if not events:
            return
        with self._report_lock:
            for ev in events:
                self._report_one(ev)

    def _report_one(self, ev: GoalEvent) -> None:
        self.counts[ev.state.value] += 1
        meta = self._meta.get(ev.goal_id, {})
        if ev.state.terminal:
            self._meta.pop(ev.goal_id, None)
        values = {'goal_id': ev.goal_id, 'state': ev.state.value, 'reason': ev.reason,
                  'stamp': meta.get('stamp', 0), 'source': meta.get('source', ''),
                  'profile': ev.profile,
                  'duration': '' if ev.duration is None else f'{ev.duration:.4f}',
                  'target': '' if ev.target is None else
                  ' '.join(f'{x:.6g}' for x in np.asarray(ev.target).ravel()),
                  'time': self.get_clock().now().nanoseconds}
        values.update(ev.values)
        if self.context.ok():
            self._status_pub.publish(status_msg(f'{self.get_name()}/goal/{ev.goal_id}', ev.state.value,
                                                level=_LEVEL[ev.state],
                                                hardware_id=self.get_fully_qualified_name(), **values))
        text = f'goal {ev.goal_id} {ev.state.value}' + (f': {ev.reason}' if ev.reason else '')
        # one call site per severity (rclpy ties a call site to one severity)
        if _LEVEL[ev.state] == OK:
            self.get_logger().info(text)
        elif _LEVEL[ev.state] == WARN:
            self.get_logger().warning(text)
        else:
            self.get_logger().error(text)
        level = ERROR if ev.state is GoalState.ABORTED else (
            WARN if ev.state is GoalState.REJECTED else OK)
        self.diagnostics.set(level, text, last_planning_ms=f'{self.last_planning_ms:.2f}',
                             **{f'goals_{k}': v for k, v in self.counts.items()})

    def shutdown(self) -> None:
        """Report queued and running goals aborted ("shutdown"), stop the planner thread
        (``run_node`` calls this while the node can still publish)."""
        with self._lock:
            self._closing = True
            pending, self._pending = self._pending, None
            events = self.runner.abort_all('shutdown: the trajectory node stopped')
            self._wake.notify_all()
        if pending is not None:
            events = [GoalEvent(pending[0].goal_id, GoalState.ACCEPTED, 'queued for planning'),
                      GoalEvent(pending[0].goal_id, GoalState.ABORTED,
                                'shutdown: the trajectory node stopped')] + events
        self._report(events)
        if events:
            # the last words reach the subscribers before the process goes (reliable: acked)
            if not self._status_pub.wait_for_all_acked(Duration(seconds=SHUTDOWN_ACK_S)):
                self.get_logger().warning(
                    f'shutdown: not every reader of {topics.GOAL_STATUS} acknowledged the last '
                    f'statuses within {SHUTDOWN_ACK_S:g} s '
                    f'({self._status_pub.get_subscription_count()} matched)')
        if self._planner.is_alive() and self._planner is not threading.current_thread():
            self._planner.join(timeout=2.0)

    def destroy_node(self) -> None:
        # a node whose constructor raised (a configuration error) is destroyed by the context
        # too: it has no planner to stop
        if not getattr(self, '_closing', True):
            self.shutdown()
        super().destroy_node()


def _floats(text: str) -> np.ndarray | None:
    try:
        return np.array([float(x) for x in text.split(',') if x], dtype=float) if text else None
    except ValueError:
        return None


def _float(text: str) -> float | None:
    try:
        return float(text) if text else None
    except ValueError:
        return None


def main(args: Sequence[str] | None = None) -> int:
    return run_node(TrajectoryNode, executable='trajectory_node', args=args,
                    summary='pose goals / paths -> /brace/pose_trajectory (minimum jerk, S-curve, '
                            'log-cosh), goal outcomes on /brace/goal_status')


if __name__ == '__main__':
    raise SystemExit(main())
