"""trajectory_node: pose goals and paths -> a smooth pose setpoint stream.

``ros2 run brace_control trajectory_node --ros-args --params-file config/lumbar_brace.yaml``

Topics and services (all in the device's ``base_frame``):

* ``/brace/pose_goal`` (``geometry_msgs/PoseStamped``): go to this pose. The goal
  carries no duration: Fitts' law (``trajectory.fitts_*``) gives it for the
  minimum-jerk and log-cosh profiles, the S-curve is time-optimal.
* ``/brace/pose_path`` (``nav_msgs/Path``): pass the intermediate poses (via points) and
  stop at the last. Each pose's ``header.stamp`` is its arrival time counted from the
  path's ``header.stamp`` (t = 0 is the start of the motion; absolute stamps with
  header = now, or relative ones with header = 0, both work). All pose stamps zero: no
  timing (Fitts' law on the path length, optimal via times). Stamps must increase.
  The path's ``header.frame_id`` must be the base frame; a pose's own frame_id must be
  the base frame too, or empty (= the path's frame).
* ``/brace/pose`` (``PoseStamped``, measured): where the first motion starts when fresh
  (else the last setpoint, else ``mechanism.home_pose``); also the tracking check
  (``safety.path_tolerance``: a larger error aborts the goal, SAFETY.md 11).
* ``/brace/pose_setpoint`` (``PoseStamped``) at ``trajectory.rate_hz``, from the first
  accepted goal on (nothing before: the node does not know where to hold).
* ``~/cancel`` (``std_srvs/Trigger``): decelerate to rest and hold.
* ``/brace/goal_status`` (``diagnostic_msgs/DiagnosticStatus``, reliable, depth 50):
  one message per goal event. ``name`` = ``trajectory_node/goal/<id>``; ``message`` =
  the state (``accepted``, then exactly one of ``succeeded``, ``rejected``,
  ``aborted``, ``cancelled``); ``level`` OK (accepted, succeeded), WARN (rejected,
  cancelled), ERROR (aborted); ``values``: ``goal_id``, ``state``, ``reason``,
  ``stamp`` (the goal message's header stamp, ns, to match it to what was sent),
  ``source`` (``pose_goal`` or ``pose_path``), ``profile``, ``duration`` (s),
  ``target``. Goal ids count from 1 per node. Every event is also logged.
* ``/diagnostics``: the node's state, counts, setpoint period and jitter.

A new goal preempts the running one smoothly (the running goal is reported cancelled,
reason "preempted by goal <id>"); a rejected goal changes nothing (the brace keeps doing
what it was doing, or holds). Planning runs in a worker thread so the setpoint timer is
not held up; the new motion takes over ``PLAN_LOOKAHEAD_S`` after the goal arrived, from
exactly the state the running motion has then (continuous position, velocity,
acceleration). All math is in :mod:`brace_control.trajectory`.
"""
from __future__ import annotations

import sys
import threading
import time
from collections import deque
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_srvs.srv import Trigger

from ..config import ConfigError
from ..mechanisms import mechanism_from_config
from ..trajectory import (FittsLaw, GoalEvent, GoalRequest, GoalState, LatePlan, Limits,
                          PlanRejected, PoseError, Profile, StartState, TrajectoryRunner,
                          arrival_times, plan_motion)
from .diagnostics import ERROR, OK, WARN, NodeDiagnostics
from .ik_node import POSE_SETPOINT_TOPIC, SETPOINT_QOS
from .msgs import (MalformedMessage, ns_to_stamp, pose_from_msg, pose_kind, pose_msg,
                   stamp_to_ns, stamp_to_sec)
from .params import declare_device_parameters
from .runner import run_node

__all__ = ['TrajectoryNode', 'main', 'GOAL_TOPIC', 'PATH_TOPIC', 'STATUS_TOPIC', 'POSE_TOPIC']

GOAL_TOPIC = '/brace/pose_goal'
PATH_TOPIC = '/brace/pose_path'
POSE_TOPIC = '/brace/pose'
STATUS_TOPIC = '/brace/goal_status'

#: s from a goal's arrival to its motion taking over (planning must finish within it).
PLAN_LOOKAHEAD_S = 0.1
#: GIL switch interval of the node's process (s): bounds how long the planner thread can
#: delay the setpoint timer.
GIL_SWITCH_INTERVAL_S = 0.0005
#: plans of a moving brace that come late are redone this many times, then forced.
PLAN_ATTEMPTS = 3
#: a measured pose older than this is not used as a start (s).
MEASURED_POSE_MAX_AGE_S = 0.2

#: goal events are state: reliable, with enough history that a burst is not lost.
STATUS_QOS = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
GOAL_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
#: the measured pose: only the latest matters; best effort matches any publisher.
MEASURED_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT)

_LEVEL = {GoalState.ACCEPTED: OK, GoalState.SUCCEEDED: OK, GoalState.REJECTED: WARN,
          GoalState.CANCELLED: WARN, GoalState.ABORTED: ERROR}


class TrajectoryNode(Node):
    """Goals in, setpoints out (see the module docstring for topics and messages)."""

    def __init__(self, *, node_name: str = 'trajectory_node', **kwargs) -> None:
        super().__init__(node_name, **kwargs)
        self.cfg = declare_device_parameters(self, ('mechanism', 'trajectory', 'actuator', 'safety'))
        self.mechanism = mechanism_from_config(self.cfg)
        self.base_frame: str = self.cfg['base_frame']
        traj = self.cfg['trajectory']
        self.rate_hz = float(traj['rate_hz'])
        self.profile = Profile(traj['profile'])
        kind = pose_kind(self.mechanism)
        try:
            limits = Limits.from_config(self.cfg, dof=self.mechanism.dof)
        except ValueError as exc:
            raise ConfigError(str(exc)) from exc
        self.runner = TrajectoryRunner(
            self.mechanism, limits,
            profile=self.profile,
            fitts=FittsLaw(a=traj['fitts_a'], b=traj['fitts_b'], w=traj['fitts_w']),
            fitts_axes=(0, 1) if kind in ('planar', 'xy') else None,
            lookahead=PLAN_LOOKAHEAD_S,
            path_tolerance=float(self.cfg['safety']['path_tolerance']),
            tracking_latency=float(self.cfg['safety']['tracking_latency']))
        # The runner is shared by the timer (executor thread) and the planner (worker
        # thread): every runner call holds this lock; planning itself runs outside it.
        self._lock = threading.Lock()
        self._report_lock = threading.Lock()      # status/log/diagnostics from both threads
        self._planner = ThreadPoolExecutor(max_workers=1, thread_name_prefix='trajectory_plan')
        self._generation = 0            # bumped by cancel: plans started before are void
        self._next_id = 1
        self._measured: tuple[np.ndarray, float] | None = None
        self._periods: deque[float] = deque(maxlen=max(int(self.rate_hz), 10))
        self._last_tick: float | None = None
        self._clock_offset_ns = self.get_clock().now().nanoseconds - round(time.monotonic() * 1e9)
        self.counts = {s.value: 0 for s in GoalState}

        self._setpoint_pub = self.create_publisher(PoseStamped, POSE_SETPOINT_TOPIC, SETPOINT_QOS)
        self._status_pub = self.create_publisher(DiagnosticStatus, STATUS_TOPIC, STATUS_QOS)
        self.create_subscription(PoseStamped, GOAL_TOPIC, self._on_goal, GOAL_QOS)
        self.create_subscription(Path, PATH_TOPIC, self._on_path, GOAL_QOS)
        self.create_subscription(PoseStamped, POSE_TOPIC, self._on_measured, MEASURED_QOS)
        self.create_service(Trigger, '~/cancel', self._on_cancel)
        self._timer = self.create_timer(1.0 / self.rate_hz, self._on_timer)
        # warm the planner up (imports, first calls) so the first goal meets the lookahead
        home = self.mechanism.home_pose
        self._planner.submit(self._warm_up, home)
        self.diagnostics = NodeDiagnostics(self, f'brace_control/{node_name}')
        self.diagnostics.set(OK, 'idle: waiting for a goal', profile=self.profile.value,
                             rate_hz=self.rate_hz)
        self.get_logger().info(
            f'{type(self.mechanism).__name__}, profile {self.profile.value}, {self.rate_hz:g} Hz: '
            f'{GOAL_TOPIC}, {PATH_TOPIC} -> {POSE_SETPOINT_TOPIC} in {self.base_frame!r}')

    # ------------------------------------------------------------------ goals
    def _new_id(self) -> str:
        gid = str(self._next_id)
        self._next_id += 1
        return gid

    def _on_goal(self, msg: PoseStamped) -> None:
        gid = self._new_id()
        meta = {'stamp': stamp_to_ns(msg.header.stamp), 'source': 'pose_goal'}
        try:
            target = pose_from_msg(msg, frame_id=self.base_frame, mechanism=self.mechanism)
        except MalformedMessage as exc:
            self._report([GoalEvent(gid, GoalState.REJECTED, f'malformed goal: {exc}')], meta)
            return
        self._submit(GoalRequest(gid, target), meta)

    def _on_path(self, msg: Path) -> None:
        gid = self._new_id()
        meta = {'stamp': stamp_to_ns(msg.header.stamp), 'source': 'pose_path'}
        try:
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
            self._report([GoalEvent(gid, GoalState.REJECTED, f'malformed path: {exc}')], meta)
            return
        via = np.array(poses[:-1]) if len(poses) > 1 else None
        self._submit(GoalRequest(gid, poses[-1], via=via, t_via=t_via, duration=duration), meta)

    def _submit(self, request: GoalRequest, meta: dict) -> None:
        now = time.monotonic()
        with self._lock:
            start = self.runner.start_state(now, measured=self._fresh_measured(now))
            generation = self._generation
        self._planner.submit(self._plan, request, start, generation, meta)

    def _plan(self, request: GoalRequest, start: StartState, generation: int, meta: dict) -> None:
        """Worker thread: plan without the lock, commit with it (re-plan if it came late)."""
        try:
            for attempt in range(PLAN_ATTEMPTS):
                try:
                    plan = self.runner.plan(request, start)
                except PlanRejected as exc:
                    events = [GoalEvent(request.goal_id, GoalState.REJECTED, exc.reason, request.target)]
                    break
                with self._lock:
                    if generation != self._generation:
                        events = [GoalEvent(request.goal_id, GoalState.CANCELLED,
                                            'cancel requested while the goal was being planned')]
                        break
                    now = time.monotonic()
                    try:
                        events = self.runner.commit(request, plan, start, now=now,
                                                    force=attempt == PLAN_ATTEMPTS - 1)
                        break
                    except LatePlan:
                        start = self.runner.start_state(now, measured=self._fresh_measured(now))
            self._report(events, meta)
        except Exception as exc:  # noqa: BLE001 - a planner bug must still end the goal
            self.get_logger().error(f'goal {request.goal_id}: planning failed: {exc!r}')
            self._report([GoalEvent(request.goal_id, GoalState.ABORTED,
                                    f'internal error while planning: {exc!r}')], meta)

    def _warm_up(self, home: np.ndarray) -> None:
        try:
            plan_motion(self.mechanism, home, home, self.profile, self.runner.limits,
                        via=[home], t_via=[0.5], duration=1.0)
        except Exception:  # noqa: BLE001 - a singular or odd home only skips the warm-up
            pass

    def _on_cancel(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        with self._lock:
            self._generation += 1
            ok, message, events = self.runner.cancel(now=time.monotonic())
        self._report(events, {})
        response.success, response.message = ok, message
        self.get_logger().info(f'cancel: {message}')
        return response

    # ------------------------------------------------------------------ measured pose
    def _fresh_measured(self, now: float) -> np.ndarray | None:
        if self._measured is None or now - self._measured[1] > MEASURED_POSE_MAX_AGE_S:
            return None
        return self._measured[0]

    def _on_measured(self, msg: PoseStamped) -> None:
        try:
            pose = pose_from_msg(msg, frame_id=self.base_frame, mechanism=self.mechanism)
        except MalformedMessage as exc:
            self.get_logger().warning(f'measured pose ignored: {exc}', throttle_duration_sec=1.0)
            return
        now = time.monotonic()
        self._measured = (pose, now)
        # the measurement's time on the runner's clock (stamps and the runner share one offset)
        measured_at = (stamp_to_ns(msg.header.stamp) - self._clock_offset_ns) * 1e-9
        if not msg.header.stamp.sec and not msg.header.stamp.nanosec:
            measured_at = now                  # unstamped: as received
        with self._lock:
            events = self.runner.check_tracking(pose, now=now, measured_at=min(measured_at, now))
        self._report(events, {})

    # ------------------------------------------------------------------ setpoints
    def _on_timer(self) -> None:
        # the stamp is the instant the setpoint is sampled at: the runner's monotonic clock
        # mapped onto the node's clock by one offset taken at start-up, so rates computed
        # downstream from stamps are exact (two clock reads per tick would add jitter)
        now = time.monotonic()
        stamp = ns_to_stamp(self._clock_offset_ns + round(now * 1e9))
        if self._last_tick is not None:
            self._periods.append(now - self._last_tick)
        self._last_tick = now
        with self._lock:
            state, events = self.runner.step(now)
            active = self.runner.active_goal
        if state is not None:
            self._setpoint_pub.publish(pose_msg(state.p, frame_id=self.base_frame, stamp=stamp,
                                                mechanism=self.mechanism))
        if events:
            self._report(events, {})
        if len(self._periods) >= 2 and len(self._periods) == self._periods.maxlen:
            p = np.asarray(self._periods)
            self.diagnostics.values.update(period_mean_ms=f'{1e3 * p.mean():.3f}',
                                           period_jitter_ms=f'{1e3 * p.std():.3f}',
                                           period_max_ms=f'{1e3 * p.max():.3f}')
            self._periods.clear()
        self.diagnostics.values['active_goal'] = active or ''

    # ------------------------------------------------------------------ status
    def _report(self, events: Sequence[GoalEvent], meta: dict) -> None:
        with self._report_lock:
            for ev in events:
                self._report_one(ev, meta)

    def _report_one(self, ev: GoalEvent, meta: dict) -> None:
        if True:
            self.counts[ev.state.value] += 1
            values = {'goal_id': ev.goal_id, 'state': ev.state.value, 'reason': ev.reason,
                      'profile': ev.profile, 'duration': '' if ev.duration is None else f'{ev.duration:.4f}',
                      'target': '' if ev.target is None else
                      ' '.join(f'{x:.6g}' for x in np.asarray(ev.target).ravel())}
            values.update({k: str(v) for k, v in meta.items()})
            self._status_pub.publish(DiagnosticStatus(
                level=_LEVEL[ev.state], name=f'{self.get_name()}/goal/{ev.goal_id}',
                message=ev.state.value, hardware_id=self.get_fully_qualified_name(),
                values=[KeyValue(key=k, value=v) for k, v in values.items()]))
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
            self.diagnostics.set(level, text, **{f'goals_{k}': v for k, v in self.counts.items()})

    def shutdown(self) -> None:
        """Stop the planner thread (``run_node`` calls this on exit)."""
        self._planner.shutdown(wait=True, cancel_futures=True)

    def destroy_node(self) -> None:
        self._planner.shutdown(wait=True, cancel_futures=True)
        super().destroy_node()


def main(args: Sequence[str] | None = None) -> int:
    # The planner thread runs Python loops (IK along the path); with the default 5 ms
    # GIL switch interval it could hold the setpoint timer up for a whole period.
    sys.setswitchinterval(GIL_SWITCH_INTERVAL_S)
    return run_node(TrajectoryNode, executable='trajectory_node', args=args,
                    summary='pose goals / paths -> /brace/pose_setpoint (minimum jerk, S-curve, log-cosh)')
