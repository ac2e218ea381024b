"""The CiA 402 master: boot, configure, enable, home and drive the brace's drives over CAN.

:class:`BraceMaster` opens a python-can bus from the device YAML (``can.interface``,
``can.channel``, ``can.bitrate``), puts a :class:`canopen.Network` on it (canopen's
Notifier is the only receive thread) and runs one cyclic thread that produces SYNC
(COB-ID 80h) at ``can.sync_rate_hz`` and the master heartbeat (700h + 127).

The master is the API over parts, each an object with its own state, composed here:

* :mod:`.lifecycle` — what the parts share: :class:`~.lifecycle.Lifecycle` (the master's
  state, the nodes, the 402 state wanted, the flags the API sets for the cycle, the waits)
  and :class:`~.lifecycle.Motion` (the executor, its lock, its events);
* :mod:`.boot` — :class:`~.boot.Boot`: the plan, bus, NMT, SDO configuration, PDO mapping,
  homing;
* :mod:`.sync` — :class:`~.sync.SyncClock`: the SYNCs sent and which one a drive's answer
  belongs to;
* :mod:`.receive` — :class:`~.receive.Receiver`: TPDO1 samples, heartbeats, EMCY, error frames
  (canopen's Notifier thread), and :class:`~.receive.BusTraffic`, the bus counters;
* :mod:`.monitors` — :class:`~.monitors.Monitors`: the per-cycle protective functions
  (:mod:`brace_control.safety`) and the fault predicates;
* :mod:`.stream` — :class:`~.stream.SetpointStream`: the teleoperation stream;
* :mod:`.cycle` — :class:`~.cycle.Cycle`: the SYNC thread: monitors, command, RPDOs, SYNC;
* :mod:`brace_control.control.execution` — the commanded motion: a planned trajectory sampled
  at every SYNC (quintic Hermite, one time base for all axes, time scaling to slow down), or
  the setpoint stream, path-synchronous.

Motion (ARCHITECTURE.md, "Data flow"): :meth:`BraceMaster.execute` takes a whole
:class:`~.execution.ActuatorTrajectory` with its start time (ros2_control's
JointTrajectoryController semantics: it replaces the running motion from its start time,
continuous in position, velocity and acceleration); :meth:`BraceMaster.stop_motion`
decelerates along the running path; :meth:`BraceMaster.set_targets` feeds the setpoint
stream (teleoperation). :meth:`BraceMaster.execution_events` reports what happened to each
trajectory. A received trajectory was checked whole, so it runs to its end unless
cancelled, halted or stopped by a fault.

Safety (docs/safety.md §1–§9, §11; :mod:`.supervision`): any fault latches a protective stop until
:meth:`BraceMaster.recover`, which resets drive faults and clears the latch only when
every cause is gone. A fault after which the drives still follow (force, wrench, step,
following error, speed) first brakes the motion along its path, all axes together; then
quick stop (6040h = 0002h, 605Ah = 6 keeps the drives in QUICK STOP ACTIVE, holding).
Halt and disable also brake along the path first.

Typical use::

    with BraceMaster.from_device_config(load_device_config('lumbar_brace')) as m:
        m.boot(); m.home(); m.enable()
        m.execute(ActuatorTrajectory(times, positions, velocities, accelerations),
                  start=time.perf_counter() + 0.05, tag=1)
        fb = m.feedback()          # SI: positions m, velocities m/s, forces N
"""
from __future__ import annotations

import logging
import math
import numbers
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import can
import canopen
import numpy as np

from ..control.execution import ActuatorTrajectory, ExecutionEvent, ExecutionState, PathExecutor
from ..safety import ForcePrediction, WrenchTiers
from .boot import Boot
from .cia402 import NmtState, State402, emcy_description
from .cycle import Cycle
from .errors import DriverInitializationError, DriverOperationError
from .lifecycle import CycleTrace, Lifecycle, Motion
from .monitors import RELIEVABLE, Monitors
from .pdo import SdoWrite
from .plan import BootPlan, ModulePlan
from .receive import BusTraffic, Receiver
from .state import (BusStatus, DriveStatus, Feedback, MasterConfig, MasterState, MasterStatus,
                    Relief, TakeUp, _Node)
from .stream import SetpointStream, checked_velocities
from .supervision import Fault, FaultKind, Limits, Supervisor
from .sync import SyncClock
from .timing import PeriodStats

__all__ = ['BraceMaster', 'MasterConfig', 'MasterState', 'DriveStatus', 'BusStatus',
           'MasterStatus', 'Feedback']

log = logging.getLogger(__name__)

#: the longest halt / disable waits for the motion to brake along its path (s)
STOP_WAIT_S = 2.0
#: s every load cell must read below the release force before a relief counts as done
#: (a single noisy reading below it is not an unloaded leg)
RELIEF_CONFIRM_S = 0.05
#: SYNCs from a command to the load cell reading its effect (the take-up's speed limit)
TAKE_UP_LAG_SYNCS = 3


class BraceMaster:
    """CiA 402 master of one device's drives (see the module docstring).

    :param config: :class:`MasterConfig` (``MasterConfig.from_device_config(cfg)``).
    :param bus: an already open python-can bus to use instead of opening one (tests,
        replays); the master shuts it down on :meth:`shutdown` only if it opened it.

    Thread model: canopen's Notifier thread runs the TPDO / heartbeat / EMCY / error
    frame callbacks; the SYNC thread runs the cycle; API calls (boot, enable, ...) come
    from any one caller thread at a time (serialised by a lock); :meth:`execute`,
    :meth:`stop_motion` and :meth:`set_targets` never wait for that lock (a node's
    stream callbacks must not queue behind a service that waits for a 402 transition).
    """

    def __init__(self, config: MasterConfig, *, bus: can.BusABC | None = None) -> None:
        self.config = config
        self.scaling = config.scaling
        #: the latched protective stops; the first reaction to one is the lifecycle's
        self.supervisor = Supervisor(on_fault=lambda fault: self.life.on_fault(fault))
        #: the SYNCs sent (the cycle stamps them; a TPDO is attributed to the SYNC it
        #: answered by its bus timestamp, not by when our thread got to it)
        self.clock = SyncClock()
        #: the state the parts share: the master's state, the nodes, the cycle's inputs
        self.life = Lifecycle(config, self.supervisor, self.clock)
        #: the commanded motion: trajectories and the stream, one time base for all axes
        self.motion = Motion(PathExecutor(len(config.node_ids), v_max=config.limits.v_max,
                                          a_max=config.limits.a_max, period=config.period,
                                          splice_tolerance=config.limits.path_tolerance))
        #: frames and bits both ways, the bus load, the controller's error state
        self.traffic = BusTraffic(config.bitrate)
        #: the receive side: samples, heartbeats, EMCY, error frames (canopen's Notifier thread)
        self.receiver = Receiver(config, self.clock, self.traffic, self.supervisor,
                                 supervising=lambda: self.life.supervising,
                                 rebooted=self._drive_rebooted,
                                 nmt_not_operational=lambda d: self.monitors.nmt_not_operational(d),
                                 emcy_present=lambda d: self.monitors.emcy_present(d))
        #: the per-SYNC protective functions (docs/safety.md §2, §4, §8, §9, §11, §14)
        self.monitors = Monitors(self.life, self.motion, self.receiver, self.clock,
                                 distance_to_go=self.distance_to_go, soft_stop=self.soft_stop)
        #: the teleoperation stream (docs/safety.md §1, §7)
        self.stream = SetpointStream(self.life, self.monitors.step_condition)
        #: the SYNC thread
        self.cycle = Cycle(self.life, self.motion, self.stream, self.monitors, self.clock,
                           self.traffic)
        #: plan, bus, NMT, SDO configuration, homing
        self.setup = Boot(self.life, self.receiver, self.traffic, self.cycle, self.monitors, bus=bus)
        self._api_lock = threading.RLock()

    # ------------------------------------------------------------------ construction

    @classmethod
    def from_device_config(cls, cfg: Mapping[str, Any], *, channel: str | None = None,
                           bus: can.BusABC | None = None, **overrides: Any) -> BraceMaster:
        """``BraceMaster(MasterConfig.from_device_config(cfg, channel=..., ...))``."""
        return cls(MasterConfig.from_device_config(cfg, channel=channel, **overrides), bus=bus)

    @property
    def names(self) -> tuple[str, ...]:
        return self.config.names

    @property
    def bus(self) -> can.BusABC | None:
        """The python-can bus (``None`` when closed)."""
        return self.setup.bus

    @property
    def network(self) -> canopen.Network | None:
        """The canopen Network on the bus (``None`` when closed)."""
        return self.setup.network

    @property
    def state(self) -> MasterState:
        return self.life.state

    @property
    def state_changes(self) -> int:
        """Bumped on every change of :attr:`state` (a node publishes the state on change)."""
        return self.life.state_changes

    @property
    def limits(self) -> Limits:
        """The monitors' thresholds (the boot narrows the saturation to the load-cell inputs)."""
        return self.life.limits

    @property
    def homed(self) -> bool:
        return self.life.homed

    @property
    def relieved(self) -> bool:
        """A relief moved the actuators since the last take-up: pull-only legs may hang slack."""
        return self.life.relieved

    @property
    def executor(self) -> PathExecutor:
        """The commanded motion (:class:`~brace_control.control.execution.PathExecutor`)."""
        return self.motion.executor

    @property
    def plans(self) -> list[BootPlan]:
        """Each drive's boot as planned against its dictionary (at :meth:`open`)."""
        return self.setup.plans

    @property
    def module_plan(self) -> ModulePlan | None:
        return self.setup.module_plan

    @property
    def boot_report(self) -> list[str]:
        """What the plans skipped and why, one line each (logged at configure)."""
        return self.setup.boot_report

    @property
    def stats(self) -> PeriodStats:
        """The SYNC period's timing."""
        return self.cycle.stats

    @property
    def platform_tiers(self) -> WrenchTiers | None:
        """The platform wrench's tiers the cycle evaluates (docs/safety.md §8, §14)."""
        return self.monitors.platform_tiers

    @property
    def force_prediction(self) -> ForcePrediction:
        return self.monitors.force_prediction

    @property
    def soft_limit_context(self) -> Callable[[int, float], str] | None:
        """``f(actuator index, force) -> str``: what the soft-limit stop adds to its reason
        (the node: the wrench capacity at the estimated pose); ``None``: nothing."""
        return self.cycle.soft_limit_context

    @soft_limit_context.setter
    def soft_limit_context(self, value: Callable[[int, float], str] | None) -> None:
        self.cycle.soft_limit_context = value

    @property
    def send_failures(self) -> int:
        return self.cycle.send_failures

    # ------------------------------------------------------------------ boot (:class:`.boot.Boot`)

    def plan(self) -> list[BootPlan]:
        """:meth:`.boot.Boot.plan`: every drive's boot planned against its dictionary."""
        return self.setup.plan()

    def sdo_writes(self, index: int) -> list[SdoWrite]:
        """The configuration of drive ``index`` (actuator order) as planned, in write order."""
        return self.setup.sdo_writes(index)

    def open(self) -> None:
        """:meth:`.boot.Boot.open`: plan, open the bus, start the SYNC thread (heartbeat only)."""
        with self._api_lock:
            self.setup.open()

    def boot(self, *, timeout: float | None = None) -> None:
        """:meth:`.boot.Boot.boot`: every drive to NMT OPERATIONAL with the planned configuration."""
        with self._api_lock:
            self.setup.boot(timeout=timeout)

    def home(self, *, timeout: float | None = None) -> None:
        """:meth:`.boot.Boot.home`: home every drive (only with the drives disabled)."""
        with self._api_lock:
            self.setup.home(timeout=timeout)

    def __enter__(self) -> BraceMaster:
        return self

    def __exit__(self, *exc: object) -> None:
        self.shutdown()

    # ------------------------------------------------------------------ bus
    # ------------------------------------------------------------------ API: motion

    def set_targets(self, positions: Sequence[float], *, stamp: float | None = None,
                    velocities: Sequence[float] | None = None) -> None:
        """The latest setpoint of the stream (m per actuator, actuator order); taken on the
        next SYNC.

        ``stamp`` (s, any clock the sender keeps) is the setpoint's sample instant, e.g. its
        message header stamp; ``velocities`` (unit/s) the sender's rate, used as the
        stream's feed-forward. The cycle step-checks it (docs/safety.md §7: a violation latches a
        STEP_LIMIT stop), takes it over from a running trajectory, and stops the stream
        when no setpoint arrives for ``safety.command_timeout`` (docs/safety.md §1).

        :raises ValueError: wrong length, non-finite, or outside the stroke (docs/safety.md §5, §6),
            or a stamp that is not a finite number (NaN compares false with every stamp: it
            would pass the stream's order check and turn it off for the setpoints after it);
            nothing is sent.
        """
        if stamp is not None and (isinstance(stamp, bool) or not isinstance(stamp, numbers.Real)
                                  or not math.isfinite(stamp)):
            raise ValueError(f'setpoint stamp {stamp!r}: expected a finite number of seconds or None')
        arr = self._checked_positions(positions, 'target')
        self.stream.receive(arr, stamp, checked_velocities(velocities, arr, self.names))

    def execute(self, trajectory: ActuatorTrajectory, *, start: float, tag: int) -> str | None:
        """Run ``trajectory`` from ``start`` (perf_counter s: when the drives are to be at its
        first point), replacing the running motion then (see :mod:`.execution`).

        :param tag: the trajectory's identity in :meth:`execution_events` (its header stamp).
        :returns: ``None`` when accepted, else the reason it was rejected (nothing moves).
        """
        now = time.perf_counter()
        motion = self.motion
        with motion.lock:
            if not self.life.tracking or self.state is not MasterState.ENABLED:
                reason = f'the drives are not enabled (master {self.state.value}' + (
                    f': {self.supervisor.summary()})' if self.supervisor.latched else ')')
                motion.events.append(ExecutionEvent(tag, 'rejected', reason, (), now))
                return reason
            lo = np.array([self.limits.stroke_of(i)[0] for i in range(len(self.names))])
            hi = np.array([self.limits.stroke_of(i)[1] for i in range(len(self.names))])
            reason = motion.executor.load(trajectory, start, tag, now=now, lo=lo, hi=hi)
            motion.collect()
            return reason

    def stop_motion(self, reason: str, *, tag: int | None = None) -> None:
        """Decelerate the running motion to rest along its path (all axes together) and hold;
        ``tag``: only if that trajectory is running or pending (a cancel naming its goal)."""
        with self.motion.lock:
            self.motion.executor.stop(reason, now=time.perf_counter(), tag=tag)
            self.motion.collect()

    def execution_events(self) -> list[ExecutionEvent]:
        """What happened to each trajectory since the last call (oldest first)."""
        return self.motion.drain()

    def trace_cycles(self, on: bool = True) -> None:
        """Record, or stop recording, what each SYNC cycle commands
        (:class:`~.lifecycle.CycleTrace`; off by default: nothing is kept)."""
        with self.motion.lock:
            if not on:
                self.motion.trace = None
            elif self.motion.trace is None:
                self.motion.trace = CycleTrace()

    def take_cycle_trace(self) -> dict[str, list]:
        """The cycle's records since the last call (:meth:`CycleTrace.take
        <.lifecycle.CycleTrace.take>`; empty lists when not recording)."""
        with self.motion.lock:
            trace = self.motion.trace
            return (trace if trace is not None else CycleTrace()).take()

    # -- the interaction mode's admittance, run in the cycle (docs/safety.md §19)

    def start_interaction(self, source: object, tag: int) -> str | None:
        """Run the admittance ``source`` in the cycle from the command at rest
        (:meth:`~brace_control.control.execution.PathExecutor.begin_interaction`).

        :returns: None when started, else why not (nothing moves).
        """
        now = time.perf_counter()
        with self.motion.lock:
            if not self.life.tracking or self.state is not MasterState.ENABLED:
                return f'the drives are not enabled (master {self.state.value})'
            reason = self.motion.executor.begin_interaction(source, tag, now=now)
            self.motion.collect()
            return reason

    def stop_interaction(self, reason: str) -> None:
        """Brake the interaction to rest along its direction, then hold (event 'stopped')."""
        with self.motion.lock:
            self.motion.executor.stop_interaction(reason, now=time.perf_counter())
            self.motion.collect()

    def set_interaction_goal(self, wrench: object) -> None:
        """The wrench goal of the running interaction (pose axes).

        :raises ValueError: no interaction runs; :raises GoalRejected: the controller's
            checks (held axis, ``max_goal_wrench``, capacity at the current pose).
        """
        with self.motion.lock:
            if self.motion.trace is not None:
                self.motion.trace.goals.append(time.time())
            src = self.motion.executor.source
            if src is None:
                raise ValueError('no interaction is running')
            src.controller.set_goal(wrench)

    @property
    def moving(self) -> bool:
        """The command is in motion (or a trajectory is scheduled). Read between two steps
        of the SYNC thread (under the motion's lock): the step that starts a trajectory takes
        it off the schedule before the executor is in motion, and a read in between saw
        neither (a client that waited for the motion's end read the events before its end)."""
        with self.motion.lock:
            return self.executor.moving

    # -- what a node reads (the same names on :class:`~.process.MasterProcess`)

    @property
    def faults(self) -> tuple[Fault, ...]:
        """The latched protective stops (docs/safety.md), oldest first."""
        return self.supervisor.faults

    @property
    def latched(self) -> bool:
        """A protective stop is latched (until :meth:`recover`)."""
        return self.supervisor.latched

    def fault_summary(self) -> str:
        """The latched protective stops in one line."""
        return self.supervisor.summary()

    @property
    def execution(self) -> ExecutionState:
        """What the command follows: hold, a trajectory, the stream, the admittance."""
        return self.executor.state

    @property
    def command(self) -> tuple[float, ...] | None:
        """The executor's command (unit per actuator), ``None`` before it is anchored."""
        ex = self.executor
        return tuple(float(v) for v in ex.q) if ex.anchored else None

    @property
    def interacting(self) -> bool:
        """The in-cycle admittance (interaction mode) drives the command."""
        return self.executor.source is not None

    @property
    def last_pose(self) -> np.ndarray | None:
        """The newest platform pose the cycle's wrench tiers solved (``None``: no model,
        no ``safety.max_wrench``, or not solved yet)."""
        tiers = self.monitors.platform_tiers
        return None if tiers is None else tiers.platform.pose.copy()

    # ------------------------------------------------------------------ what was received
    def feedback(self) -> Feedback:
        """Positions (m), velocities (m/s), load-cell forces (N) in actuator order: one
        consistent snapshot (:meth:`.receive.Receiver.feedback`)."""
        return self.receiver.feedback()

    def heartbeat_age(self, d: _Node) -> float:
        """s since node ``d``'s last heartbeat, on the bus's clock (docs/safety.md §4)."""
        return self.receiver.heartbeat_age(d)

    def foreign_master(self) -> str:
        """What another master on the bus was heard sending ('' if nothing)."""
        return self.receiver.foreign_master()

    @property
    def error_frames(self) -> int:
        """CAN error frames received since the bus opened."""
        return self.traffic.error_frames

    @property
    def attribution_window(self) -> int:
        """The most SYNCs a TPDO1 may answer late and still be counted (:class:`.sync.SyncClock`)."""
        return self.clock.attribution_window

    @attribution_window.setter
    def attribution_window(self, value: int) -> None:
        self.clock.attribution_window = int(value)

    @property
    def all_silent_periods(self) -> int:
        """SYNCs every drive may be silent before that is stale feedback (:class:`.receive.Receiver`)."""
        return self.receiver.all_silent_periods

    def _drive_rebooted(self) -> None:
        """A supervised drive sent a boot-up: its configuration and homing are gone."""
        self.life.homed = False

    def _checked_positions(self, positions: Sequence[float], what: str) -> np.ndarray:
        arr = np.asarray(positions, dtype=float)
        n = len(self.life.drives) or len(self.config.node_ids)
        if arr.shape != (n,):
            raise ValueError(f'expected {n} {what} positions ({", ".join(self.names)}), got shape {arr.shape}')
        u = self.limits.unit
        for i, v in enumerate(arr):
            if not math.isfinite(v):
                raise ValueError(f'{what} of {self.names[i]} is not finite: {v}')
            lo, hi = self.limits.stroke_of(i)
            if not lo <= v <= hi:
                raise ValueError(f'{what} of {self.names[i]} = {v:.5f} {u} is outside the '
                                 f'{"stroke" if u == "m" else "joint range"} {lo:.3f}–{hi:.3f} {u}')
        return arr

    # ------------------------------------------------------------------ API: drive states

    def enable(self, *, timeout: float | None = None) -> None:
        """All drives to OPERATION ENABLED in CSP; the command is anchored at the drives'
        measured positions first (no jump, whatever was commanded before).

        :raises FaultLatchedError: a protective stop is latched (call :meth:`recover`).
        :raises DriverOperationError: not booted, or not homed (call :meth:`home`).
        :raises DriverTimeoutError: a drive did not reach OPERATION ENABLED.
        """
        life = self.life
        with self._api_lock:
            life.require_ready()
            if not life.homed and self.config.homing_method:
                raise DriverOperationError(
                    'not homed: park the brace at the home pose and call home() first '
                    '(incremental encoders read 0 at power-up)')
            if life.state is MasterState.ENABLED and life.all_in(State402.OPERATION_ENABLED):
                return
            self.stream.restart()
            life.desired = State402.OPERATION_ENABLED
            life.wait(lambda: life.all_in(State402.OPERATION_ENABLED), timeout=timeout,
                      what='OPERATION ENABLED')
            life.wait_syncs(2)
            with self.motion.lock:
                fb = self.feedback()
                self.motion.executor.anchor(fb.position, time.perf_counter() + self.config.period,
                                            reason='drives enabled: command anchored at their position')
                self.motion.collect()
                self.stream.skip_received()
                life.tracking = True
            life.set_state(MasterState.ENABLED)

    def disable(self, *, timeout: float | None = None) -> None:
        """All drives to SWITCH ON DISABLED (power stage off); allowed in any state. A
        motion in progress is braked along its path first."""
        life = self.life
        with self._api_lock:
            life.require_open()
            self._brake_and_release('disable requested')
            life.desired = State402.SWITCH_ON_DISABLED
            if self.supervisor.latched:
                return          # the protective stop already holds; recover() disables
            life.wait(lambda: all(d.state in (State402.SWITCH_ON_DISABLED, State402.FAULT)
                                  for d in life.drives), timeout=timeout, what='SWITCH ON DISABLED')
            life.set_state(MasterState.DISABLED)

    def halt(self, *, timeout: float | None = None) -> None:
        """Brake the motion along its path, then quick stop (6040h = 0002h) and hold in
        QUICK STOP ACTIVE (605Ah = 6). Not a fault: :meth:`enable` resumes. Drives not
        enabled are disabled."""
        life = self.life
        with self._api_lock:
            life.require_open()
            self._brake_and_release('halt requested')
            life.desired = State402.QUICK_STOP_ACTIVE
            if self.supervisor.latched:
                return
            life.wait(lambda: all(d.state in (State402.QUICK_STOP_ACTIVE, State402.SWITCH_ON_DISABLED)
                                  for d in life.drives), timeout=timeout, what='QUICK STOP ACTIVE')
            life.set_state(MasterState.HALTED)

    def _brake_and_release(self, reason: str) -> None:
        """Stop taking commands: brake a running motion along its path (bounded wait), then
        drop it (reported stopped with ``reason``)."""
        life, motion = self.life, self.motion
        if life.tracking and not self.supervisor.latched:
            with motion.lock:
                self.stream.drop()
                motion.executor.stop(reason, now=time.perf_counter())
            end = time.monotonic() + STOP_WAIT_S
            while motion.executor.moving and time.monotonic() < end and not self.supervisor.latched:
                time.sleep(self.config.period)
        life.tracking = False
        motion.release(reason)

    def relieve(self, *, speed_share: float = 0.1, max_travel: float | None = None,
                timeout: float = 20.0) -> str:
        """Back a loaded brace off after a protective stop (docs/safety.md §15): nobody stays clamped.

        With a stop latched whose cause is load (force, wrench, saturation, following error,
        step, speed: :data:`~.monitors.RELIEVABLE`), the drives are enabled again under
        force supervision and every actuator moves, slowly (``speed_share`` of ``v_max``,
        10 % by default), the way that unloads its own leg (its measured force's opposite
        sign, all axes as one vector) until every force has read below
        ``safety.release_force`` for :data:`RELIEF_CONFIRM_S`; then they decelerate and hold in QUICK STOP ACTIVE. The stop stays latched:
        :meth:`recover` then succeeds, its cause being gone. A relief moves at most
        ``max_travel`` (m or rad; by default half the shortest actuator range: a body
        pressed back from the limit unloads well before that) and stops on any fault it
        cannot back off from.

        :returns: what happened (forces before and after, travel).
        :raises DriverOperationError: nothing latched, a fault the relief cannot handle (a
            drive or communication fault: the message names it), or the relief stopped
            before the forces were below the release force (why, and the forces).
        """
        life = self.life
        with self._api_lock:
            life.require_open()
            if not self.supervisor.latched:
                raise DriverOperationError('nothing to relieve: no protective stop is latched')
            others = [f for f in self.supervisor.faults if f.kind not in RELIEVABLE]
            if others:
                raise DriverOperationError(
                    f'cannot relieve: {others[0].describe()} is not a load the drives can back off '
                    'from; fix its cause and recover first')
            fb = self.feedback()
            release = self.limits.release_force
            if np.all(np.abs(fb.force) < release):
                return (f'nothing to relieve: every force is below safety.release_force = '
                        f'{release:g} N ({np.round(fb.force, 1).tolist()} N); call recover')
            if any(d.state in (State402.FAULT, State402.FAULT_REACTION_ACTIVE) for d in life.drives):
                life.reset_pulse = True                # a drive's own fault: reset it first
                try:
                    life.wait(lambda: not any(d.state in (State402.FAULT, State402.FAULT_REACTION_ACTIVE)
                                              for d in life.drives),
                              timeout=0.5, what='drive fault reset', raise_=False)
                finally:
                    life.reset_pulse = False
            ranges, max_travel = self._slow_move_ranges(max_travel)
            relief = Relief(release_force=release, speed=speed_share * self.limits.v_max,
                            force_limit=self.limits.force_limit,
                            max_travel=max_travel, deadline=time.perf_counter() + timeout,
                            start=fb.position, forces=fb.force, relievable=RELIEVABLE,
                            lo=np.array([r[0] for r in ranges]), hi=np.array([r[1] for r in ranges]),
                            names=self.names,
                            confirm=math.ceil(RELIEF_CONFIRM_S / self.config.period),
                            unit=self.limits.unit)
            ex = self.motion.executor
            with self.motion.lock:
                ex.anchor(fb.position, time.perf_counter() + self.config.period,
                          reason='relief: command anchored at the drives')
                ex.events.clear()
                life.relief = relief
            life.set_state(MasterState.RELIEVING)
            life.desired = State402.OPERATION_ENABLED
            log.warning('relief: backing off from forces %s N', np.round(fb.force, 1).tolist())
            try:
                relief.finished.wait(timeout + 2.0)
            finally:
                life.relief = None
                life.desired = State402.QUICK_STOP_ACTIVE
                with self.motion.lock:
                    ex.release('relief ended')
                    ex.events.clear()
                life.wait(lambda: all(d.state in (State402.QUICK_STOP_ACTIVE, State402.SWITCH_ON_DISABLED,
                                                  State402.FAULT) for d in life.drives),
                          timeout=1.0, what='QUICK STOP ACTIVE after the relief', raise_=False)
                life.set_state(MasterState.FAULT if self.supervisor.latched else MasterState.DISABLED)
            after = self.feedback().force
            life.relieved = life.relieved or relief.travel > 0.0
            if relief.outcome:
                raise DriverOperationError(f'relief stopped: {relief.outcome}')
            if relief.outcome is None:
                raise DriverOperationError('relief did not finish in time: forces '
                                           f'{np.round(after, 1).tolist()} N')
            return (f'relieved: forces {np.round(relief.forces_before, 1).tolist()} N -> '
                    f'{np.round(after, 1).tolist()} N (below safety.release_force = {release:g} N) '
                    f'after {relief.travel * 1e3:.2f} {relief.milli}; call recover')

    def _slow_move_ranges(self, max_travel: float | None) -> tuple[list[tuple[float, float]], float]:
        """Each actuator's range, and the most a relief or take-up may travel: ``max_travel``,
        by default half the shortest range."""
        ranges = [self.limits.stroke_of(i) for i in range(len(self.names))]
        if max_travel is None:
            max_travel = 0.5 * min(hi - lo for lo, hi in ranges)
        return ranges, max_travel

    @property
    def taking_up(self) -> bool:
        """A :meth:`take_up` is under way (enabled, but not yet following goals)."""
        return self.life.take_up is not None

    def distance_to_go(self, stream_horizon: float = 0.25) -> float | None:
        """:meth:`~.execution.PathExecutor.distance_to_go` of the command (m or rad), ``None``
        when no motion a soft limit may stop runs."""
        if self.state is not MasterState.ENABLED:
            return None
        with self.motion.lock:
            return self.motion.executor.distance_to_go(stream_horizon)

    def soft_stop(self, reason: str) -> bool:
        """A soft limit found beside the per-drive monitors (the platform wrench's or a load
        cell's prediction, docs/safety.md §14; or a caller's): the running trajectory or
        setpoint stream brakes along its path at the next SYNC
        and holds, reported stopped with ``reason``; nothing latches. ``False`` (nothing
        done) when no such motion runs, it already brakes, or a soft stop is pending."""
        if self.distance_to_go() is None or self.life.soft_stop is not None:
            return False
        self.life.soft_stop = str(reason)
        return True

    def take_up(self, *, below: float, speed_share: float = 0.1, max_travel: float | None = None,
                timeout: float | None = None) -> str:
        """Take up the slack of pull-only legs (cables) at rest: every leg reading less tension
        than ``below`` (N) shortens slowly until it reads at least that, the taut ones hold;
        then the command decelerates and holds, enabled. Slowly: at most ``speed_share`` of
        ``v_max``, and so that a leg turning taut gains at most ``below`` in the
        :data:`TAKE_UP_LAG_SYNCS` SYNCs its load cell takes to say so (the legs' stiffness);
        ``timeout`` (s) by default covers ``max_travel`` at that speed, at most a minute.

        After a relief (docs/safety.md §15) a cable brace's cables hang slack: their lengths no
        longer agree with any pose, and a motion planned from the pose would start far from
        them. Taken up, the lengths are the cables' at the platform's true pose again.

        :returns: what happened (tensions before and after, the most any cable shortened);
            nothing to do when every leg is taut.
        :raises DriverOperationError: not enabled, moving, or the take-up stopped short
            (stroke end, ``max_travel`` -- half the shortest range by default --, time out, a
            protective stop): why, and the tensions.
        """
        life = self.life
        with self._api_lock:
            life.require_open()
            if self.state is not MasterState.ENABLED or self.supervisor.latched:
                raise DriverOperationError(f'take-up needs the drives enabled (now {self.state.value})')
            with self.motion.lock:
                if self.motion.executor.moving:
                    raise DriverOperationError('take-up starts from rest: a motion is running')
            fb = self.feedback()
            ranges, max_travel = self._slow_move_ranges(max_travel)
            speed = min(speed_share * self.limits.v_max,
                        below / (self.config.stiffness * TAKE_UP_LAG_SYNCS * self.config.period))
            if timeout is None:
                timeout = min(60.0, 5.0 + 1.5 * max_travel / speed)
            take = TakeUp(below=below, speed=speed, max_travel=max_travel,
                          deadline=time.perf_counter() + timeout, start=fb.position, forces=fb.force,
                          lo=np.array([r[0] for r in ranges]), names=self.names,
                          confirm=math.ceil(RELIEF_CONFIRM_S / self.config.period), unit=self.limits.unit)
            if not np.any(take.slack(fb.force)):
                life.relieved = False
                return f'nothing to take up: every leg holds {below:g} N or more'
            log.warning('take-up: tensions %s N', np.round(-fb.force, 1).tolist())
            life.take_up = take
            try:
                take.finished.wait(timeout + 2.0)
            finally:
                life.take_up = None
                life.wait(lambda: not self.motion.executor.moving, timeout=1.0,
                          what='rest after the take-up', raise_=False)
            after = self.feedback().force
            if take.outcome is None:
                take.outcome = f'time out with tensions {np.round(-after, 1).tolist()} N'
            if take.outcome:
                raise DriverOperationError(f'take-up stopped: {take.outcome}')
            life.relieved = False
            return (f'slack taken up: tensions {np.round(-take.forces_before, 1).tolist()} N -> '
                    f'{np.round(-after, 1).tolist()} N, cables shortened up to '
                    f'{np.max(take.travel) * 1e3:.2f} {take.milli}')

    def recover(self, *, timeout: float | None = None) -> list[Fault]:
        """Fault reset (6040h bit 7 edge) and clear the latch — only if every cause is gone.

        The commands that were in force are discarded (a stream setpoint, a trajectory):
        after :meth:`enable` the command starts where the drives are. Drives that left
        OPERATIONAL are re-configured and started. On success the drives are in SWITCH ON
        DISABLED; call :meth:`enable` to move again.

        :returns: the faults whose cause is still present (empty list: recovered).
        :raises DriverOperationError: nothing is latched (nothing was changed).
        """
        life = self.life
        with self._api_lock:
            life.require_open()
            if not self.supervisor.latched and not any(
                    d.state in (State402.FAULT, State402.FAULT_REACTION_ACTIVE) for d in life.drives):
                raise DriverOperationError(
                    f'nothing to recover: no protective stop is latched and no drive is in FAULT '
                    f'(master {self.state.value}); nothing was changed')
            life.tracking = False
            self.stream.drop()
            self.cycle.forget_fault_stop()
            self.motion.release('recover: commands discarded')
            life.recover_time = time.monotonic()
            restarted = []
            for d in life.nodes:
                if d.nmt is not None and d.nmt != NmtState.OPERATIONAL and \
                        not self.monitors.heartbeat_missing(d)():
                    try:
                        if d is life.module:
                            self.setup.configure_module(d)
                        else:
                            self.setup.configure(d)
                            d.checked = None
                            d.history.clear()
                            # it left OPERATIONAL: it may have restarted without a boot-up
                            # message (its position counter then starts anew), so its
                            # reference is not trusted: home again (a fault sweep: a silent
                            # reboot kept `homed`, and a2 read 390 mm off the truth)
                            if life.homed:
                                log.warning('recover: %s left OPERATIONAL: home again', d.name)
                            life.homed = False
                        d.node.nmt.send_command(0x01)
                        restarted.append(d)
                    except DriverInitializationError as exc:
                        log.error('recover: %s', exc)
            if restarted:
                start = self.receiver.tpdo_total
                life.wait(lambda: all(d.nmt == NmtState.OPERATIONAL and (d.rx_total > start or d is life.module)
                                      for d in restarted),
                          timeout=max(0.5, 4 * self.config.drive_heartbeat_ms * 1e-3),
                          what='restarted drives OPERATIONAL', raise_=False)
            life.desired = State402.SWITCH_ON_DISABLED
            life.reset_pulse = True
            try:
                life.wait(lambda: life.all_in(State402.SWITCH_ON_DISABLED),
                          timeout=min(0.5, timeout or 0.5), what='SWITCH ON DISABLED', raise_=False)
                # one more monitor pass on fresh samples before judging the causes
                life.wait_syncs(2)
            finally:
                life.reset_pulse = False
            blocking = self.supervisor.try_clear()
            if blocking:
                life.set_state(MasterState.FAULT)
                return blocking
            self.supervisor.unwarn('setpoint')
            life.set_state(MasterState.DISABLED)
            return []

    def protective_stop(self, kind: FaultKind, cause: str, *, drive: str | None = None,
                        still_present: Callable[[], bool] | None = None) -> Fault | None:
        """Latch a fault found outside the master (e.g. the node's wrench monitor)."""
        return self.supervisor.report(kind, cause, drive=drive, still_present=still_present)

    def status(self) -> MasterStatus:
        """Snapshot for diagnostics."""
        now = time.monotonic()
        drives = []
        for d in self.life.drives:
            s = d.sample
            nmt = ('-' if d.nmt is None else
                   NmtState(d.nmt).name if d.nmt in NmtState._value2member_map_ else str(d.nmt))
            emcy = ''
            if d.emcy is not None:
                code, reg, t = d.emcy
                emcy = f'{code:04X}h {emcy_description(code)} ({now - t:.1f} s ago)'
            drives.append(DriveStatus(
                d.name, d.node_id, nmt, d.state, s.statusword if s else 0,
                s.position if s else math.nan, d.velocity, s.force if s else math.nan,
                self.scaling.to_si(d.target), self.receiver.heartbeat_age(d), emcy, d.samples))
        traffic = self.traffic
        frames, load = traffic.rate
        bus = BusStatus(frames, load, traffic.error_state, traffic.error_frames, self.send_failures)
        return MasterStatus(self.state, tuple(drives), bus, self.stats.report(),
                            self.supervisor.faults, tuple(w.message for w in self.supervisor.warnings),
                            self.stream.stale_holds, self.homed, self.stream.accepted,
                            self.stream.rejected, self.executor.state.value,
                            self.executor.running_tag)

    def shutdown(self, *, timeout: float = 0.5) -> None:
        """Disable the drives, NMT pre-operational, stop SYNC, close the bus. Idempotent."""
        life = self.life
        with self._api_lock:
            if life.state is MasterState.CLOSED:
                return
            if life.pdo_running and self.bus is not None:
                life.tracking = False
                life.supervising = False      # the drives will miss our heartbeat: expected
                life.closing = True
                life.desired = State402.SWITCH_ON_DISABLED
                try:
                    life.wait(lambda: all(d.state in (State402.SWITCH_ON_DISABLED, State402.FAULT,
                                                      State402.UNKNOWN) for d in life.drives),
                              timeout=timeout, what='SWITCH ON DISABLED', raise_=False)
                except Exception:  # noqa: BLE001 - closing anyway
                    pass
            life.pdo_running = False
            life.supervising = False
            self.motion.release('the driver shut down')
            if self.network is not None and life.drives and self.cycle.heartbeat_on:
                # (only drives this master took over: a master refused at boot leaves them be)
                for d in life.nodes:
                    try:
                        d.node.nmt.send_command(0x80)     # pre-operational: PDOs off, SDO kept
                    except Exception:  # noqa: BLE001 - bus may be gone already
                        pass
            self.cycle.stop()
            self.setup.close()
            life.set_state(MasterState.CLOSED)
