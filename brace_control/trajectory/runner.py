"""Goals in, setpoints out: the trajectory node's logic, without ROS.

:class:`TrajectoryRunner` keeps the motion being executed, starts each new goal from
where the brace is (continuing the running motion's position, velocity and
acceleration, so a preemption is smooth), brakes to rest on cancel or abort, and
reports each goal's end exactly once (:class:`GoalState`). Time is whatever monotonic
clock the caller passes (s).

Planning takes time, so a new motion is planned from the state the running motion will
have ``lookahead`` seconds from now and takes over exactly then: the switch is continuous
in position, velocity and acceleration as long as planning finishes within
``lookahead`` (a late plan still switches, at the state it was planned from, and says so).

Not thread-safe: the node serialises calls (its lock); :meth:`plan` needs no lock.
"""
from __future__ import annotations

import enum
from collections import deque
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from .base import MotionState, Trajectory
from .limits import Limits, check_path
from .minimum_jerk import FittsLaw, brake
from .planner import Plan, PlanRejected, Profile, plan_motion

if TYPE_CHECKING:  # pragma: no cover
    from ..mechanisms.base import Mechanism

__all__ = ['GoalState', 'GoalRequest', 'GoalEvent', 'StartState', 'TrajectoryRunner', 'LatePlan']


class LatePlan(RuntimeError):
    """A plan for a moving brace finished after its takeover time: plan again."""


class GoalState(str, enum.Enum):
    """A goal's reported state. ``ACCEPTED`` is reported first for goals that move; every
    goal then ends in exactly one terminal state."""

    ACCEPTED = 'accepted'
    SUCCEEDED = 'succeeded'
    REJECTED = 'rejected'
    ABORTED = 'aborted'
    CANCELLED = 'cancelled'

    @property
    def terminal(self) -> bool:
        return self is not GoalState.ACCEPTED


@dataclass(frozen=True)
class GoalRequest:
    """A pose goal (``via`` empty) or a path (``via`` the intermediate poses).

    ``duration`` and ``t_via`` (s from the motion's start) are ``None`` when the goal carries
    no timing: Fitts' law / the optimal via times / time-optimal S-curve apply.
    """

    goal_id: str
    target: np.ndarray
    via: np.ndarray | None = None
    t_via: np.ndarray | None = None
    duration: float | None = None


@dataclass(frozen=True)
class GoalEvent:
    """One status report: ``reason`` is empty for plain successes."""

    goal_id: str
    state: GoalState
    reason: str = ''
    target: np.ndarray | None = None
    duration: float | None = None
    profile: str = ''


@dataclass(frozen=True)
class StartState:
    """Where a new motion starts: at time ``t0`` (the runner's clock), in ``state``."""

    t0: float
    state: MotionState
    source: str                      # 'motion', 'measured', 'setpoint' or 'home'


@dataclass
class _Motion:
    t0: float
    trajectory: Trajectory
    goal_id: str | None             # None: a brake (cancel/abort) that belongs to no goal
    target: np.ndarray | None = None
    notes: list[str] = field(default_factory=list)


class TrajectoryRunner:
    """Executes one goal at a time on ``mech`` within ``limits``.

    :param mech: the mechanism model (IK, Jacobian, workspace).
    :param limits: the limits every motion is checked against.
    :param profile: the motion profile for goals.
    :param fitts: Fitts' law for goals without a duration.
    :param fitts_axes: coordinates whose distance is Fitts' amplitude (default all).
    :param lookahead: s between planning a goal and its motion taking over.
    :param path_tolerance: tracking error that aborts the goal, or ``None``: in actuator
        coordinates (m or rad, like the drives' following error), since a measured pose of
        an ill-conditioned mechanism amplifies encoder resolution (the lumbar brace near
        theta = 0: 10 um on a2 is mm of x).
    :param tracking_latency: s; a measurement is compared with the setpoints of the last
        ``tracking_latency`` before its time (the setpoint -> IK -> CAN -> drive -> encoder
        -> forward-kinematics pipeline delay); the smallest error counts.
    """

    def __init__(self, mech: 'Mechanism', limits: Limits, *, profile: Profile | str,
                 fitts: FittsLaw, fitts_axes: tuple[int, ...] | None = None,
                 lookahead: float = 0.0, path_tolerance: float | None = None,
                 tracking_latency: float = 0.25) -> None:
        self.mech = mech
        self.limits = limits
        self.profile = Profile(profile)
        self.fitts = fitts
        self.fitts_axes = fitts_axes
        self.lookahead = float(lookahead)
        self.path_tolerance = path_tolerance
        self.tracking_latency = float(tracking_latency)
        # (time, actuator coordinates) of recent setpoints, for the tracking check
        self._recent: deque[tuple[float, np.ndarray]] = deque(maxlen=4096)
        self._motion: _Motion | None = None
        self._pending: _Motion | None = None
        self._active_goal: str | None = None
        self._last_setpoint: np.ndarray | None = None
        self._last_t = -np.inf

    # -- state -----------------------------------------------------------------------
    @property
    def active_goal(self) -> str | None:
        """The goal being executed (``None`` when idle or braking)."""
        return self._active_goal

    @property
    def has_setpoint(self) -> bool:
        """``False`` until the first motion: the runner then has nothing to hold."""
        return self._motion is not None or self._pending is not None

    @property
    def moving(self) -> bool:
        """A motion is pending or not yet at its end (as of the last :meth:`step`)."""
        if self._pending is not None:
            return True
        m = self._motion
        return m is not None and self._last_t < m.t0 + m.trajectory.duration

    def _motion_at(self, t: float) -> _Motion | None:
        if self._pending is not None and t >= self._pending.t0:
            return self._pending
        return self._motion

    def start_state(self, now: float, *, measured: np.ndarray | None = None) -> StartState:
        """Where a goal received at ``now`` starts (``now + lookahead``).

        The commanded motion (running, or holding its end) once there is one, so commands
        stay continuous; before the first motion the ``measured`` pose if given (the caller
        passes it only when fresh), else the last setpoint, else home.
        """
        t0 = now + self.lookahead
        m = self._motion_at(t0)
        if m is not None:
            p, v, a = m.trajectory.sample(t0 - m.t0)
            return StartState(t0, MotionState(p, v, a), 'motion')
        zero = np.zeros(self.mech.dof)
        if measured is not None:
            return StartState(t0, MotionState(np.asarray(measured, float), zero, zero), 'measured')
        if self._last_setpoint is not None:
            return StartState(t0, MotionState(self._last_setpoint.copy(), zero, zero), 'setpoint')
        return StartState(t0, MotionState(np.asarray(self.mech.home_pose, float), zero, zero), 'home')

    # -- goals -------------------------------------------------------------------------
    def plan(self, request: GoalRequest, start: StartState) -> Plan:
        """Plan ``request`` from ``start`` (pure: may run without the node's lock).

        :raises PlanRejected: with the reason for the status.
        """
        return plan_motion(self.mech, start.state.p, request.target, self.profile, self.limits,
                           via=request.via, t_via=request.t_via, duration=request.duration,
                           v0=start.state.v, a0=start.state.a, fitts=self.fitts,
                           fitts_axes=self.fitts_axes)

    def commit(self, request: GoalRequest, plan: Plan, start: StartState, *,
               now: float, force: bool = True) -> list[GoalEvent]:
        """Make ``plan`` the motion from ``start.t0``; the goal it replaces is reported cancelled.

        A plan that comes after ``start.t0`` (planning took longer than the lookahead):
        from rest it simply starts now (exact); while moving, the running motion has gone
        on since ``start.t0``, so with ``force=False`` :class:`LatePlan` is raised (plan
        again from :meth:`start_state`), with ``force=True`` the new motion takes over
        on its own clock from ``start.t0``: position, velocity and acceleration differ
        from the old motion's only by the difference in jerk times the lateness (and its
        square and cube), and the event says how late it was.
        """
        events: list[GoalEvent] = []
        notes = list(plan.notes)
        t0 = start.t0
        if now > t0:
            m = self._motion_at(now)
            at_rest = not (np.any(start.state.v) or np.any(start.state.a))
            held = m is None or np.array_equal(m.trajectory.sample(now - m.t0)[0], start.state.p)
            if at_rest and held:
                t0 = now
            elif not force:
                raise LatePlan(f'plan finished {now - t0:.3f} s after its takeover time')
            else:
                notes.append(f'planning took longer than the lookahead {self.lookahead:.3f} s: '
                             f'takeover {now - t0:.3f} s late')
        if self._active_goal is not None:
            events.append(GoalEvent(self._active_goal, GoalState.CANCELLED,
                                    f'preempted by goal {request.goal_id}'))
        motion = _Motion(t0, plan.trajectory, request.goal_id,
                         np.asarray(request.target, float), notes)
        self._install(motion, now)
        self._active_goal = request.goal_id
        events.append(GoalEvent(request.goal_id, GoalState.ACCEPTED, '; '.join(notes),
                                motion.target, plan.duration, plan.profile.value))
        return events

    def submit(self, request: GoalRequest, *, now: float,
               measured: np.ndarray | None = None) -> list[GoalEvent]:
        """:meth:`start_state`, :meth:`plan` and :meth:`commit` in one call.

        A rejected goal changes nothing: the running motion (or the hold) continues.
        """
        start = self.start_state(now, measured=measured)
        try:
            plan = self.plan(request, start)
        except PlanRejected as exc:
            return [GoalEvent(request.goal_id, GoalState.REJECTED, exc.reason,
                              np.asarray(request.target, float) if request.target is not None else None)]
        return self.commit(request, plan, start, now=now)

    def reject(self, goal_id: str, reason: str) -> list[GoalEvent]:
        """Report a goal rejected before planning (malformed message)."""
        return [GoalEvent(goal_id, GoalState.REJECTED, reason)]

    def _install(self, motion: _Motion, now: float) -> None:
        if motion.t0 > now:
            # keep the running motion until the switch; a pending one not yet started is dropped
            self._pending = motion
        else:
            self._motion, self._pending = motion, None

    def _brake(self, now: float) -> tuple[_Motion | None, str]:
        """A stop from the state at ``now + lookahead``, checked against the mechanism."""
        start = self.start_state(now)
        s = start.state
        if start.source != 'motion':
            return None, 'at rest'
        if not (np.any(s.v) or np.any(s.a)):
            hold = brake(s.p, s.v, s.a, max_acceleration=self.limits.max_acceleration)
            return _Motion(start.t0, hold, None), 'at rest'
        traj = brake(s.p, s.v, s.a, max_acceleration=self.limits.max_acceleration)
        for _ in range(4):
            if check_path(self.mech, traj, self.limits, samples=50).ok:
                return _Motion(start.t0, traj, None), f'decelerating to rest in {traj.duration:.3f} s'
            # stopping within the platform limits leaves the checked region: stop harder
            traj = brake(s.p, s.v, s.a, max_acceleration=4.0 * self.limits.max_acceleration,
                         min_duration=traj.duration / 2.0)
        return None, 'no stop within the limits was found: finishing the checked motion'

    def cancel(self, *, now: float) -> tuple[bool, str, list[GoalEvent]]:
        """Decelerate to rest and hold (``~/cancel``). Returns (success, message, events)."""
        goal = self._active_goal
        if goal is None and not self.moving:
            return True, 'no active goal; holding', []
        motion, how = self._brake(now)
        if motion is not None:
            self._install(motion, now)
        self._active_goal = None
        events = [GoalEvent(goal, GoalState.CANCELLED, f'cancel requested; {how}')] if goal else []
        return True, (f'goal {goal} cancelled; {how}' if goal else f'stopping; {how}'), events

    def abort(self, reason: str, *, now: float) -> list[GoalEvent]:
        """Stop the active goal (brake to rest and hold) and report it aborted with ``reason``."""
        goal = self._active_goal
        if goal is None:
            return []
        motion, how = self._brake(now)
        if motion is not None:
            self._install(motion, now)
        self._active_goal = None
        return [GoalEvent(goal, GoalState.ABORTED, f'{reason}; {how}')]

    def check_tracking(self, measured: np.ndarray, *, now: float,
                       measured_at: float | None = None) -> list[GoalEvent]:
        """Abort the active goal if the brace is off its path (SAFETY.md 11).

        The error is taken in actuator coordinates: ``|IK(measured) - IK(setpoint)|`` per
        actuator, against every setpoint of the ``tracking_latency`` before
        ``measured_at`` (the measurement's time on this runner's clock; default ``now``);
        the smallest such error must stay within ``path_tolerance``.
        """
        if self.path_tolerance is None or self._active_goal is None or not self._recent:
            return []
        measured = np.asarray(measured, float)
        if not np.all(np.isfinite(measured)):
            return self.abort('measured pose is not finite', now=now)
        t_meas = now if measured_at is None else float(measured_at)
        window = [q for t, q in self._recent if t_meas - self.tracking_latency <= t <= t_meas + 1e-3]
        if not window:
            return []
        try:
            q_meas = self.mech.inverse(measured)
        except ValueError as exc:            # UnreachablePose: off the stroke
            return self.abort(f'measured pose is off the actuators\' range: {exc}', now=now)
        err = np.abs(np.asarray(window) - q_meas).max(axis=1)
        best = int(np.argmin(err))
        if float(err[best]) > self.path_tolerance:
            i = int(np.argmax(np.abs(window[best] - q_meas)))
            name = self.mech.actuator_names[i]
            return self.abort(f'tracking error {err[best]:.4f} on actuator {name} exceeds the path '
                              f'tolerance {self.path_tolerance:.4f}', now=now)
        return []

    # -- setpoints ---------------------------------------------------------------------
    def step(self, now: float) -> tuple[MotionState | None, list[GoalEvent]]:
        """The setpoint at ``now`` (``None`` before the first motion) and any goal that ended."""
        if self._pending is not None and now >= self._pending.t0:
            self._motion, self._pending = self._pending, None
        self._last_t = now
        m = self._motion
        if m is None:
            return None, []
        p, v, a = m.trajectory.sample(now - m.t0)
        self._last_setpoint = p.copy()
        if self.path_tolerance is not None:
            try:
                self._recent.append((now, self.mech.inverse(p)))
            except ValueError:               # planned paths are checked; keep the history clean
                pass
            while self._recent and self._recent[0][0] < now - self.tracking_latency - 1.0:
                self._recent.popleft()
        events: list[GoalEvent] = []
        if (m.goal_id is not None and m.goal_id == self._active_goal
                and now - m.t0 >= m.trajectory.duration):
            self._active_goal = None
            events.append(GoalEvent(m.goal_id, GoalState.SUCCEEDED, '', m.target,
                                    m.trajectory.duration, self.profile.value))
        return MotionState(p, v, a), events
