"""Goals in, planned motions out, honest outcomes back: the trajectory node's logic, without ROS.

:class:`TrajectoryRunner` plans each goal from the state the commanded motion will have
when the new motion takes over (``lookahead`` from now: continuous position, velocity and
acceleration), hands the whole motion out once (the node publishes it; the driver samples
it in its SYNC loop), and decides how each goal ends from what the rest of the stack
reports (docs/safety.md §12, §16):

* **succeeded** only when the driver reported the motion finished, the drives were enabled
  all along, and the estimated platform pose (load aware) came within ``pose_tolerance``
  of the goal within ``settle_time`` after that (on the estimates' stamps: evidence that
  arrives late on a loaded host still counts; none for ``report_timeout`` more aborts) and
  stayed within it for
  :data:`SETTLE_CONFIRM_S` (a ring still creeping across the edge of the tolerance has not
  arrived: the estimate samples it, and a ring judged on its first sample inside may be
  outside again by the time the success is reported), with the mean of that window's
  estimates plus twice their uncertainty inside too: the window's scatter and what the
  encoders cannot resolve at the goal (one count of reading and one of homing per
  actuator, the estimator's own quantisation term, through the Jacobian: on the lumbar
  brace's near-parallel legs 0.12 um of count is ~30 um of x). A ring resting at the edge
  is not judged on the estimate's noise or its last count;
* **aborted** when the driver rejected or stopped the motion (halt, disable, protective
  stop: the reason is the driver's), when the drives left the enabled state, when the
  ring did not follow (the estimate stayed off the goal: by how much, per coordinate), or
  when no report came in time;
* **cancelled** when a newer goal preempted it or a cancel was requested;
* **rejected** before anything moves when it cannot be planned within the limits, or
  while the drives are not enabled.

Its model of the command: the motion it last handed out (sampled on its own clock), or
the pose the command holds. After the driver re-anchors (enable) or stops a motion early
(cancel, halt, fault), the hold is the forward kinematics of the positions the driver
reports, so the next motion starts exactly where the drives are commanded. A motion the
driver refuses changes nothing there (the running motion goes on), so the model goes back
to the motion or hold it was planned from, not to where the refusal found the command. While a
cancelled motion is still braking the model is unknown (:attr:`settled` is False) and no
new motion is planned from it. The same holds while the driver's in-cycle admittance
(interaction) moves the command: a goal then waits until the mode has ended at rest and the
driver reported where (:meth:`on_interaction`); the node ends the mode for it.

Time is whatever monotonic clock the caller passes (s). Not thread-safe: the node
serialises calls (its lock); :meth:`plan` needs no lock.
"""
from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from ..mechanisms.pose_estimate import weighted_covariance
from .base import MotionState, Trajectory
from .limits import Limits
from .minimum_jerk import FittsLaw
from .planner import Plan, Profile, plan_motion

if TYPE_CHECKING:  # pragma: no cover
    from ..mechanisms.base import Mechanism

__all__ = ['GoalState', 'GoalRequest', 'GoalEvent', 'StartState', 'TrajectoryRunner',
           'SETTLE_CONFIRM_S']

#: s the estimate must stay within the pose tolerance before a goal succeeds (five
#: estimates at the 100 Hz joint-state rate)
SETTLE_CONFIRM_S = 0.05
#: handed-out motions whose predecessor the runner remembers (a driver's refusal names one
#: of the last few: each is refused or started within a lookahead of being handed out)
_CHAIN = 32


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
    """One status report: ``reason`` is empty for plain successes; ``values`` adds numbers
    (e.g. the final error, the path's minimum wrench capacity)."""

    goal_id: str
    state: GoalState
    reason: str = ''
    target: np.ndarray | None = None
    duration: float | None = None
    profile: str = ''
    values: dict = field(default_factory=dict)


@dataclass(frozen=True)
class StartState:
    """Where a new motion starts: at time ``t0`` (the runner's clock), in ``state``."""

    t0: float
    state: MotionState
    source: str                      # 'motion', 'hold', 'measured' or 'home'


@dataclass
class _Motion:
    t0: float
    trajectory: Trajectory
    tag: int                         # the stamp it was handed out with (ns)


@dataclass
class _Goal:
    goal_id: str
    target: np.ndarray
    tag: int
    duration: float
    profile: str
    started: bool = False
    finished_at: float | None = None      # when the driver reported the motion finished
    best_error: np.ndarray | None = None
    inside_since: float | None = None     # stamp of the first estimate of the run inside the tolerance
    #: the run of estimates inside the tolerance, (stamp, error per axis), signed
    inside: list[tuple[float, np.ndarray]] = field(default_factory=list)
    #: 1-sigma per pose coordinate the encoders' quantisation leaves at the target
    resolution: np.ndarray | None = None
    #: stamp of the newest estimate since the motion finished (the settle time runs on it)
    last_stamp: float | None = None
    #: the last confirmation's window (docs: honest outcomes): |mean| + 2 sigma per
    #: coordinate, and its scatter (std) alone; None: no run inside lasted SETTLE_CONFIRM_S
    judged: np.ndarray | None = None
    scatter: np.ndarray | None = None
    #: the longest run of estimates inside the tolerance (s, by their stamps)
    longest_inside: float = 0.0
    estimates: int = 0                    # estimates since the motion finished


class TrajectoryRunner:
    """Plans goals on ``mech`` within ``limits`` and tracks how each ends (module docstring).

    :param mech: the mechanism model (IK, Jacobian, forward kinematics, workspace).
    :param limits: the limits every motion is checked against.
    :param profile: the motion profile for goals.
    :param fitts: Fitts' law for goals without a duration.
    :param fitts_axes: coordinates whose distance is Fitts' amplitude (default all).
    :param lookahead: s between planning a goal and its motion taking over.
    :param pose_tolerance: largest |estimate - goal| per pose coordinate for success.
    :param settle_time: s after the motion finished for the estimate to get there.
    :param report_timeout: s of silence from the driver (no start after the takeover, no
        end after the planned duration and half of it again) before a goal is aborted.
    """

    def __init__(self, mech: 'Mechanism', limits: Limits, *, profile: Profile | str,
                 fitts: FittsLaw, fitts_axes: tuple[int, ...] | None = None,
                 lookahead: float = 0.1, pose_tolerance: np.ndarray | float = 0.002,
                 settle_time: float = 0.5, report_timeout: float = 1.0,
                 actuator_resolution: float | None = None) -> None:
        self.mech = mech
        #: m or rad of actuator per encoder count (``None``: not known, no resolution margin)
        self.actuator_resolution = actuator_resolution
        self.limits = limits
        self.profile = Profile(profile)
        self.fitts = fitts
        self.fitts_axes = fitts_axes
        self.lookahead = float(lookahead)
        self.pose_tolerance = np.broadcast_to(np.asarray(pose_tolerance, float), (mech.dof,)).copy()
        self.settle_time = float(settle_time)
        self.report_timeout = float(report_timeout)
        self._motion: _Motion | None = None
        self._hold: np.ndarray | None = None
        #: per handed-out motion (its tag), the model it replaced: what the driver goes on
        #: with if it rejects that motion (:meth:`on_execution`); the last :data:`_CHAIN` kept
        self._replaced: dict[int, tuple[_Motion | None, np.ndarray | None]] = {}
        #: the driver's in-cycle admittance moves the command (its 'started' event): the
        #: model is unknown until it ends at rest ('stopped' / 'aborted' with the positions)
        self.interacting = False
        self._stopping: int | None = None        # tag of a motion braking after a cancel
        self._goal: _Goal | None = None
        self.driver_enabled = False
        self.driver_reason = 'no driver state received yet'
        self._estimate: np.ndarray | None = None
        #: s the driver's motion runs behind its plan (SYNCs a stalled host missed while
        #: moving), as its last execution event said
        self.driver_lag = 0.0

    # -- state -----------------------------------------------------------------------
    @property
    def active_goal(self) -> str | None:
        """The goal being executed or settling (``None`` when idle)."""
        return None if self._goal is None else self._goal.goal_id

    @property
    def settled(self) -> bool:
        """The commanded motion is known (no cancelled motion still braking)."""
        return self._stopping is None

    @property
    def hold(self) -> np.ndarray | None:
        """The pose the command holds when idle (``None`` before the driver said where)."""
        return None if self._hold is None else self._hold.copy()

    def start_state(self, now: float, *, measured: np.ndarray | None = None) -> StartState | None:
        """Where a goal planned now starts (at ``now + lookahead``); ``None`` while a
        cancelled motion is still braking (its end is known only when the driver says).

        The handed-out motion when one runs then, else the hold; before the driver said
        where the command is, the ``measured`` pose (fresh estimate), else home.
        """
        if self._stopping is not None or self.interacting:
            return None
        t0 = now + self.lookahead
        m = self._motion
        zero = np.zeros(self.mech.dof)
        if m is not None and t0 < m.t0 + m.trajectory.duration:
            p, v, a = m.trajectory.sample(t0 - m.t0)
            return StartState(t0, MotionState(p, v, a), 'motion')
        if m is not None:
            return StartState(t0, MotionState(m.trajectory.sample(m.trajectory.duration)[0], zero,
                                              zero.copy()), 'motion')
        if self._hold is not None:
            return StartState(t0, MotionState(self._hold.copy(), zero, zero.copy()), 'hold')
        if measured is not None:
            return StartState(t0, MotionState(np.asarray(measured, float), zero, zero.copy()), 'measured')
        return StartState(t0, MotionState(np.asarray(self.mech.home_pose, float), zero, zero.copy()),
                          'home')

    # -- goals -------------------------------------------------------------------------
    def admit(self, goal_id: str) -> list[GoalEvent]:
        """A goal arrives: rejected at once while the drives are not enabled."""
        if not self.driver_enabled:
            return [GoalEvent(goal_id, GoalState.REJECTED,
                              f'the drives are not enabled ({self.driver_reason})')]
        return []

    def plan(self, request: GoalRequest, start: StartState) -> Plan:
        """Plan ``request`` from ``start`` (pure: may run without the node's lock).

        :raises PlanRejected: with the reason for the status.
        """
        return plan_motion(self.mech, start.state.p, request.target, self.profile, self.limits,
                           via=request.via, t_via=request.t_via, duration=request.duration,
                           v0=start.state.v, a0=start.state.a, fitts=self.fitts,
                           fitts_axes=self.fitts_axes)

    def commit(self, request: GoalRequest, plan: Plan, start: StartState, *, tag: int,
               now: float) -> list[GoalEvent]:
        """Make ``plan`` the motion handed out with ``tag``, from ``start.t0``; the goal it
        replaces is reported cancelled. The caller publishes it (stamp = ``tag``)."""
        events: list[GoalEvent] = []
        if not self.driver_enabled:
            return [GoalEvent(request.goal_id, GoalState.REJECTED,
                              f'the drives are not enabled ({self.driver_reason})')]
        if self._goal is not None:
            events.append(GoalEvent(self._goal.goal_id, GoalState.CANCELLED,
                                    f'preempted by goal {request.goal_id}'))
        if start.source in ('motion', 'hold'):
            self._replaced[tag] = (self._motion, self._hold)
            while len(self._replaced) > _CHAIN:
                del self._replaced[next(iter(self._replaced))]
        self._motion = _Motion(start.t0, plan.trajectory, tag)
        target = np.asarray(request.target, float)
        self._goal = _Goal(request.goal_id, target, tag, plan.duration, plan.profile.value)
        notes = list(plan.notes)
        events.append(GoalEvent(request.goal_id, GoalState.ACCEPTED, '; '.join(notes), target,
                                plan.duration, plan.profile.value, dict(plan.values)))
        return events

    def cancel(self, *, now: float) -> tuple[str, int | None, list[GoalEvent]]:
        """``~/cancel``: ``(message, tag of the motion to stop or None, events)``.

        The driver decelerates the motion along its path; until it reports where that ended
        (:meth:`on_execution`), no new motion is planned.
        """
        goal = self._goal
        m = self._motion
        moving = m is not None and \
            now < m.t0 + m.trajectory.duration + self.driver_lag + self.report_timeout
        events: list[GoalEvent] = []
        if goal is not None:
            events.append(GoalEvent(goal.goal_id, GoalState.CANCELLED,
                                    'cancel requested; decelerating along the path'))
            self._goal = None
        if not moving:
            return ('no motion; holding' if goal is None else f'goal {goal.goal_id} cancelled; holding',
                    None, events)
        assert m is not None
        self._stopping = m.tag
        return ((f'goal {goal.goal_id} cancelled' if goal else 'stopping') +
                '; decelerating along the path', m.tag, events)

    def abort_all(self, reason: str) -> list[GoalEvent]:
        """Report the active goal aborted (shutdown, a node gone)."""
        goal, self._goal = self._goal, None
        return [] if goal is None else [GoalEvent(goal.goal_id, GoalState.ABORTED, reason)]

    # -- what the stack reports ----------------------------------------------------------
    def on_driver_state(self, enabled: bool, reason: str, command: np.ndarray | None, *,
                        executing: bool, now: float) -> list[GoalEvent]:
        """The driver's latched state. Leaving ``enabled`` aborts the active goal with the
        driver's reason; while enabled and holding (not ``executing``) with nothing of ours
        under way, the hold is FK of its ``command`` (re-anchoring after enable or a stop).
        """
        events: list[GoalEvent] = []
        was = self.driver_enabled
        self.driver_enabled = bool(enabled)
        self.driver_reason = reason
        if not enabled:
            if self._goal is not None:
                events += self.abort_all(f'the drives stopped: {reason}')
            self._motion = None
            self._stopping = None
            self.interacting = False
        if enabled and command is not None and (not executing or not was) and self._goal is None:
            pose = self._forward(command)
            if pose is not None:
                self._hold = pose
                self._motion = None
                self._stopping = None
        return events

    def on_execution(self, tag: int, kind: str, reason: str, positions: np.ndarray | None, *,
                     now: float, lag: float | None = None) -> list[GoalEvent]:
        """An event of the trajectory handed out with ``tag`` (ik node or driver); ``lag``:
        s the driver's motion then ran behind its plan (the driver says; ``None``: unknown)."""
        events: list[GoalEvent] = []
        if lag is not None and math.isfinite(lag) and lag >= 0.0:
            self.driver_lag = float(lag)
        goal = self._goal if self._goal is not None and self._goal.tag == tag else None
        ours = self._motion is not None and self._motion.tag == tag
        if kind == 'started' and goal is not None:
            goal.started = True
        elif kind == 'finished':
            if ours:
                assert self._motion is not None
                self._hold = np.asarray(self._motion.trajectory.sample(
                    self._motion.trajectory.duration)[0], float)
                self._motion = None
            if self._stopping == tag:
                self._stopping = None
            if goal is not None:
                goal.finished_at = now
        elif kind == 'rejected' and tag in self._replaced:
            # the driver refused it and goes on with what it would have replaced (a splice
            # too far from the command, a check that failed: "the running motion continues"),
            # which is not where the refusal found the command when that was moving: the
            # model goes back to the motion or hold this one was planned from. A later motion
            # planned from this one's model is planned from that too.
            replaced = self._replaced.pop(tag)
            for later, (motion, hold) in self._replaced.items():
                if motion is not None and motion.tag == tag:
                    self._replaced[later] = replaced
            if ours:
                self._motion, self._hold = replaced
            if self._stopping == tag:
                self._stopping = None
            if goal is not None:
                self._goal = None
                events.append(GoalEvent(goal.goal_id, GoalState.ABORTED,
                                        f'its motion was rejected: {reason}'))
        elif kind in ('stopped', 'rejected'):
            if ours or self._stopping == tag:
                self._motion = None
                self._stopping = None
                pose = self._forward(positions) if positions is not None and len(positions) else None
                if pose is not None:
                    self._hold = pose
            if goal is not None:
                self._goal = None
                what = 'the driver stopped its motion' if kind == 'stopped' else 'its motion was rejected'
                events.append(GoalEvent(goal.goal_id, GoalState.ABORTED, f'{what}: {reason}'))
        return events

    def on_interaction(self, kind: str, positions: np.ndarray | None) -> None:
        """An event of the driver's in-cycle admittance (docs/interaction.md): 'started' makes
        the model unknown (:meth:`start_state` is None: a goal waits, and the node ends the
        mode); 'stopped' / 'aborted' (at rest) re-anchor the hold at FK of the reported
        command; 'preempted' (a motion took over, which its own events describe) ends it."""
        if kind == 'started':
            self.interacting = True
        elif kind in ('stopped', 'aborted', 'preempted'):
            self.interacting = False
            if kind != 'preempted' and positions is not None and len(positions):
                pose = self._forward(positions)
                if pose is not None:
                    self._hold = pose
                    self._motion = None

    def on_estimate(self, pose: np.ndarray, *, stamp: float, now: float) -> list[GoalEvent]:
        """The estimated platform pose at ``stamp`` (runner clock): a finished goal succeeds
        once it is within ``pose_tolerance`` of the goal."""
        self._estimate = np.asarray(pose, float)
        goal = self._goal
        if goal is None or goal.finished_at is None or stamp < goal.finished_at:
            return []
        goal.last_stamp = stamp if goal.last_stamp is None else max(goal.last_stamp, stamp)
        goal.estimates += 1
        signed = self._estimate - goal.target
        err = np.abs(signed)
        if goal.best_error is None or np.max(err / self.pose_tolerance) < np.max(goal.best_error / self.pose_tolerance):
            goal.best_error = err
        if not np.all(err <= self.pose_tolerance):
            goal.inside_since = None
            goal.inside.clear()
            return []
        if goal.inside_since is None:
            goal.inside_since = stamp
        goal.inside.append((stamp, signed))
        goal.longest_inside = max(goal.longest_inside, stamp - goal.inside_since)
        if stamp - goal.inside_since >= SETTLE_CONFIRM_S - 1e-9:
            # the estimates of the last SETTLE_CONFIRM_S: their mean plus twice their scatter
            # inside the tolerance (a ring resting at its edge is not judged on the noise of
            # the estimate: the truth may be just outside)
            while len(goal.inside) > 1 and goal.inside[1][0] <= stamp - SETTLE_CONFIRM_S + 1e-9:
                goal.inside.pop(0)
            window = np.array([e for _, e in goal.inside])
            if goal.resolution is None:
                goal.resolution = self.resolution_sigma(goal.target)
            goal.scatter = window.std(axis=0)
            sigma = np.hypot(goal.scatter, goal.resolution)
            goal.judged = np.abs(window.mean(axis=0)) + 2.0 * sigma
            if np.all(goal.judged <= self.pose_tolerance):
                self._goal = None
                return [GoalEvent(goal.goal_id, GoalState.SUCCEEDED, '', goal.target, goal.duration,
                                  goal.profile, {'final_error': err.tolist()})]
        return []

    def check(self, now: float) -> list[GoalEvent]:
        """Timeouts: no start, no end, or an estimate that never got to the goal."""
        goal = self._goal
        m = self._motion
        if goal is None:
            return []
        if goal.finished_at is not None:
            # an estimate inside the tolerance when the time is up gets its confirmation
            confirming = SETTLE_CONFIRM_S if goal.inside_since is not None else 0.0
            window = self.settle_time + confirming
            # the settle time runs on the estimates' own stamps: on a loaded host they arrive
            # late, and a platform at the goal is not judged on evidence still on its way;
            # estimates that stop coming end it report_timeout later by the clock
            seen = goal.last_stamp is not None and goal.last_stamp - goal.finished_at > window
            if not seen and now - goal.finished_at <= window + self.report_timeout:
                return []
            self._goal = None
            if goal.best_error is None:
                return [GoalEvent(goal.goal_id, GoalState.ABORTED,
                                  f'no pose estimate within {self.settle_time:g} s after the motion '
                                  'finished: where the platform is cannot be told')]
            why = 'the platform did not follow: ' + self.describe_error(goal.best_error)
            if np.all(goal.best_error <= self.pose_tolerance):
                why += '; ' + self._why_unconfirmed(goal)
            return [GoalEvent(goal.goal_id, GoalState.ABORTED, why,
                              values={'final_error': goal.best_error.tolist()})]
        if m is not None and m.tag == goal.tag:
            if not goal.started and now > m.t0 + self.driver_lag + self.report_timeout:
                self._goal = None
                return [GoalEvent(goal.goal_id, GoalState.ABORTED,
                                  f'the driver did not start the motion within {self.report_timeout:g} s '
                                  'of its start time (is can_driver_node running?)')]
            # a late SYNC delays the driver's motion (it never steps it): the delay the
            # driver reported, and half the duration again before calling the driver silent
            late = self.report_timeout + 0.5 * m.trajectory.duration + self.driver_lag
            if now > m.t0 + m.trajectory.duration + late:
                self._goal = None
                return [GoalEvent(goal.goal_id, GoalState.ABORTED,
                                  'the driver did not report the motion finished within '
                                  f'{late:.2f} s of its planned end')]
        return []

    def resolution_sigma(self, pose: np.ndarray) -> np.ndarray:
        """1-sigma per pose coordinate that the encoders' quantisation leaves at ``pose``:
        per actuator ``res^2 / 6`` (a count of reading and a count of homing, uniform; the
        estimator's eq. 3 without its force terms) through ``J`` (eq. 4,
        :func:`~brace_control.mechanisms.pose_estimate.weighted_covariance`). Zeros without
        :attr:`actuator_resolution` or where ``J`` cannot be evaluated."""
        res = self.actuator_resolution
        zeros = np.zeros(self.mech.dof)
        if not res:
            return zeros
        try:
            jac = np.atleast_2d(np.asarray(self.mech.jacobian(pose), dtype=float))
        except ValueError:             # UnreachablePose, SingularPose: no margin to give
            return zeros
        if not np.isfinite(jac).all():
            return zeros
        cov = weighted_covariance(jac, np.full(jac.shape[0], res * res / 6.0))
        return np.sqrt(np.clip(np.diag(cov), 0.0, None))

    def _units(self) -> list[tuple[str, float, str, int]]:
        """Per pose coordinate (name, scale, unit, decimals) for messages: mm / deg where it helps."""
        names = getattr(self.mech, 'pose_names', None) or (('x', 'y', 'theta') if self.mech.dof == 3
                                                             else tuple(f'q{i}' for i in range(self.mech.dof)))
        angular = self.mech.pose_kind == 'planar'
        out = []
        for i in range(self.mech.dof):
            if angular and i == 2:
                out.append((names[i], math.degrees(1.0), ' deg', 3))
            elif angular or self.mech.dof == 2:
                out.append((names[i], 1e3, ' mm', 2))
            else:
                out.append((names[i], 1.0, '', -1))
        return out

    @staticmethod
    def _fmt(value: float, scale: float, unit: str, decimals: int) -> str:
        return f'{value * scale:.{decimals}f}{unit}' if decimals >= 0 else f'{value:.4g}'

    def _why_unconfirmed(self, goal: _Goal) -> str:
        """Why estimates inside the tolerance made no success: what the confirmation saw."""
        res = goal.resolution if goal.resolution is not None else self.resolution_sigma(goal.target)
        if goal.judged is None:
            # (the settle time ran out first, or the runs inside kept being broken)
            return (f'inside the tolerance for {goal.longest_inside:.3f} s of estimates at most, '
                    f'not the {SETTLE_CONFIRM_S:g} s a success needs ({goal.estimates} estimates '
                    'since the motion finished)')
        if np.all(goal.scatter <= res):
            # inside, but never by the estimate's uncertainty (the last count)
            return ('inside the tolerance by less than the estimate resolves (2 sigma of the '
                    f'encoder counts: {self.describe_values(2.0 * res)})')
        return ('inside the tolerance by less than the estimates scattered: their last '
                f'{SETTLE_CONFIRM_S:g} s gave |mean| + 2 sigma of {self.describe_values(goal.judged)} '
                f'(scatter {self.describe_values(goal.scatter)}, 2 sigma of the encoder counts '
                f'{self.describe_values(2.0 * res)})')

    def describe_error(self, err: np.ndarray) -> str:
        """The final error per coordinate against the tolerance, in mm / deg where it helps."""
        return '; '.join(f'{n} off by {self._fmt(e, *u)} (tolerance {self._fmt(tol, *u)})'
                         for (n, *u), e, tol in zip(self._units(), err, self.pose_tolerance))

    def describe_values(self, values: np.ndarray) -> str:
        """``x 0.06 mm, y 0.00 mm, ...``: one value per pose coordinate, in the same units."""
        return ', '.join(f'{n} {self._fmt(v, *u)}' for (n, *u), v in zip(self._units(), values))

    # -- helpers -----------------------------------------------------------------------
    def _forward(self, q: np.ndarray) -> np.ndarray | None:
        """FK of actuator positions, continuous with what the runner last knew."""
        hint = self._hold if self._hold is not None else (
            self._estimate if self._estimate is not None else np.asarray(self.mech.home_pose, float))
        try:
            return np.asarray(self.mech.forward_nearest(np.asarray(q, float), hint), float)
        except ValueError:
            return None
