"""The SYNC cycle: monitors, the commanded motion, RPDOs, SYNC — once per control period.

A part of :class:`~.master.BraceMaster` with its own state: the SYNC thread, the master's
heartbeat, what it sent and when it last woke, a fault's braking. :meth:`Cycle.start` starts
the thread on the bus the boot opened; the thread is the only caller of :meth:`Cycle.cycle`.
Per cycle (docs/can.md "PDO mapping"):

1. the master heartbeat when due (by time: an overrun skips cycles, never heartbeats);
2. the monitors on the TPDO1 samples that answered the previous SYNC (:class:`~.monitors.Monitors`);
3. the command: :class:`~.execution.PathExecutor` advanced to the instant one
   interpolation period ahead (the drive interpolates 607Ah linearly over 60C2h = the SYNC
   period, so its reference equals the plan at the SYNC instants), from the running
   trajectory or the setpoint stream, one time base for all axes; after a brakeable fault
   it first brakes the motion along its path;
4. per drive the RPDOs as planned against its dictionary (:mod:`.plan`; by default RPDO1
   controlword 6040h + target 607Ah and RPDO2 velocity offset 60B1h, the feed-forward)
   when their content changed (every SYNC while moving; at rest every ``RPDO_REFRESH``
   SYNCs: a synchronous RPDO not received keeps its value), then SYNC.

The setpoint stream (teleoperation; docs/safety.md §1, §7) is :class:`~.stream.SetpointStream`,
fed in step 3.
"""
from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

import can
import numpy as np

from .cia402 import Controlword, NmtState, State402, controlword_towards, decode_state
from .frame import Frame
from ..control.execution import ExecutionState
from .monitors import BRAKEABLE
from .state import Relief, TakeUp, _Drive
from .supervision import FaultKind
from .timing import PeriodStats, run_periodic

if TYPE_CHECKING:
    import canopen

    from .lifecycle import Lifecycle, Motion
    from .monitors import Monitors
    from .receive import BusTraffic
    from .stream import SetpointStream
    from .sync import SyncClock

__all__ = ['Cycle', 'set_thread_priority']

log = logging.getLogger('brace_control.can.master')

#: the longest a protective stop brakes along the path before the drives' own quick stop (s)
FAULT_BRAKE_LIMIT_S = 1.0
#: SYNCs between repeats of an unchanged RPDO (controlword + target, velocity offset)
RPDO_REFRESH = 50
#: a relief's force gain as a share of the stiffest direction's one-cycle limit
RELIEF_GAIN = 0.2
#: the slowest a relief on rotary joints moves, as a share of its speed
RELIEF_MIN_SHARE = 0.25
_SYNC_ID = 0x80


class Cycle:
    """The SYNC thread's cycle (see the module docstring).

    :param life: the master's shared state (drives, the 402 state wanted, the flags the API
        sets, the relief and take-up under way, a soft stop requested).
    :param motion: the commanded motion the cycle samples.
    :param stream: the setpoint stream it takes setpoints from.
    :param monitors: the protective functions it runs first.
    """

    def __init__(self, life: Lifecycle, motion: Motion, stream: SetpointStream,
                 monitors: Monitors, clock: SyncClock, traffic: BusTraffic) -> None:
        config = life.config
        self._life = life
        self._motion = motion
        self._stream = stream
        self._monitors = monitors
        self._clock = clock
        self._traffic = traffic
        self._supervisor = life.supervisor
        self._config = config
        self._scaling = config.scaling
        self.stats = PeriodStats(config.period)
        #: ``f(actuator index, force) -> str``: what the soft-limit stop adds to its reason
        #: (the node: the wrench capacity at the estimated pose); ``None``: nothing
        self.soft_limit_context: Callable[[int, float], str] | None = None
        self._bus: can.BusABC | None = None
        self._network: canopen.Network | None = None
        self.stop_event = threading.Event()
        self._thread: threading.Thread | None = None
        self._last_wake = 0.0
        self._commanding = False               # last cycle's targets came from the executor
        self._fault_brake_until = 0.0
        self._hb_period = config.master_heartbeat_ms * 1e-3
        self._next_hb = 0.0
        #: the master's heartbeat is produced (once the boot found no other master: ours
        #: would make a running master stop)
        self.heartbeat_on = False
        self._hb_msg = Frame(arbitration_id=0x700 + config.master_node_id,
                             data=bytes([NmtState.OPERATIONAL]), is_extended_id=False)
        self._sync_msg = Frame(arbitration_id=_SYNC_ID, data=b'', is_extended_id=False)
        self.send_failures = 0
        self._last_send_failed = False

    # ------------------------------------------------------------------ the thread
    def start(self, bus: can.BusABC, network: canopen.Network) -> None:
        """Start the SYNC thread on ``bus`` (heartbeat only until the PDOs run)."""
        self._bus, self._network = bus, network
        self.heartbeat_on = False
        self.stop_event.clear()
        self._thread = threading.Thread(target=self._run, name='brace-can-sync', daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """End the SYNC thread (waits up to 2 s unless called from it) and let go of the bus."""
        self.stop_event.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)
        self._thread = None
        self._bus = self._network = None

    def forget_fault_stop(self) -> None:
        """A recover discards the command: no braking for a fault from here."""
        self._fault_brake_until = 0.0

    def _run(self) -> None:
        set_thread_priority(self._config.thread_priority)
        try:
            run_periodic(self._config.period, self.cycle, self.stop_event, stats=self.stats,
                         spin_s=self._config.spin_s)
        except Exception as exc:  # noqa: BLE001 - report, the drives stop on heartbeat loss
            log.exception('SYNC thread died')
            self._supervisor.report(FaultKind.CYCLE_STOPPED,
                                    f'SYNC thread died: {exc!r}; restart the driver',
                                    still_present=lambda: True)

    def _send(self, msg: can.Message) -> bool:
        bus = self._bus
        if bus is None:
            return False
        if msg is not self._sync_msg:         # the SYNC's is set with the SYNC log's entry
            msg.timestamp = time.time()       # kept by a virtual bus (preserve_timestamps)
        try:
            with self._network.send_lock:      # type: ignore[union-attr]
                bus.send(msg, timeout=self._config.send_timeout)
        except (can.CanError, OSError) as exc:
            self.send_failures += 1
            self._last_send_failed = True
            self._supervisor.report(
                FaultKind.SEND_FAILED, f'frame {msg.arbitration_id:03X}h not sent: {exc}',
                still_present=lambda: self._last_send_failed)
            return False
        self._last_send_failed = False
        self._traffic.sent(msg.dlc)
        return True

    def cycle(self, k: int, t_wake: float) -> None:
        """One control period (the SYNC thread; see the module docstring)."""
        life = self._life
        if t_wake >= self._next_hb:          # by time: overruns skip cycles, not heartbeats
            self._next_hb += self._hb_period
            if self._next_hb <= t_wake:
                self._next_hb = t_wake + self._hb_period
            if self.heartbeat_on:
                self._send(self._hb_msg)
        if k % 256 == 0:
            self._traffic.update_rates(t_wake)
        if not life.pdo_running:
            self._last_wake = t_wake
            return
        if t_wake - self._last_wake > 3 * self._config.period and self._last_wake:
            # this process did not run for a while: frames queued meanwhile are not yet
            # received; give the receive thread a moment before judging silence by time
            self._monitors.grace_until = time.monotonic() + max(0.02, 10 * self._config.period)
            self._monitors.host_stalled(t_wake - self._last_wake - self._config.period)
        self._last_wake = t_wake
        if life.supervising:
            self._monitors.run()
        stopped = self._supervisor.latched
        relief = life.relief
        if stopped and life.fault_to_handle:
            life.fault_to_handle = False
            if relief is not None:
                relief.check_faults(self._supervisor.faults)
                if relief.outcome:             # a fault it cannot back off from: stop as usual
                    life.relief = relief = None
            if relief is None:
                self._begin_fault_stop(t_wake)
        if not stopped and life.soft_stop is not None:
            self._begin_soft_stop(t_wake)
        braking = stopped and self._fault_braking(t_wake)
        drives = life.drives
        enabled = [d.sample is not None and decode_state(d.sample.statusword) is State402.OPERATION_ENABLED
                   for d in drives]
        following = ((life.tracking and not stopped) or braking or relief is not None) and any(enabled)
        take = life.take_up
        if take is not None and stopped and take.outcome is None:
            take.outcome = f'protective stop: {self._supervisor.summary()}'
            take.finished.set()
        if following:
            if relief is not None:
                self._feed_relief(relief, t_wake)
            elif take is not None and not stopped:
                self._feed_take_up(take, t_wake)
            self._command(t_wake, feed=life.tracking and not stopped)
            if self._supervisor.latched and not stopped:
                stopped = True
                braking = self._fault_braking(t_wake)
        if not following:
            self._commanding = False
        for d, on in zip(drives, enabled):
            s = d.sample
            if s is None:
                continue
            state = decode_state(s.statusword)
            cw = self._controlword(d, state, stopped and not braking and relief is None)
            if not (following and on):
                d.target = life.actual_counts(d)     # hold where it is; enable without a jump
                d.velocity_offset = 0
            # a synchronous RPDO the drive does not receive keeps its last value (CiA 301): an
            # RPDO goes out when its content changes (every SYNC while moving) and every
            # RPDO_REFRESH SYNCs anyway; at rest only SYNC and the TPDOs are on the bus
            refresh = k % RPDO_REFRESH == 0
            values = {'controlword': cw, 'target': d.to_wire(d.target),
                      'velocity_offset': d.rate_to_wire(d.velocity_offset), 'mode': life.mode}
            for j, lay in enumerate(d.rpdos):
                data = lay.codec.pack(*[values[r] for r in lay.roles])
                if data != d.rpdo_sent[j] or refresh:
                    self._send(Frame(arbitration_id=lay.cob_id, data=data, is_extended_id=False))
                    d.rpdo_sent[j] = data
            d.sent.append((self._clock.index + 1, d.target))     # for the SYNC sent next
        # the TPDOs answering this SYNC may arrive before send() returns: stamp first; the
        # frame carries the time the log keeps
        self._sync_msg.timestamp = self._clock.stamp()
        self._send(self._sync_msg)

    # ------------------------------------------------------------------ the command
    def _command(self, t_wake: float, *, feed: bool) -> None:
        """Advance the executor one period ahead and turn its command into targets.

        ``feed``: the stream's setpoints are taken (not while braking for a fault).
        """
        period = self._config.period
        motion = self._motion
        ex = motion.executor
        with motion.lock:
            if feed:
                self._stream.feed(ex, t_wake)
            if ex.source is not None:
                ex.forces = self._latest_forces()
            q, v = ex.step(t_wake + period)
            motion.collect()
            if motion.trace is not None:
                now = time.time()
                motion.trace.cycles.append(now)
                if ex.source is not None:
                    motion.trace.commands.append((now, tuple(float(x) for x in q)))
        cpu = self._scaling.counts_per_unit
        limits = self._life.limits
        for d in self._life.drives:
            qi = float(q[d.index])
            target = round(qi * cpu)
            # docs/safety.md §7 at the source: the executor never steps (it advances at most 1.5
            # periods per cycle within v_max); a larger step is a fault, not a command
            step = abs(target - d.target) / cpu
            if d.sample is not None and step > 2.0 * limits.v_max * period + limits.step_margin \
                    and self._commanding:
                self._supervisor.report(
                    FaultKind.STEP_LIMIT, f'commanded step {step * 1e3:.3f} mm (or mrad) in one '
                    f'period exceeds 2 v_max T + margin; command held', drive=d.name,
                    still_present=self._monitors.step_condition)
                return
            d.target = target
            d.velocity_offset = round(float(v[d.index]) * cpu)
        self._commanding = True

    def _latest_forces(self) -> np.ndarray:
        """Each drive's load-cell force (N or N·m) of its latest TPDO1: the answers to the
        last SYNC (NaN for a drive that has not answered: the admittance stops on it)."""
        return np.array([d.sample.force if d.sample is not None else math.nan for d in self._life.drives])

    # ------------------------------------------------------------------ soft force limit
    def _begin_soft_stop(self, t_wake: float) -> None:
        """docs/safety.md §14: a leg above the soft limit while the motion presses on (or a soft
        limit the node found: :meth:`~.master.BraceMaster.soft_stop`, its reason given):
        brake along the path and hold; reported as the motion's stop, nothing latches."""
        life = self._life
        pending, life.soft_stop = life.soft_stop, None
        if isinstance(pending, str):
            key = 'soft_force' if pending.startswith('soft force') else 'soft_wrench'
            reason = pending
        else:
            index, force = pending
            name = self._config.names[index]
            context = ''
            if self.soft_limit_context is not None:
                try:
                    context = self.soft_limit_context(index, force)
                except Exception as exc:  # noqa: BLE001 - the stop matters, not its description
                    context = f' (capacity unknown: {exc!r})'
            unit = life.limits.force_unit
            key = 'soft_force'
            reason = (f'soft force limit: {name} at {force:.1f} {unit}, above safety.soft_force_limit = '
                      f'{life.limits.soft_force_limit:.3g} {unit}{context}; decelerated along the path, holding')
        log.warning(reason)
        self._supervisor.warn(key, reason)
        with self._motion.lock:
            self._motion.executor.stop(reason, now=t_wake)

    # ------------------------------------------------------------------ relief
    def _feed_relief(self, relief: 'Relief', t_wake: float) -> None:
        """One cycle of a relief (docs/safety.md §15): every actuator moves the way that unloads its
        own leg, at most ``speed`` (one vector, scaled as a whole), until every force is below
        the release force; then the command decelerates and holds."""
        def velocity(forces: np.ndarray) -> np.ndarray:
            # steepest descent of the elastic energy: dE/dq_i = f_i (the legs and the body at
            # equilibrium). The gain keeps the stiffest direction (a leg against its own
            # stiffness k) from stepping past zero in one cycle: k g T = RELIEF_GAIN < 1.
            gain = RELIEF_GAIN / (self._config.stiffness * self._config.period)
            v = -gain * forces
            fastest = float(np.max(np.abs(v)))
            if fastest > relief.speed:
                v = v * (relief.speed / fastest)
            elif self._life.limits.unit == 'rad' and 0.0 < fastest < RELIEF_MIN_SHARE * relief.speed:
                # a rotary joint modelled rigid (1e7 N·m/rad) meets only the body through the
                # mechanism: paced by its own figure it would crawl at micro-radians per second
                v = v * (RELIEF_MIN_SHARE * relief.speed / fastest)
            return v
        self._feed_force_move(relief, t_wake, velocity)

    def _feed_take_up(self, take: 'TakeUp', t_wake: float) -> None:
        """One cycle of a take-up: every slack leg shortens at the take-up's speed, the taut
        ones hold; once all are taut (or it stopped short) the command decelerates and holds."""
        self._feed_force_move(take, t_wake, lambda forces: np.where(take.slack(forces), -take.speed, 0.0))

    def _feed_force_move(self, move: 'Relief | TakeUp', t_wake: float,
                         velocity: Callable[[np.ndarray], np.ndarray]) -> None:
        """One cycle of a slow move steered by the load cells (a relief, a take-up): judged on
        the latest forces (``move.update``), moved at ``velocity(forces)`` while it runs; once
        it has ended the command decelerates, and at rest ``move.finished`` is set."""
        forces = np.array([d.sample.force if d.sample is not None else 0.0 for d in self._life.drives])
        with self._motion.lock:
            ex = self._motion.executor
            if move.outcome is None:
                move.update(forces, ex.q, t_wake)
            if move.outcome is None:
                v = velocity(forces)
                ex.set_stream(ex.q + v * self._config.period, v, t_wake)
            elif ex.state is not ExecutionState.HOLD and not ex.braking:
                ex.stream_stale()
            elif ex.state is ExecutionState.HOLD:
                move.finished.set()

    # ------------------------------------------------------------------ protective stop
    def _begin_fault_stop(self, t_wake: float) -> None:
        """A fault latched: brake the motion along its path when the drives still follow
        and every latched fault allows it, else hand over to the drives' quick stop."""
        kinds = {f.kind for f in self._supervisor.faults}
        reason = f'protective stop: {self._supervisor.summary()}'
        motion = self._motion
        with motion.lock:
            if motion.executor.moving and kinds <= BRAKEABLE and self._commanding:
                motion.executor.stop(reason, now=t_wake)
                self._fault_brake_until = t_wake + FAULT_BRAKE_LIMIT_S
            else:
                motion.executor.release(reason)
                motion.collect()
                self._fault_brake_until = 0.0

    def _fault_braking(self, t_wake: float) -> bool:
        """Still braking along the path after a fault (else the drives quick-stop)."""
        if not self._fault_brake_until:
            return False
        kinds = {f.kind for f in self._supervisor.faults}
        if t_wake < self._fault_brake_until and self._motion.executor.moving and kinds <= BRAKEABLE:
            return True
        self._fault_brake_until = 0.0
        self._motion.release(f'protective stop: {self._supervisor.summary()}')
        return False

    def _controlword(self, d: _Drive, state: State402, stopped: bool) -> int:
        life = self._life
        if life.closing:
            return int(Controlword.DISABLE_VOLTAGE)
        if life.reset_pulse:
            if state in (State402.FAULT, State402.FAULT_REACTION_ACTIVE):
                d.reset_phase = not d.reset_phase          # 0000h, 0080h, 0000h, ... edges
                return int(Controlword.FAULT_RESET) if d.reset_phase else 0
            return int(Controlword.DISABLE_VOLTAGE)
        if stopped:
            return int(Controlword.QUICK_STOP)
        if life.homing_start and state is State402.OPERATION_ENABLED:
            return int(Controlword.START_HOMING)
        cw = controlword_towards(state, life.desired)
        return int(Controlword.DISABLE_VOLTAGE) if cw is None else cw


def set_thread_priority(priority: int) -> bool:
    """SCHED_FIFO ``priority`` for the calling thread (Linux; needs CAP_SYS_NICE).

    Returns whether it took effect; 0 leaves the thread as it is.
    """
    if priority <= 0:
        return False
    import os
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        return True
    except (AttributeError, OSError) as exc:
        log.warning('SYNC thread keeps normal scheduling: SCHED_FIFO %d refused (%s)', priority, exc)
        return False
