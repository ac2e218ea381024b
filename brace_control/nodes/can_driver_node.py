"""can_driver_node: the brace's CiA 402 drives on CAN, as a ROS 2 lifecycle (managed) node.

``ros2 run brace_control can_driver_node [--manual-lifecycle] --ros-args --params-file config/lumbar_brace.yaml``

A hardware driver is a lifecycle node (``rclpy.lifecycle``, like ros2_canopen's drivers and
ros2_control's hardware components); ``/can_driver_node/change_state``, ``get_state``,
``get_available_transitions`` ... (``lifecycle_msgs``) drive it, e.g. ``ros2 lifecycle set
/can_driver_node configure``:

* **unconfigured** (after construction; after ``cleanup``; after a failed ``configure`` or an
  error): no bus is open, nothing is sent;
* ``configure``: open the bus (``can.sim``: first start the simulated brace on the same
  python-can channel), boot the drives (NMT, the SDO configuration and PDO mapping of
  docs/can.md, NMT OPERATIONAL); a drive that does not boot, a bus that does not open or an
  SDO a drive rejects: FAILURE, logged with the cause, everything opened is closed again and
  the node stays unconfigured;
* **inactive**: the drives are configured, OPERATIONAL and SWITCH ON DISABLED (power stage
  off). The SYNC cycle runs from the boot on: the boot proves each drive answers SYNC with its
  TPDO, and the supervision (heartbeats, stale encoders, EMCY; docs/safety.md §2, §9) judges those
  answers; a fault while inactive is latched and reported. Nothing can move: motion services
  are refused, trajectories and setpoints rejected, no ``/brace/joint_states`` (ros2_control's
  INACTIVE: "states can be read, command interfaces are not available");
* ``activate``: commands are accepted (``~/home``, ``~/enable``, trajectories, setpoints) and
  ``/brace/joint_states`` and the simulator's truth are published (lifecycle publishers). The
  drives stay disabled until ``~/home`` and ``~/enable``;
* ``deactivate``: stop taking commands, brake a running motion along its path (all axes on
  one time base), then disable the drives (SWITCH ON DISABLED) and stop publishing. Refused
  (FAILURE, the node stays active) while a protective stop is latched and a drive still holds
  the load in QUICK STOP ACTIVE: ``~/relieve`` and ``~/recover`` need the node active
  (docs/safety.md §15: nobody stays clamped); ``shutdown`` powers the drives off regardless;
* ``cleanup``: close the bus (drives disabled, NMT pre-operational, SYNC stopped, the
  simulated brace powered off; it keeps its physical pose for the next ``configure``);
* ``shutdown`` (from any state) closes as cleanup does; an exception inside a transition is
  logged with its traceback and ends in ERROR; ``on_error`` disables the drives, closes the bus
  and returns to unconfigured.

``std_srvs/Trigger`` services called in a state that does not allow them answer
``success=False`` with the lifecycle state in the message (``~/disable`` is allowed when
inactive too). Without ``--manual-lifecycle`` the executable configures and activates the node
itself at start-up (exit code 1 if that fails); ``brace-bringup`` and ``launch/brace.launch.py``
bring it to active the same way unless told ``--manual-lifecycle`` / ``manual_lifecycle:=true``.

When active:

* subscribes ``/brace/actuator_trajectory`` (``trajectory_msgs/JointTrajectory``, by
  actuator name): a planned motion, executed in the SYNC thread (ros2_control's
  JointTrajectoryController semantics, :mod:`brace_control.control.execution`): sampled at every
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
  (docs/safety.md §5, §6). No setpoint for ``safety.command_timeout``: decelerate along the
  current direction and hold (docs/safety.md §1); a step beyond the step limit: protective stop
  (docs/safety.md §7);
* publishes ``/brace/execution_status`` (``diagnostic_msgs/DiagnosticStatus``, one message
  per event of a trajectory: ``name`` = ``can_driver_node/trajectory/<stamp ns>``,
  ``message`` = accepted | rejected | started | finished | stopped | preempted, ``values``
  stamp, kind, reason, positions, time: when it happened, ns of ROS time; ``started``: the
  SYNC whose targets are the trajectory's first); and per event of an interaction
  (``name`` = ``can_driver_node/interaction/<n>``): started, stopping, stopped, aborted,
  preempted, and per wrench goal from ``/brace/interaction/goal``: ``goal_applied`` (the
  cycle's admittance has it: ``applied_ns``, the wall clock then) or ``goal_rejected`` (the
  reason), each with ``goal_stamp`` (ns, the goal message's stamp: which goal);
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
  (docs/safety.md §15): slowly, under force supervision, the way that unloads each leg, until
  every force is below ``safety.release_force``; ``~/recover`` then succeeds;
* above ``safety.soft_force_limit`` a motion that keeps pressing decelerates along its path
  and holds (its trajectory reported stopped with the leg, the force and the wrench capacity
  at that pose); nothing latches. ``safety.force_limit`` latches a protective stop;
* ``/diagnostics``: one status per drive (NMT, 402 state, last EMCY, heartbeat age),
  the bus (load, error state) and the SYNC cycle (period error p50/p99, overruns; with
  ``can.sim``, ``simulator_cpu_s``: the CPU seconds the simulated brace took so far);
* reports the platform-wrench tiers the master runs in its SYNC cycle
  (:mod:`brace_control.safety`): beyond ``safety.max_wrench`` a protective stop
  (docs/safety.md §8), a motion heading past it braked (§14).

The control cycle runs in a process of its own (``can.cycle_process``, default on;
:mod:`brace_control.can.process`): the master, its SYNC thread and the bus, where rclpy never
runs, so no callback, recorder or DDS call of this node holds the interpreter lock past a
SYNC deadline. The node reads the master's state from the samples that process sends at
``can.joint_state_rate_hz`` and after every command; commands are calls into it. The
process ends with the node, however the node ends (it disables the drives first).

With ``can.sim: true`` the simulated brace (:mod:`brace_control.sim`) is started in the
cycle's process on the same python-can channel before the master boots (a ``virtual`` bus
only exists inside one process), and its ground truth is published at ``sim.truth_rate_hz``
(what a user compares an estimator or a controller against; nothing of the stack
subscribes to it), with ``topics.truth_qos`` (``topics.TRUTH_KEPT_S`` of it kept for a
reader that has not acknowledged it yet; a tick that came late publishes the truths it
missed, each with its own SYNC's stamp), each topic while something subscribes it (they
are volatile: a reader gets the next sample either way, and nobody pays for truth nobody
reads). Two truths published in turn more than ``TRUTH_HOLE_WARN_S`` apart are a warning in
the log, and the cycle's process link says whose side the time was on (a cycle that stood
still, or a node behind): a hole in a recorded truth is explained in the run's log. The
topics:

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

One mechanism model per driver process: the node builds it once and hands it to the master
(home lengths, actuator ranges) and to the simulated brace. The mechanism classes keep no
per-call state (every attribute is set in their constructor, every method reads only, the
arrays they hand out are copies), so the executor thread (wrench check, ground truth), the SYNC
thread (the soft-limit context) and the simulator's receive thread may call one instance at
the same time. The simulator's second model (its stroke widened by 1 cm for the physics at the
end stops) is a different mechanism and stays its own.

In-process use (one-process bring-up, tests)::

    node = CanDriverNode(context=ctx, cli_args=['--ros-args', '--params-file', yaml])
    node.autostart()                  # configure + activate; DriverError if either fails
    ...
    node.shutdown(); node.destroy_node()
"""
from __future__ import annotations

import math
import sys
import threading
import time
import traceback
from collections.abc import Callable, Sequence
from typing import Any

import can
import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rclpy.task import Future
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger
from trajectory_msgs.msg import JointTrajectory

from ..can import (ActuatorTrajectory, BraceMaster, DriverError, DriverInitializationError,
                   MasterConfig, MasterState, State402, TrajectoryInvalid)
from ..can.process import MasterProcess, label_threads, sync_truth, wrench_capacity_context
from ..config import ConfigError
from . import topics
from .msgs import (MalformedMessage, joint_knots_from_msg, joint_state, joint_state_arrays,
                   ns_to_stamp, stamp_to_ns, status_msg)
from .params import declare_device_parameters
from .runner import allow_long_work
from .timers import timer_callback

__all__ = ['CanDriverNode', 'main']

#: rejection errors at most once per this many seconds (the stream runs at 200 Hz)
REJECT_LOG_PERIOD = 1.0
#: m: pull-only legs whose lengths are farther than this from the lengths of the pose that
#: fits them best hang slack: ~/enable takes the slack up (so it does after a relief)
TAKE_UP_GAP_M = 0.0005
#: N: the tension a take-up brings every cable to when the mechanism sets no tension_min
TAKE_UP_TENSION_N = 1.0
#: Hz: execution events and the driver state are published this often (when they change)
EVENT_RATE_HZ = 50.0
#: s between two ground truths published in turn past which the node warns: the simulated
#: world runs a SYNC every few ms, so a hole that long is a cycle that stood still or truths
#: this node could not keep (``can.process.TRUTH_BACKLOG``)
TRUTH_HOLE_WARN_S = 1.0

#: lifecycle states in which a Trigger service is taken
ACTIVE = frozenset({'active'})
CONFIGURED = frozenset({'inactive', 'active'})
#: what a failed configure expects (a bus, a drive, a parameter of the simulator); anything
#: else is a bug: ERROR, with its traceback
_EXPECTED_ERRORS = (DriverError, ConfigError, can.CanError, OSError)

_LEVEL = {'ok': DiagnosticStatus.OK, 'warn': DiagnosticStatus.WARN, 'error': DiagnosticStatus.ERROR}


class CanDriverNode(LifecycleNode):
    """The CAN driver: a :class:`~brace_control.can.BraceMaster` behind topics and services,
    managed by the ROS 2 lifecycle (module docstring).

    The constructor reads and checks the parameters and builds the mechanism model; it opens
    no bus (the node starts unconfigured). :meth:`autostart` (or ``ros2 lifecycle set``, or a
    ``lifecycle_msgs/ChangeState`` call) configures and activates it.

    :param node_name: ROS node name (services are ``~/enable`` etc. under it).
    :param kwargs: passed to :class:`rclpy.lifecycle.LifecycleNode` (``context``,
        ``cli_args``, ``parameter_overrides``, ...).
    :raises ConfigError: a bad parameter (named).
    """

    def __init__(self, *, node_name: str = 'can_driver_node', **kwargs: Any) -> None:
        self.sim: Any = None
        self.master: BraceMaster | MasterProcess | None = None
        self._lifecycle = 'unconfigured'
        self._active = False
        #: why the last transition failed ('' if it did not): :meth:`autostart` raises it
        self.last_transition_error = ''
        # transitions and the services' work never overlap: a transition waits for a running
        # service (a 402 transition, a relief) and a service never sees the bus half closed
        self._transition_lock = threading.RLock()
        self._previous_switch_interval: float | None = None
        self._constructed = False             # a ConfigError leaves a half-built node to destroy
        super().__init__(node_name, **kwargs)
        self.cfg = declare_device_parameters(self, ('mechanism', 'actuator', 'can', 'safety', 'sim',
                                                     'trajectory', 'interaction'), cli_args=kwargs.get('cli_args'))
        self.names: tuple[str, ...] = tuple(self.cfg['mechanism']['actuator_names'])
        self.mechanism = self._mechanism()
        self.master_config = MasterConfig.from_device_config(self.cfg, mechanism=self.mechanism)
        self.rejected = 0
        self.accepted = 0
        self.last_rejection = ''
        self._last_reject_log = -math.inf
        self._last_faults: tuple = ()
        # services take up to seconds (402 transitions, braking, a relief): their work runs in
        # a thread and the callback awaits it (_trigger), so one thread of an executor serves
        # the streams meanwhile; a multi-threaded executor would cost a core share for nothing.
        # The lifecycle services run in the node's default group (nothing else uses it).
        self._service_group = MutuallyExclusiveCallbackGroup()
        self._stream_group = MutuallyExclusiveCallbackGroup()
        self._service_lock = _AsyncLock()
        # measurements flow only when active (lifecycle publishers); the driver's state, the
        # trajectories' events and the diagnostics are published in every state: they say
        # why nothing moves (an inactive driver answers a trajectory "rejected", with why)
        self._js_pub = self.create_lifecycle_publisher(JointState, topics.JOINT_STATES, topics.STATE_QOS)
        self._diag_pub = self.create_publisher(DiagnosticArray, topics.DIAGNOSTICS,
                                               topics.DIAGNOSTICS_QOS)
        self._exec_pub = self.create_publisher(DiagnosticStatus, topics.EXECUTION_STATUS,
                                               topics.STATUS_QOS)
        self._state_pub = self.create_publisher(DiagnosticStatus, topics.DRIVER_STATE,
                                                topics.LATCHED_QOS)
        self._last_state_key: tuple | None = None
        self._last_js_wall = 0.0                # the SYNC (wall clock) of the last joint state
        self._last_js_stamp = -1.0              # the SYNC (perf_counter) of the last joint state
        # ROS time (ns) minus perf_counter (s) at start-up: trajectory stamps -> the master's
        # clock, SYNC instants -> message stamps (one offset: no jitter from two clock reads)
        self._ros_minus_perf_ns = self.get_clock().now().nanoseconds - round(time.perf_counter() * 1e9)
        self._sub = self.create_subscription(JointState, topics.ACTUATOR_SETPOINT, self._on_setpoint,
                                             topics.SETPOINT_QOS, callback_group=self._stream_group)
        self._traj_sub = self.create_subscription(JointTrajectory, topics.ACTUATOR_TRAJECTORY,
                                                  self._on_trajectory, topics.TRAJECTORY_QOS,
                                                  callback_group=self._stream_group)
        for name, fn, allowed in (('enable', self._enable, ACTIVE), ('disable', self._disable, CONFIGURED),
                                  ('halt', self._halt, ACTIVE), ('recover', self._recover, ACTIVE),
                                  ('home', self._home, ACTIVE), ('relieve', self._relieve, ACTIVE)):
            self.create_service(Trigger, f'~/{name}', self._trigger(name, fn, allowed),
                                callback_group=self._service_group)
        self._init_interaction()
        rate = float(self.cfg['can']['joint_state_rate_hz'])
        # timers of the active state are created cancelled (rclpy's create_timer has no
        # autostart in Humble) and reset on activate
        self._js_timer = self.create_timer(1.0 / rate, timer_callback(self._publish_joint_states),
                                           callback_group=self._stream_group)
        self._js_timer.cancel()
        self._diag_timer = self.create_timer(1.0, timer_callback(self.publish_diagnostics),
                                             callback_group=self._stream_group)
        self._event_timer = self.create_timer(1.0 / EVENT_RATE_HZ, timer_callback(self.publish_events),
                                              callback_group=self._stream_group)
        self._event_timer.cancel()
        self._truth_timer: Any = None
        self._truth_published = 0.0             # stamp of the newest truth published (s)
        if self.cfg['can']['sim']:
            self._truth_publishers()
        self._constructed = True
        self.publish_state(force=True)

    def _mechanism(self) -> Any:
        from ..mechanisms import mechanism_from_config
        return self.cfg.model or mechanism_from_config(self.cfg)

    # ------------------------------------------------------------------ lifecycle

    @property
    def lifecycle_state(self) -> str:
        """The primary lifecycle state: ``unconfigured``, ``inactive``, ``active`` or ``finalized``."""
        return self._lifecycle

    def autostart(self) -> None:
        """Configure and activate (what ``brace-bringup`` and the executable do unless
        ``--manual-lifecycle``).

        :raises DriverError: a transition failed (the message says which and why); the node is
            then unconfigured (configure failed) or inactive (activate failed).
        """
        for name, trigger in (('configure', self.trigger_configure), ('activate', self.trigger_activate)):
            self.last_transition_error = ''
            if trigger() != TransitionCallbackReturn.SUCCESS:
                raise DriverInitializationError(
                    self.last_transition_error or f'{name} failed (node {self._lifecycle})')

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Open the bus (``can.sim``: start the simulated brace first), boot and configure the
        drives. SUCCESS: inactive, drives OPERATIONAL and disabled. FAILURE (the bus did not
        open, a drive did not boot or rejected its set-up, a bad simulator parameter): all
        opened is closed again, the cause logged, the node stays unconfigured. ERROR (an
        unexpected exception): logged with its traceback, then :meth:`on_error`."""
        allow_long_work()         # in the executor's thread: seconds on a loaded host
        with self._transition_lock:
            try:
                self._open()
            except _EXPECTED_ERRORS as exc:
                self._close()
                return self._failed('configure', f'{exc}; the node stays unconfigured',
                                    TransitionCallbackReturn.FAILURE)
            except Exception as exc:  # noqa: BLE001 - a transition must answer
                self._close()
                return self._failed('configure', repr(exc), TransitionCallbackReturn.ERROR, trace=True)
            self._set_lifecycle('inactive')
            self._event_timer.reset()
            mc = self.master_config
            self.get_logger().info(
                f'configured: {len(self.names)} drives OPERATIONAL (nodes {list(mc.node_ids)}) on '
                f'{mc.interface}:{mc.channel}, SYNC {mc.sync_rate_hz:g} Hz, drives disabled; '
                'activate to command them')
            return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Accept commands, publish joint states and the simulator's truth. The drives stay
        disabled (``~/home``, ``~/enable``). FAILURE: the bus is not open (not configured)."""
        allow_long_work()         # in the executor's thread: seconds on a loaded host
        with self._transition_lock:
            if self.master is None:
                return self._failed('activate', 'the bus is not open (configure first)',
                                    TransitionCallbackReturn.FAILURE)
            ret = super().on_activate(state)          # the lifecycle publishers
            if ret != TransitionCallbackReturn.SUCCESS:
                return self._failed('activate', 'a lifecycle publisher did not activate', ret)
            self._active = True
            self._set_lifecycle('active')
            if not isinstance(self.master, MasterProcess):   # else each sample publishes
                self._js_timer.reset()
            if self._truth_timer is not None:
                self._truth_published = 0.0          # the record starts now, not with a backlog
                self._truth_timer.reset()
            self.get_logger().info(f'active: drives {self.master.state.value}; call ~/home then ~/enable')
            return TransitionCallbackReturn.SUCCESS

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Stop taking commands, brake a running motion along its path, disable the drives,
        stop publishing measurements. FAILURE (still active): a protective stop is latched and
        a drive holds the load (relieve and recover first, or shut down). ERROR: the drives did
        not reach SWITCH ON DISABLED (:meth:`on_error` then powers them off with the bus)."""
        allow_long_work()         # in the executor's thread: seconds on a loaded host
        with self._transition_lock:
            m = self.master
            if m is None:
                return self._failed('deactivate', 'the bus is not open', TransitionCallbackReturn.FAILURE)
            holding = [d.name for d in m.status().drives
                       if d.state in (State402.QUICK_STOP_ACTIVE, State402.OPERATION_ENABLED)]
            if m.latched and holding:
                return self._failed(
                    'deactivate',
                    f'a protective stop is latched ({m.fault_summary()}) and drive(s) '
                    f'{holding} hold the load in quick stop; call ~/relieve and ~/recover while '
                    'active, then deactivate (or shutdown to power the drives off as they are)',
                    TransitionCallbackReturn.FAILURE)
            self._active = False                      # no new command from here on
            self._js_timer.cancel()
            if self._truth_timer is not None:
                self._truth_timer.cancel()
            try:
                m.disable()                           # brakes along the path first
            except Exception as exc:  # noqa: BLE001 - a transition must answer
                return self._failed('deactivate', f'the drives were not disabled: {exc}',
                                    TransitionCallbackReturn.ERROR)
            super().on_deactivate(state)
            self._set_lifecycle('inactive')
            where = f' at {self._positions()}' if m.homed else ''
            self.get_logger().info(f'inactive: drives disabled{where}')
            return TransitionCallbackReturn.SUCCESS

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Close the bus (drives disabled, NMT pre-operational, SYNC stopped), power the
        simulated brace off. SUCCESS: unconfigured."""
        allow_long_work()         # in the executor's thread: seconds on a loaded host
        with self._transition_lock:
            self._close()
            self._set_lifecycle('unconfigured')
            self.get_logger().info('cleaned up: CAN bus closed')
            return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        """From any state: disable the drives (whatever a protective stop says), close the bus.
        SUCCESS: finalized."""
        with self._transition_lock:
            self._close()
            super().on_deactivate(state)
            self._set_lifecycle('finalized')
            self.get_logger().info(f'shut down (from {state.label}): drives disabled, CAN bus closed')
            return TransitionCallbackReturn.SUCCESS

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        """A transition raised or ended in ERROR: power the drives off (SWITCH ON DISABLED,
        whatever a protective stop says), close the bus. SUCCESS: unconfigured."""
        with self._transition_lock:
            self._close()
            super().on_deactivate(state)
            self._set_lifecycle('unconfigured')
            self.get_logger().error(f'error during a transition from {state.label}: drives disabled, '
                                    'CAN bus closed; the node is unconfigured')
            return TransitionCallbackReturn.SUCCESS

    def _failed(self, transition: str, why: str, ret: TransitionCallbackReturn, *,
                trace: bool = False) -> TransitionCallbackReturn:
        """Log a failed transition (the reason, or the traceback) and return ``ret``."""
        self.last_transition_error = f'{transition} failed: {why}'
        text = self.last_transition_error + (f'\n{traceback.format_exc()}' if trace else '')
        self.get_logger().error(text)
        return ret

    def _set_lifecycle(self, label: str) -> None:
        self._lifecycle = label
        self.publish_state(force=True)

    def _open(self) -> None:
        """Start the simulated brace (``can.sim``) and boot the drives (a new master: one
        master object per configure, its supervision and statistics start afresh).

        :raises DriverError: the bus could not be opened or a drive did not boot.
        """
        mc = self.master_config
        switch_us = int(self.cfg['can']['gil_switch_interval_us'])
        if switch_us > 0 and self._previous_switch_interval is None:
            # process-wide: a thread busy in Python (the executor, the simulator in this
            # process, the cycle process's link) then holds the GIL at most this long when
            # another wakes (the SYNC thread; a reply from the cycle process): Python's
            # default is 5 ms; restored when the bus closes (in-process bring-ups, tests)
            self._previous_switch_interval = sys.getswitchinterval()
            sys.setswitchinterval(switch_us * 1e-6)
        if self.cfg['can']['cycle_process']:
            # the cycle, the drives' bus and the simulated brace in a process where rclpy
            # never runs (brace_control.can.process); its GIL switch interval is its own
            self.master = MasterProcess(self.cfg, mc, on_snapshot=self._on_sample)
            self.sim = self.master.sim
            if self.sim is not None:
                self.get_logger().info(f'simulated brace on {mc.interface}:{mc.channel} '
                                       f'(control cycle process {self.master.pid})')
            self.master.boot()
            return
        if self.cfg['can']['sim']:
            if self.sim is None:
                from ..sim import SimulatedBrace
                # the EDS as the master resolved it (the node's parameters carry no file path)
                self.sim = SimulatedBrace(self.cfg, channel=mc.channel, interface=mc.interface,
                                          eds=mc.eds, mechanism=self.mechanism, start=False)
            self.sim.start()
            self.get_logger().info(f'simulated brace on {mc.interface}:{mc.channel}')
        master = BraceMaster(mc)
        master.soft_limit_context = wrench_capacity_context(
            master, self.mechanism, float(self.cfg['actuator']['max_force']))
        self.master = master
        master.boot()
        label_threads(master)

    def _close(self) -> None:
        """Stop taking commands, disable the drives, close the bus, power the simulated brace
        off. Never raises (a failure is logged): every transition that closes ends closed."""
        self._active = False
        for timer in (self._js_timer, self._event_timer, self._truth_timer):
            if timer is not None:
                timer.cancel()
        m = self.master
        if m is not None:
            try:
                m.shutdown()              # drives disabled whatever the latch says, bus closed
            except Exception as exc:  # noqa: BLE001 - closing anyway
                self.get_logger().error(f'closing the CAN master: {exc!r}')
            try:
                self.publish_events()     # the motions the shutdown ended
            except Exception:  # noqa: BLE001
                pass
            self.master = None
        if self.sim is not None:
            try:
                self.sim.shutdown()
            except Exception as exc:  # noqa: BLE001
                self.get_logger().error(f'stopping the simulated brace: {exc!r}')
            if isinstance(m, MasterProcess):
                self.sim = None             # it lived and ended with the cycle's process
        if self._previous_switch_interval is not None:
            sys.setswitchinterval(self._previous_switch_interval)
            self._previous_switch_interval = None
        self._last_faults = ()

    def _truth_publishers(self) -> None:
        """Publishers and timer of the simulator's ground truth (module docstring): lifecycle
        publishers, the timer runs while active."""
        if self.mechanism is None:
            return
        from geometry_msgs.msg import PoseStamped, WrenchStamped

        from .kinetics_node import platform_frame_wrench
        from .msgs import pose_kind, pose_msg, wrench_msg
        self.create_subscription(PoseStamped, topics.SIM_BODY_REST, self._on_body_rest,
                                 topics.BODY_REST_QOS, callback_group=self._stream_group)
        rate = float(self.cfg['sim']['truth_rate_hz'])
        qos = topics.truth_qos(rate)
        self._truth_pubs = tuple(self.create_lifecycle_publisher(t, name, qos) for t, name in (
            (JointState, topics.SIM_JOINT_STATES), (PoseStamped, topics.SIM_POSE),
            (WrenchStamped, topics.SIM_WRENCH), (PoseStamped, topics.SIM_BODY_POSE)))
        kind = pose_kind(self.mechanism)
        base, platform = self.cfg['base_frame'], self.cfg['platform_frame']
        last_wrench: list[Any] = [None, None]       # (pose, efforts) bytes, the platform wrench
        # the cycle's process: the truths of its snapshots, one per joint-state sample; kept
        # at least this far apart (s): the truth's rate, with half a sample's slack
        spacing = max(1.0 / rate - 0.5 / float(self.cfg['can']['joint_state_rate_hz']), 0.0)

        def truths(sim: Any) -> list[Any]:
            """What this tick publishes: in this process, the truth of the SYNC the last
            /brace/joint_states described (same stamp: a comparison with the estimate pairs
            the same instant, not two SYNCs ms apart). From the cycle's process, every
            snapshot's truth since the last one published, ``spacing`` apart: a tick that
            came late (this process starved for a while) publishes the ones it missed,
            stamped as they were, instead of leaving a hole in the record. Nothing new for
            two ticks (the world stands still): the newest again."""
            if not hasattr(sim, 'truths_since'):
                return [sync_truth(sim, self._last_js_wall)]
            newest = sim.truth()
            last = self._truth_published
            if not last:                            # the first tick: the newest
                self._truth_published = newest.stamp if newest is not None else 0.0
                return [newest] if newest is not None else []
            out: list[Any] = []
            kept = sim.truths_since(last)
            for truth in kept:
                if truth.stamp >= last + spacing:
                    out.append(truth)
                    last = truth.stamp
            if out:
                stamps = [self._truth_published] + [t.stamp for t in out]
                hole = max(b - a for a, b in zip(stamps, stamps[1:]))
                if hole > TRUTH_HOLE_WARN_S:
                    # the evidence a hole in a recorded truth needs: the world stood still
                    # (the cycle process's own warning says so), or this node published
                    # nothing for longer than the truths it keeps
                    self.get_logger().warning(
                        f'ground truth: {hole:.2f} s between two truths published in turn; the '
                        f'truths kept reach back {time.time() - kept[0].stamp:.2f} s')
                self._truth_published = last
                return out
            # none new for two ticks: the world stands still (no SYNC), its truth goes on
            stale = newest is not None and time.time() - newest.stamp > 2.0 / rate
            return [newest] if stale and newest.stamp <= last else []

        def publish() -> None:
            sim = self.sim
            if not self.context.ok() or sim is None or not self._active:
                return                    # shutting down / closed: the publishers are going
            # volatile topics: a message nobody reads is not made (a reader that matches gets
            # the next one, as it would anyway)
            wanted = [p.get_subscription_count() > 0 for p in self._truth_pubs]
            if any(wanted):
                for truth in truths(sim):
                    publish_one(truth, wanted)
            else:
                self._truth_published = 0.0   # a reader that comes gets the newest: no hole

        def publish_one(truth: Any, wanted: list[bool]) -> None:
            js_pub, pose_pub, wrench_pub, body_pub = self._truth_pubs
            stamp = ns_to_stamp(round(truth.stamp * 1e9) if truth.stamp else
                                self.get_clock().now().nanoseconds)
            if wanted[0]:
                js_pub.publish(joint_state(self.names, position=truth.lengths,
                                           velocity=truth.velocities, effort=truth.forces, stamp=stamp))
            if wanted[1]:
                pose_pub.publish(pose_msg(truth.pose, frame_id=base, stamp=stamp, mechanism=self.mechanism))
            if wanted[3] and truth.body_pose is not None:
                body_pub.publish(pose_msg(truth.body_pose, frame_id=base, stamp=stamp,
                                          mechanism=self.mechanism))
            if not wanted[2]:
                return
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
        self._truth_timer = self.create_timer(1.0 / rate,
                                              timer_callback(publish), callback_group=self._stream_group)
        self._truth_timer.cancel()                  # runs while active

    def _on_body_rest(self, msg: Any) -> None:
        """Simulation: where the patient's body rests (a test or a script moves the patient)."""
        from .msgs import pose_from_msg, stamp_to_sec
        sim = self.sim
        if sim is None:
            self.get_logger().warning('body rest pose ignored: the simulated brace starts on configure',
                                      throttle_duration_sec=1.0)
            return
        try:
            pose = pose_from_msg(msg, frame_id=self.cfg['base_frame'], mechanism=self.mechanism)
            stamp = stamp_to_sec(msg.header.stamp)
            sim.set_rest_pose(pose, stamp if stamp > 0.0 else None)
        except ValueError as exc:
            self.get_logger().warning(f'body rest pose ignored: {exc}', throttle_duration_sec=1.0)

    def shutdown(self) -> None:
        """The lifecycle ``shutdown`` transition from whatever state the node is in: drives
        disabled, bus closed, simulator stopped; the node is finalized. Idempotent; if the
        state machine cannot take the transition now (another one is under way) the bus is
        closed directly."""
        if self._lifecycle == 'finalized':
            return
        if not self._constructed:             # nothing was opened
            self._lifecycle = 'finalized'
            return
        try:
            self.trigger_shutdown()
        except Exception as exc:  # noqa: BLE001 - rcl refuses a shutdown in a transition state
            self.get_logger().warning(f'lifecycle shutdown not possible now ({exc}); closing the bus')
        if self._lifecycle != 'finalized':
            with self._transition_lock:
                self._close()
                self._lifecycle = 'finalized'

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

    def _refusal(self, what: str) -> str:
        """Why ``what`` is not taken in the current lifecycle state (with what to do)."""
        state = self._lifecycle
        todo = {'unconfigured': f'no bus is open; ros2 lifecycle set {self.get_fully_qualified_name()} '
                                'configure, then activate',
                'inactive': f'ros2 lifecycle set {self.get_fully_qualified_name()} activate first',
                'finalized': 'the node was shut down; restart it'}.get(state, 'wait for the transition to end')
        return f'{what} refused: the driver is {state} (lifecycle); {todo}'

    def _on_setpoint(self, msg: JointState) -> None:
        m = self.master
        if not self._active or m is None:
            self._reject(self._refusal('setpoint'))
            return
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
            m.set_targets(arrays['position'], stamp=stamp * 1e-9 if stamp else None,
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
        controller checks again against the pose it is at). Either way an event says what
        became of it, named by the goal's stamp: ``goal_applied`` when the cycle has it (a
        client times a step from then, not from its own publish: a starved host delivers a
        goal seconds late) or ``goal_rejected``."""
        from ..interaction import GoalRejected
        from .msgs import pose_kind
        kind = pose_kind(self.mechanism)
        f, t = msg.wrench.force, msg.wrench.torque
        w = {'spherical': [t.x, t.y, t.z], 'planar': [f.x, f.y, t.z], 'xy': [f.x, f.y]}.get(kind, [f.x])
        tag = self._interaction_sessions
        goal_stamp = stamp_to_ns(msg.header.stamp)
        try:
            self.master.set_interaction_goal(w)
        except (ValueError, GoalRejected) as exc:
            self._exec_pub.publish(status_msg(f'{self.get_name()}/interaction/{tag}', 'goal_rejected',
                                              level=DiagnosticStatus.WARN, stamp=tag, kind='goal_rejected',
                                              reason=str(exc), goal=list(w), goal_stamp=goal_stamp))
            return
        self._exec_pub.publish(status_msg(f'{self.get_name()}/interaction/{tag}', 'goal_applied',
                                          stamp=tag, kind='goal_applied', reason='', goal=list(w),
                                          goal_stamp=goal_stamp, applied_ns=time.time_ns()))

    # ------------------------------------------------------------------ planned motions

    def _on_trajectory(self, msg: JointTrajectory) -> None:
        """A whole planned motion: checked, then executed from its stamp (module docstring)."""
        tag = stamp_to_ns(msg.header.stamp)
        now_perf = time.perf_counter()
        m = self.master
        if not self._active or m is None:
            if msg.points:                # a cancel (no points) has nothing to stop here
                why = self._refusal('trajectory')
                self._exec_pub.publish(status_msg(
                    f'{self.get_name()}/trajectory/{tag}', 'rejected', level=DiagnosticStatus.ERROR,
                    stamp=tag, kind='rejected', reason=why))
                self.get_logger().error(f'trajectory {tag} rejected: {why}')
            return
        try:
            _, times, q, qd, qdd = joint_knots_from_msg(msg, self.names)
            if times.size == 0:
                # during interaction the planner's empty trajectory ends the mode for a
                # position goal (trajectory_node plans it once the 'aborted' event says where)
                why = ('a position goal arrived (empty trajectory)' if m.interacting
                       else 'cancel requested (empty trajectory)')
                m.stop_motion(why, tag=tag if tag else None)
                self.publish_events()
                return
            trajectory = ActuatorTrajectory(times, q, qd, qdd)
        except (MalformedMessage, TrajectoryInvalid) as exc:
            self._exec_pub.publish(status_msg(
                f'{self.get_name()}/trajectory/{tag}', 'rejected', level=DiagnosticStatus.ERROR,
                stamp=tag, kind='rejected', reason=f'malformed trajectory: {exc}'))
            self.get_logger().error(f'trajectory {tag} rejected: {exc}')
            return
        start = now_perf if tag == 0 else (tag - self._ros_minus_perf_ns) * 1e-9
        reason = m.execute(trajectory, start=start, tag=tag)
        if reason is not None:
            self.get_logger().warning(f'trajectory {tag} rejected: {reason}')
        self.publish_events()

    def publish_events(self) -> None:
        """Execution events since the last call, new faults (logged, in ``/diagnostics`` at
        once), and the driver's state when it changed."""
        m = self.master
        if not self.context.ok():
            return
        if m is None:
            self.publish_state()
            return
        self._note_faults(m)
        for e in m.execution_events():
            level = (DiagnosticStatus.ERROR if e.kind == 'rejected' or 'protective stop' in e.reason
                     else DiagnosticStatus.WARN if e.kind == 'stopped' else DiagnosticStatus.OK)
            self._exec_pub.publish(status_msg(
                f'{self.get_name()}/{e.motion}/{e.tag}', e.kind, level=level, stamp=e.tag,
                kind=e.kind, reason=e.reason, positions=list(e.positions),
                time=self._ros_minus_perf_ns + round(e.time * 1e9), lag=e.lag))
        self.publish_state()

    def _note_faults(self, m: BraceMaster | MasterProcess) -> None:
        """A new fault: logged, and in ``/diagnostics`` at once."""
        faults = m.faults
        if faults != self._last_faults:
            for f in faults:
                if f not in self._last_faults:
                    self.get_logger().error(f'protective stop (latched until ~/recover): {f.describe()}')
            self._last_faults = faults
            self.publish_diagnostics()

    def publish_state(self, *, force: bool = False) -> None:
        """``/brace/driver_state`` (latched) when the lifecycle state, the master's state, the
        faults or homing changed. Not active: the message starts with the lifecycle state
        (``inactive: disabled``, ``unconfigured``), ``enabled`` is false."""
        if not self.context.ok():
            return
        m = self.master
        lifecycle = self._lifecycle
        if m is None:
            key: tuple = (lifecycle,)
            if key == self._last_state_key and not force:
                return
            self._last_state_key = key
            self._state_pub.publish(status_msg(
                f'{self.get_name()}/state', lifecycle, level=DiagnosticStatus.WARN, state=lifecycle,
                lifecycle=lifecycle, enabled='false', homed='false', faults='none', execution='hold',
                command=[], stamp=self.get_clock().now().nanoseconds))
            return
        faults = m.faults
        execution = m.execution.value
        taking_up = m.taking_up
        key = (lifecycle, m.state, tuple(f.describe() for f in faults), m.homed, execution, taking_up)
        if key == self._last_state_key and not force:
            return
        self._last_state_key = key
        state = m.state
        text = ('protective stop' if state is MasterState.FAULT else
                'enabled, taking up the cables\' slack' if taking_up else state.value)
        level = (DiagnosticStatus.ERROR if faults else
                 DiagnosticStatus.OK if state is MasterState.ENABLED else DiagnosticStatus.WARN)
        message = f'{text}: {m.fault_summary()}' if faults else text
        if lifecycle != 'active':
            message = f'{lifecycle}: {message}'
        self._state_pub.publish(status_msg(
            f'{self.get_name()}/state', message, level=level, state=state.value, lifecycle=lifecycle,
            enabled=str(state is MasterState.ENABLED and lifecycle == 'active' and not taking_up).lower(),
            homed=str(m.homed).lower(),
            faults=m.fault_summary() if faults else 'none', execution=execution,
            command=list(m.command or ()),
            stamp=self.get_clock().now().nanoseconds))

    # ------------------------------------------------------------------ joint states, wrench

    def _on_sample(self) -> None:
        """A sample of the control cycle's process arrived (``can.cycle_process``; its link's
        reader thread): published at once, one message per sample."""
        if self._active and self.context.ok():
            self._publish_joint_states()

    def _publish_joint_states(self) -> None:
        """``/brace/joint_states`` (active only), once per SYNC sample."""
        m = self.master
        if m is None or not self._active:
            return
        self._note_faults(m)
        fb = m.feedback()
        if not fb.valid or not (m.homed or not self.master_config.homing_method):
            return       # an incremental encoder reads 0 until homed: no measurement yet
        if fb.stamp == self._last_js_stamp:
            return       # this SYNC's samples went out already
        self._last_js_stamp = fb.stamp
        # stamped with the SYNC the samples answer (its wall-clock send time: ROS time), not
        # when this timer ran
        stamp = ns_to_stamp(round(fb.wall * 1e9) if fb.wall else
                            self._ros_minus_perf_ns + round(fb.stamp * 1e9))
        self._last_js_wall = fb.wall
        self._js_pub.publish(joint_state(self.names, position=fb.position, velocity=fb.velocity,
                                         effort=fb.force, stamp=stamp))

    # ------------------------------------------------------------------ services

    def _trigger(self, name: str, fn: Callable[[], str],
                 allowed: frozenset[str]) -> Callable[[Any, Any], Any]:
        """A Trigger service whose work (a 402 transition, a brake along the path, a relief:
        up to seconds) runs in a thread of its own while the executor goes on publishing:
        the callback is a coroutine that awaits the work's future. Taken only in the
        lifecycle states ``allowed``; in any other the answer is ``success=False`` naming the
        state. The work holds the transition lock: no transition runs meanwhile."""
        async def handle(request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
            done: Future = Future(executor=self.executor)

            def work() -> None:
                try:
                    with self._transition_lock:
                        if self._lifecycle not in allowed or self.master is None:
                            raise _Refused(self._refusal(name))
                        done.set_result((True, fn()))
                except DriverError as exc:
                    done.set_result((False, str(exc)))
                except Exception as exc:  # noqa: BLE001 - a service must answer
                    done.set_result((False, f'{name} failed: {exc!r}'))
            async with self._service_lock:    # one service at a time
                if self._lifecycle not in allowed:
                    response.success, response.message = False, self._refusal(name)
                else:
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
        done = f'OPERATION ENABLED at {self._positions()}'
        if getattr(self.mechanism, 'actuation', None) != 'cable':
            return done
        gap = self._slack_gap()
        if gap is None and not self.master.relieved:
            return done
        # cables hanging slack (after a relief): their lengths are not the head's, and a
        # motion planned from the pose would start far from them: take the slack up first
        why = ('after the relief' if gap is None else
               f'the lengths fit no pose ({gap * 1e3:.2f} mm off)')
        below = float(getattr(self.mechanism, 'tension_min', 0.0)) or TAKE_UP_TENSION_N
        try:
            took = self.master.take_up(below=below)
        except DriverError as exc:
            raise _Refused(f'{done}, but {why} the cables could not be taken up: {exc}; a goal '
                           'cannot start from their lengths') from exc
        return f'{done}; {why}: {took}'

    def _slack_gap(self) -> float | None:
        """For pull-only legs (cables): how far (m) the measured lengths are from the lengths
        of the pose that fits them best, when more than :data:`TAKE_UP_GAP_M`; else None."""
        m = self.mechanism
        if m is None or getattr(m, 'actuation', None) != 'cable' or self.master is None:
            return None
        q = np.asarray(self.master.feedback().position, float)
        try:
            pose = np.asarray(m.forward_nearest(q, self._pose_guess()), float)
            gap = float(np.max(np.abs(np.asarray(m.inverse(pose), float) - q)))
        except ValueError as exc:           # InconsistentLengths: its residual; else unknown
            gap = float(getattr(exc, 'residual', math.inf))
        return gap if gap > TAKE_UP_GAP_M else None

    def _disable(self) -> str:
        self.master.disable()
        if self.master.latched:
            return f'disabled on recover; protective stop latched: {self.master.fault_summary()}'
        return 'SWITCH ON DISABLED'

    def _halt(self) -> str:
        self.master.halt()
        return f'QUICK STOP ACTIVE, holding at {self._positions()}'

    def _recover(self) -> str:
        m = self.master
        if not m.latched and not any(
                d.state in (State402.FAULT, State402.FAULT_REACTION_ACTIVE) for d in m.status().drives):
            return f'nothing to recover: no protective stop is latched (drives {m.state.value}); nothing was changed'
        blocking = m.recover()
        if blocking:
            raise _Refused('not recovered, cause still present: '
                           + '; '.join(f.describe() for f in blocking))
        return 'recovered: drives SWITCH ON DISABLED, call ~/enable'

    def _relieve(self) -> str:
        return self.master.relieve()

    def _pose_guess(self) -> Any:
        """The newest pose the cycle's wrench tiers solved (a starting guess for forward
        kinematics), else the home pose."""
        pose = None if self.master is None else self.master.last_pose
        return pose if pose is not None else np.asarray(self.mechanism.home_pose, float)

    def _home(self) -> str:
        self.master.home()
        return f'homed (method {self.master_config.homing_method}) at {self._positions()}'

    # ------------------------------------------------------------------ diagnostics

    def diagnostics(self) -> DiagnosticArray:
        """One status per drive, one for the bus, one for the cycle, one for safety; with no
        bus open (unconfigured, finalized) one status saying so."""
        prefix = f'brace_control/{self.get_name()}'
        hw = f'{self.master_config.interface}:{self.master_config.channel}'
        out: list[DiagnosticStatus] = []

        def status(name: str, level: str, message: str, **values: Any) -> None:
            out.append(DiagnosticStatus(
                level=_LEVEL[level], name=f'{prefix}/{name}', message=message, hardware_id=hw,
                values=[KeyValue(key=k, value=str(v)) for k, v in values.items()]))

        msg = DiagnosticArray()
        m = self.master
        st = None
        closed = m is None
        if m is not None:
            try:
                st = m.status()
            except DriverError as exc:          # the cycle's process is gone (or going)
                # closed on purpose (the node shutting down, a cleanup) is no fault, and no
                # report of one (a diagnostics pass between the close and the node's own
                # teardown said ERROR here and the demo counted a protective stop)
                closed = getattr(m, 'closing', False)
                if not closed:
                    status('safety', 'error', f'{self._lifecycle}: {exc}', lifecycle=self._lifecycle)
        if st is None:
            if closed:
                status('safety', 'warn', f'{self._lifecycle}: CAN bus closed, drives not driven',
                       lifecycle=self._lifecycle)
            msg.header.stamp = self.get_clock().now().to_msg()
            msg.status = out
            return msg

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
        report = m.boot_report
        warned = [line for line in report if line.startswith('warning')]
        status('boot_plan', 'warn' if warned else 'ok',
               f'{len(report)} object(s) of the drives\' dictionaries skipped' + (
                   f', {len(warned)} needing action' if warned else '') if report else
               "every object of docs/can.md written", **{f'skip_{i + 1}': line for i, line in enumerate(report)})
        t = st.timing
        overrun_frac = t.overrun_fraction
        sim_cpu = {}
        if self.sim is not None:            # its share of the CPU where it runs (bench_stack)
            try:
                sim_cpu['simulator_cpu_s'] = f'{float(self.sim.cpu_seconds):.3f}'
            except DriverError:
                pass
        status('cycle', 'warn' if overrun_frac > 1e-3 else 'ok',
               f'SYNC {self.master_config.sync_rate_hz:g} Hz, period error p99 {t.p99 * 1e6:.0f} us',
               period_error_p50_us=f'{t.p50 * 1e6:.0f}', period_error_p99_us=f'{t.p99 * 1e6:.0f}',
               period_error_max_us=f'{t.max * 1e6:.0f}', overruns=t.overruns, cycles=t.cycles,
               **sim_cpu)
        if st.faults:
            level, message = 'error', f'protective stop: {st.faults[0].describe()}'
        elif st.warnings:
            level, message = 'warn', st.warnings[0]
        else:
            level, message = 'ok', st.state.value
        if self._lifecycle != 'active':
            message = f'{self._lifecycle}: {message}'
        status('safety', level, message, state=st.state.value, homed=st.homed, lifecycle=self._lifecycle,
               faults=' | '.join(f.describe() for f in st.faults) or 'none',
               warnings=' | '.join(st.warnings) or 'none',
               stale_setpoint_holds=st.stale_setpoint_holds,
               accepted_setpoints=st.accepted_setpoints,
               setpoints_accepted=self.accepted, setpoints_rejected=self.rejected,
               last_rejection=self.last_rejection or 'none')
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.status = out
        return msg

    def publish_diagnostics(self) -> None:
        if self.context.ok():
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


#: the executable's option (before ``--ros-args``): start unconfigured, for ``ros2 lifecycle set``
MANUAL_LIFECYCLE = '--manual-lifecycle'


def main(args: Sequence[str] | None = None) -> int:
    """``ros2 run brace_control can_driver_node [--manual-lifecycle]``: configured and
    activated at start-up unless ``--manual-lifecycle`` (then it waits unconfigured for
    ``ros2 lifecycle set``). Exit code 0, 1 when the bus or a drive did not come up at
    start-up, 2 on a configuration error (:func:`~.runner.run_node`)."""
    from .runner import run_node
    argv = list(sys.argv if args is None else args)
    own = argv[1:argv.index('--ros-args')] if '--ros-args' in argv else argv[1:]
    manual = MANUAL_LIFECYCLE in own
    return run_node(CanDriverNode, executable='can_driver_node',
                    summary='CiA 402 drives of the brace on CAN (or the simulated brace), '
                            'trajectories and setpoints in, joint states out; a lifecycle node, '
                            f'configured and activated at start-up unless {MANUAL_LIFECYCLE}',
                    args=argv, start=None if manual else (lambda node: node.autostart()),
                    startup_errors=(DriverError,))


if __name__ == '__main__':
    sys.exit(main())
