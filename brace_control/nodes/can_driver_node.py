"""can_driver_node: the brace's CiA 402 drives on CAN, as ROS topics and services.

``ros2 run brace_control can_driver_node --ros-args --params-file config/lumbar_brace.yaml``

* subscribes ``/brace/actuator_setpoint`` (``sensor_msgs/JointState``, by actuator name,
  ``position`` in m): the latest setpoint goes to the drives on the next SYNC. Malformed
  input (unknown / missing names, wrong lengths, NaN, outside the stroke) is rejected
  with a throttled error; nothing is sent and the drives hold (SAFETY.md 1, 5, 6). No
  setpoint for ``safety.command_timeout``: hold and report; a step beyond
  ``v_max · (time between stamps) + margin``: protective stop (SAFETY.md 7);
* publishes ``/brace/joint_states`` (position m, velocity m/s, effort = load-cell force
  N) at ``can.joint_state_rate_hz``, once homed (incremental encoders read 0 before);
* services ``~/enable``, ``~/disable``, ``~/halt``, ``~/recover``, ``~/home``
  (``std_srvs/Trigger``, like ros2_canopen; the message says why on failure);
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
  the true pose and efforts).

In-process use (one-process bring-up, tests)::

    node = CanDriverNode(context=ctx, cli_args=['--ros-args', '--params-file', yaml])
    ...
    node.shutdown(); node.destroy_node()
"""
from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger

from ..can import (BraceMaster, DriverError, FaultKind, MasterConfig, MasterState, State402)
from .msgs import MalformedMessage, joint_state, joint_state_arrays, stamp_to_ns
from .params import declare_device_parameters

__all__ = ['CanDriverNode', 'main', 'ACTUATOR_SETPOINT_TOPIC', 'JOINT_STATES_TOPIC',
           'SIM_JOINT_STATES_TOPIC', 'SIM_POSE_TOPIC', 'SIM_WRENCH_TOPIC']

ACTUATOR_SETPOINT_TOPIC = '/brace/actuator_setpoint'
JOINT_STATES_TOPIC = '/brace/joint_states'
SIM_JOINT_STATES_TOPIC = '/brace/sim/joint_states'
SIM_POSE_TOPIC = '/brace/sim/pose'
SIM_WRENCH_TOPIC = '/brace/sim/wrench'

#: Setpoints: reliable depth 10, as ik_node publishes them (a dropped sample would be a
#: double step for the step limit; the staleness check keeps a backlog from mattering).
SETPOINT_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
#: joint_states is state: reliable, short history.
STATE_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
#: rejection errors at most once per this many seconds (the stream runs at 200 Hz)
REJECT_LOG_PERIOD = 1.0

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
        self.cfg = declare_device_parameters(self, ('mechanism', 'actuator', 'can', 'safety', 'sim'))
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
        self.rejected = 0
        self.accepted = 0
        self.last_rejection = ''
        self._last_reject_log = -math.inf
        self._pose_hint = None if self.mechanism is None else np.asarray(self.mechanism.home_pose, float)
        self._wrench_limit = np.asarray(self.cfg['safety']['max_wrench'], float)
        self._last_faults: tuple = ()
        # services may block up to ~1 s (402 transitions): their own group, so the
        # setpoint stream and joint_states never wait on them on a multi-threaded executor
        self._service_group = MutuallyExclusiveCallbackGroup()
        self._stream_group = MutuallyExclusiveCallbackGroup()
        self._js_pub = self.create_publisher(JointState, JOINT_STATES_TOPIC, STATE_QOS)
        self._diag_pub = self.create_publisher(
            DiagnosticArray, '/diagnostics', QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
        self._sub = self.create_subscription(JointState, ACTUATOR_SETPOINT_TOPIC, self._on_setpoint,
                                             SETPOINT_QOS, callback_group=self._stream_group)
        for name, fn in (('enable', self._enable), ('disable', self._disable), ('halt', self._halt),
                         ('recover', self._recover), ('home', self._home)):
            self.create_service(Trigger, f'~/{name}', self._trigger(name, fn),
                                callback_group=self._service_group)
        rate = float(self.cfg['can']['joint_state_rate_hz'])
        self._js_timer = self.create_timer(1.0 / rate, self._publish_joint_states,
                                           callback_group=self._stream_group)
        self._diag_timer = self.create_timer(1.0, self.publish_diagnostics,
                                             callback_group=self._stream_group)
        if boot:
            self.start()

    def _mechanism(self) -> Any:
        try:
            from ..mechanisms import mechanism_from_config
            return mechanism_from_config(self.cfg)
        except ImportError:
            return None

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
        self._truth_pubs = (self.create_publisher(JointState, SIM_JOINT_STATES_TOPIC, STATE_QOS),
                            self.create_publisher(PoseStamped, SIM_POSE_TOPIC, STATE_QOS),
                            self.create_publisher(WrenchStamped, SIM_WRENCH_TOPIC, STATE_QOS))
        kind = pose_kind(self.mechanism)
        base, platform = self.cfg['base_frame'], self.cfg['platform_frame']

        def publish() -> None:
            if not self.context.ok():         # shutting down: the publishers are going
                return
            truth = self.sim.truth()
            stamp = self.get_clock().now().to_msg()
            js_pub, pose_pub, wrench_pub = self._truth_pubs
            js_pub.publish(joint_state(self.names, position=truth.lengths, velocity=truth.velocities,
                                       effort=truth.forces, stamp=stamp))
            pose_pub.publish(pose_msg(truth.pose, frame_id=base, stamp=stamp, mechanism=self.mechanism))
            try:
                w = np.asarray(self.mechanism.wrench(truth.pose, truth.forces), dtype=float)
            except ValueError:                  # e.g. a pose the mechanism's statics rejects
                return
            wrench_pub.publish(wrench_msg(platform_frame_wrench(truth.pose, w, kind), frame_id=platform,
                                          stamp=stamp, kind=kind))
        self._truth_timer = self.create_timer(1.0 / float(self.cfg['sim']['truth_rate_hz']), publish,
                                              callback_group=self._stream_group)

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
            q = joint_state_arrays(msg, self.names, ('position',))['position']
        except MalformedMessage as exc:
            self._reject(str(exc))
            return
        # The stamp is the setpoint's sample instant: the master's step limit uses the time
        # between stamps. Staleness is judged by arrival in the master (a stream that
        # stopped), not by the stamp's age, which is transport latency.
        stamp = stamp_to_ns(msg.header.stamp)
        try:
            self.master.set_targets(q, stamp=stamp * 1e-9 if stamp else None)
        except ValueError as exc:
            self._reject(str(exc))
            return
        self.accepted += 1

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
        self._js_pub.publish(joint_state(self.names, position=fb.position, velocity=fb.velocity,
                                         effort=fb.force, stamp=self.get_clock().now().to_msg()))
        if self.master.state is MasterState.ENABLED:
            self._check_wrench(fb.position, fb.force)

    def _wrench(self, q: np.ndarray, forces: np.ndarray) -> np.ndarray | None:
        if self.mechanism is None or self._pose_hint is None:
            return None
        try:
            pose = np.asarray(self.mechanism.forward_nearest(q, self._pose_hint), float)
        except ValueError:
            return None
        self._pose_hint = pose
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
        def handle(request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
            try:
                response.message = fn()
                response.success = True
            except DriverError as exc:
                response.success = False
                response.message = str(exc)
            except Exception as exc:  # noqa: BLE001 - a service must answer
                response.success = False
                response.message = f'{name} failed: {exc!r}'
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
        blocking = self.master.recover()
        if blocking:
            raise _Refused('not recovered, cause still present: '
                           + '; '.join(f.describe() for f in blocking))
        return 'recovered: drives SWITCH ON DISABLED, call ~/enable'

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


class _Refused(DriverError):
    """A service request the master declined (the message says why)."""


def main(args: Sequence[str] | None = None) -> int:
    """``ros2 run brace_control can_driver_node``; exit code 0, 1 when the bus or a drive
    did not come up, 2 on a configuration error (:func:`~.runner.run_node`)."""
    from .runner import run_node
    # 2 threads: services (blocking up to ~1 s) never delay the setpoint stream
    return run_node(lambda: CanDriverNode(boot=False), executable='can_driver_node',
                    summary='CiA 402 drives of the brace on CAN (or the simulated brace), '
                            'setpoints in, joint states out',
                    args=args, executor=lambda: MultiThreadedExecutor(num_threads=2),
                    start=lambda node: node.start(), startup_errors=(DriverError,))


if __name__ == '__main__':
    sys.exit(main())
