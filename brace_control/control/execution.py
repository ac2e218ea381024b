"""Path-synchronous execution of actuator motion in the SYNC loop: one time base for all axes.

Why (ARCHITECTURE.md, "Data flow"): on a parallel mechanism near a singularity (the lumbar
brace's legs are nearly parallel) any relative error between the actuators becomes internal
force at nearly the full leg stiffness (1 um ~ 1 N at 1e6 N/m). The commanded lengths must
stay on the inverse-kinematics manifold at every SYNC, so nothing here ever limits, brakes
or delays one axis alone:

* a planned motion arrives once, whole (:class:`ActuatorTrajectory`, knots with position,
  velocity and acceleration) and is sampled at every SYNC by quintic Hermite
  interpolation from one path time ``tau`` for all axes;
* slowing down (cancel, halt, a protective stop, a held stream) changes only how fast
  ``tau`` advances: ``tau_dot = s``, ``s`` from 1 to 0 along a quintic smoothstep, so the
  command is ``q(tau)`` (on the path), ``q_dot(tau) s`` and ``q_ddot(tau) s^2 + q_dot(tau)
  s_dot``: every axis decelerates together and the motion can never pass the end of the
  path (a cancel never overshoots the goal it cancels);
* a new trajectory replaces the running one from its start time (ros2_control's
  JointTrajectoryController semantics): the schedule is a queue ordered by start time; a
  new trajectory drops the scheduled ones that would start at or after its own start and
  keeps the earlier ones (it was planned from their path: a trajectory still waiting when
  the next arrives runs until that one's start). If it starts from the commanded state (the
  planner planned it from there) the splice is exact; otherwise the difference in
  position, velocity and acceleration is blended out by a quintic correction over a time
  long enough that the correction stays within a small share of the limits. A
  trajectory whose start is already past starts now when the brace is at rest (it was
  planned from rest there: the executor's clock goes back to its start, behind the
  master's until the brace rests again, so that what was planned on its timeline splices
  where it was planned to), and is sampled on its own clock when moving (the motion it
  replaces went on meanwhile);
* a stream of setpoints (teleoperation) is tracked with one scale for all axes: the
  velocity change of a cycle is one vector, scaled down as a whole to the acceleration
  limit, and the velocity as a whole to the speed limit. When the stream stops, the
  velocity vector shrinks to zero within ``a_max`` along its current direction, from where
  the command is (it does not travel on to the last setpoint);
* interaction (admittance control in the cycle, :mod:`brace_control.interaction.inloop`):
  an *interaction source* takes over from the command at rest and, every ``n`` SYNCs,
  turns the load-cell forces of the latest SYNC into the command ``dt`` ahead (the pose of
  the virtual mass-damper, through the inverse kinematics: on the manifold by
  construction; ``n > 1``: a cubic Hermite segment per period). A trajectory splices onto
  it (a position goal wins; the interaction is reported preempted), so does a setpoint
  stream; :meth:`PathExecutor.stop` brakes the virtual motion along its direction.

Pure numpy: no bus, no ROS. :class:`PathExecutor` is driven by the master's SYNC thread
(one caller thread); its inputs come from API threads through the master.
"""
from __future__ import annotations

import enum
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..trajectory.base import TrajectoryError
from ..trajectory.hermite import KnotTrajectory, segment_coefficients

__all__ = ['ActuatorTrajectory', 'TrajectoryInvalid', 'PathExecutor', 'ExecutionEvent',
           'ExecutionState', 'smoothstep5']

#: a planned actuator motion: knots with position, velocity and acceleration (quintic Hermite)
ActuatorTrajectory = KnotTrajectory
#: what a malformed trajectory raises
TrajectoryInvalid = TrajectoryError

#: share of the speed / acceleration limits a splice correction may use (the plan keeps
#: ``trajectory.limit_margin`` below the limits for it)
BLEND_SHARE = 0.1
#: the shortest splice correction (s)
BLEND_MIN_S = 0.02
#: a splice difference below this (m or rad; per axis) needs no correction
EXACT_SPLICE = 1e-9
#: the words of a splice refusal's reason (a trajectory whose start is too far from the
#: running command: delivered after its takeover time while the brace moved); the
#: trajectory node plans such a goal again (``trajectory_node``, "Late splices")
SPLICE_REFUSED = 'more than the splice tolerance'
#: |v| (unit/s) and |a| at a trajectory's last point that still count as at rest
END_AT_REST_V = 1e-6
END_AT_REST_A = 1e-4


def smoothstep5(u: float) -> tuple[float, float, float]:
    """``S(u) = 10 u^3 - 15 u^4 + 6 u^5`` clamped to [0, 1], with ``S'`` and ``S''``.

    The minimum-jerk blend of Flash and Hogan: zero first and second derivative at both ends.
    """
    if u <= 0.0:
        return 0.0, 0.0, 0.0
    if u >= 1.0:
        return 1.0, 0.0, 0.0
    u2 = u * u
    return (u2 * u * (10.0 - 15.0 * u + 6.0 * u2), 30.0 * u2 * (1.0 - u) ** 2,
            60.0 * u * (1.0 - u) * (1.0 - 2.0 * u))


#: peak of S'(u) (at u = 1/2) and of |S''(u)| (at u = 1/2 -+ sqrt(3)/6)
SMOOTHSTEP_V = 1.875
SMOOTHSTEP_A = 10.0 / math.sqrt(3.0)
#: the stretch of path a brake is sized on, over the one it passes (25 samples of it)
BRAKE_STRETCH_MARGIN = 1.1


class ExecutionState(str, enum.Enum):
    """What the executor is doing."""

    HOLD = 'hold'                  # at rest at the commanded position
    TRAJECTORY = 'trajectory'      # following a trajectory (possibly braking along it)
    STREAM = 'stream'              # tracking the setpoint stream (possibly braking)
    INTERACTION = 'interaction'    # the admittance in the cycle (possibly braking)


@dataclass(frozen=True)
class ExecutionEvent:
    """One report about a trajectory (``tag`` identifies it: its header stamp, ns).

    ``kind``: ``'accepted'`` (scheduled), ``'rejected'``, ``'started'``, ``'finished'``
    (its last point reached), ``'stopped'`` (braked to rest before its end: cancel, halt,
    protective stop, the stream took over; ``reason`` says which), ``'preempted'`` (a newer
    trajectory replaced it). ``motion``: ``'trajectory'``, or ``'interaction'`` for the
    in-cycle admittance (``tag`` its session), whose kinds are ``'started'``,
    ``'stopping'`` (braking: ``reason`` why), ``'stopped'`` (at rest after a requested stop),
    ``'aborted'`` (at rest after a limit, halt or fault), ``'preempted'`` (a trajectory or
    the stream took over, continuously). ``positions``: the command when it happened; ``time``: when, on
    the executor's clock; ``lag``: s that clock was behind the master's then (SYNCs a stalled
    host missed while moving: the motion runs that much later than planned).
    """

    tag: int
    kind: str
    reason: str = ''
    positions: tuple[float, ...] = ()
    time: float = 0.0
    lag: float = 0.0
    motion: str = 'trajectory'


@dataclass
class _Blend:
    """Splice correction ``c(t)``: quintic from ``(dq, dv, da)`` at ``t0`` to zero at ``t0 + T``."""

    t0: float
    duration: float
    coef: np.ndarray        # (6, n)

    def at(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        s = t - self.t0
        if s >= self.duration:
            return None
        s = max(s, 0.0)
        c = self.coef
        p = c[0] + s * (c[1] + s * (c[2] + s * (c[3] + s * (c[4] + s * c[5]))))
        v = c[1] + s * (2.0 * c[2] + s * (3.0 * c[3] + s * (4.0 * c[4] + s * 5.0 * c[5])))
        a = 2.0 * c[2] + s * (6.0 * c[3] + s * (12.0 * c[4] + s * 20.0 * c[5]))
        return p, v, a


@dataclass
class _Brake:
    """Time scaling ``s(t) = s0 (1 - S((t - t0) / T))`` (:func:`smoothstep5`)."""

    t0: float
    duration: float
    s0: float
    reason: str

    def rate(self, t: float) -> tuple[float, float]:
        """``(s, s_dot)`` at ``t``."""
        S, dS, _ = smoothstep5((t - self.t0) / self.duration)
        return self.s0 * (1.0 - S), -self.s0 * dS / self.duration


@dataclass
class _Running:
    traj: ActuatorTrajectory
    t_start: float            # executor time of tau = 0
    tag: int
    tau: float = 0.0
    started: bool = False


class PathExecutor:
    """The commanded actuator state, advanced once per SYNC (see the module docstring).

    :param n: number of actuators.
    :param v_max: speed limit per actuator (scalar or (n,)), unit/s.
    :param a_max: acceleration limit per actuator, unit/s^2.
    :param period: the SYNC period (s): what one :meth:`step` advances a motion by (after a
        host stall the motion is delayed, never stepped).
    :param splice_tolerance: largest position difference (per axis) a splice may blend out;
        a trajectory further from the command than this is rejected.
    :param stream_gain: 1/s, the proportional correction of the stream's position error.
    """

    def __init__(self, n: int, *, v_max: float | Sequence[float], a_max: float | Sequence[float],
                 period: float, splice_tolerance: float = 0.005, stream_gain: float = 25.0) -> None:
        self.n = int(n)
        self.v_max = np.broadcast_to(np.asarray(v_max, dtype=float), (self.n,)).copy()
        self.a_max = np.broadcast_to(np.asarray(a_max, dtype=float), (self.n,)).copy()
        self.period = float(period)
        self.splice_tolerance = float(splice_tolerance)
        self.stream_gain = float(stream_gain)
        self.q = np.zeros(self.n)
        self.v = np.zeros(self.n)
        self.a = np.zeros(self.n)
        self.t: float | None = None
        self.state = ExecutionState.HOLD
        self.anchored = False
        self._running: _Running | None = None
        self._pending: list[_Running] = []     # scheduled, by start time
        #: s the executor's clock is behind the master's (SYNCs a stalled host missed while
        #: moving delay the motion; 0 at rest): reported with each event
        self.lag = 0.0
        self._blend: _Blend | None = None
        self._brake: _Brake | None = None
        self._s = 1.0
        self._stream: tuple[np.ndarray, np.ndarray, float] | None = None   # (q, v, time received)
        self._stream_stopping = False
        self.events: list[ExecutionEvent] = []
        #: the interaction source while interacting (:mod:`brace_control.interaction.inloop`)
        self.source = None
        self._source_tag = 0
        self._source_end = 'stopped'
        self._source_k = 0
        self._segment: tuple[np.ndarray, ...] | None = None   # (q0, v0, q1, v1) over n SYNCs
        #: the load-cell forces of the latest SYNC (the cycle sets them before :meth:`step`)
        self.forces: np.ndarray | None = None

    # ------------------------------------------------------------------ inputs
    @property
    def moving(self) -> bool:
        """Anything but holding at rest (a pending trajectory counts as motion to come)."""
        return self.state is not ExecutionState.HOLD or bool(self._pending)

    @property
    def braking(self) -> bool:
        return self._brake is not None or self._stream_stopping

    def distance_to_go(self, stream_horizon: float) -> float | None:
        """How far (actuator-space norm) the command goes on: to the running trajectory's
        end, or for a setpoint stream (its end unknown) its speed times ``stream_horizon``;
        ``None`` at rest, braking, or in interaction (the motions a soft limit may stop,
        docs/safety.md §14)."""
        if self.braking:
            return None
        if self.state is ExecutionState.STREAM:
            return float(np.linalg.norm(self.v)) * float(stream_horizon)
        run = self._running
        if self.state is not ExecutionState.TRAJECTORY or run is None:
            return None
        return float(np.linalg.norm(run.traj.positions[-1] - self.q))

    @property
    def running_tag(self) -> int | None:
        return None if self._running is None else self._running.tag

    def anchor(self, q: Sequence[float], t: float | None = None, *, reason: str = '') -> None:
        """Hold at ``q`` from now on (the drives' measured position on enable, after a stop):
        whatever was running or pending is dropped and reported stopped with ``reason``."""
        self._drop(reason or 're-anchored at the drives\' position')
        self.q = np.asarray(q, dtype=float).copy()
        self.v = np.zeros(self.n)
        self.a = np.zeros(self.n)
        if t is not None:
            self.t = float(t)
        self.state = ExecutionState.HOLD
        self.anchored = True

    def release(self, reason: str) -> None:
        """The drives no longer follow the command (disabled, halted, faulted): drop the
        motion (reported stopped with ``reason``) and reject trajectories until
        :meth:`anchor`."""
        self._drop(reason)
        self.v = np.zeros(self.n)
        self.a = np.zeros(self.n)
        self.state = ExecutionState.HOLD
        self.anchored = False

    def load(self, traj: ActuatorTrajectory, t_start: float, tag: int, *, now: float,
             lo: np.ndarray | None = None, hi: np.ndarray | None = None) -> str | None:
        """Schedule ``traj`` to replace the current motion at ``t_start`` (executor clock).

        Checked whole first: joints, stroke ``[lo, hi]``, speed and acceleration limits of the
        interpolated motion, at rest at its end. Returns ``None`` when accepted (events
        'accepted', later 'started'), else the reason (event 'rejected'); a rejected
        trajectory changes nothing. Scheduled trajectories that would start at or after
        ``t_start`` are dropped (event 'preempted'); earlier ones stay scheduled and run until
        ``t_start``.
        """
        reason = self._check(traj, lo, hi)
        if reason is None and not self.anchored:
            reason = 'the drives are not following commands (not enabled)'
        if reason is not None:
            self.events.append(self._event(tag, 'rejected', reason, now))
            return reason
        t_start = float(t_start)
        keep = [p for p in self._pending if p.t_start < t_start]
        for p in self._pending[len(keep):]:
            self.events.append(self._event(p.tag, 'preempted',
                                           f'replaced by trajectory {tag} before it started', now))
        self._pending = keep + [_Running(traj, t_start, int(tag))]
        self.events.append(self._event(tag, 'accepted', '', now))
        return None

    def stop(self, reason: str, *, now: float, tag: int | None = None,
             a_share: float = 1.0) -> None:
        """Decelerate to rest along the current path within ``a_share * a_max``, then hold.

        ``tag``: stop only if that trajectory is the running one (a cancel that names what it
        cancels); a pending trajectory is dropped either way.
        """
        if tag is not None and self.running_tag not in (None, tag) and \
                all(p.tag != tag for p in self._pending):
            return
        self._drop_pending(reason, now)
        if self.state is ExecutionState.TRAJECTORY and self._brake is None:
            # ``now`` is the master's clock; the motion runs on the executor's, ``lag``
            # behind it: the brake begins at the next step, not ``lag`` later
            self._start_brake(now - self.lag, reason, a_share)
        elif self.state is ExecutionState.STREAM:
            self._stream = None
            self._stream_stopping = True
        elif self.state is ExecutionState.INTERACTION:
            self.stop_interaction(reason, now=now, end='aborted')

    # ------------------------------------------------------------------ interaction
    def begin_interaction(self, source: object, tag: int, *, now: float) -> str | None:
        """The interaction ``source`` takes over from the command (at rest, nothing pending).

        :returns: None when started (event 'started'), else the reason (nothing changes).
        """
        if not self.anchored:
            return 'the drives are not following commands (not enabled)'
        if self.state is not ExecutionState.HOLD or self._pending:
            return f'the brace is moving ({self.state.value}); interaction starts from rest'
        try:
            source.begin(self.q, self.v)
        except ValueError as exc:
            return f'the commanded pose cannot start interaction: {exc}'
        self.source, self._source_tag, self._source_end = source, int(tag), 'stopped'
        self._source_k = 0
        self._segment = None
        self.state = ExecutionState.INTERACTION
        self.events.append(self._event(tag, 'started', '', now, motion='interaction'))
        return None

    def stop_interaction(self, reason: str, *, now: float, end: str = 'stopped') -> None:
        """Brake the interaction's virtual motion to rest (direction kept), then hold;
        ``end``: the final event's kind ('stopped' requested, 'aborted' a limit or halt)."""
        src = self.source
        if src is None or self.state is not ExecutionState.INTERACTION:
            return
        if src.controller.mode.value == 'active':
            src.controller.stop(reason)
            self._source_end = end
            self.events.append(self._event(self._source_tag, 'stopping', reason, now, motion='interaction'))

    def _end_interaction(self, kind: str, reason: str, t: float) -> None:
        if self.source is not None:
            self.events.append(self._event(self._source_tag, kind, reason, t, motion='interaction'))
        self.source = None
        self._segment = None

    def _track_interaction(self, t: float, dt: float) -> None:
        """One SYNC of the interaction: every ``n`` SYNCs the source's update from the latest
        forces (the command one admittance period ahead), in between the Hermite segment."""
        if dt <= 0.0:
            return
        src = self.source
        n = src.n_syncs
        if self._source_k % n == 0:
            forces = self.forces if self.forces is not None else np.full(self.n, math.nan)
            q1, v1, reason = src.update(forces)
            if reason:
                self._source_end = 'aborted'
                self.events.append(self._event(self._source_tag, 'stopping', reason, t, motion='interaction'))
            self._segment = (self.q.copy(), self.v.copy(), np.asarray(q1, float), np.asarray(v1, float))
        self._source_k += 1
        q0, v0, q1, v1 = self._segment
        j = (self._source_k - 1) % n + 1
        if j == n:
            q, v = q1, v1
        else:
            # cubic Hermite from (q0, v0) to (q1, v1) over h = n periods, at s = j / n
            h = n * dt
            s = j / n
            h00, h10, h01, h11 = (2 * s ** 3 - 3 * s ** 2 + 1, s ** 3 - 2 * s ** 2 + s,
                                  -2 * s ** 3 + 3 * s ** 2, s ** 3 - s ** 2)
            d00, d10, d01, d11 = (6 * s ** 2 - 6 * s, 3 * s ** 2 - 4 * s + 1, -6 * s ** 2 + 6 * s,
                                  3 * s ** 2 - 2 * s)
            q = h00 * q0 + h10 * h * v0 + h01 * q1 + h11 * h * v1
            v = (d00 * q0 + d10 * h * v0 + d01 * q1 + d11 * h * v1) / h
        self.a = (v - self.v) / dt
        self.q, self.v = q, v
        if j == n and src.controller.mode.value == 'idle':
            reason = src.controller.stop_reason
            self._end_interaction(self._source_end, reason, t)
            self.v = np.zeros(self.n)
            self.a = np.zeros(self.n)
            self.state = ExecutionState.HOLD

    def set_stream(self, q: Sequence[float], v: Sequence[float] | None, received: float) -> None:
        """The latest setpoint of the stream (already step-checked); it takes over from a
        running trajectory (reported stopped) at the next :meth:`step`."""
        qs = np.asarray(q, dtype=float)
        vs = np.zeros(self.n) if v is None else np.asarray(v, dtype=float)
        self._stream = (qs, vs, float(received))
        self._stream_stopping = False

    def stream_stale(self) -> None:
        """No setpoint within the command timeout: decelerate along the current direction."""
        if self.state is ExecutionState.STREAM:
            self._stream = None
            self._stream_stopping = True

    # ------------------------------------------------------------------ the cycle
    def step(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Advance the command one SYNC, to the instant ``t`` (the master's clock: when the
        drives should be there); returns ``(q, q_dot)`` (copies).

        While anything moves, the command advances exactly one period per step, whatever
        the wall clock says: a CSP drive interpolates each target over one interpolation
        period, so a late SYNC must delay the motion, never stretch or squeeze one step of
        it. Holding at rest, the executor's clock re-joins ``t`` (a trajectory then starts
        on the wall clock's time).
        """
        if self.t is None or (self.state is ExecutionState.HOLD and self._blend is None):
            dt = 0.0 if self.t is None else self.period
            t_exec = t
        else:
            dt = self.period
            t_exec = self.t + dt
        self.lag = max(0.0, t - t_exec)
        if self._stream is not None and self.state is not ExecutionState.STREAM:
            # the stream takes over from the command as it is (continuous p, v, a)
            self._drop_pending('the setpoint stream took over', t_exec)
            if self.state is ExecutionState.INTERACTION:
                self._end_interaction('preempted', 'the setpoint stream took over', t_exec)
            if self._running is not None:
                self._finish('stopped', 'the setpoint stream took over', t_exec, rest=False)
            self.state = ExecutionState.STREAM
            self._blend = None
        if self._pending and t_exec >= self._pending[0].t_start:
            # every scheduled trajectory due by now, in start order (two due in one step:
            # the first starts and is replaced at once, the second splices onto its command)
            advanced = False
            while self._pending and t_exec >= self._pending[0].t_start:
                t_exec = self._splice(t_exec, dt, advance=not advanced)
                advanced = True
        elif self.state is ExecutionState.TRAJECTORY:
            self._advance(t_exec, dt)
        elif self.state is ExecutionState.STREAM:
            self._track_stream(dt)
        elif self.state is ExecutionState.INTERACTION:
            self._track_interaction(t_exec, dt)
        self.t = t_exec
        return self.q.copy(), self.v.copy()

    def _event(self, tag: int, kind: str, reason: str, t: float,
               positions: np.ndarray | None = None, *, motion: str = 'trajectory') -> ExecutionEvent:
        q = self.q if positions is None else positions
        return ExecutionEvent(tag, kind, reason, tuple(q), t, self.lag, motion)

    # ------------------------------------------------------------------ trajectory
    def _check(self, traj: ActuatorTrajectory, lo: np.ndarray | None,
               hi: np.ndarray | None) -> str | None:
        if traj.n != self.n:
            return f'{traj.n} joints, expected {self.n}'
        _, q, v, a = traj.dense()
        if lo is not None and hi is not None:
            below = q < lo - 1e-12
            above = q > hi + 1e-12
            if np.any(below | above):
                k, i = np.argwhere(below | above)[0]
                return (f'joint {i + 1} would reach {q[k, i]:.5f}, outside its range '
                        f'{lo[i]:.4f}..{hi[i]:.4f}')
        vr = np.max(np.abs(v) / self.v_max, axis=0)
        if np.any(vr > 1.0 + 1e-6):
            i = int(np.argmax(vr))
            return f'joint {i + 1} would move at {vr[i]:.2f} x its speed limit {self.v_max[i]:.4g}/s'
        ar = np.max(np.abs(a) / self.a_max, axis=0)
        if np.any(ar > 1.0 + 1e-6):
            i = int(np.argmax(ar))
            return (f'joint {i + 1} would accelerate at {ar[i]:.2f} x its limit '
                    f'{self.a_max[i]:.4g}/s^2')
        if np.any(np.abs(traj.velocities[-1]) > END_AT_REST_V) or \
                np.any(np.abs(traj.accelerations[-1]) > END_AT_REST_A):
            return 'its last point is not at rest (velocity and acceleration must be zero)'
        return None

    def _splice(self, t: float, dt: float, *, advance: bool = True) -> float:
        """The first scheduled trajectory takes over at ``t``; ``advance``: the running one
        has not been advanced to ``t`` yet in this step. Returns the executor's time of the
        takeover (``t``, or earlier for a late start from rest)."""
        new = self._pending.pop(0)
        at_rest = self.state is ExecutionState.HOLD
        # the old motion's command at t (a stream keeps its last command), then the new one's
        if self.state is ExecutionState.TRAJECTORY and advance:
            self._advance(t, dt)
            at_rest = self.state is ExecutionState.HOLD
        old_q, old_v, old_a = self.q.copy(), self.v.copy(), self.a.copy()
        traj = new.traj
        if traj.start_time > 0.0:
            traj = new.traj = traj.with_start(old_q, old_v, old_a)
        # from rest, a late start means now: the executor's clock goes back to the motion's
        # start and runs behind the master's by the delay (reported as lag) until the brace
        # is at rest again. What is planned on the motion's timeline (scheduled after it, or
        # arriving later, planned from it while the planner believed it on time: a plan
        # delivered late on a busy host) then splices where it was planned to
        t_take = new.t_start if at_rest and new.t_start < t else t
        new.tau = min(t_take - new.t_start, traj.duration)
        q, v, a = traj.sample(new.tau)
        dq, dv, da = old_q - q, old_v - v, old_a - a
        if np.max(np.abs(dq)) > self.splice_tolerance:
            i = int(np.argmax(np.abs(dq)))
            self.events.append(self._event(
                new.tag, 'rejected', f'its start is {abs(dq[i]) * 1e3:.3f} mm (or mrad) from the '
                f'command on joint {i + 1}, {SPLICE_REFUSED} '
                f'{self.splice_tolerance * 1e3:.3f}; the running motion continues', t, old_q))
            return t
        if t_take < t:
            self.lag += t - t_take
            t = t_take
        if self._running is not None:
            self._finish('preempted', f'replaced by trajectory {new.tag}', t, rest=False)
        if self.state is ExecutionState.INTERACTION:
            self._end_interaction('preempted', f'replaced by trajectory {new.tag}', t)
        self._blend = None
        if np.max(np.abs(dq)) > EXACT_SPLICE or np.max(np.abs(dv)) > 1e-9 or np.max(np.abs(da)) > 1e-7:
            self._blend = self._make_blend(t, dq, dv, da)
        self._running = new
        self._brake = None
        self._s = 1.0
        self.state = ExecutionState.TRAJECTORY
        self._stream = None
        self._stream_stopping = False
        new.started = True
        self.events.append(self._event(new.tag, 'started', '', t, old_q))
        self._command(t, q, v, a)
        return t

    def _make_blend(self, t: float, dq: np.ndarray, dv: np.ndarray, da: np.ndarray) -> _Blend:
        """A correction from ``(dq, dv, da)`` to zero that uses about BLEND_SHARE of the limits.

        For the quintic from ``(dq, dv, da)`` to rest over ``T``: peak speed ~ 1.875 |dq| / T
        + |dv|, peak acceleration ~ 5.77 |dq| / T^2 + 4 |dv| / T + |da|.
        """
        vs, as_ = BLEND_SHARE * self.v_max, BLEND_SHARE * self.a_max
        T = max(BLEND_MIN_S,
                float(np.max(SMOOTHSTEP_V * np.abs(dq) / vs)),
                float(np.max(np.sqrt(SMOOTHSTEP_A * np.abs(dq) / as_))),
                float(np.max(4.0 * np.abs(dv) / as_)))
        h = np.array([[T]])
        z = np.zeros((1, self.n))
        coef = segment_coefficients(h, dq[None], dv[None], da[None], z, z, z)[:, 0]
        return _Blend(t, T, coef)

    def _start_brake(self, t: float, reason: str, a_share: float) -> None:
        """Brake along the path: ``s`` from its value to 0 on the smoothstep over ``T``.

        The command's acceleration is ``q''(tau) s^2 + q'(tau) s_dot``; ``T`` keeps it within
        ``a_share x a_max`` with the path's peak speed and acceleration over the stretch of
        path the brake passes. That stretch is ``s T / 2`` of path time (the smoothstep's mean
        is one half), so ``T`` is found from the next second of path first and then from the
        stretch the previous ``T`` passes (three rounds, each one's stretch covering the
        next's, so every round's ``T`` is safe). Sized on the next whole second, a brake early
        in a minimum-jerk motion took the motion's peak speed ahead and ran far while the
        path sped up under it: 146 mrad (now 51) 50 ms into a 0.9 rad, 0.88 s move of a
        15 rad/s^2 joint, 211 (now 155) at 100 ms; from mid-motion on both are the same.
        """
        run = self._running
        assert run is not None
        horizon = 1.0
        for _ in range(3):
            taus = np.linspace(run.tau, min(run.tau + horizon, run.traj.duration), 25)
            _, v, a = run.traj.sample_many(taus)
            vpeak = np.max(np.abs(v), axis=0) * self._s
            apeak = np.max(np.abs(a), axis=0) * self._s ** 2
            budget = np.maximum(a_share * self.a_max - apeak, 0.25 * a_share * self.a_max)
            T = max(2.0 * self.period, float(np.max(SMOOTHSTEP_V * vpeak / budget)))
            horizon = min(horizon, BRAKE_STRETCH_MARGIN * 0.5 * self._s * T)
        if self._blend is not None:
            T = max(T, self._blend.duration - (t - self._blend.t0))
        self._brake = _Brake(t, T, self._s, reason)

    def _advance(self, t: float, dt: float) -> None:
        run = self._running
        assert run is not None
        s_prev = self._s
        s_dot = 0.0
        if self._brake is not None:
            self._s, s_dot = self._brake.rate(t)
        run.tau = min(run.tau + 0.5 * (s_prev + self._s) * dt, run.traj.duration)
        q, v, a = run.traj.sample(run.tau)
        s = self._s
        self._command(t, q, v * s, a * s * s + v * s_dot)
        ended = run.tau >= run.traj.duration and self._blend is None
        stopped = self._brake is not None and t >= self._brake.t0 + self._brake.duration \
            and self._blend is None
        if ended:
            self._finish('finished', '', t)
        elif stopped:
            self._finish('stopped', self._brake.reason, t)

    def _command(self, t: float, q: np.ndarray, v: np.ndarray, a: np.ndarray) -> None:
        if self._blend is not None:
            c = self._blend.at(t)
            if c is None:
                self._blend = None
            else:
                q, v, a = q + c[0], v + c[1], a + c[2]
        self.q, self.v, self.a = q, v, a

    def _finish(self, kind: str, reason: str, t: float, *, rest: bool = True) -> None:
        """End the running trajectory with event ``kind``; ``rest``: it ended at rest and the
        executor holds (exact zeros), else another motion takes over from the command."""
        run = self._running
        self._running = None
        self._brake = None
        self._s = 1.0
        if run is not None:
            self.events.append(self._event(run.tag, kind, reason, t))
        if rest:
            self._blend = None
            self.v = np.zeros(self.n)
            self.a = np.zeros(self.n)
            self.state = ExecutionState.HOLD

    def _drop_pending(self, reason: str, t: float | None) -> None:
        for p in self._pending:
            self.events.append(self._event(p.tag, 'stopped', reason, t or 0.0))
        self._pending = []

    def _drop(self, reason: str) -> None:
        t = self.t or 0.0
        self._drop_pending(reason, t)
        if self._running is not None:
            run, self._running = self._running, None
            self.events.append(self._event(run.tag, 'stopped', reason, t))
        self._brake = None
        self._blend = None
        self._s = 1.0
        self._stream = None
        self._stream_stopping = False
        if self.source is not None:
            self._end_interaction('aborted', reason, t)

    # ------------------------------------------------------------------ stream
    def _track_stream(self, dt: float) -> None:
        """One cycle of the stream ramp (path-synchronous: vectors scaled as a whole)."""
        if dt <= 0.0:
            return
        v_c = self.v
        if self._stream is None:
            # stopping: shrink the velocity vector within a_max on every axis
            speed = np.abs(v_c)
            with np.errstate(divide='ignore'):
                room = np.where(speed > 0.0, self.a_max * dt / np.maximum(speed, 1e-300), np.inf)
            factor = max(0.0, 1.0 - float(np.min(room)))
            v_new = v_c * factor
            if factor == 0.0:
                self._stream_stopping = False
                self.state = ExecutionState.HOLD
        else:
            q_sp, v_sp, _ = self._stream
            v_des = v_sp + self.stream_gain * (q_sp - self.q)
            dv = v_des - v_c
            ratio = float(np.max(np.abs(dv) / (self.a_max * dt)))
            if ratio > 1.0:
                dv = dv / ratio
            v_new = v_c + dv
            over = float(np.max(np.abs(v_new) / self.v_max))
            if over > 1.0:
                v_new = v_new / over
        self.q = self.q + 0.5 * (v_c + v_new) * dt
        self.a = (v_new - v_c) / dt
        self.v = v_new
        if self.state is ExecutionState.HOLD:
            self.v = np.zeros(self.n)
            self.a = np.zeros(self.n)
