"""can_driver_node: the brace's CiA 402 drives on CAN, as ROS topics and services.

``ros2 run brace_control can_driver_node --ros-args --params-file config/lumbar_brace.yaml``

* subscribes ``/brace/actuator_trajectory`` (``trajectory_msgs/JointTrajectory``, by
  actuator name): a planned motion, executed in the SYNC thread (ros2_control's
  JointTrajectoryController semantics, :mod:`brace_control.can.execution`): sampled at every
  SYNC from one time base for all axes (quintic Hermite), 607Ah target + 60B1h velocity
  feed-forward; it replaces the running motion from its ``header.stamp`` (0 or a stamp in
  the past: now) with continuous position, velocity and acceleration. A received
  trajectory was checked whole (stroke, speed, acceleration, at rest at its end), so it
  runs to its end unless it is cancelled (an empty trajectory: decelerate along the path
  and hold; a nonzero stamp names the trajectory it stops), halted, or stopped by a fault;
* subscribes ``/brace/actuator_setpoint`` (``sensor_msgs/JointState``, by actuator name,
  ``position`` in m, optional ``velocity`` as feed-forward): the teleoperation stream,
  tracked with one scale for all axes. Malformed input (unknown / missing names, wrong
  lengths, NaN, outside the stroke) is rejected with a throttled error; nothing is sent
  (SAFETY.md 5, 6). No setpoint for ``safety.command_timeout``: decelerate along the
  current direction and hold (SAFETY.md 1); a step beyond the step limit: protective stop
  (SAFETY.md 7);
* publishes ``/brace/execution_status`` (``diagnostic_msgs/DiagnosticStatus``, one message
  per event of a trajectory: ``name`` = ``can_driver_node/trajectory/<stamp ns>``,
  ``message`` = accepted | rejected | started | finished | stopped | preempted, ``values``
  stamp, kind, reason, positions, time: when it happened, ns of ROS time; ``started``: the
  SYNC whose targets are the trajectory's first);
* publishes ``/brace/driver_state`` (``DiagnosticStatus``, latched: transient local) on every
  change of state, faults, homing, or motion (a motion starting or ending):
  ``message`` = disabled | enabled | halted | homing | protective stop: <faults> | ...,
  ``values`` state, enabled, homed, faults, execution (hold | trajectory | stream), command
  (the commanded positions: where the command was anchored on enable, or holds);
* publishes ``/brace/joint_states`` (position m, velocity m/s, effort = load-cell force
  N) at ``can.joint_state_rate_hz``, once homed (incremental encoders read 0 before),
  stamped with the SYNC its samples answer;
* services ``~/enable``, ``~/disable``, ``~/halt``, ``~/recover``, ``~/home``, ``~/relieve``
  (``std_srvs/Trigger``, like ros2_canopen; the message says why on failure). ``~/home`` only
  with the drives disabled. ``~/relieve`` backs a loaded brace off after a protective stop
  (SAFETY.md 15): slowly, under force supervision, the way that unloads each leg, until
  every force is below ``safety.release_force``; ``~/recover`` then succeeds;
* above ``safety.soft_force_limit`` a motion that keeps pressing decelerates along its path
  and holds (its trajectory reported stopped with the leg, the force and the wrench capacity
  at that pose); nothing latches. ``safety.force_limit`` latches a protective stop;
* ``/diagnostics``: one status per drive (NMT, 402 state, last EMCY, heartbeat age),
  the bus (load, error state) and the SYNC cycle (period error p50/p99, overruns);
* monitors the platform wrench from the load cells against ``safety.max_wrench``
  (SAFETY.md 8) and latches a protective stop beyond it.

With ``can.sim: true`` the simulated brace (:mod:`brace_control.sim`) is started in this
process on the same python-can channel before the master boots (a ``virtual`` bus only
exists inside one process), and its ground truth is published at ``sim.truth_rate_hz``
(what a user compares an estimator or a controller against; nothing of the stack
subscribes to it):

* ``/brace/sim/joint_states`` (``JointState``): the true actuator positions, rates and
  efforts (force N / torque N·m, before load-cell noise and quantisation);
* ``/brace/sim/pose`` (``PoseStamped`` in ``base_frame``): the true platform pose;
* ``/brace/sim/wrench`` (``WrenchStamped`` in ``platform_frame``): the wrench the brace
  applies to the body, in ``/brace/wrench``'s convention (the mechanism's ``wrench`` of
  the true pose and efforts);
* ``/brace/sim/body_pose`` (``PoseStamped`` in ``base_frame``): where the simulated
  patient's trunk wants to be now (its rest pose plus the sway ``sim.sway_*``);
* and it subscribes ``/brace/sim/body_rest`` (``PoseStamped``): where the simulated
  patient's body rests (the body's stiffness pulls the ring towards it; the sway is
  added on top).

In-process use (one-process bring-up, tests)::

    node = CanDriverNode(context=ctx, cli_args=['--ros-args', '--params-file', yaml])
    ...
    node.shutdown(); node.destroy_node()
"""
from __future__ import annotations

import math
import sys
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.task import Future
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger
from trajectory_msgs.msg import JointTrajectory

from ..can import (ActuatorTrajectory, BraceMaster, DriverError, FaultKind, MasterConfig,
                   MasterState, State402, TrajectoryInvalid)
from . import topics
from .msgs import (MalformedMessage, joint_knots_from_msg, joint_state, joint_state_arrays,
                   ns_to_stamp, stamp_to_ns, status_msg)
from .params import declare_device_parameters
from .timers import timer_callback

__all__ = ['CanDriverNode', 'main']

#: rejection errors at most once per this many seconds (the stream runs at 200 Hz)
REJECT_LOG_PERIOD = 1.0
#: Hz: execution events and the driver state are published this often (when they change)
EVENT_RATE_HZ = 50.0

_LEVEL = {'ok': DiagnosticStatus.OK, 'warn': DiagnosticStatus.WARN, 'error': DiagnosticStatus.ERROR}


class CanDriverNode(Node):
    """The CAN driver: a :class:`~brace_control.can.BraceMaster` behind topics and services.

    :param node_name: ROS node name (services are ``~/enable`` etc. under it).
    :param boot: boot the drives in the constructor (else call :meth:`start`).
    :param kwargs: passed to :class:`rclpy.node.Node` (``context``, ``cli_args``,
        ``parameter_overrides``, ...).
    :raises ConfigError: a bad parameter (named); :raises DriverError: the bus or a drive
        did not come up (the message says which).
    """

    def __init__(self, *, node_name: str = 'can_driver_node', boot: bool = True,
                 **kwargs: Any) -> None:
        self._closed = False
        self.sim: Any = None
        self.master: BraceMaster | None = None
        super().__init__(node_name, **kwargs)
        self.cfg = declare_device_parameters(self, ('mechanism', 'actuator', 'can', 'safety', 'sim',
                                                     'trajectory', 'interaction'))
        self.names: tuple[str, ...] = tuple(self.cfg['mechanism']['actuator_names'])
        self.mechanism = self._mechanism()
        self.master_config = MasterConfig.from_device_config(self.cfg)
        switch_us = int(self.cfg['can']['gil_switch_interval_us'])
        self._previous_switch_interval = sys.getswitchinterval()
        if switch_us > 0:
            # process-wide: a thread busy in Python (executor, simulator) then holds the GIL
            # at most this long when the SYNC thread wakes (Python's default: 5 ms);
            # restored on shutdown (in-process bring-ups, tests)
            sys.setswitchinterval(switch_us * 1e-6)
        self.master = BraceMaster(self.master_config)
        self.master.soft_limit_context = self._soft_limit_context
        self.rejected = 0
        self.accepted = 0
        self.last_rejection = ''
        self._last_reject_log = -math.inf
        self._pose_hint = None if self.mechanism is None else np.asarray(self.mechanism.home_pose, float)
        self._fk_key: tuple[bytes, bytes] | None = None     # (q, hint) of the last forward kinematics
        self._fk_pose: np.ndarray | None = None
        self._fk_rows: list[tuple[float, float, float]] | None = None   # J's rows at that pose
        #: a planar RPR's legs in plain floats (the wrench check's J^T f), None: the mechanism's
        self._legs = None if self.mechanism is None else self._float_legs()
        self._wrench_limit = np.asarray(self.cfg['safety']['max_wrench'], float)
        self._last_faults: tuple = ()
        # services take up to seconds (402 transitions, braking, a relief): their work runs in
        # a thread and the callback awaits it (_trigger), so one thread of an executor serves
        # the streams meanwhile; a multi-threaded executor would cost a core share for nothing
        self._service_group = MutuallyExclusiveCallbackGroup()
        self._stream_group = MutuallyExclusiveCallbackGroup()
        self._service_lock = _AsyncLock()
        self._js_pub = self.create_publisher(JointState, topics.JOINT_STATES, topics.STATE_QOS)
        self._diag_pub = self.create_publisher(DiagnosticArray, topics.DIAGNOSTICS,
                                               topics.DIAGNOSTICS_QOS)
        self._exec_pub = self.create_publisher(DiagnosticStatus, topics.EXECUTION_STATUS,
                                               topics.STATUS_QOS)
        self._state_pub = self.create_publisher(DiagnosticStatus, topics.DRIVER_STATE,
                                                topics.LATCHED_QOS)
        self._last_state_key: tuple | None = None
        self._last_js_wall = 0.0                # the SYNC (wall clock) of the last joint state
        # ROS time (ns) minus perf_counter (s) at start-up: trajectory stamps -> the master's
        # clock, SYNC instants -> message stamps (one offset: no jitter from two clock reads)
        self._ros_minus_perf_ns = self.get_clock().now().nanoseconds - round(time.perf_counter() * 1e9)
        self._sub = self.create_subscription(JointState, topics.ACTUATOR_SETPOINT, self._on_setpoint,
                                             topics.SETPOINT_QOS, callback_group=self._stream_group)
        self._traj_sub = self.create_subscription(JointTrajectory, topics.ACTUATOR_TRAJECTORY,
                                                  self._on_trajectory, topics.TRAJECTORY_QOS,
                                                  callback_group=self._stream_group)
        for name, fn in (('enable', self._enable), ('disable', self._disable), ('halt', self._halt),
                         ('recover', self._recover), ('home', self._home), ('relieve', self._relieve)):
            self.create_service(Trigger, f'~/{name}', self._trigger(name, fn),
                                callback_group=self._service_group)
        self._init_interaction()
        rate = float(self.cfg['can']['joint_state_rate_hz'])
        self._js_timer = self.create_timer(1.0 / rate, timer_callback(self._publish_joint_states),
                                           callback_group=self._stream_group)
        self._diag_timer = self.create_timer(1.0, timer_callback(self.publish_diagnostics),
                                             callback_group=self._stream_group)
        self._event_timer = self.create_timer(1.0 / EVENT_RATE_HZ, timer_callback(self.publish_events),
                                              callback_group=self._stream_group)
        if boot:
            self.start()

    def _mechanism(self) -> Any:
        try:
            from ..mechanisms import mechanism_from_config
            return mechanism_from_config(self.cfg)
        except ImportError:
            return None

    def _float_legs(self) -> Any:
        """:meth:`PlanarRprFloats.of <brace_control.mechanisms.planar_floats.PlanarRprFloats.of>`
        the mechanism (``None`` unless a planar RPR that agrees with its model)."""
        from ..mechanisms.planar_floats import PlanarRprFloats
        return PlanarRprFloats.of(self.mechanism)

    # ------------------------------------------------------------------ lifecycle

    def start(self) -> None:
        """Start the simulated brace (``can.sim``) and boot the drives.

        :raises DriverError: the bus could not be opened or a drive did not boot.
        """
        can_cfg = self.cfg['can']
        if can_cfg['sim'] and self.sim is None:
            from ..sim import SimulatedBrace
            # the EDS as the master resolved it (the node's parameters carry no file path)
            self.sim = SimulatedBrace(self.cfg, channel=self.master_config.channel,
                                      interface=self.master_config.interface,
                                      eds=self.master_config.eds)
            self.get_logger().info(f'simulated brace on {self.master_config.interface}:'
                                   f'{self.master_config.channel}')
            self._start_truth()
        try:
            self.master.boot()
        except DriverError:
            self.shutdown()
            raise
        self.get_logger().info(
            f'{len(self.names)} drives OPERATIONAL (nodes {list(self.master_config.node_ids)}) on '
            f'{self.master_config.interface}:{self.master_config.channel}, SYNC '
            f'{self.master_config.sync_rate_hz:g} Hz; call ~/home then ~/enable')

    def _start_truth(self) -> None:
        """Publishers and timer of the simulator's ground truth (module docstring)."""
        if self.mechanism is None:
            return
        from geometry_msgs.msg import PoseStamped, WrenchStamped

        from .kinetics_node import platform_frame_wrench
        from .msgs import pose_kind, pose_msg, wrench_msg
        self.create_subscription(PoseStamped, topics.SIM_BODY_REST, self._on_body_rest,
                                 topics.STATE_QOS, callback_group=self._stream_group)
        self._truth_pubs = (self.create_publisher(JointState, topics.SIM_JOINT_STATES, topics.STATE_QOS),
                            self.create_publisher(PoseStamped, topics.SIM_POSE, topics.STATE_QOS),
                            self.create_publisher(WrenchStamped, topics.SIM_WRENCH, topics.STATE_QOS),
                            self.create_publisher(PoseStamped, topics.SIM_BODY_POSE, topics.STATE_QOS))
        kind = pose_kind(self.mechanism)
        base, platform = self.cfg['base_frame'], self.cfg['platform_frame']
        last_wrench: list[Any] = [None, None]       # (pose, efforts) bytes, the platform wrench

        def publish() -> None:
            if not self.context.ok():         # shutting down: the publishers are going
                return
            # the truth of the SYNC the last /brace/joint_states described (same stamp): a
            # comparison with the estimate pairs the same instant, not two SYNCs ms apart
            wall = self._last_js_wall
            truth = self.sim.truth_at(wall) if wall and time.time() - wall < 0.1 else self.sim.truth()
            stamp = ns_to_stamp(round(truth.stamp * 1e9) if truth.stamp else
                                self.get_clock().now().nanoseconds)
            js_pub, pose_pub, wrench_pub, body_pub = self._truth_pubs
            js_pub.publish(joint_state(self.names, position=truth.lengths, velocity=truth.velocities,
                                       effort=truth.forces, stamp=stamp))
            pose_pub.publish(pose_msg(truth.pose, frame_id=base, stamp=stamp, mechanism=self.mechanism))
            if truth.body_pose is not None:
                body_pub.publish(pose_msg(truth.body_pose, frame_id=base, stamp=stamp,
                                          mechanism=self.mechanism))
            # a pure function of (pose, efforts), which at rest repeat bit for bit: computed
            # again only when they changed
            key = (truth.pose.tobytes(), truth.forces.tobytes())
            if key != last_wrench[0]:
                try:
                    w = np.asarray(self.mechanism.wrench(truth.pose, truth.forces), dtype=float)
                except ValueError:                  # e.g. a pose the mechanism's statics rejects
                    return
                last_wrench[:] = key, platform_frame_wrench(truth.pose, w, kind)
            wrench_pub.publish(wrench_msg(last_wrench[1], frame_id=platform, stamp=stamp, kind=kind))
        self._truth_timer = self.create_timer(1.0 / float(self.cfg['sim']['truth_rate_hz']),
                                              timer_callback(publish), callback_group=self._stream_group)

    def _on_body_rest(self, msg: Any) -> None:
        """Simulation: where the patient's body rests (a test or a script moves the patient)."""
        from .msgs import pose_from_msg
        try:
            pose = pose_from_msg(msg, frame_id=self.cfg['base_frame'], mechanism=self.mechanism)
            self.sim.set_rest_pose(pose)
        except ValueError as exc:
            self.get_logger().warning(f'body rest pose ignored: {exc}', throttle_duration_sec=1.0)

    def shutdown(self) -> None:
        """Disable the drives, stop SYNC, close the bus, stop the simulator. Idempotent."""
        if self._closed:
            return
        self._closed = True
        try:
            if self.master is not None:
                self.master.shutdown()
        finally:
            if self.sim is not None:
                self.sim.shutdown()
            if getattr(self, '_previous_switch_interval', None):
                sys.setswitchinterval(self._previous_switch_interval)

    def destroy_node(self) -> None:
        self.shutdown()
        super().destroy_node()

    # ------------------------------------------------------------------ setpoints

    def _reject(self, why: str) -> None:
        self.rejected += 1
        self.last_rejection = why
        now = time.monotonic()
        if now - self._last_reject_log >= REJECT_LOG_PERIOD:
            self._last_reject_log = now
            self.get_logger().error(f'actuator setpoint rejected ({self.rejected} so far), '
                                    f'nothing sent, drives hold: {why}')

    def _on_setpoint(self, msg: JointState) -> None:
        try:
            arrays = joint_state_arrays(msg, self.names, ('position', 'velocity'),
                                        optional=('velocity',))
        except MalformedMessage as exc:
            self._reject(str(exc))
            return
        # The stamp is the setpoint's sample instant: the master's step limit uses the
        # smaller of the time between stamps and between arrivals. Staleness is judged by
        # arrival in the master (a stream that stopped), not by the stamp's age.
        stamp = stamp_to_ns(msg.header.stamp)
        try:
            self.master.set_targets(arrays['position'], stamp=stamp * 1e-9 if stamp else None,
                                    velocities=arrays['velocity'])
        except ValueError as exc:
            self._reject(str(exc))
            return
        self.accepted += 1

    # ------------------------------------------------------------------ interaction (in the cycle)

    def _init_interaction(self) -> None:
        """The in-cycle admittance's interface (docs/interaction.md): services
        ``~/interaction_start`` / ``~/interaction_stop`` (Trigger) and the goal topic
        ``/brace/interaction/goal``; its events go out on ``/brace/execution_status`` as
        ``can_driver_node/interaction/<session>``. interaction_node is the user-facing side."""
        from geometry_msgs.msg import WrenchStamped
        self._interaction_sessions = 0
        self.create_service(Trigger, '~/interaction_start', self._on_interaction_start,
                            callback_group=self._stream_group)
        self.create_service(Trigger, '~/interaction_stop', self._on_interaction_stop,
                            callback_group=self._stream_group)
        self.create_subscription(WrenchStamped, topics.INTERACTION_GOAL, self._on_interaction_goal,
                                 topics.GOAL_QOS, callback_group=self._stream_group)

    def _interaction_source(self) -> Any:
        from ..interaction import AdmittanceParams
        from ..interaction.inloop import InLoopAdmittance
        params = AdmittanceParams.from_config(self.cfg, self.mechanism)
        return InLoopAdmittance(self.mechanism, params, sync_period=self.master_config.period,
                                a_max=self.master_config.limits.a_max)

    def _on_interaction_start(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        if self.mechanism is None:
            response.success, response.message = False, 'no mechanism model: no interaction'
            return response
        try:
            source = self._interaction_source()
        except (ValueError, KeyError) as exc:
            response.success, response.message = False, f'interaction parameters: {exc}'
            return response
        self._interaction_sessions += 1
        tag = self._interaction_sessions
        why = self.master.start_interaction(source, tag)
        response.success = why is None
        response.message = (f'interaction {tag} started at {source.dt * 1e3:g} ms '
                            f'({source.n_syncs} SYNC)' if why is None else why)
        self.publish_events()
        return response

    def _on_interaction_stop(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        self.master.stop_interaction('stop requested')
        response.success, response.message = True, 'decelerating to rest'
        self.publish_events()
        return response

    def _on_interaction_goal(self, msg: Any) -> None:
        """The wrench goal in pose-axis components (interaction_node checked it; the
        controller checks again against the pose it is at; a rejection is an event)."""
        from ..interaction import GoalRejected
        from .msgs import pose_kind
        kind = pose_kind(self.mechanism)
        f, t = msg.wrench.force, msg.wrench.torque
        w = {'spherical': [t.x, t.y, t.z], 'planar': [f.x, f.y, t.z], 'xy': [f.x, f.y]}.get(kind, [f.x])
        try:
            self.master.set_interaction_goal(w)
        except (ValueError, GoalRejected) as exc:
            tag = self._interaction_sessions
            self._exec_pub.publish(status_msg(f'{self.get_name()}/interaction/{tag}', 'goal_rejected',
                                              level=DiagnosticStatus.WARN, stamp=tag, kind='goal_rejected',
                                              reason=str(exc), goal=list(w)))

    # ------------------------------------------------------------------ planned motions

    def _on_trajectory(self, msg: JointTrajectory) -> None:
        """A whole planned motion: checked, then executed from its stamp (module docstring)."""
        tag = stamp_to_ns(msg.header.stamp)
        now_perf = time.perf_counter()
        try:
            _, times, q, qd, qdd = joint_knots_from_msg(msg, self.names)
            if times.size == 0:
                self.master.stop_motion('cancel requested (empty trajectory)',
                                        tag=tag if tag else None)
                return
            trajectory = ActuatorTrajectory(times, q, qd, qdd)
        except (MalformedMessage, TrajectoryInvalid) as exc:
            self._exec_pub.publish(status_msg(
                f'{self.get_name()}/trajectory/{tag}', 'rejected', level=DiagnosticStatus.ERROR,
                stamp=tag, kind='rejected', reason=f'malformed trajectory: {exc}'))
            self.get_logger().error(f'trajectory {tag} rejected: {exc}')
            return
        start = now_perf if tag == 0 else (tag - self._ros_minus_perf_ns) * 1e-9
        reason = self.master.execute(trajectory, start=start, tag=tag)
        if reason is not None:
            self.get_logger().warning(f'trajectory {tag} rejected: {reason}')
        self.publish_events()

    def publish_events(self) -> None:
        """Execution events since the last call, and the driver's state when it changed."""
        if not self.context.ok():
            return
        for e in self.master.execution_events():
            level = (DiagnosticStatus.ERROR if e.kind == 'rejected' or 'protective stop' in e.reason
                     else DiagnosticStatus.WARN if e.kind == 'stopped' else DiagnosticStatus.OK)
            self._exec_pub.publish(status_msg(
                f'{self.get_name()}/{e.motion}/{e.tag}', e.kind, level=level, stamp=e.tag,
                kind=e.kind, reason=e.reason, positions=list(e.positions),
                time=self._ros_minus_perf_ns + round(e.time * 1e9), lag=e.lag))
        self.publish_state()

    def publish_state(self, *, force: bool = False) -> None:
        """``/brace/driver_state`` (latched) when the state, the faults or homing changed."""
        m = self.master
        faults = m.supervisor.faults
        execution = m.executor.state.value
        key = (m.state, tuple(f.describe() for f in faults), m.homed, execution)
        if key == self._last_state_key and not force:
            return
        self._last_state_key = key
        state = m.state
        text = 'protective stop' if state is MasterState.FAULT else state.value
        level = (DiagnosticStatus.ERROR if faults else
                 DiagnosticStatus.OK if state is MasterState.ENABLED else DiagnosticStatus.WARN)
        message = f'{text}: {m.supervisor.summary()}' if faults else text
        self._state_pub.publish(status_msg(
            f'{self.get_name()}/state', message, level=level, state=state.value,
            enabled=str(state is MasterState.ENABLED).lower(), homed=str(m.homed).lower(),
            faults=m.supervisor.summary() if faults else 'none', execution=execution,
            command=list(m.executor.q) if m.executor.anchored else [],
            stamp=self.get_clock().now().nanoseconds))

    # ------------------------------------------------------------------ joint states, wrench

    def _publish_joint_states(self) -> None:
        faults = self.master.supervisor.faults
        if faults != self._last_faults:
            for f in faults:
                if f not in self._last_faults:
                    self.get_logger().error(f'protective stop (latched until ~/recover): {f.describe()}')
            self._last_faults = faults
            self.publish_diagnostics()            # a new fault is in /diagnostics at once
        fb = self.master.feedback()
        if not fb.valid or not (self.master.homed or not self.master_config.homing_method):
            return       # an incremental encoder reads 0 until homed: no measurement yet
        # stamped with the SYNC the samples answer (its wall-clock send time: ROS time), not
        # when this timer ran
        stamp = ns_to_stamp(round(fb.wall * 1e9) if fb.wall else
                            self._ros_minus_perf_ns + round(fb.stamp * 1e9))
        self._last_js_wall = fb.wall
        self._js_pub.publish(joint_state(self.names, position=fb.position, velocity=fb.velocity,
                                         effort=fb.force, stamp=stamp))
        if self.master.state is MasterState.ENABLED:
            self._check_wrench(fb.position, fb.force)

    def _wrench(self, q: np.ndarray, forces: np.ndarray) -> np.ndarray | None:
        """The platform wrench of measured positions and efforts: the pose by
        ``forward_nearest`` from the last one, then ``J^T f`` there (the mechanism's ``wrench``).

        ``forward_nearest`` is a pure function of ``(q, hint)``; at rest both repeat bit for bit
        (the hint is the pose found from the same ``q`` the sample before), so the pose of the
        last call with the same inputs, and the rows of ``J`` there, serve again instead of
        solving the forward kinematics anew. The wrench is computed for every sample (the
        efforts change): for a planar RPR in plain floats (:class:`~brace_control.mechanisms.
        planar_floats.PlanarRprFloats`, checked against the model at start-up; equal to the
        model's to rounding), else by the mechanism.
        """
        if self.mechanism is None or self._pose_hint is None:
            return None
        q = np.asarray(q, dtype=float)
        key = (q.tobytes(), self._pose_hint.tobytes())
        if key == self._fk_key:
            pose, rows = self._fk_pose, self._fk_rows
        else:
            try:
                pose = np.asarray(self.mechanism.forward_nearest(q, self._pose_hint), float)
            except ValueError:
                return None
            rows = None
            if self._legs is not None and pose.shape == (3,) and np.isfinite(pose).all():
                try:
                    lengths, rows = self._legs.lengths_and_rows(*pose.tolist())
                except ZeroDivisionError:               # a leg of zero length: the model raises
                    rows = None
                if rows is not None and min(lengths) <= 1e-12:
                    rows = None
            self._fk_key, self._fk_pose, self._fk_rows = key, pose, rows
        self._pose_hint = pose
        f = np.asarray(forces, dtype=float)
        if rows is not None and f.shape == (len(rows),) and np.isfinite(f).all():
            return np.array(self._legs.wrench(rows, f.tolist()))
        return np.asarray(self.mechanism.wrench(pose, forces), float)

    def _wrench_exceeds(self) -> bool:
        fb = self.master.feedback()
        w = self._wrench(fb.position, fb.force) if fb.valid else None
        return w is not None and bool(np.any(np.abs(w[:self._wrench_limit.size]) >
                                             self._wrench_limit[:w.size]))

    def _check_wrench(self, q: np.ndarray, forces: np.ndarray) -> None:
        """SAFETY.md 8: platform wrench from the load cells beyond ``safety.max_wrench``."""
        w = self._wrench(q, forces)
        if w is None:
            return
        n = min(w.size, self._wrench_limit.size)
        over = np.abs(w[:n]) > self._wrench_limit[:n]
        if np.any(over):
            self.master.protective_stop(
                FaultKind.WRENCH_LIMIT,
                f'platform wrench {np.round(w, 1).tolist()} exceeds safety.max_wrench '
                f'{self._wrench_limit.tolist()} on axis {np.flatnonzero(over).tolist()}',
                still_present=self._wrench_exceeds)

    # ------------------------------------------------------------------ services

    def _trigger(self, name: str, fn: Callable[[], str]) -> Callable[[Any, Any], Any]:
        """A Trigger service whose work (a 402 transition, a brake along the path, a relief:
        up to seconds) runs in a thread of its own while the executor goes on publishing:
        the callback is a coroutine that awaits the work's future."""
        async def handle(request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
            done: Future = Future(executor=self.executor)

            def work() -> None:
                try:
                    done.set_result((True, fn()))
                except DriverError as exc:
                    done.set_result((False, str(exc)))
                except Exception as exc:  # noqa: BLE001 - a service must answer
                    done.set_result((False, f'{name} failed: {exc!r}'))
            async with self._service_lock:    # one service at a time
                threading.Thread(target=work, name=f'can_driver_{name}', daemon=True).start()
                response.success, response.message = await done
            self.publish_events()                # the new state, at once
            # rclpy wants one severity per call site: two calls
            if response.success:
                self.get_logger().info(f'~/{name}: {response.message}')
            else:
                self.get_logger().error(f'~/{name}: {response.message}')
            return response
        return handle

    def _positions(self) -> str:
        fb = self.master.feedback()
        u = self.master_config.limits.unit
        return ', '.join(f'{n} {p:.4f} {u}' for n, p in zip(self.names, fb.position))

    def _enable(self) -> str:
        self.master.enable()
        return f'OPERATION ENABLED at {self._positions()}'

    def _disable(self) -> str:
        self.master.disable()
        if self.master.supervisor.latched:
            return f'disabled on recover; protective stop latched: {self.master.supervisor.summary()}'
        return 'SWITCH ON DISABLED'

    def _halt(self) -> str:
        self.master.halt()
        return f'QUICK STOP ACTIVE, holding at {self._positions()}'

    def _recover(self) -> str:
        m = self.master
        if not m.supervisor.latched and not any(
                d.state in (State402.FAULT, State402.FAULT_REACTION_ACTIVE) for d in m.status().drives):
            return f'nothing to recover: no protective stop is latched (drives {m.state.value}); nothing was changed'
        blocking = m.recover()
        if blocking:
            raise _Refused('not recovered, cause still present: '
                           + '; '.join(f.describe() for f in blocking))
        return 'recovered: drives SWITCH ON DISABLED, call ~/enable'

    def _relieve(self) -> str:
        return self.master.relieve()

    def _soft_limit_context(self, index: int, force: float) -> str:
        """What a soft-limit stop adds to its reason: the wrench capacity at the pose (SAFETY.md 14)."""
        if self.mechanism is None or not hasattr(self.mechanism, 'wrench_capacity'):
            return ''
        fb = self.master.feedback()
        try:
            pose = np.asarray(self.mechanism.forward_nearest(fb.position, self._pose_hint), float)
            cap, limiting = self.mechanism.wrench_capacity(
                pose, float(self.cfg['actuator']['max_force']), return_limiting=True)
        except ValueError as exc:
            return f' (capacity unknown: {exc})'
        axes = getattr(self.mechanism, 'wrench_axes', tuple(f'#{i}' for i in range(len(cap))))
        parts = ', '.join(f'{a} {c:.3g}' for a, c in zip(axes, cap))
        return f'; wrench capacity at pose {np.round(pose, 4).tolist()}: {parts}'

    def _home(self) -> str:
        self.master.home()
        return f'homed (method {self.master_config.homing_method}) at {self._positions()}'

    # ------------------------------------------------------------------ diagnostics

    def diagnostics(self) -> DiagnosticArray:
        """One status per drive, one for the bus, one for the cycle, one for safety."""
        st = self.master.status()
        prefix = f'brace_control/{self.get_name()}'
        hw = f'{self.master_config.interface}:{self.master_config.channel}'
        out: list[DiagnosticStatus] = []

        def status(name: str, level: str, message: str, **values: Any) -> None:
            out.append(DiagnosticStatus(
                level=_LEVEL[level], name=f'{prefix}/{name}', message=message, hardware_id=hw,
                values=[KeyValue(key=k, value=str(v)) for k, v in values.items()]))

        faults_by_drive: dict[str | None, list[str]] = {}
        for f in st.faults:
            faults_by_drive.setdefault(f.drive, []).append(f'{f.kind.value}: {f.cause}')
        for d in st.drives:
            bad = (d.state in (State402.FAULT, State402.FAULT_REACTION_ACTIVE)
                   or bool(faults_by_drive.get(d.name)))
            level = 'error' if bad else ('ok' if d.nmt == 'OPERATIONAL' else 'warn')
            status(f'drive/{d.name}', level, f'{d.nmt} / {d.state.value}',
                   node_id=d.node_id, nmt=d.nmt, state_402=d.state.value,
                   statusword=f'{d.statusword:04X}h', position_m=f'{d.position:.6f}',
                   velocity_mps=f'{d.velocity:.5f}', force_n=f'{d.force:.2f}',
                   target_m=f'{d.target:.6f}', heartbeat_age_s=f'{d.heartbeat_age:.3f}',
                   last_emcy=d.last_emcy or 'none',
                   faults='; '.join(faults_by_drive.get(d.name, [])) or 'none')
        b = st.bus
        status('bus', 'error' if b.error_state == 'bus off' else
               'warn' if b.error_state != 'active' else 'ok',
               f'{b.error_state}, load {b.load * 100:.1f} %',
               load_percent=f'{b.load * 100:.1f}', frames_per_s=f'{b.frames_per_s:.0f}',
               error_state=b.error_state, error_frames=b.error_frames, send_failures=b.send_failures,
               bitrate=self.master_config.bitrate)
        t = st.timing
        overrun_frac = t.overrun_fraction
        status('cycle', 'warn' if overrun_frac > 1e-3 else 'ok',
               f'SYNC {self.master_config.sync_rate_hz:g} Hz, period error p99 {t.p99 * 1e6:.0f} us',
               period_error_p50_us=f'{t.p50 * 1e6:.0f}', period_error_p99_us=f'{t.p99 * 1e6:.0f}',
               period_error_max_us=f'{t.max * 1e6:.0f}', overruns=t.overruns, cycles=t.cycles)
        if st.faults:
            level, message = 'error', f'protective stop: {st.faults[0].describe()}'
        elif st.warnings:
            level, message = 'warn', st.warnings[0]
        else:
            level, message = 'ok', st.state.value
        status('safety', level, message, state=st.state.value, homed=st.homed,
               faults=' | '.join(f.describe() for f in st.faults) or 'none',
               warnings=' | '.join(st.warnings) or 'none',
               stale_setpoint_holds=st.stale_setpoint_holds,
               accepted_setpoints=st.accepted_setpoints,
               setpoints_accepted=self.accepted, setpoints_rejected=self.rejected,
               last_rejection=self.last_rejection or 'none')
        msg = DiagnosticArray()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.status = out
        return msg

    def publish_diagnostics(self) -> None:
        self._diag_pub.publish(self.diagnostics())


class _AsyncLock:
    """An ``async with`` lock for coroutine service callbacks on one executor thread: a second
    service waits (yielding to the executor) until the first has answered."""

    def __init__(self) -> None:
        self._held = False

    async def __aenter__(self) -> None:
        while self._held:
            await _yield()
        self._held = True

    async def __aexit__(self, *exc: object) -> None:
        self._held = False


class _Yield:
    def __await__(self):
        yield


def _yield() -> _Yield:
    """Give the executor back one turn (rclpy resumes pending coroutine tasks on its next wake)."""
    return _Yield()


class _Refused(DriverError):
    """A service request the master declined (the message says why)."""


def main(args: Sequence[str] | None = None) -> int:
    """``ros2 run brace_control can_driver_node``; exit code 0, 1 when the bus or a drive
    did not come up, 2 on a configuration error (:func:`~.runner.run_node`)."""
    from .runner import run_node
    return run_node(lambda: CanDriverNode(boot=False), executable='can_driver_node',
                    summary='CiA 402 drives of the brace on CAN (or the simulated brace), '
                            'trajectories and setpoints in, joint states out',
                    args=args, start=lambda node: node.start(), startup_errors=(DriverError,))


if __name__ == '__main__':
    sys.exit(main())
