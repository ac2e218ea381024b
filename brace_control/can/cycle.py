"""The SYNC cycle: monitors, the commanded motion, RPDOs, SYNC — once per control period.

Part of :class:`~.master.BraceMaster` (a mixin; the SYNC thread is the only caller of
:meth:`CycleMixin._cycle`). Per cycle (docs/can.md "PDO mapping"):

1. the master heartbeat when due (by time: an overrun skips cycles, never heartbeats);
2. the monitors on the TPDO1 samples that answered the previous SYNC (:mod:`.monitors`);
3. the command: :class:`~.execution.PathExecutor` advanced to the instant one
   interpolation period ahead (the drive interpolates 607Ah linearly over 60C2h = the SYNC
   period, so its reference equals the plan at the SYNC instants), from the running
   trajectory or the setpoint stream, one time base for all axes; after a brakeable fault
   it first brakes the motion along its path;
4. per drive the RPDOs as planned against its dictionary (:mod:`.plan`; by default RPDO1
   controlword 6040h + target 607Ah and RPDO2 velocity offset 60B1h, the feed-forward)
   when their content changed (every SYNC while moving; at rest every ``RPDO_REFRESH``
   SYNCs: a synchronous RPDO not received keeps its value), then SYNC.

The setpoint stream (teleoperation): a new setpoint is step-checked (docs/safety.md §7) over the
smaller of the time between its stamp and the previous one and the time between their
arrivals, plus one period (a sender's clock cannot license a jump); setpoints whose stamps
do not increase are counted as rejected and reported once per burst; no setpoint for
``command_timeout`` stops the stream (docs/safety.md §1): the executor decelerates along the current
direction and holds.
"""
from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable

import can
import numpy as np

from .cia402 import Controlword, State402, controlword_towards, decode_state
from .frame import Frame
from ..control.execution import ExecutionState
from .monitors import BRAKEABLE
from .pdo import frame_bits
from .state import Relief, TakeUp, _Drive, _Setpoint, sender_rate
from .supervision import FaultKind, check_step
from .timing import run_periodic

__all__ = ['CycleMixin', 'set_thread_priority']

log = logging.getLogger('brace_control.can.master')

#: the longest a protective stop brakes along the path before the drives' own quick stop (s)
FAULT_BRAKE_LIMIT_S = 1.0
#: SYNCs between repeats of an unchanged RPDO (controlword + target, velocity offset)
RPDO_REFRESH = 50
#: a relief's force gain as a share of the stiffest direction's one-cycle limit
RELIEF_GAIN = 0.2
#: the slowest a relief on rotary joints moves, as a share of its speed
RELIEF_MIN_SHARE = 0.25


class CycleMixin:
    """The SYNC thread's cycle (see the module docstring)."""

    def _run(self) -> None:
        set_thread_priority(self.config.thread_priority)
        try:
            run_periodic(self.config.period, self._cycle, self._stop, stats=self.stats,
                         spin_s=self.config.spin_s)
        except Exception as exc:  # noqa: BLE001 - report, the drives stop on heartbeat loss
            log.exception('SYNC thread died')
            self.supervisor.report(FaultKind.CYCLE_STOPPED,
                                   f'SYNC thread died: {exc!r}; restart the driver',
                                   still_present=lambda: True)

    def _send(self, msg: can.Message) -> bool:
        bus = self._bus
        if bus is None:
            return False
        if msg is not self._sync_msg:         # the SYNC's is set with the SYNC log's entry
            msg.timestamp = time.time()       # kept by a virtual bus (preserve_timestamps)
        try:
            with self.network.send_lock:       # type: ignore[union-attr]
                bus.send(msg, timeout=self.config.send_timeout)
        except (can.CanError, OSError) as exc:
            self.send_failures += 1
            self._last_send_failed = True
            self.supervisor.report(
                FaultKind.SEND_FAILED, f'frame {msg.arbitration_id:03X}h not sent: {exc}',
                still_present=lambda: self._last_send_failed)
            return False
        self._last_send_failed = False
        self.traffic.sent(msg.dlc)
        return True

    def _cycle(self, k: int, t_wake: float) -> None:
        if t_wake >= self._next_hb:          # by time: overruns skip cycles, not heartbeats
            self._next_hb += self._hb_period
            if self._next_hb <= t_wake:
                self._next_hb = t_wake + self._hb_period
            if self._heartbeat_on:
                self._send(self._hb_msg)
        if k % 256 == 0:
            self.traffic.update_rates(t_wake)
        if not self._pdo_running:
            self._last_wake = t_wake
            return
        if t_wake - self._last_wake > 3 * self.config.period and self._last_wake:
            # this process did not run for a while: frames queued meanwhile are not yet
            # received; give the receive thread a moment before judging silence by time
            self._grace_until = time.monotonic() + max(0.02, 10 * self.config.period)
        self._last_wake = t_wake
        if self._supervising:
            self._monitor()
        stopped = self.supervisor.latched
        relief = self._relief
        if stopped and self._fault_to_handle:
            self._fault_to_handle = False
            if relief is not None:
                relief.check_faults(self.supervisor.faults)
                if relief.outcome:             # a fault it cannot back off from: stop as usual
                    self._relief = relief = None
            if relief is None:
                self._begin_fault_stop(t_wake)
        if not stopped and self._soft_stop is not None:
            self._begin_soft_stop(t_wake)
        braking = stopped and self._fault_braking(t_wake)
        drives = self._drives
        enabled = [d.sample is not None and decode_state(d.sample.statusword) is State402.OPERATION_ENABLED
                   for d in drives]
        following = ((self._tracking and not stopped) or braking or relief is not None) and any(enabled)
        take = self._take_up
        if take is not None and stopped and take.outcome is None:
            take.outcome = f'protective stop: {self.supervisor.summary()}'
            take.finished.set()
        if following:
            if relief is not None:
                self._feed_relief(relief, t_wake)
            elif take is not None and not stopped:
                self._feed_take_up(take, t_wake)
            self._command(t_wake, feed=self._tracking and not stopped)
            if self.supervisor.latched and not stopped:
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
                d.target = self._actual_counts(d)     # hold where it is; enable without a jump
                d.velocity_offset = 0
            # a synchronous RPDO the drive does not receive keeps its last value (CiA 301): an
            # RPDO goes out when its content changes (every SYNC while moving) and every
            # RPDO_REFRESH SYNCs anyway; at rest only SYNC and the TPDOs are on the bus
            refresh = k % RPDO_REFRESH == 0
            values = {'controlword': cw, 'target': d.to_wire(d.target),
                      'velocity_offset': d.rate_to_wire(d.velocity_offset), 'mode': self._mode}
            for j, lay in enumerate(d.rpdos):
                data = lay.codec.pack(*[values[r] for r in lay.roles])
                if data != d.rpdo_sent[j] or refresh:
                    self._send(Frame(arbitration_id=lay.cob_id, data=data, is_extended_id=False))
                    d.rpdo_sent[j] = data
            d.sent.append((self.clock.index + 1, d.target))     # for the SYNC sent next
        # the TPDOs answering this SYNC may arrive before send() returns: stamp first; the
        # frame carries the time the log keeps
        self._sync_msg.timestamp = self.clock.stamp()
        self._send(self._sync_msg)

    # ------------------------------------------------------------------ the command
    def _command(self, t_wake: float, *, feed: bool) -> None:
        """Advance the executor one period ahead and turn its command into targets.

        ``feed``: the stream's setpoints are taken (not while braking for a fault).
        """
        period = self.config.period
        with self._exec_lock:
            if feed:
                self._feed_stream(t_wake)
            if self.executor.source is not None:
                self.executor.forces = self._latest_forces()
            q, v = self.executor.step(t_wake + period)
            if self.executor.events:
                self._events.extend(self.executor.events)
                self.executor.events.clear()
        cpu = self.scaling.counts_per_unit
        limits = self.limits
        for d in self._drives:
            qi = float(q[d.index])
            target = round(qi * cpu)
            # docs/safety.md §7 at the source: the executor never steps (it advances at most 1.5
            # periods per cycle within v_max); a larger step is a fault, not a command
            step = abs(target - d.target) / cpu
            if d.sample is not None and step > 2.0 * limits.v_max * period + limits.step_margin \
                    and self._commanding:
                self.supervisor.report(
                    FaultKind.STEP_LIMIT, f'commanded step {step * 1e3:.3f} mm (or mrad) in one '
                    f'period exceeds 2 v_max T + margin; command held', drive=d.name,
                    still_present=self._step_condition)
                return
            d.target = target
            d.velocity_offset = round(float(v[d.index]) * cpu)
        self._commanding = True

    def _feed_stream(self, t_wake: float) -> None:
        """Take the newest setpoint of the stream (step-checked), or stop a stale stream."""
        sp = self._setpoint
        limits = self.limits
        if sp is not None and sp.seq != self._last_sp_seq:
            self._accept_setpoint(sp)
        elif self._was_fresh and (sp is None or t_wake - sp.time > limits.command_timeout):
            self._was_fresh = False
            self.stale_setpoint_holds += 1
            self.supervisor.warn('setpoint', 'setpoints stale (none for safety.command_timeout '
                                 f'= {limits.command_timeout * 1e3:.0f} ms): decelerating to rest')
            self.executor.stream_stale()

    def _accept_setpoint(self, sp: _Setpoint) -> None:
        """docs/safety.md §7 on a new setpoint, then hand it to the executor (caller holds _exec_lock)."""
        limits = self.limits
        period = self.config.period
        self._last_sp_seq = sp.seq
        prev_stamp, prev_time = self._last_sp_stamp, self._last_sp_time
        if sp.stamp is not None and prev_stamp is not None and sp.stamp <= prev_stamp:
            self.rejected_setpoints += 1
            if not self._stamp_burst:
                self._stamp_burst = True
                log.warning('setpoint rejected: its stamp %.6f s does not follow the previous '
                            'one %.6f s (stamps must increase); further ones of this burst are '
                            'counted, not logged', sp.stamp, prev_stamp)
            self.supervisor.warn('setpoint_stamps', f'{self.rejected_setpoints} setpoint(s) '
                                 'rejected: stamps not increasing')
            return
        self._stamp_burst = False
        arrival = sp.time - prev_time
        if prev_stamp is not None and sp.stamp is not None:
            dt = min(sp.stamp - prev_stamp, arrival) + period
            basis = 'the smaller of the stamp and arrival intervals, plus one period'
        elif math.isfinite(prev_time):
            dt = min(max(arrival, period), limits.command_timeout) + period
            basis = 'since the last setpoint\'s arrival, plus one period'
        else:
            dt = limits.command_timeout
            basis = 'the first setpoint of the stream, from the command held'
        reference = self._last_sp_position if self._last_sp_position is not None else self.executor.q
        for d in self._drives:
            cause = check_step(d.name, float(reference[d.index]), float(sp.position[d.index]),
                               dt, limits, d.index)
            if cause:
                self.supervisor.report(FaultKind.STEP_LIMIT, f'setpoint rejected: {cause}; time {basis}',
                                       drive=d.name, still_present=self._step_condition)
                return
        if not self._was_fresh:
            self.supervisor.unwarn('setpoint')
            self._was_fresh = True
        self.supervisor.unwarn('setpoint_stamps')
        velocity = sp.velocity
        if velocity is None:
            # (set_targets gives the sender's rate from its own last two setpoints; none for
            # the first of a stream) the rate since the last setpoint taken (stamps, else
            # arrivals)
            velocity = np.zeros(len(self._drives))
            if self._last_sp_position is not None:
                interval = (sp.stamp - prev_stamp if sp.stamp is not None and prev_stamp is not None
                            else arrival)
                velocity = sender_rate(sp.position, self._last_sp_position, interval, period=period,
                                       v_max=limits.v_max)
        self._last_sp_time = sp.time
        self._last_sp_stamp = sp.stamp
        self._last_sp_position = sp.position
        self.accepted_setpoints += 1
        self.executor.set_stream(sp.position, velocity, sp.time)

    # ------------------------------------------------------------------ interaction
    def _latest_forces(self) -> np.ndarray:
        """Each drive's load-cell force (N or N·m) of its latest TPDO1: the answers to the
        last SYNC (NaN for a drive that has not answered: the admittance stops on it)."""
        return np.array([d.sample.force if d.sample is not None else math.nan for d in self._drives])

    def start_interaction(self, source: object, tag: int) -> str | None:
        """Run the admittance ``source`` in the cycle from the command at rest
        (:meth:`~.execution.PathExecutor.begin_interaction`).

        :returns: None when started, else why not (nothing moves).
        """
        now = time.perf_counter()
        with self._exec_lock:
            if not self._tracking or self.state.value != 'enabled':
                return f'the drives are not enabled (master {self.state.value})'
            reason = self.executor.begin_interaction(source, tag, now=now)
            self._events.extend(self.executor.events)
            self.executor.events.clear()
            return reason

    def stop_interaction(self, reason: str) -> None:
        """Brake the interaction to rest along its direction, then hold (event 'stopped')."""
        with self._exec_lock:
            self.executor.stop_interaction(reason, now=time.perf_counter())
            self._events.extend(self.executor.events)
            self.executor.events.clear()

    def set_interaction_goal(self, wrench: object) -> None:
        """The wrench goal of the running interaction (pose axes).

        :raises ValueError: no interaction runs; :raises GoalRejected: the controller's
            checks (held axis, ``max_goal_wrench``, capacity at the current pose).
        """
        with self._exec_lock:
            src = self.executor.source
            if src is None:
                raise ValueError('no interaction is running')
            src.controller.set_goal(wrench)

    # ------------------------------------------------------------------ soft force limit
    def _begin_soft_stop(self, t_wake: float) -> None:
        """docs/safety.md §14: a leg above the soft limit while the motion presses on (or a soft
        limit the node found: :meth:`~.master.BraceMaster.soft_stop`, its reason given):
        brake along the path and hold; reported as the motion's stop, nothing latches."""
        pending, self._soft_stop = self._soft_stop, None
        if isinstance(pending, str):
            key = 'soft_force' if pending.startswith('soft force') else 'soft_wrench'
            reason = pending
        else:
            index, force = pending
            name = self.names[index]
            context = ''
            if self.soft_limit_context is not None:
                try:
                    context = self.soft_limit_context(index, force)
                except Exception as exc:  # noqa: BLE001 - the stop matters, not its description
                    context = f' (capacity unknown: {exc!r})'
            unit = self.limits.force_unit
            key = 'soft_force'
            reason = (f'soft force limit: {name} at {force:.1f} {unit}, above safety.soft_force_limit = '
                      f'{self.limits.soft_force_limit:.3g} {unit}{context}; decelerated along the path, holding')
        log.warning(reason)
        self.supervisor.warn(key, reason)
        with self._exec_lock:
            self.executor.stop(reason, now=t_wake)

    # ------------------------------------------------------------------ relief
    def _feed_relief(self, relief: 'Relief', t_wake: float) -> None:
        """One cycle of a relief (docs/safety.md §15): every actuator moves the way that unloads its
        own leg, at most ``speed`` (one vector, scaled as a whole), until every force is below
        the release force; then the command decelerates and holds."""
        def velocity(forces: np.ndarray) -> np.ndarray:
            # steepest descent of the elastic energy: dE/dq_i = f_i (the legs and the body at
            # equilibrium). The gain keeps the stiffest direction (a leg against its own
            # stiffness k) from stepping past zero in one cycle: k g T = RELIEF_GAIN < 1.
            gain = RELIEF_GAIN / (self.config.stiffness * self.config.period)
            v = -gain * forces
            fastest = float(np.max(np.abs(v)))
            if fastest > relief.speed:
                v = v * (relief.speed / fastest)
            elif self.limits.unit == 'rad' and 0.0 < fastest < RELIEF_MIN_SHARE * relief.speed:
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
        forces = np.array([d.sample.force if d.sample is not None else 0.0 for d in self._drives])
        with self._exec_lock:
            ex = self.executor
            if move.outcome is None:
                move.update(forces, ex.q, t_wake)
            if move.outcome is None:
                v = velocity(forces)
                ex.set_stream(ex.q + v * self.config.period, v, t_wake)
            elif ex.state is not ExecutionState.HOLD and not ex.braking:
                ex.stream_stale()
            elif ex.state is ExecutionState.HOLD:
                move.finished.set()

    # ------------------------------------------------------------------ protective stop
    def _begin_fault_stop(self, t_wake: float) -> None:
        """A fault latched: brake the motion along its path when the drives still follow
        and every latched fault allows it, else hand over to the drives' quick stop."""
        kinds = {f.kind for f in self.supervisor.faults}
        reason = f'protective stop: {self.supervisor.summary()}'
        with self._exec_lock:
            if self.executor.moving and kinds <= BRAKEABLE and self._commanding:
                self.executor.stop(reason, now=t_wake)
                self._fault_brake_until = t_wake + FAULT_BRAKE_LIMIT_S
            else:
                self.executor.release(reason)
                self._events.extend(self.executor.events)
                self.executor.events.clear()
                self._fault_brake_until = 0.0

    def _fault_braking(self, t_wake: float) -> bool:
        """Still braking along the path after a fault (else the drives quick-stop)."""
        if not self._fault_brake_until:
            return False
        kinds = {f.kind for f in self.supervisor.faults}
        if t_wake < self._fault_brake_until and self.executor.moving and kinds <= BRAKEABLE:
            return True
        self._fault_brake_until = 0.0
        with self._exec_lock:
            self.executor.release(f'protective stop: {self.supervisor.summary()}')
            self._events.extend(self.executor.events)
            self.executor.events.clear()
        return False

    def _controlword(self, d: _Drive, state: State402, stopped: bool) -> int:
        if self._closing:
            return int(Controlword.DISABLE_VOLTAGE)
        if self._reset_pulse:
            if state in (State402.FAULT, State402.FAULT_REACTION_ACTIVE):
                d.reset_phase = not d.reset_phase          # 0000h, 0080h, 0000h, ... edges
                return int(Controlword.FAULT_RESET) if d.reset_phase else 0
            return int(Controlword.DISABLE_VOLTAGE)
        if stopped:
            return int(Controlword.QUICK_STOP)
        if self._homing_start and state is State402.OPERATION_ENABLED:
            return int(Controlword.START_HOMING)
        cw = controlword_towards(state, self._desired)
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
