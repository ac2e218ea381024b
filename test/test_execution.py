"""The SYNC loop's trajectory schedule (:class:`brace_control.control.execution.PathExecutor`),
without a bus: JTC replacement semantics with a queue, missed SYNCs, late starts.

Oracle: closed-form quintics (Flash & Hogan minimum jerk, and the quintic from a moving
state to rest, :func:`brace_control.trajectory.base.quintic_coefficients` checked against
eqs. (2.2)-(2.3) in test_trajectory.py). Knots sampled from a quintic reproduce it exactly
under quintic Hermite interpolation, so the command at every SYNC must equal the closed
form to rounding.
"""
from __future__ import annotations

import threading
from types import SimpleNamespace

import numpy as np
import pytest

from brace_control.control.execution import ActuatorTrajectory, ExecutionState, PathExecutor
from brace_control.trajectory.base import quintic_coefficients

T_SYNC = 0.002
Q0 = np.array([0.3737, 0.3900, 0.4076])        # the lumbar brace's home lengths (m)


class Quintic:
    """``q(t)`` from ``(p0, v0, a0)`` to rest at ``p1`` over ``T`` (closed form)."""

    def __init__(self, p0, v0, a0, p1, T):
        self.T = T
        self.b = quintic_coefficients(np.asarray(p0, float), np.asarray(v0, float),
                                      np.asarray(a0, float), np.asarray(p1, float),
                                      np.zeros(3), np.zeros(3), T)

    def __call__(self, t):
        s = min(max(t, 0.0), self.T) / self.T
        b, T = self.b, self.T
        p = sum(b[k] * s ** k for k in range(6))
        v = sum(k * b[k] * s ** (k - 1) for k in range(1, 6)) / T
        a = sum(k * (k - 1) * b[k] * s ** (k - 2) for k in range(2, 6)) / T ** 2
        return p, v, a

    def knots(self, dt=0.01):
        t = np.linspace(0.0, self.T, int(round(self.T / dt)) + 1)
        P, V, A = zip(*(self(x) for x in t))
        return ActuatorTrajectory(t, np.array(P), np.array(V), np.array(A))


def executor():
    ex = PathExecutor(3, v_max=0.05, a_max=0.5, period=T_SYNC)
    ex.anchor(Q0, t=0.0)
    return ex


def run(ex, t_from, t_to):
    """Step the executor SYNC by SYNC; ``[(t, q)]``."""
    out = []
    for k in range(int(round(t_from / T_SYNC)), int(round(t_to / T_SYNC)) + 1):
        t = k * T_SYNC
        q, _ = ex.step(t)
        out.append((t, q))
    return out


def kinds(ex):
    return [(e.tag, e.kind) for e in ex.events]


def test_a_trajectory_waiting_when_the_next_arrives_runs_until_the_next_starts():
    """A scheduled at 0.1 s, B (planned from A's state at 0.3 s) at 0.3 s, both loaded before
    A starts: the command is A from 0.1 s, B from 0.3 s, exactly; nothing rejected."""
    ex = executor()
    A = Quintic(Q0, np.zeros(3), np.zeros(3), Q0 + [0.004, 0.010, 0.016], 1.0)
    t_a, t_b = 0.1, 0.3
    B = Quintic(*A(t_b - t_a), Q0 - [0.002, 0.004, 0.006], 1.2)
    assert ex.load(A.knots(), t_a, 1, now=0.0) is None
    assert ex.load(B.knots(), t_b, 2, now=0.0) is None
    samples = run(ex, T_SYNC, 1.6)
    for t, q in samples:
        if t < t_a:
            expected = Q0
        elif t < t_b:
            expected = A(t - t_a)[0]
        else:
            expected = B(t - t_b)[0]
        assert np.max(np.abs(q - expected)) < 1e-9, (t, q - expected)
    assert kinds(ex) == [(1, 'accepted'), (2, 'accepted'), (1, 'started'), (1, 'preempted'),
                         (2, 'started'), (2, 'finished')]
    started = {e.tag: e.time for e in ex.events if e.kind == 'started'}
    assert started == pytest.approx({1: t_a, 2: t_b}, abs=1e-12)


def test_a_trajectory_starting_earlier_drops_the_ones_scheduled_after_it():
    """B starts before the scheduled A: A is preempted before it started, B runs alone."""
    ex = executor()
    A = Quintic(Q0, np.zeros(3), np.zeros(3), Q0 + 0.01, 1.0)
    B = Quintic(Q0, np.zeros(3), np.zeros(3), Q0 - 0.005, 0.8)
    assert ex.load(A.knots(), 0.3, 1, now=0.0) is None
    assert ex.load(B.knots(), 0.1, 2, now=0.0) is None
    assert kinds(ex) == [(1, 'accepted'), (1, 'preempted'), (2, 'accepted')]
    assert 'before it started' in ex.events[1].reason
    for t, q in run(ex, T_SYNC, 1.2):
        expected = Q0 if t < 0.1 else B(t - 0.1)[0]
        assert np.max(np.abs(q - expected)) < 1e-9, t
    assert kinds(ex)[-2:] == [(2, 'started'), (2, 'finished')]


def test_missed_syncs_delay_the_motion_and_the_events_say_by_how_much():
    """A stalled host skips 10 SYNCs mid-motion: the command advances one period per step
    run (never a 10-period jump), so the motion ends 20 ms late, and the events from then on
    carry that lag."""
    ex = executor()
    A = Quintic(Q0, np.zeros(3), np.zeros(3), Q0 + [0.0, 0.008, 0.015], 0.6)
    assert ex.load(A.knots(), 0.1, 1, now=0.0) is None
    run(ex, T_SYNC, 0.3)
    q_before = ex.q.copy()
    q, _ = ex.step(0.3 + 11 * T_SYNC)          # 10 SYNCs missed
    assert np.max(np.abs(q - A(0.3 + T_SYNC - 0.1)[0])) < 1e-9
    assert np.max(np.abs(q - q_before)) <= 0.05 * T_SYNC * 1.01
    assert ex.lag == pytest.approx(10 * T_SYNC)
    t = 0.3 + 11 * T_SYNC
    while ex.state.value != 'hold':
        t += T_SYNC
        ex.step(t)
    finished = [e for e in ex.events if e.kind == 'finished']
    assert len(finished) == 1
    assert finished[0].lag == pytest.approx(10 * T_SYNC)
    assert finished[0].time == pytest.approx(0.1 + 0.6, abs=T_SYNC)     # on the executor's clock
    assert t == pytest.approx(0.1 + 0.6 + 10 * T_SYNC, abs=T_SYNC)      # 20 ms late by the master's
    ex.step(t + T_SYNC)                          # at rest the clock re-joins the master's
    assert ex.lag == 0.0


def test_a_late_start_from_rest_moves_the_whole_schedule():
    """The host stalls from rest past both scheduled starts: A starts at once and B (planned
    on A's timeline, 0.1 s after A) follows 0.1 s later, both exactly."""
    ex = executor()
    A = Quintic(Q0, np.zeros(3), np.zeros(3), Q0 + [0.003, 0.006, 0.009], 0.8)
    B = Quintic(*A(0.1), Q0, 0.9)
    assert ex.load(A.knots(), 0.1, 1, now=0.0) is None
    assert ex.load(B.knots(), 0.2, 2, now=0.0) is None
    first = 0.25                                  # the first SYNC after the stall
    for t, q in run(ex, first, 1.6):
        expected = A(t - first)[0] if t < first + 0.1 else B(t - first - 0.1)[0]
        assert np.max(np.abs(q - expected)) < 1e-9, t
    assert [k for k in kinds(ex) if k[1] in ('started', 'finished', 'preempted')] == \
        [(1, 'started'), (1, 'preempted'), (2, 'started'), (2, 'finished')]


def test_a_plan_arriving_after_its_predecessor_started_late_splices_where_it_was_planned():
    """A's plan reached the driver 0.5 s after its start (a busy host): from rest it starts at
    once, 0.5 s behind its plan. B, planned from A's state 0.3 s into A while the planner
    believed A on time, arrives 0.2 s after A started (after B's own start time on the
    planner's clock): it takes over 0.3 s into A, exactly, never "sampled on its own
    clock" 16 mm away (the seeded operator's refusal)."""
    ex = executor()
    A = Quintic(Q0, np.zeros(3), np.zeros(3), Q0 + [0.004, 0.010, 0.016], 1.0)
    t_a, late = 0.1, 0.5
    t_b = t_a + 0.3
    B = Quintic(*A(t_b - t_a), Q0 - [0.002, 0.004, 0.006], 1.2)
    assert ex.load(A.knots(), t_a, 1, now=t_a + late) is None
    first = t_a + late                                   # A starts here, on the master's clock
    samples = run(ex, first, first + 0.2)
    assert ex.load(B.knots(), t_b, 2, now=first + 0.2) is None
    samples += run(ex, first + 0.2 + T_SYNC, first + 1.6)
    for t, q in samples:
        expected = A(t - first)[0] if t < first + 0.3 - 1e-9 else B(t - first - 0.3)[0]
        assert np.max(np.abs(q - expected)) < 1e-9, (t, q - expected)
    assert [k for k in kinds(ex) if k[1] in ('started', 'finished', 'preempted', 'rejected')] == \
        [(1, 'started'), (1, 'preempted'), (2, 'started'), (2, 'finished')]
    assert ex.events[-1].lag == pytest.approx(late, abs=1e-9)    # B ended 0.5 s late, and says so


def test_a_stop_while_the_motion_runs_late_brakes_from_the_next_step():
    """A started 0.5 s late (the executor's clock that far behind the master's): a cancel at
    master time 1.0 s brakes from the next step, not 0.5 s later; the motion is at rest
    short of where it would have gone, within the brake's time of the cancel."""
    ex = executor()
    A = Quintic(Q0, np.zeros(3), np.zeros(3), Q0 + [0.004, 0.010, 0.016], 1.0)
    assert ex.load(A.knots(), 0.1, 1, now=0.6) is None
    run(ex, 0.6, 1.0)
    v_before = np.linalg.norm(ex.v)
    assert v_before > 0.01 and ex.lag == pytest.approx(0.5)
    ex.stop('cancel requested', now=1.0)
    t, speeds = 1.0, []
    while ex.state.value != 'hold':
        t += T_SYNC
        ex.step(t)
        speeds.append(np.linalg.norm(ex.v))
        assert t < 2.0
    assert speeds[round(0.1 / T_SYNC)] < 0.8 * v_before      # braking 0.1 s after the cancel
    stopped = [e for e in ex.events if e.kind == 'stopped']
    assert len(stopped) == 1 and 'cancel' in stopped[0].reason
    assert t - 1.0 <= 0.3, t                     # the brake's time (~0.2 s), not 0.5 s more
    assert np.max(np.abs(ex.q - A(1.0)[0])) > 1e-3   # short of A's end


def test_a_stop_drops_every_scheduled_trajectory():
    ex = executor()
    A = Quintic(Q0, np.zeros(3), np.zeros(3), Q0 + 0.01, 1.0)
    assert ex.load(A.knots(), 0.1, 1, now=0.0) is None
    assert ex.load(A.knots(), 0.2, 2, now=0.0) is None
    ex.stop('cancel requested', now=0.05)
    assert kinds(ex)[-2:] == [(1, 'stopped'), (2, 'stopped')]
    assert not ex.moving
    for t, q in run(ex, T_SYNC, 0.5):
        assert np.array_equal(q, Q0), t


@pytest.mark.parametrize('stop_at', [0.05, 0.1, 0.3, 0.44, 0.6])
def test_a_brake_early_in_a_motion_is_short_and_always_within_the_acceleration_limit(stop_at):
    """A stop (cancel, soft limit) at any instant of a minimum-jerk move of 0.9 rad over
    0.88 s (a 3-RRR joint: 2 rad/s, 15 rad/s^2): every commanded acceleration, by
    differences of the commanded speed at the SYNCs, is within a_max; the joint rests
    short of the goal. 50 ms into the move the brake, once sized on the path's next whole
    second (the motion's peak speed ahead), ran 0.146 rad while the path sped up under it
    and a stiff neck's moment went from 1 to 2 N·m; sized on the stretch it passes, it
    runs 0.051 rad."""
    T, A, a_max = 0.88, 0.9, 15.0
    move = Quintic([0.0] * 3, [0.0] * 3, [0.0] * 3, [A, 0.0, 0.0], T)
    ex = PathExecutor(3, v_max=2.0, a_max=a_max, period=T_SYNC)
    ex.anchor(np.zeros(3), t=0.0)
    assert ex.load(move.knots(0.005), 0.0, 1, now=0.0) is None
    run(ex, 0.0, stop_at)
    q_stop = ex.q[0]
    ex.stop('test', now=stop_at)
    qs, vs = [], []
    for k in range(int(round(stop_at / T_SYNC)) + 1, int(round((stop_at + 1.5) / T_SYNC))):
        q, v = ex.step(k * T_SYNC)
        qs.append(q[0])
        vs.append(v[0])
    acc = np.abs(np.diff(vs)) / T_SYNC
    assert np.max(acc) <= a_max * 1.001, np.max(acc)
    assert qs[-1] < A and abs(vs[-1]) < 1e-9
    if stop_at <= 0.05:
        assert qs[-1] - q_stop < 0.06, qs[-1] - q_stop


def test_the_master_s_moving_is_not_read_halfway_through_a_start():
    """``BraceMaster.moving`` never says "at rest" while a trajectory starts. The SYNC
    thread's step takes a starting trajectory off the schedule before the executor's state
    says TRAJECTORY; another thread that read in between saw neither, took the motion for
    ended and read its events without an end (test_durand_peer, a run of 2026-11-29:
    ``[('accepted', ''), ('started', '')]``). The read waits for the step (the motion's lock,
    which every step holds)."""
    from brace_control.can.lifecycle import Motion
    from brace_control.can.master import BraceMaster

    ex = executor()
    motion = Motion(ex)
    master = SimpleNamespace(motion=motion, executor=ex)
    moving = BraceMaster.moving.fget
    assert ex.load(Quintic(Q0, np.zeros(3), np.zeros(3), Q0 + 0.01, 1.0).knots(), 0.5, 7, now=0.0) is None
    assert moving(master)                                   # scheduled: motion to come
    answers: list[bool] = []
    with motion.lock:                                       # the SYNC thread's step ...
        starting = ex._pending.pop(0)                       # ... halfway through the start
        assert not ex.moving                                # premise: the executor says rest
        reader = threading.Thread(target=lambda: answers.append(moving(master)))
        reader.start()
        reader.join(0.2)
        assert answers == [], 'moving was answered in the middle of a step'
        ex._pending.insert(0, starting)
        ex.step(0.5)                                        # the step as it runs: the start
        assert ex.state is ExecutionState.TRAJECTORY
    reader.join(5.0)
    assert answers == [True]
