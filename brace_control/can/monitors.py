"""Supervision in the cycle: the per-SYNC monitors and the "cause still present" predicates.

A part of :class:`~.master.BraceMaster` with its own state (the SYNC its load tiers last
judged, the grace after a host stall). :meth:`Monitors.run` runs in the SYNC thread on each
drive's newest TPDO1 and heartbeat (docs/safety.md §2, §4, §8, §9, §11, §14); every fault it
latches carries a predicate that ``recover()`` evaluates (the fault table is in
:mod:`.supervision`). The first reaction to a latched fault is
:meth:`~.lifecycle.Lifecycle.on_fault`: stop tracking commands; when the drives are healthy
and the fault is one the command can be braked from (force, wrench, step, following error,
speed), the cycle first brakes the motion along its path (all axes together), then
quick-stops.
"""
from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable

from ..safety import OK, Action, ForcePrediction, PlatformWrench, Verdict, WrenchTiers
from ..safety.force import pressing_past_soft_limit
from ..safety.liveness import heartbeat, overspeed, stale_feedback
from ..safety.wrench import SOFT_STREAM_S
from .cia402 import (NmtState, OpMode, State402, Statusword, decode_state, describe_statusword,
                     emcy_description)
from .lifecycle import Lifecycle, Motion
from .receive import Receiver
from .state import MasterConfig, MasterState, _Drive, _Module, _Node
from .sync import SyncClock
from .supervision import FaultKind, Sample, check_sample

__all__ = ['Monitors', 'BRAKEABLE', 'RELIEVABLE', 'NO_FEEDFORWARD_LAG_S', 'platform_tiers']

log = logging.getLogger('brace_control.can.master')

_SW_FAULT = 1 << 3
_SW_WARNING = 1 << 7
_SW_REMOTE = int(Statusword.REMOTE)
_CSP = int(OpMode.CYCLIC_SYNC_POSITION)
_SW_LIMIT = 1 << 11

#: s of position-loop lag allowed a drive without velocity feed-forward (60B1h): a loop of
#: gain Kp lags v / Kp (10 1/s and up: 0.1 s); its tracking is judged against the targets
#: of this long ago as well (safety.path_tolerance still applies to the nearest)
NO_FEEDFORWARD_LAG_S = 0.1
#: faults after which the drives still follow commands: the motion is braked along its
#: path before the quick stop (a per-axis quick stop would leave the axes inconsistent)
BRAKEABLE = frozenset({FaultKind.FORCE_LIMIT, FaultKind.WRENCH_LIMIT, FaultKind.STEP_LIMIT,
                       FaultKind.FOLLOWING_ERROR, FaultKind.OVERSPEED,
                       FaultKind.LOAD_CELL_SATURATED, FaultKind.EXTERNAL})


#: latched stops a relief may back off from: the drives are healthy and the cause is load
RELIEVABLE = frozenset({FaultKind.FORCE_LIMIT, FaultKind.WRENCH_LIMIT, FaultKind.LOAD_CELL_SATURATED,
                        FaultKind.FOLLOWING_ERROR, FaultKind.STEP_LIMIT, FaultKind.OVERSPEED,
                        FaultKind.EXTERNAL})


def platform_tiers(config: MasterConfig) -> WrenchTiers | None:
    """The platform wrench's tiers of a device (docs/safety.md §8, §14), ``None`` without a
    mechanism model or a ``safety.max_wrench``. A planar RPR's statics run in plain floats
    (:class:`~brace_control.mechanisms.planar_floats.PlanarRprFloats`, checked against the
    model when built)."""
    mech = config.mechanism
    if mech is None or not config.max_wrench:
        return None
    from ..mechanisms.planar_floats import PlanarRprFloats
    return WrenchTiers(PlatformWrench(mech, legs=PlanarRprFloats.of(mech)), config.max_wrench)


class Monitors:
    """Per-cycle monitors and fault predicates (see the module docstring).

    :param life: the master's shared state (drives, module, tracking, limits, ...).
    :param motion: the commanded motion (is it moving, braking).
    :param receiver: what the drives sent (heartbeat ages, TPDO counts).
    :param distance_to_go: the master's :meth:`~.master.BraceMaster.distance_to_go`.
    :param soft_stop: the master's :meth:`~.master.BraceMaster.soft_stop` (a soft tier brakes).
    """

    def __init__(self, life: Lifecycle, motion: Motion, receiver: Receiver, clock: SyncClock,
                 *, distance_to_go: Callable[[float], float | None],
                 soft_stop: Callable[[str], bool]) -> None:
        config = life.config
        self._life = life
        self._motion = motion
        self._receiver = receiver
        self._clock = clock
        self._supervisor = life.supervisor
        self._scaling = config.scaling
        self._period = config.period
        self._distance_to_go = distance_to_go
        self._soft_stop = soft_stop
        #: docs/safety.md §8, §14: the platform wrench's hard and soft tiers (``None``: no
        #: mechanism model or no ``safety.max_wrench``) and the prediction on each actuator's
        #: load cell (:mod:`brace_control.safety`)
        self.platform_tiers = platform_tiers(config)
        self.force_prediction = ForcePrediction(config.names, config.limits.force_limit,
                                                config.limits.force_unit)
        #: SYNCs of position-loop lag allowed a drive without velocity feed-forward
        self._lag_syncs = math.ceil(NO_FEEDFORWARD_LAG_S / config.period)
        self._loads_stamp: int | None = None     # the SYNC the load tiers last judged
        #: monotonic: silence is not judged by the clock until then (after a host stall)
        self.grace_until = 0.0

    def host_stalled(self, seconds: float) -> None:
        """The SYNC thread woke ``seconds`` later than its period: this process did not run
        (:meth:`.receive.Receiver.host_stalled`; heartbeat ages leave it out)."""
        self._receiver.host_stalled(seconds)

    # ------------------------------------------------------------------ "cause still present" predicates

    def heartbeat_missing(self, d: _Node) -> Callable[[], bool]:
        return lambda: self._receiver.heartbeat_age(d) > self._life.limits.heartbeat_timeout

    def nmt_not_operational(self, d: _Node) -> Callable[[], bool]:
        return lambda: d.nmt != NmtState.OPERATIONAL

    def emcy_present(self, d: _Node) -> Callable[[], bool]:
        return lambda: (d.state in (State402.FAULT, State402.FAULT_REACTION_ACTIVE)
                        or d.emcy_nonzero_time > self._life.recover_time)

    def _drive_faulted(self, d: _Drive) -> Callable[[], bool]:
        return lambda: d.state in (State402.FAULT, State402.FAULT_REACTION_ACTIVE)

    def _stale(self, d: _Drive, *, timed: bool = True) -> bool:
        """No TPDO1 from ``d`` for ``stale_periods`` SYNCs (docs/safety.md §9).

        Judged on what was received, in bus order, so a receive thread (or a simulator)
        that runs late does not make a drive look silent: ``d`` is stale when the other
        drives have sent ``stale_periods`` TPDO1 each since its last one, or when every
        drive has been silent for ``all_silent_periods`` SYNCs (:class:`.receive.Receiver`:
        bus, wiring, or a host too loaded to receive: heartbeat and error-frame supervision
        cover those too).
        """
        s = d.sample
        if s is None:
            return True
        r = self._receiver
        return stale_feedback(behind=r.tpdo_total - d.rx_total, others=len(self._life.drives) - 1,
                              stale_periods=self._life.limits.stale_periods,
                              syncs_silent=self._clock.index - s.sync_index,
                              all_silent_periods=r.all_silent_periods,
                              silent_s=time.perf_counter() - d.rx_time, period=self._period,
                              timed=timed)

    def _sample_condition(self, d: _Drive, kind: FaultKind) -> Callable[[], bool]:
        def present() -> bool:
            s = d.sample
            if s is None or self._stale(d):
                return True
            found = check_sample(None, s, self._life.limits, commanded=self._scaling.to_si(d.target))
            return any(k is kind for k, _ in found)
        return present

    def step_condition(self) -> bool:
        """A step-limit stop's cause is the command, which ``recover`` discards: it is gone
        once every drive holds still."""
        return any(abs(d.velocity) > 0.01 * self._life.limits.v_max for d in self._life.drives)

    def run(self) -> None:
        """Per-cycle monitors on each drive's latest TPDO1 and heartbeat
        (docs/safety.md §2, §4, §8, §9, §11)."""
        life = self._life
        limits = life.limits
        now = time.monotonic()
        tracking = life.tracking and life.state is MasterState.ENABLED
        in_grace = now < self.grace_until
        # a jump is judged at rest too (disabled, halted: an encoder that jumps there made the
        # next enable start from a reading millimetres off the truth), not while homing moves
        # the reference on purpose
        jump = life.state is not MasterState.HOMING and life.mode == _CSP
        if self._life.module is not None:
            self._monitor_module(self._life.module, in_grace)
        for d in self._life.drives:
            name = d.name
            alive = heartbeat(self._receiver.heartbeat_age(d), limits.heartbeat_timeout, d.node_id) \
                if d.heartbeat and not in_grace else OK
            if not alive.ok:
                self._supervisor.report(FaultKind.HEARTBEAT_LOST, alive.reason, drive=name,
                                       still_present=self.heartbeat_missing(d))
            elif d.nmt is not None and d.nmt != NmtState.OPERATIONAL:
                self._supervisor.report(
                    FaultKind.NMT_STATE, f'node {d.node_id} reports NMT state '
                    f'{NmtState(d.nmt).name if d.nmt in NmtState._value2member_map_ else d.nmt}',
                    drive=name, still_present=self.nmt_not_operational(d))
            s = d.sample
            if s is None:
                continue
            if self._stale(d, timed=not in_grace):
                self._supervisor.report(
                    FaultKind.STALE_FEEDBACK,
                    f'no TPDO1 (position, load cell) from node {d.node_id} for '
                    f'{self._clock.index - s.sync_index} SYNC periods (the other drives answered)'
                    if self._receiver.tpdo_total - d.rx_total >= self._life.limits.stale_periods * max(1, len(self._life.drives) - 1)
                    else f'no TPDO1 from any drive for {self._clock.index - s.sync_index} SYNC periods',
                    drive=name,
                    still_present=lambda d=d: self._stale(d))
            if s is d.checked:
                continue
            sw = s.statusword
            if sw & _SW_FAULT:
                code = d.emcy[0] if d.emcy and d.emcy[0] else None
                why = f' (last EMCY {code:04X}h {emcy_description(code)})' if code else ''
                self._supervisor.report(FaultKind.DRIVE_FAULT,
                                       f'statusword {sw:04X}h: {describe_statusword(sw)}{why}',
                                       drive=name, code=code, still_present=self._drive_faulted(d))
            if sw & _SW_REMOTE:
                d.remote_seen = True
            elif d.remote_seen:
                # docs/safety.md §4: taken under local control (its panel, a vendor's setup
                # tool), the drive ignores the controlword from the bus: the master can no
                # longer stop it, so the others stop and it is named (a fault sweep: after a
                # protective stop that drive stayed OPERATION ENABLED, unreported)
                self._supervisor.report(
                    FaultKind.DRIVE_FAULT,
                    f'statusword {sw:04X}h: bit 9 (remote) clear: under local control (its panel, a '
                    'setup tool), the drive ignores the controlword from the bus and the master '
                    'cannot stop it; stop it at the drive, give control back to the bus, recover',
                    drive=name, still_present=lambda d=d: d.sample is not None
                    and not d.sample.statusword & _SW_REMOTE)
            if sw & (_SW_WARNING | _SW_LIMIT) or d.flagged:
                d.flagged = bool(sw & (_SW_WARNING | _SW_LIMIT))
                if sw & _SW_WARNING:
                    self._supervisor.warn(f'{name}.warning', f'{name}: statusword warning bit set ({sw:04X}h)')
                else:
                    self._supervisor.unwarn(f'{name}.warning')
                if sw & _SW_LIMIT:
                    self._supervisor.warn(f'{name}.limit', f'{name}: internal limit active ({sw:04X}h)')
                else:
                    self._supervisor.unwarn(f'{name}.limit')
            commanded = (self._scaling.to_si(self._commanded_for(d, s))
                         if tracking and decode_state(sw) is State402.OPERATION_ENABLED else None)
            for kind, cause in check_sample(d.checked, s, limits, commanded=commanded, jump=jump):
                self._supervisor.report(kind, cause, drive=name,
                                       still_present=(None if kind is FaultKind.POSITION_JUMP
                                                      else self._sample_condition(d, kind)))
                if kind is FaultKind.POSITION_JUMP:
                    life.homed = False         # the encoder reference is suspect
            # docs/safety.md §14: above the soft limit a motion that keeps pressing is braked (the
            # cycle does it); a motion that unloads the leg (the force falling) goes on
            trend = d.force_trend
            # (once: while the motion brakes for it the force may still rise a little)
            if (tracking and life.soft_stop is None and self._motion.executor.moving
                    and not self._motion.executor.braking
                    and pressing_past_soft_limit(s.force, trend, limits.soft_force_limit)):
                life.soft_stop = (d.index, s.force)
            trend.append(abs(s.force))
            if commanded is not None:
                speed = overspeed(d.velocity, limits.v_max, limits.speed_factor, limits.unit)
                if not speed.ok:
                    self._supervisor.report(
                        FaultKind.OVERSPEED, speed.reason, drive=name,
                        still_present=lambda d=d: not overspeed(d.velocity, self._life.limits.v_max,
                                                                self._life.limits.speed_factor).ok)
            d.checked = s
        if life.state is MasterState.ENABLED:
            self.monitor_loads(now, tracking)

    def monitor_loads(self, now: float, tracking: bool) -> None:
        """docs/safety.md §8, §14 on each drive's newest sample, once per new SYNC answered:
        the platform wrench's hard tier latches, its soft tier and the actuator forces'
        prediction brake a motion heading past the limit. Plain floats (22 us median a cycle
        at rest, bench/RESULTS.md "Load tiers in the cycle")."""
        samples = [d.sample for d in self._life.drives]
        if not samples or None in samples:
            return
        stamp = max(s.sync_index for s in samples)
        if stamp == self._loads_stamp:
            return
        self._loads_stamp = stamp
        q = [s.position for s in samples]
        forces = [s.force for s in samples]

        def togo() -> float | None:
            return self._distance_to_go(SOFT_STREAM_S)

        tiers = self.platform_tiers
        verdicts: list[Verdict] = []
        if tiers is not None:
            verdict = tiers.check(now, q, forces, togo)
            if verdict.action is Action.PROTECTIVE_STOP:
                self._supervisor.report(FaultKind.WRENCH_LIMIT, verdict.reason,
                                       still_present=self._wrench_present)
                return
            verdicts.append(verdict)
        if tracking and self._motion.executor.moving:
            verdicts.append(self.force_prediction.check(now, q, forces, togo))
        for verdict in verdicts:
            if verdict.action is Action.SOFT_STOP and self._soft_stop(verdict.reason):
                break

    def _wrench_present(self) -> bool:
        """A wrench stop's cause: the platform wrench of the newest sample above the limit."""
        fb = self._receiver.feedback()
        tiers = self.platform_tiers
        return bool(fb.valid and tiers is not None and tiers.exceeds(fb.position, fb.force))

    def _monitor_module(self, m: '_Module', in_grace: bool) -> None:
        """The load-cell module: its heartbeat, its NMT state, and its TPDO keeping up with the
        drives' (its readings are every actuator's force: a silent module is stale feedback)."""
        limits = self._life.limits
        who = f'{m.name} (node {m.node_id})'
        alive = heartbeat(self._receiver.heartbeat_age(m), limits.heartbeat_timeout, m.node_id) \
            if m.heartbeat and not in_grace else OK
        if not alive.ok:
            self._supervisor.report(FaultKind.HEARTBEAT_LOST, alive.reason, drive=who,
                                   still_present=self.heartbeat_missing(m))
        elif m.nmt is not None and m.nmt != NmtState.OPERATIONAL:
            self._supervisor.report(FaultKind.NMT_STATE, f'node {m.node_id} reports NMT state {m.nmt}',
                                   drive=who, still_present=self.nmt_not_operational(m))
        behind = self._receiver.tpdo_total - m.rx_total
        if behind >= limits.stale_periods * len(self._life.drives) and not in_grace:
            self._supervisor.report(
                FaultKind.STALE_FEEDBACK, f'no TPDO (load cells) from node {m.node_id} while the drives '
                f'sent {behind}', drive=who,
                still_present=lambda: self._receiver.tpdo_total - m.rx_total >= limits.stale_periods * len(self._life.drives))

    def _commanded_for(self, d: _Drive, s: Sample) -> int:
        """The target (counts) a sample is judged against: of the targets sent from two SYNCs
        before the one it answers up to now, the one nearest to its position.

        A drive answers SYNC k with where it was after following the targets up to SYNC
        k - 1; an answer that arrives late (a loaded host, a simulator in the same process)
        must not be judged against targets sent after it was sampled: with a fast actuator
        one SYNC of the target ramp (v_max x period) can exceed the path tolerance.
        Without a record (before the first SYNC of tracking) the current target. A drive
        without the velocity feed-forward (no 60B1h in its RPDOs) lags the plan by its
        position loop's lag: its sample is judged against the targets of the last
        :data:`NO_FEEDFORWARD_LAG_S` as well.
        """
        pos = self._scaling.to_counts(s.position)
        best = None
        window = 2 if d.feedforward else 2 + self._lag_syncs
        # no copy of the record: the SYNC thread appends to it and is the only caller (via
        # Cycle -> run), so it does not change while this loop reads it
        for index, target in reversed(d.sent):
            if index < s.sync_index - window:
                break
            if best is None or abs(target - pos) < abs(best - pos):
                best = target
        return d.target if best is None else best
