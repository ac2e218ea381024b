"""The setpoint stream (teleoperation): setpoints received by the API, taken by the SYNC cycle.

A part of :class:`~.master.BraceMaster` with its own state. :meth:`SetpointStream.receive`
(any thread, :meth:`~.master.BraceMaster.set_targets`) keeps the newest setpoint with the
sender's rate; :meth:`SetpointStream.feed` (the SYNC thread, under the motion's lock) takes it:

* a new setpoint is step-checked (docs/safety.md §7) over the smaller of the time between its
  stamp and the previous one and the time between their arrivals, plus one period (a sender's
  clock cannot license a jump); a violation latches a STEP_LIMIT stop;
* setpoints whose stamps do not increase are rejected as they arrive (a setpoint is compared
  with the newest one kept, whether or not the cycle took that one: a burst that arrived
  within one period is judged in the order it was sent), counted, and reported once per burst
  by the cycle;
* no setpoint for ``safety.command_timeout`` stops the stream (docs/safety.md §1): the
  executor decelerates along the current direction and holds.
"""
from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

import numpy as np

from .state import _Setpoint, sender_rate
from .supervision import FaultKind, check_step

if TYPE_CHECKING:
    from ..control.execution import PathExecutor
    from .lifecycle import Lifecycle

__all__ = ['SetpointStream']

log = logging.getLogger('brace_control.can.master')


class SetpointStream:
    """The newest setpoint received and what the cycle took of the stream (module docstring).

    :param life: the master's shared state (drives, limits, supervisor).
    :param step_condition: a STEP_LIMIT stop's "cause still present" predicate.
    """

    def __init__(self, life: Lifecycle, step_condition: Callable[[], bool]) -> None:
        self._life = life
        self._step_condition = step_condition
        self._period = life.config.period
        self.latest: _Setpoint | None = None       # not yet taken when its seq is new
        #: the last setpoint received (the sender's rate is taken from it), taken or not
        self._received: _Setpoint | None = None
        self.seq = 0                               # setpoints received
        self.taken_seq = 0                         # the newest one the cycle looked at
        self._last_time = -math.inf
        self._last_stamp: float | None = None
        self._last_position: np.ndarray | None = None
        self._was_fresh = False
        self._stamp_burst = False
        #: the newest stamp kept by receive (None: no stamped setpoint since the stream began)
        self._newest_stamp: float | None = None
        #: (stamp, the newest kept) of the first setpoint refused since the cycle last reported
        self._refused: tuple[float, float] | None = None
        self._reported = 0                         # rejections the cycle has reported
        self.stale_holds = 0
        self.accepted = 0
        self.rejected = 0

    # ------------------------------------------------------------------ the API side
    def receive(self, position: np.ndarray, stamp: float | None,
                velocity: np.ndarray | None) -> None:
        """Keep ``position`` (checked by the caller) as the newest setpoint; taken on the next
        SYNC. Without ``velocity`` the sender's rate comes from its own last two setpoints
        (stamps, else arrivals), not from the last one the cycle took: a cycle that takes only
        the newest of a few would see a repeat of the final position as still moving, and a
        stream that stops there would brake past it."""
        limits = self._life.limits
        now = time.perf_counter()
        stamp = None if stamp is None else float(stamp)
        newest = self._newest_stamp
        if stamp is not None and newest is not None and stamp <= newest:
            # not a newer command: refused here, not only if the cycle happens to look at it
            # (run 1002: two setpoints of one stamp within a period; the cycle took the second
            # as a stream's first, and the brace moved 2.75 mm)
            if self._refused is None:
                self._refused = (stamp, newest)
            self.rejected += 1
            return
        if stamp is not None:
            self._newest_stamp = stamp
        prev = self._received
        if velocity is None and prev is not None and now - prev.time <= limits.command_timeout:
            interval = (stamp - prev.stamp if stamp is not None and prev.stamp is not None
                        and stamp > prev.stamp else now - prev.time)
            velocity = sender_rate(position, prev.position, interval, period=self._period,
                                   v_max=limits.v_max)
        self.seq += 1
        self.latest = self._received = _Setpoint(position.copy(), now, self.seq, stamp, velocity)

    def drop(self) -> None:
        """Forget the setpoint not yet taken (a stop, a recover: it is not to run later)."""
        self.latest = self._received = None

    def restart(self) -> None:
        """A new stream from the command in force (the drives enabled): nothing received
        before counts, and the first setpoint is checked from the command."""
        self.drop()
        self._last_stamp = self._newest_stamp = None
        self._last_time = -math.inf
        self._last_position = None
        self._was_fresh = False

    def skip_received(self) -> None:
        """Take nothing received so far (the command was anchored after it)."""
        self.taken_seq = self.seq

    # ------------------------------------------------------------------ the cycle's side
    def feed(self, executor: PathExecutor, t_wake: float) -> None:
        """Take the newest setpoint (step-checked), or stop a stale stream (SYNC thread, under
        the motion's lock)."""
        sp = self.latest
        life = self._life
        limits = life.limits
        if sp is not None and sp.seq != self.taken_seq:
            self._accept(sp, executor)
        elif self._was_fresh and (sp is None or t_wake - sp.time > limits.command_timeout):
            self._was_fresh = False
            # the warning first: whoever reads a count of stale holds also finds its warning
            life.supervisor.warn('setpoint', 'setpoints stale (none for safety.command_timeout '
                                 f'= {limits.command_timeout * 1e3:.0f} ms): decelerating to rest')
            self.stale_holds += 1
            executor.stream_stale()
        if self.rejected != self._reported:      # after the take: refused ones came after it
            self._report_rejected()

    def _report_rejected(self) -> None:
        """The setpoints refused for their stamps since the last report: logged once per burst
        (until a setpoint is accepted), counted in the driver's warnings."""
        self._reported = self.rejected
        refused, self._refused = self._refused, None
        if not self._stamp_burst and refused is not None:
            self._stamp_burst = True
            log.warning('setpoint rejected: its stamp %.6f s does not follow the previous '
                        'one %.6f s (stamps must increase); further ones of this burst are '
                        'counted, not logged', *refused)
        self._life.supervisor.warn('setpoint_stamps', f'{self.rejected} setpoint(s) '
                                   'rejected: stamps not increasing')

    def _accept(self, sp: _Setpoint, executor: PathExecutor) -> None:
        """docs/safety.md §7 on a new setpoint, then hand it to the executor."""
        life = self._life
        limits = life.limits
        supervisor = life.supervisor
        period = self._period
        self.taken_seq = sp.seq
        # (a stamp that does not increase never gets here: receive refused it against the
        # newest one kept, which is at least the last one taken)
        prev_stamp, prev_time = self._last_stamp, self._last_time
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
        reference = self._last_position if self._last_position is not None else executor.q
        for d in life.drives:
            cause = check_step(d.name, float(reference[d.index]), float(sp.position[d.index]),
                               dt, limits, d.index)
            if cause:
                supervisor.report(FaultKind.STEP_LIMIT, f'setpoint rejected: {cause}; time {basis}',
                                  drive=d.name, still_present=self._step_condition)
                return
        if not self._was_fresh:
            supervisor.unwarn('setpoint')
            self._was_fresh = True
        supervisor.unwarn('setpoint_stamps')
        velocity = sp.velocity
        if velocity is None:
            # (receive gives the sender's rate from its own last two setpoints; none for the
            # first of a stream) the rate since the last setpoint taken (stamps, else arrivals)
            velocity = np.zeros(len(life.drives))
            if self._last_position is not None:
                interval = (sp.stamp - prev_stamp if sp.stamp is not None and prev_stamp is not None
                            else arrival)
                velocity = sender_rate(sp.position, self._last_position, interval, period=period,
                                       v_max=limits.v_max)
        self._last_time = sp.time
        self._last_stamp = sp.stamp
        self._last_position = sp.position
        self.accepted += 1
        executor.set_stream(sp.position, velocity, sp.time)


def checked_velocities(velocities: Sequence[float] | None, positions: np.ndarray,
                       names: Sequence[str]) -> np.ndarray | None:
    """``velocities`` as an array of the positions' shape, all finite (else ValueError)."""
    if velocities is None:
        return None
    vel = np.asarray(velocities, dtype=float)
    if vel.shape != positions.shape or not np.all(np.isfinite(vel)):
        raise ValueError(f'expected {positions.size} finite velocities ({", ".join(names)}), '
                         f'got {np.asarray(velocities).tolist()}')
    return vel
