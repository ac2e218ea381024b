"""Trajectory math (no rclpy): minimum jerk (thesis 002 eqs. 2.2–2.12), Ruckig S-curve,
log-cosh (thesis 004), limit-respecting planning and the goal runner.

Oracles come from the seeds' equations or from independent computations in this file.
"""
from __future__ import annotations

import math
import os

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from brace_control.config import load_device_config
from brace_control.trajectory import (
    FittsLaw, GoalRequest, GoalState, Limits, LogCosh, MinimumJerk, PlanRejected, Profile,
    SCurve, TrajectoryError, TrajectoryRunner, Violation, ViaPointMinimumJerk, fitts_duration,
    plan_motion)
from brace_control.trajectory.poses import PoseError, arrival_times
from rpr_oracles import lumbar_eq3

CONFIG = 'config/lumbar_brace.yaml'
# The configured home (0, 0.390, 0) of the 3-RPR with collinear anchors is singular
# (det J = 0 whenever theta = 0); the tests use the same geometry tilted to theta = 0.1.
HOME = np.array([0.0, 0.39, 0.1])
# derandomize: CI runs the same examples every time; BRACE_HYPOTHESIS_EXAMPLES=3000 for a search
PROPS = settings(max_examples=int(os.environ.get("BRACE_HYPOTHESIS_EXAMPLES", "25")), deadline=None, database=None,
                 derandomize=True,
                 suppress_health_check=[HealthCheck.too_slow])


@pytest.fixture(scope='module')
def cfg():
    c = load_device_config(CONFIG)
    c['mechanism']['home_pose'] = HOME.tolist()
    return c


@pytest.fixture(scope='module')
def mech(cfg):
    from brace_control.mechanisms import mechanism_from_config
    return mechanism_from_config(cfg)


@pytest.fixture(scope='module')
def limits(cfg):
    return Limits.from_config(cfg)


def eq_2_2(x0, xf, tf, t):
    """Thesis eq. (2.2) and its derivatives as App. A writes them (VPx, APx)."""
    tau = t / tf
    x = x0 + (x0 - xf) * (15 * tau**4 - 6 * tau**5 - 10 * tau**3)
    v = (x0 - xf) * (-30 * tau**2 + 60 * tau**3 - 30 * tau**4) / tf
    a = (x0 - xf) * (-60 * tau + 180 * tau**2 - 120 * tau**3) / tf**2
    return x, v, a


# ---------------------------------------------------------------- minimum jerk
def test_minimum_jerk_matches_eq_2_2_of_appendix_a():
    x0, xf, y0, tf = 0.2591242, 0.006618034, 0.2777567, 0.5     # App. A
    tr = MinimumJerk([x0, y0], [xf, y0], tf)
    for t in np.linspace(0.0, tf, 37):
        p, v, a = tr.sample(t)
        x, vx, ax = eq_2_2(x0, xf, tf, t)
        assert p[0] == pytest.approx(x, abs=1e-12)
        assert v[0] == pytest.approx(vx, abs=1e-10)
        assert a[0] == pytest.approx(ax, abs=1e-9)
        assert p[1] == y0 and v[1] == 0.0


def test_minimum_jerk_peak_speed_is_1_875_A_over_T_at_half_time_and_ends_at_rest():
    A, T = np.array([0.2525, -0.03, 0.1]), 0.5
    tr = MinimumJerk(np.zeros(3), A, T)
    ts = np.linspace(0.0, T, 10001)
    _, v, _ = tr.sample_many(ts)
    speed = np.abs(v)
    np.testing.assert_allclose(speed.max(axis=0), 1.875 * np.abs(A) / T, rtol=1e-9)
    assert np.all(ts[np.argmax(speed, axis=0)] == pytest.approx(T / 2))
    for t in (0.0, T):
        _, v_end, a_end = tr.sample(t)
        np.testing.assert_allclose(v_end, 0.0, atol=1e-12)
        np.testing.assert_allclose(a_end, 0.0, atol=1e-12)


def test_minimum_jerk_clamps_outside_its_duration_and_holds():
    tr = MinimumJerk([0.0], [1.0], 2.0)
    assert tr.sample(-1.0)[0][0] == 0.0
    p, v, a = tr.sample(5.0)
    assert (p[0], v[0], a[0]) == (1.0, 0.0, 0.0)
    assert tr.jerk(5.0)[0] == 0.0
    assert tr.jerk(0.0)[0] == pytest.approx(60.0 / 8.0)        # 60 A / T^3


def test_minimum_jerk_from_a_moving_start_keeps_v0_a0_and_ends_at_rest():
    v0, a0 = np.array([0.02, -0.01]), np.array([0.05, 0.1])
    tr = MinimumJerk([0.0, 0.0], [0.03, 0.01], 1.2, v0=v0, a0=a0)
    p, v, a = tr.sample(0.0)
    np.testing.assert_allclose(v, v0, atol=1e-12)
    np.testing.assert_allclose(a, a0, atol=1e-12)
    p, v, a = tr.sample(1.2)
    np.testing.assert_allclose(p, [0.03, 0.01], atol=1e-12)
    np.testing.assert_allclose([v, a], 0.0, atol=1e-12)


@pytest.mark.parametrize('bad', [dict(duration=0.0), dict(duration=math.nan),
                                 dict(goal=[1.0, math.inf]), dict(goal=[1.0])])
def test_minimum_jerk_rejects_bad_input(bad):
    args = dict(start=[0.0, 0.0], goal=[1.0, 1.0], duration=1.0) | bad
    with pytest.raises(TrajectoryError):
        MinimumJerk(**args)


# ---------------------------------------------------------------- via points
X0, Y0, X1, Y1, XF, YF, TF = -0.01197358, 0.2932582, 0.1207077, 0.3330677, 0.2692255, 0.2941459, 0.5


def eqs_2_4_to_2_11(t, t1):
    """The thesis's closed form (App. B), both coordinates."""
    tau1, tau = t1 / TF, t / TF
    out = []
    for q0, q1, qf in ((X0, X1, XF), (Y0, Y1, YF)):
        c = 1 / (TF**5 * tau1**2 * (1 - tau1)**5) * (
            (qf - q0) * (300 * tau1**5 - 1200 * tau1**4 + 1600 * tau1**3)
            + tau1**2 * (-720 * qf + 120 * q1 + 600 * q0) + (q0 - q1) * (300 * tau1 - 200))
        pi = 1 / (TF**5 * tau1**5 * (1 - tau1)**5) * (
            (qf - q0) * (120 * tau1**5 - 300 * tau1**4 + 200 * tau1**3) - 20 * (q1 - q0))
        if t <= t1:
            x = TF**5 / 720 * (pi * (tau1**4 * (15 * tau**4 - 30 * tau**3)
                                     + tau1**3 * (80 * tau**3 - 30 * tau**4)
                                     - 60 * tau**3 * tau1**2 + 30 * tau**4 * tau1 - 6 * tau**5)
                               + c * (15 * tau**4 - 10 * tau**3 - 6 * tau**5)) + q0
        else:
            x = TF**5 / 720 * (pi * (tau1**4 * (15 * tau**4 - 30 * tau**3 + 30 * tau - 15)
                                     + tau1**3 * (80 * tau**3 - 30 * tau**4 - 60 * tau**2 + 10))
                               + c * (15 * tau**4 - 10 * tau**3 - 6 * tau**5 + 1)) + qf
        out.append(x)
    return np.array(out)


def independent_piecewise_quintic(points, times):
    """Power-basis quintics in absolute time, one linear solve: p, v, a fixed at the ends
    (rest), position at each via point, C1..C4 across it (Flash–Hogan interior point)."""
    m = len(times) - 1
    dim = points.shape[1]
    A = np.zeros((6 * m, 6 * m))
    b = np.zeros((6 * m, dim))

    def row(t, k):
        r = np.zeros(6)
        for j in range(k, 6):
            r[j] = math.perm(j, k) * t ** (j - k)
        return r
    i = 0
    for k in range(3):
        A[i, 0:6] = row(times[0], k); b[i] = points[0] if k == 0 else 0; i += 1
        A[i, 6 * (m - 1):] = row(times[-1], k); b[i] = points[-1] if k == 0 else 0; i += 1
    for s in range(m - 1):
        t = times[s + 1]
        A[i, 6 * s:6 * s + 6] = row(t, 0); b[i] = points[s + 1]; i += 1
        A[i, 6 * (s + 1):6 * s + 12] = row(t, 0); b[i] = points[s + 1]; i += 1
        for k in range(1, 5):
            A[i, 6 * s:6 * s + 6] = row(t, k)
            A[i, 6 * (s + 1):6 * s + 12] = -row(t, k); i += 1
    c = np.linalg.solve(A, b).reshape(m, 6, dim)

    def position(t):
        s = min(int(np.searchsorted(times, t, side='right')) - 1, m - 1)
        return row(t, 0) @ c[s]
    return position


def test_via_point_solution_matches_eqs_2_4_to_2_11_of_appendix_b():
    tr = ViaPointMinimumJerk([X0, Y0], [X1, Y1], [XF, YF], TF, t_via=0.25)
    for t in np.linspace(0.0, TF, 51):
        np.testing.assert_allclose(tr.sample(t)[0], eqs_2_4_to_2_11(t, 0.25), atol=1e-12)


def test_several_via_points_match_an_independent_piecewise_quintic_solve_c4():
    pts = np.array([[0.0, 0.0], [0.1, 0.05], [0.15, -0.02], [0.3, 0.0]])
    times = np.array([0.0, 0.3, 0.75, 1.2])
    tr = ViaPointMinimumJerk(pts[0], pts[1:-1], pts[-1], 1.2, t_via=times[1:-1])
    ref = independent_piecewise_quintic(pts, times)
    for t in np.linspace(0.0, 1.2, 61):
        np.testing.assert_allclose(tr.sample(t)[0], ref(t), atol=1e-11)
    for tv, pv in zip(times[1:-1], pts[1:-1]):
        np.testing.assert_allclose(tr.sample(tv)[0], pv, atol=1e-12)
        # C4: derivatives 1..4 agree from both sides (segment polynomials evaluated at the join)
        left = tr._evaluate(np.array([tv - 1e-12]), 3)
        right = tr._evaluate(np.array([tv + 1e-12]), 3)
        for k in range(1, 4):
            np.testing.assert_allclose(left[k], right[k], rtol=1e-6, atol=1e-7)


def jerk_cost_by_quadrature(tr, n=4000):
    """1/2 int |jerk|^2 dt (eq. 2.1): midpoint rule on the jerk from finite differences
    of the sampled acceleration (independent of the closed-form cost)."""
    ts = np.linspace(0.0, tr.duration, n + 1)
    acc = tr.sample_many(ts)[2]
    j = np.diff(acc, axis=0) / np.diff(ts)[:, None]
    return 0.5 * float(np.sum((j ** 2).sum(axis=1) * np.diff(ts)))


def test_optimised_via_time_minimises_the_jerk_cost():
    start, via, goal = [0.0, 0.0], [0.05, 0.12], [0.25, 0.02]
    tr = ViaPointMinimumJerk(start, via, goal, 1.0)
    t1 = float(tr.t_via[0])
    best = jerk_cost_by_quadrature(tr)
    assert tr.jerk_cost() == pytest.approx(best, rel=1e-3)
    for dt in (-0.02, -0.005, 0.005, 0.02):
        other = ViaPointMinimumJerk(start, via, goal, 1.0, t_via=t1 + dt)
        assert jerk_cost_by_quadrature(other) > best


def test_appendix_b_optimal_via_time_is_the_thesis_0_243349_s():
    """The thesis (sec. 4.2): t1 = 0.243349 (s: tf = 0.5 s, App. B rounds it to t1 = 0.25 s,
    tau1 = t1/tf = 0.5); the cost (2.1) for the App. B points is minimal at t1 = 0.24335 s."""
    tr = ViaPointMinimumJerk([X0, Y0], [X1, Y1], [XF, YF], TF)
    assert tr.t_via[0] == pytest.approx(0.243349, abs=2e-6)
    rounded = ViaPointMinimumJerk([X0, Y0], [X1, Y1], [XF, YF], TF, t_via=0.25)
    assert tr.jerk_cost() < rounded.jerk_cost() < 1.02 * tr.jerk_cost()     # the rounding costs ~1.3 %


def test_several_via_times_are_optimised_jointly():
    pts = np.array([[0.0, 0.0], [0.1, 0.05], [0.15, -0.02], [0.3, 0.0]])
    tr = ViaPointMinimumJerk(pts[0], pts[1:-1], pts[-1], 1.2)
    base = tr.jerk_cost()
    for d in ([0.01, 0.0], [-0.01, 0.0], [0.0, 0.01], [0.0, -0.01]):
        other = ViaPointMinimumJerk(pts[0], pts[1:-1], pts[-1], 1.2, t_via=tr.t_via + d)
        assert other.jerk_cost() > base


def test_via_times_out_of_order_are_rejected():
    with pytest.raises(TrajectoryError, match='increase'):
        ViaPointMinimumJerk([0.0], [[0.5], [0.7]], [1.0], 1.0, t_via=[0.6, 0.4])


# ---------------------------------------------------------------- Fitts
def test_fitts_law_eq_2_12():
    assert fitts_duration(0.2525, a=0.1, b=0.1, w=0.05) == pytest.approx(
        0.1 + 0.1 * math.log2(2 * 0.2525 / 0.05))
    # a reach shorter than half the target: zero index of difficulty
    assert fitts_duration(0.001, a=0.2, b=0.3, w=0.01) == pytest.approx(0.2)
    assert fitts_duration(0.0, a=0.0, b=0.3, w=0.01) == pytest.approx(0.05)   # floor
    with pytest.raises(TrajectoryError):
        fitts_duration(math.nan, a=0.2, b=0.3, w=0.01)


# ---------------------------------------------------------------- log-cosh
def test_logcosh_starts_and_ends_exactly_at_rest_and_follows_the_thesis_curve():
    start, goal = np.array([0.0, 0.39, 0.1]), np.array([0.02, 0.40, 0.2])
    tr = LogCosh(start, goal, 2.0)
    p, v, a = tr.sample(0.0)
    np.testing.assert_array_equal(p, start)
    np.testing.assert_allclose([v, a], 0.0, atol=1e-15)
    p, v, a = tr.sample(2.0)
    np.testing.assert_allclose(p, goal, atol=1e-15)
    np.testing.assert_allclose([v, a], 0.0, atol=1e-13)
    # the thesis formula, straight from seed 004 (Sd = 1)
    ve, ae, d = tr.ve, tr.ae, tr.delta
    ts = np.linspace(0.0, 2.0, 401)
    S = 0.5 + ve**2 / (4 * ae) * np.log(np.cosh(2 * ae * ts / ve - d)
                                         / np.cosh(2 * ae * ts / ve - d - 2 * ae / ve**2))
    s = (tr.sample_many(ts)[0] - start) / (goal - start)
    np.testing.assert_allclose(s, S[:, None] * np.ones(3), atol=2e-3)
    _, V, A = tr.sample_many(ts)
    # the end corrections (order e^{-2 delta}) move the peaks by ~0.1 %
    assert np.all(np.abs(V[:, 0] / (goal - start)[0]) <= ve * 1.002)
    assert np.all(np.abs(A[:, 0] / (goal - start)[0]) <= ae * 1.002)


def test_logcosh_from_limits_respects_them():
    tr = LogCosh([0.0, 0.0], [0.05, -0.02], max_velocity=[0.03, 0.03], max_acceleration=[0.1, 0.1])
    _, V, A = tr.sample_many(np.linspace(0.0, tr.duration, 2001))
    assert np.all(np.abs(V) <= 0.03 * (1 + 1e-9)) and np.all(np.abs(A) <= 0.1 * (1 + 1e-6))


# ---------------------------------------------------------------- S-curve (Ruckig)
def assert_within(tr, vmax, amax, jmax, *, n=2001, slack=1e-6):
    if tr.duration < 1e-9:                # at the goal (a denormal start state gives a
        return                            # denormal duration: no time step to difference)
    ts = np.linspace(0.0, tr.duration, n)
    _, V, A = tr.sample_many(ts)
    assert np.all(np.abs(V) <= vmax * (1 + slack) + 1e-12)
    assert np.all(np.abs(A) <= amax * (1 + slack) + 1e-12)
    # jerk from the sampled acceleration (independent of the planner's jerk)
    J = np.diff(A, axis=0) / np.diff(ts)[:, None]
    assert np.all(np.abs(J) <= jmax * (1 + 1e-3) + 1e-9)


def test_scurve_respects_every_limit_and_all_axes_finish_together():
    vmax, amax, jmax = np.array([0.03, 0.03, 0.3]), np.array([0.1, 0.1, 1.0]), np.array([1.0, 1.0, 10.0])
    start, goal = np.array([0.0, 0.39, 0.1]), np.array([0.04, 0.385, 0.3])
    tr = SCurve(start, goal, vmax, amax, jmax)
    assert tr.uses_ruckig and tr.fallback is None
    assert_within(tr, vmax, amax, jmax)
    np.testing.assert_allclose(tr.sample(tr.duration)[0], goal, atol=1e-12)
    # synchronised: every moving axis is still moving just before the end
    ts = np.linspace(0.9 * tr.duration, 0.999 * tr.duration, 50)
    _, V, _ = tr.sample_many(ts)
    assert np.all(np.abs(V).max(axis=0) > 0)
    # ... and the slowest axis alone takes exactly as long (time-optimal)
    alone = [SCurve(start[i:i + 1], goal[i:i + 1], vmax[i:i + 1], amax[i:i + 1], jmax[i:i + 1]).duration
             for i in range(3)]
    assert tr.duration == pytest.approx(max(alone), rel=1e-9)


def test_scurve_from_a_moving_start_is_continuous():
    v0, a0 = np.array([0.01, -0.02, 0.1]), np.array([0.05, 0.0, -0.5])
    tr = SCurve([0.0, 0.39, 0.1], [0.02, 0.40, 0.2], [0.03, 0.03, 0.3], [0.1, 0.1, 1.0],
                [1.0, 1.0, 10.0], v0=v0, a0=a0)
    p, v, a = tr.sample(0.0)
    np.testing.assert_allclose(v, v0, atol=1e-12)
    np.testing.assert_allclose(a, a0, atol=1e-12)


# Inputs on which ruckig 0.19.4 fails (found with hypothesis, see the property test below).
# Ruckig refuses any plan longer than 7.6e3 s (its numerical limit: result -101,
# ErrorTrajectoryDuration, in ruckig's calculator). Both inputs need far longer, by the bounds
# below, so no retry (limits relaxed by <= 1e-3 only lengthen the plan, synchronisation off
# does not shorten the slowest axis) can succeed: the minimum-jerk fallback takes over.
RUCKIG_MAX_DURATION_S = 7.6e3


def _stop_and_return_s(v0, amax):
    """Shortest time (s) for an axis at speed ``v0`` to come back to its start at rest, with
    ``|a| <= amax`` (jerk ignored: a lower bound): brake at ``amax`` over ``v0 / amax``,
    which carries it ``v0^2 / (2 amax)`` away, then cover that distance rest to rest in at
    least ``2 sqrt(d / amax)`` (bang-bang)."""
    d = v0 * v0 / (2 * amax)
    return v0 / amax + 2 * math.sqrt(d / amax)


def _overshoot_then_crawl_back_s(start, goal, vmax, jmax, a0):
    """Lower bound (s) for an axis that starts with ``v0 >= 0`` and acceleration ``a0 > 0`` and
    must end at ``goal < start + a0^3 / (3 jmax^2)``: with ``|jerk| <= jmax`` the acceleration
    is >= ``a0 - jmax t`` until ``a0 / jmax``, so the axis first travels at least
    ``a0^3 / (3 jmax^2)`` forward; once braked back within its limits it returns at no
    more than ``vmax``."""
    ahead = a0 ** 3 / (3 * jmax * jmax) - (goal - start)
    return a0 / jmax + ahead / vmax


RUCKIG_FAILURES = [
    # axis 2 moves at its speed limit 4 m/s with 0.001 m/s^2 to brake and must return to
    # its start: >= 4000 s of braking, 8000 m away, then >= 5657 s back (9657 s).
    # Ruckig answers -101, which the binding's enum lacks: it raises ValueError.
    pytest.param(
        dict(start=[0.0, 0.0], goal=[0.0, 0.0], vmax=[1.0, 4.0], amax=[1.0, 0.001],
             jmax=[1.0, 1.0], v0=[0.0, 4.0], a0=[0.0, 0.0]),
        'Ruckig: -101 is not a valid Result', lambda: _stop_and_return_s(4.0, 0.001),
        id='duration-beyond-ruckig-limit'),
    # a large initial acceleration with a tiny jerk limit: 827 s before the acceleration
    # can be zero, ~1.9e6 m ahead, then back at 0.01 m/s (~1.9e8 s). Ruckig fails even
    # earlier, in its step 1 (time-optimal profile per axis): RuckigError "error in step 1".
    pytest.param(
        dict(start=[0.32271772871503335], goal=[-0.08293065729113347], vmax=[0.01],
             amax=[9.246750331443113], jmax=[0.01], v0=[5.960464477539063e-10],
             a0=[8.265176432506733]),
        '[ruckig] error in step 1',
        lambda: _overshoot_then_crawl_back_s(0.32271772871503335, -0.08293065729113347,
                                             0.01, 0.01, 8.265176432506733),
        id='initial-acceleration-with-tiny-jerk'),
]


@pytest.mark.parametrize('case, ruckig_error, shortest_s', RUCKIG_FAILURES)
def test_scurve_never_raises_on_ruckig_failures_and_the_fallback_reaches_the_goal(
        case, ruckig_error, shortest_s):
    assert shortest_s() > RUCKIG_MAX_DURATION_S          # beyond what Ruckig may plan ...
    tr = SCurve(case['start'], case['goal'], case['vmax'], case['amax'], case['jmax'],
                v0=case['v0'], a0=case['a0'])
    # ... so every attempt failed (each relaxation, with and without synchronisation) and
    # the minimum-jerk fallback took over, naming Ruckig's error
    assert not tr.uses_ruckig
    assert tr.attempts > 1 and len(tr.retries) == tr.attempts
    assert set(tr.retries) == {tr.fallback} and tr.fallback.startswith(ruckig_error)
    p, v, a = tr.sample(tr.duration)
    np.testing.assert_allclose(p, case['goal'], atol=1e-9)
    np.testing.assert_allclose([v, a], 0.0, atol=1e-9)


@pytest.mark.xfail(strict=True, reason='minimum_jerk_within gives up at 1e4 s and returns a '
                   'plan that exceeds the acceleration limit (issue for brace_control.trajectory)')
def test_the_fallback_keeps_the_limits_when_a_slow_enough_plan_exists():
    """Axis 2 of the first Ruckig failure: a plan within every limit exists (9657 s, by
    ``_stop_and_return_s``), so the fallback must not exceed ``amax`` (0.001 m/s^2)."""
    case = RUCKIG_FAILURES[0].values[0]
    tr = SCurve(case['start'], case['goal'], case['vmax'], case['amax'], case['jmax'],
                v0=case['v0'], a0=case['a0'])
    assert tr.duration >= _stop_and_return_s(4.0, 0.001)
    assert_within(tr, np.array(case['vmax']), np.array(case['amax']), np.array(case['jmax']),
                  n=20001)


axis = st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(-1, 1), st.floats(-1, 1),
                 st.floats(1e-2, 10), st.floats(1e-2, 10), st.floats(1e-2, 10))


@PROPS
@given(st.lists(axis, min_size=1, max_size=3))
def test_scurve_property_never_raises_and_respects_limits_from_feasible_states(axes):
    p0, v0f, a0f, pf, vmax, amax, jmax = map(np.array, zip(*axes))
    a0 = a0f * amax
    # a state the limits can stop from: |v0| plus the velocity gained while the
    # acceleration ramps down at max jerk stays within vmax
    v0 = v0f * vmax * 0.5
    assume(np.all(np.abs(v0 + a0 * np.abs(a0) / (2 * jmax)) <= vmax)
           and np.all(np.abs(v0) + a0 ** 2 / (2 * jmax) <= vmax))
    tr = SCurve(p0, pf, vmax, amax, jmax, v0=v0, a0=a0)
    assert np.all(np.isfinite(tr.sample(tr.duration / 2)[0]))
    np.testing.assert_allclose(tr.sample(tr.duration)[0], pf, atol=1e-8)
    if tr.uses_ruckig:
        assert_within(tr, vmax, amax, jmax, n=801)


@PROPS
@given(st.lists(axis, min_size=1, max_size=3))
def test_scurve_property_never_raises_even_where_ruckig_fails(axes):
    # any start within the velocity and acceleration limits, including states from which
    # the limits cannot be kept (where Ruckig raises or returns error codes)
    p0, v0f, a0f, pf, vmax, amax, jmax = map(np.array, zip(*axes))
    tr = SCurve(p0, pf, vmax, amax, jmax, v0=v0f * vmax, a0=a0f * amax)
    p, v, a = tr.sample(tr.duration)
    np.testing.assert_allclose(p, pf, atol=1e-6 * max(1.0, tr.duration))
    np.testing.assert_allclose([v, a], 0.0, atol=1e-6)


# ---------------------------------------------------------------- planning with limits
def dense_actuator_speed(mech, tr, n=2000):
    ts = np.linspace(0.0, tr.duration, n)
    P, V, _ = tr.sample_many(ts)
    return max(float(np.max(np.abs(mech.jacobian(p) @ v))) for p, v in zip(P, V))


@pytest.mark.parametrize('profile', list(Profile))
def test_plan_slows_a_fast_motion_down_to_the_actuator_speed(mech, limits, profile):
    goal = HOME + [0.03, 0.0, 0.08]
    plan = plan_motion(mech, HOME, goal, profile, limits, duration=0.3 if profile != Profile.SCURVE else None)
    assert dense_actuator_speed(mech, plan.trajectory) <= limits.actuator_max_velocity * 1.01
    np.testing.assert_allclose(plan.trajectory.sample(plan.duration)[0], goal, atol=1e-9)
    if profile is not Profile.SCURVE:
        assert plan.stretch > 1.0 and plan.duration > 0.3


def test_plan_without_duration_uses_fitts_law(mech, limits):
    goal = HOME + [0.005, 0.0, 0.0]
    fitts = FittsLaw(a=0.2, b=0.3, w=0.01)
    plan = plan_motion(mech, HOME, goal, Profile.MINIMUM_JERK, limits, fitts=fitts, fitts_axes=(0, 1))
    assert plan.duration == pytest.approx(0.2 + 0.3 * math.log2(2 * 0.005 / 0.01))


def test_unreachable_goal_is_rejected_naming_the_actuator(mech, limits):
    with pytest.raises(PlanRejected) as err:
        plan_motion(mech, HOME, HOME + [0.0, 0.2, 0.0], Profile.MINIMUM_JERK, limits)
    assert err.value.violation is Violation.STROKE
    assert 'actuator a' in err.value.reason and 'goal' in err.value.reason


def test_path_through_a_singularity_is_rejected_before_anything_moves(mech, limits):
    # theta = 0 is singular for the collinear 3-RPR; going from +0.1 to -0.1 crosses it
    with pytest.raises(PlanRejected) as err:
        plan_motion(mech, HOME, [0.0, 0.39, -0.1], Profile.SCURVE, limits)
    assert err.value.violation is Violation.SINGULARITY
    assert 'singular' in err.value.reason


def test_path_leaving_the_stroke_between_reachable_ends_is_rejected(mech, limits):
    # start, via point and goal are all reachable; passing the via point early (0.5 s of
    # 4 s) the path overshoots it and a3 would leave its stroke
    via = HOME + [0.0, 0.025, 0.0]
    mech.inverse(via)
    with pytest.raises(PlanRejected) as err:
        plan_motion(mech, HOME, HOME, Profile.MINIMUM_JERK, limits,
                    via=[via], t_via=[0.5], duration=4.0)
    assert err.value.violation is Violation.STROKE
    assert err.value.reason.startswith('path rejected at t = ') and 'actuator a3' in err.value.reason
    # the same via point at 1.5 s is fine
    plan_motion(mech, HOME, HOME, Profile.MINIMUM_JERK, limits, via=[via], t_via=[1.5], duration=4.0)


@pytest.mark.parametrize('bad', [[math.nan, 0.39, 0.1], [0.0, math.inf, 0.1], [0.0, 0.39]])
def test_non_finite_or_short_goal_is_rejected(mech, limits, bad):
    with pytest.raises(PlanRejected, match='bad goal'):
        plan_motion(mech, HOME, bad, Profile.MINIMUM_JERK, limits)


@PROPS
@given(st.floats(-0.06, 0.06), st.floats(-0.06, 0.06), st.floats(-0.3, 0.3),
       st.sampled_from(list(Profile)), st.one_of(st.none(), st.floats(0.05, 3.0)))
def test_plan_property_random_goals_never_raise_anything_but_a_rejection(mech, limits, dx, dy, dth,
                                                                         profile, duration):
    goal = HOME + [dx, dy, dth]
    try:
        plan = plan_motion(mech, HOME, goal, profile, limits, duration=duration)
    except PlanRejected as exc:
        assert exc.reason
        return
    assert dense_actuator_speed(mech, plan.trajectory, n=400) <= limits.actuator_max_velocity * 1.02
    for p in plan.trajectory.sample_many(np.linspace(0, plan.duration, 50))[0]:
        mech.inverse(p)                                   # raises if outside the stroke


# ---------------------------------------------------------------- runner: goals and outcomes
TOL = np.array([0.002, 0.002, 0.005])


def make_runner(mech, limits, profile, *, lookahead=0.1, enabled=True):
    run = TrajectoryRunner(mech, limits, profile=profile, fitts=FittsLaw(), fitts_axes=(0, 1),
                           lookahead=lookahead, pose_tolerance=TOL, settle_time=0.5,
                           report_timeout=1.0)
    if enabled:
        # the driver's latched state: enabled, the command anchored at IK(HOME) (paper eq. 3)
        run.on_driver_state(True, 'enabled', lumbar_eq3(HOME), executing=False, now=0.0)
    return run


def submit(run, goal_id, target, now, tag):
    """Plan and commit as the node does (the node's planner thread)."""
    req = GoalRequest(goal_id, np.asarray(target, float))
    start = run.start_state(now)
    try:
        plan = run.plan(req, start)
    except PlanRejected as exc:
        return [GoalEventLike(goal_id, GoalState.REJECTED, exc.reason)], None
    return run.commit(req, plan, start, tag=tag, now=now), plan


class GoalEventLike:
    def __init__(self, goal_id, state, reason):
        self.goal_id, self.state, self.reason = goal_id, state, reason


def test_the_hold_is_where_the_driver_anchored_the_command(mech, limits):
    """Enable anchors the command at the drives' positions: the first motion starts at
    FK of them (oracle: the paper's eq. 3 gives the lengths of HOME)."""
    run = make_runner(mech, limits, Profile.MINIMUM_JERK)
    start = run.start_state(0.0)
    assert start.source == 'hold'
    np.testing.assert_allclose(start.state.p, HOME, atol=1e-9)
    assert not np.any(start.state.v) and not np.any(start.state.a)


@pytest.mark.parametrize('profile', list(Profile))
def test_preemption_starts_from_the_handed_out_motion_at_its_takeover(mech, limits, profile):
    run = make_runner(mech, limits, profile)
    events, plan1 = submit(run, '1', HOME + [0.02, 0.01, 0.05], 0.0, tag=1)
    assert [e.state for e in events] == [GoalState.ACCEPTED]
    t0_1 = 0.1                                          # lookahead after 0.0
    now = 0.4
    start = run.start_state(now)
    assert start.source == 'motion' and start.t0 == pytest.approx(now + 0.1)
    p, v, a = plan1.trajectory.sample(start.t0 - t0_1)
    assert np.linalg.norm(v) > 0                        # preempted while moving
    events, plan2 = submit(run, '2', HOME + [-0.01, 0.0, 0.12], now, tag=2)
    assert [(e.goal_id, e.state) for e in events] == [('1', GoalState.CANCELLED),
                                                     ('2', GoalState.ACCEPTED)]
    q, w, b = plan2.trajectory.sample(0.0)
    np.testing.assert_allclose(q, p, atol=1e-12)
    np.testing.assert_allclose(w, v, atol=1e-10)
    np.testing.assert_allclose(b, a, atol=1e-8)


def test_success_needs_the_motion_finished_and_the_estimate_at_the_goal(mech, limits):
    run = make_runner(mech, limits, Profile.MINIMUM_JERK)
    goal = HOME + [0.0, 0.01, 0.05]
    submit(run, '1', goal, 0.0, tag=7)
    # an estimate at the goal before the driver reported the end does not count
    assert run.on_estimate(goal, stamp=0.5, now=0.5) == []
    assert run.on_execution(7, 'started', '', None, now=0.1) == []
    assert run.on_execution(7, 'finished', '', lumbar_eq3(goal), now=2.0) == []
    assert run.on_estimate(goal + [0.0, 0.0, 0.5], stamp=1.9, now=2.0) == []   # older than the end
    # inside the tolerance (2 mm, 2 mm, 0.3 deg), but it has to stay there for 50 ms
    assert run.on_estimate(goal + [0.0019, -0.001, 0.004], stamp=2.01, now=2.01) == []
    assert run.on_estimate(goal + [0.0021, -0.001, 0.004], stamp=2.03, now=2.03) == []   # out again
    assert run.on_estimate(goal + [0.0015, -0.001, 0.004], stamp=2.04, now=2.04) == []
    assert run.on_estimate(goal + [0.0015, -0.001, 0.004], stamp=2.08, now=2.08) == []   # 40 ms inside
    events = run.on_estimate(goal + [0.0015, -0.001, 0.004], stamp=2.09, now=2.09)
    assert [(e.goal_id, e.state) for e in events] == [('1', GoalState.SUCCEEDED)]
    assert events[0].values['final_error'] == pytest.approx([0.0015, 0.001, 0.004], abs=1e-12)
    np.testing.assert_allclose(run.start_state(3.0).state.p, goal, atol=1e-12)   # holds the goal


def test_a_ring_resting_at_the_edge_of_the_tolerance_is_not_judged_on_the_noise(mech, limits):
    """The true ring rests 2.0024 mm off in x (tolerance 2 mm): its estimate scatters around
    that by a few microns, and a run of noisy samples inside for 50 ms is no success: the
    window's mean plus twice its scatter must be inside (the truth may be just outside).
    A ring that then settles well inside succeeds."""
    run = make_runner(mech, limits, Profile.MINIMUM_JERK)
    goal = HOME + [0.0, 0.01, 0.05]
    submit(run, '1', goal, 0.0, tag=4)
    run.on_execution(4, 'started', '', None, now=0.1)
    run.on_execution(4, 'finished', '', lumbar_eq3(goal), now=2.0)
    noisy = [0.00199, 0.001998, 0.001994, 0.001999, 0.001992, 0.001997, 0.001993, 0.001999]
    for k, dx in enumerate(noisy):                     # 70 ms inside, every 10 ms
        t = 2.01 + 0.01 * k
        assert run.on_estimate(goal + [dx, 0.0, 0.0], stamp=t, now=t) == []
    events = []
    for k in range(8):                                 # the ring comes to rest 1.2 mm off
        t = 2.09 + 0.01 * k
        events += run.on_estimate(goal + [0.0012, 0.0, 0.0], stamp=t, now=t)
    assert [(e.goal_id, e.state) for e in events] == [('1', GoalState.SUCCEEDED)]


#: m per encoder count of the lumbar brace's actuators (YAML: screw_lead / encoder_counts_per_rev)
LUMBAR_COUNT = 0.001 / 8192


def _count_sigma(pose) -> np.ndarray:
    """Oracle: 1-sigma per pose coordinate from one count of reading and one of homing per
    leg (uniform: res^2/12 each), through paper eq. 3's Jacobian by central differences:
    Sigma = (res^2 / 6) (J^T J)^-1."""
    h = 1e-7
    jac = np.column_stack([(lumbar_eq3(pose + dp) - lumbar_eq3(pose - dp)) / (2 * h)
                           for dp in np.eye(3) * h])
    return np.sqrt(np.diag(np.linalg.inv(jac.T @ jac)) * LUMBAR_COUNT ** 2 / 6)


def test_a_ring_inside_by_less_than_the_encoders_resolve_is_no_success(mech, limits):
    """The lumbar brace's legs are nearly parallel: one encoder count (0.12 um) of leg is
    tens of microns of x. An estimate resting inside the tolerance by less than twice that
    is no success (the true ring may be just outside, CI saw it 2.0024 mm off); the abort
    says so. By three times that it is a success."""
    goal = HOME + [0.0, 0.01, 0.05]
    sigma = _count_sigma(goal)
    assert sigma[0] > 10e-6                        # x: amplified by the near-parallel legs
    for k, (dx, outcome) in enumerate([(TOL[0] - 1.5 * sigma[0], GoalState.ABORTED),
                                       (TOL[0] - 3.0 * sigma[0], GoalState.SUCCEEDED)]):
        run = make_runner(mech, limits, Profile.MINIMUM_JERK)
        run.actuator_resolution = LUMBAR_COUNT
        np.testing.assert_allclose(run.resolution_sigma(goal), sigma, rtol=1e-4)
        submit(run, '1', goal, 0.0, tag=4)
        run.on_execution(4, 'started', '', None, now=0.1)
        run.on_execution(4, 'finished', '', lumbar_eq3(goal), now=2.0)
        events = []
        for i in range(56):                        # at rest there, no scatter, past the settle time
            t = 2.01 + 0.01 * i
            events += run.on_estimate(goal + [dx, 0.0, 0.0], stamp=t, now=t)
        events += run.check(2.6)
        assert [(e.goal_id, e.state) for e in events] == [('1', outcome)], (k, events)
        if outcome is GoalState.ABORTED:
            assert 'inside the tolerance by less than the estimate resolves' in events[0].reason
            assert f'x {2 * sigma[0] * 1e3:.2f} mm' in events[0].reason, events[0].reason


def test_an_abort_inside_the_tolerance_says_what_the_confirmation_saw(mech, limits):
    """Run 1002 (vendor drives, cia402_slave): goal aborted 'x off by 0.48 mm (tolerance 2.00
    mm) ... inside the tolerance by less than the estimate resolves (2 sigma: x 0.02 mm)': a
    reason that could not be true. The abort says what kept the estimates from a success:
    estimates scattered inside the tolerance (|mean| + 2 sigma of the last 0.05 s beyond it,
    computed here from the estimates sent), or a run inside too short for the confirmation
    before the settle time ran out."""
    goal = HOME + [0.0, 0.01, 0.05]

    def run_with(errors_x, stamps):
        run = make_runner(mech, limits, Profile.MINIMUM_JERK)
        submit(run, '1', goal, 0.0, tag=4)
        run.on_execution(4, 'started', '', None, now=0.1)
        run.on_execution(4, 'finished', '', lumbar_eq3(goal), now=2.0)
        events = []
        for dx, t in zip(errors_x, stamps):
            events += run.on_estimate(goal + [dx, 0.0, 0.0], stamp=t, now=t)
        events += run.check(2.6)
        assert [(e.goal_id, e.state) for e in events] == [('1', GoalState.ABORTED)], events
        return events[0].reason

    # scattered: 0.2 and 1.9 mm in turn, 10 ms apart, all inside the 2 mm
    stamps = [2.01 + 0.01 * i for i in range(56)]
    xs = [0.0002 if i % 2 else 0.0019 for i in range(56)]
    why = run_with(xs, stamps)
    window = np.array(xs[-6:])                      # the last 0.05 s: six estimates
    judged = abs(window.mean()) + 2.0 * window.std()
    assert judged > TOL[0]                          # premise
    assert 'by less than the estimates scattered' in why, why
    assert f'x {judged * 1e3:.2f} mm' in why, why
    assert 'resolves' not in why
    # outside until 0.53 s after the motion, then inside: 2.53 .. 2.56, 0.03 s of it when the
    # settle time (0.5 s, plus the confirmation's 0.05 s once inside) has run out
    xs = [0.003 if t < 2.53 - 1e-9 else 0.0005 for t in stamps]
    why = run_with(xs, stamps)
    assert 'inside the tolerance for 0.030 s of estimates at most, not the 0.05 s' in why, why
    assert '(56 estimates since the motion finished)' in why, why


def test_the_settle_time_runs_on_the_estimates_stamps_not_on_their_arrival(mech, limits):
    """On a loaded host the estimates arrive late: a platform at the goal whose estimates
    (stamped 10 ms apart from the motion's end) reach the runner 0.8 s late succeeds, and
    is not aborted at the end of the settle time by the runner's clock. Estimates that stop
    coming end it ``report_timeout`` after the settle time, saying none came."""
    run = make_runner(mech, limits, Profile.MINIMUM_JERK)
    goal = HOME + [0.0, 0.01, 0.05]
    submit(run, '1', goal, 0.0, tag=6)
    run.on_execution(6, 'started', '', None, now=0.1)
    run.on_execution(6, 'finished', '', lumbar_eq3(goal), now=2.0)
    assert run.check(2.6) == []                        # 0.6 s by the clock, no estimate yet
    events = []
    for k in range(8):                                 # stamped 2.01.., arriving at 2.81..
        events += run.on_estimate(goal + [0.0005, 0.0, 0.0], stamp=2.01 + 0.01 * k, now=2.81 + 0.01 * k)
    assert [(e.goal_id, e.state) for e in events] == [('1', GoalState.SUCCEEDED)]

    run = make_runner(mech, limits, Profile.MINIMUM_JERK)
    submit(run, '2', goal, 0.0, tag=7)
    run.on_execution(7, 'started', '', None, now=0.1)
    run.on_execution(7, 'finished', '', lumbar_eq3(goal), now=2.0)
    assert run.check(3.4) == []                        # within settle (0.5) + report time-out (1)
    events = run.check(3.6)
    assert [(e.goal_id, e.state) for e in events] == [('2', GoalState.ABORTED)]
    assert 'no pose estimate' in events[0].reason


def test_a_platform_that_does_not_follow_is_aborted_saying_by_how_much(mech, limits):
    run = make_runner(mech, limits, Profile.MINIMUM_JERK)
    goal = HOME + [0.015, 0.0, 0.0]
    submit(run, '1', goal, 0.0, tag=3)
    run.on_execution(3, 'started', '', None, now=0.1)
    run.on_execution(3, 'finished', '', lumbar_eq3(goal), now=2.0)
    ring = HOME + [0.0001, 0.0, 0.0]                    # the ring stayed home (lateral)
    for k in range(9):
        assert run.on_estimate(ring, stamp=2.0 + 0.05 * k, now=2.0 + 0.05 * k) == []
    assert run.check(2.4) == []                        # still within the settle time
    for k in range(9, 12):                             # estimates past the settle time (0.5 s)
        assert run.on_estimate(ring, stamp=2.0 + 0.05 * k, now=2.0 + 0.05 * k) == []
    events = run.check(2.6)
    assert [(e.goal_id, e.state) for e in events] == [('1', GoalState.ABORTED)]
    assert 'did not follow' in events[0].reason and 'x off by 14.90 mm' in events[0].reason


def test_goals_are_rejected_while_the_drives_are_not_enabled(mech, limits):
    run = make_runner(mech, limits, Profile.MINIMUM_JERK, enabled=False)
    events = run.admit('1')
    assert [e.state for e in events] == [GoalState.REJECTED]
    assert 'not enabled' in events[0].reason and 'no driver state' in events[0].reason
    run.on_driver_state(False, 'protective stop: a2: force limit', lumbar_eq3(HOME),
                        executing=False, now=0.0)
    assert 'force limit' in run.admit('2')[0].reason


def test_a_stop_aborts_with_the_drivers_reason_and_the_hold_is_where_it_stopped(mech, limits):
    run = make_runner(mech, limits, Profile.MINIMUM_JERK)
    goal = HOME + [0.0, 0.02, 0.05]
    _, plan = submit(run, '1', goal, 0.0, tag=5)
    run.on_execution(5, 'started', '', None, now=0.1)
    where = plan.trajectory.sample(0.4)[0]             # where the motion was braked to
    events = run.on_execution(5, 'stopped', 'halt requested', lumbar_eq3(where), now=0.6)
    assert [(e.goal_id, e.state) for e in events] == [('1', GoalState.ABORTED)]
    assert 'halt requested' in events[0].reason
    np.testing.assert_allclose(run.start_state(1.0).state.p, where, atol=1e-9)


def test_a_refused_preemption_leaves_the_model_on_the_motion_that_goes_on(mech, limits):
    """The driver refuses motion 2 (a splice too far from its command: "the running motion
    continues") while motion 1 still runs: goal 2 is aborted with the driver's reason and
    the next goal starts from motion 1's state at its takeover (the motion the driver goes
    on with), not from where the refusal found the command. Motion 3, planned from motion 2
    before its refusal came, is refused too; the model stays on motion 1."""
    run = make_runner(mech, limits, Profile.MINIMUM_JERK)
    _, plan1 = submit(run, '1', HOME + [0.02, 0.01, 0.05], 0.0, tag=1)
    run.on_execution(1, 'started', '', None, now=0.1)
    submit(run, '2', HOME + [-0.01, 0.0, 0.12], 0.2, tag=2)
    submit(run, '3', HOME + [0.0, 0.01, 0.05], 0.25, tag=3)
    at_refusal = plan1.trajectory.sample(0.3 - 0.1)[0]           # the command, still moving
    why = 'its start is 9.1 mm from the command on joint 2; the running motion continues'
    events = run.on_execution(2, 'rejected', why, lumbar_eq3(at_refusal), now=0.3)
    assert events == []                                           # goal 2 was already cancelled by 3
    events = run.on_execution(3, 'rejected', why, lumbar_eq3(at_refusal), now=0.36)
    assert [(e.goal_id, e.state) for e in events] == [('3', GoalState.ABORTED)]
    assert 'rejected' in events[0].reason and '9.1 mm' in events[0].reason
    start = run.start_state(0.4)
    assert start.source == 'motion'
    p, v, a = plan1.trajectory.sample(0.5 - 0.1)                  # motion 1 at the takeover
    assert np.linalg.norm(v) > 0
    np.testing.assert_allclose(start.state.p, p, atol=1e-12)
    np.testing.assert_allclose(start.state.v, v, atol=1e-12)
    np.testing.assert_allclose(start.state.a, a, atol=1e-12)
    # and motion 1's end is the hold once the driver says it finished
    run.on_execution(1, 'finished', '', None, now=3.0)
    np.testing.assert_allclose(run.start_state(3.1).state.p,
                               plan1.trajectory.sample(plan1.trajectory.duration)[0], atol=1e-12)


def test_a_refused_motion_from_rest_leaves_the_hold(mech, limits):
    """Refused at rest, a motion leaves the hold where it was (the driver's check failed:
    nothing moved)."""
    run = make_runner(mech, limits, Profile.MINIMUM_JERK)
    submit(run, '1', HOME + [0.0, 0.01, 0.05], 0.0, tag=4)
    events = run.on_execution(4, 'rejected', 'joint 1 would reach 0.61, outside its range', (),
                              now=0.05)
    assert [(e.goal_id, e.state) for e in events] == [('1', GoalState.ABORTED)]
    start = run.start_state(0.2)
    assert start.source == 'hold'
    np.testing.assert_allclose(start.state.p, HOME, atol=1e-9)


def test_the_drives_leaving_enabled_abort_the_goal_at_once(mech, limits):
    run = make_runner(mech, limits, Profile.MINIMUM_JERK)
    submit(run, '1', HOME + [0.0, 0.01, 0.05], 0.0, tag=9)
    events = run.on_driver_state(False, 'protective stop: a1: following error', None,
                                 executing=False, now=0.5)
    assert [(e.goal_id, e.state) for e in events] == [('1', GoalState.ABORTED)]
    assert 'following error' in events[0].reason
    assert run.active_goal is None


def test_cancel_waits_for_the_driver_to_say_where_the_motion_stopped(mech, limits):
    run = make_runner(mech, limits, Profile.MINIMUM_JERK)
    _, plan = submit(run, '1', HOME + [0.0, 0.02, 0.05], 0.0, tag=11)
    message, tag, events = run.cancel(now=0.5)
    assert tag == 11 and [(e.goal_id, e.state) for e in events] == [('1', GoalState.CANCELLED)]
    assert run.start_state(0.55) is None               # braking: nothing is planned from it
    where = plan.trajectory.sample(0.6)[0]
    assert run.on_execution(11, 'stopped', 'cancel requested', lumbar_eq3(where), now=0.8) == []
    np.testing.assert_allclose(run.start_state(0.9).state.p, where, atol=1e-9)
    assert run.cancel(now=1.0)[2] == []                # nothing left to cancel


def test_no_report_from_the_driver_aborts(mech, limits):
    run = make_runner(mech, limits, Profile.MINIMUM_JERK)
    submit(run, '1', HOME + [0.0, 0.01, 0.05], 0.0, tag=13)
    assert run.check(1.0) == []
    events = run.check(1.2)                            # takeover 0.1 s + 1 s report timeout
    assert [e.state for e in events] == [GoalState.ABORTED]
    assert 'did not start' in events[0].reason


offset = st.tuples(st.floats(-0.04, 0.04), st.floats(-0.03, 0.03), st.floats(-0.1, 0.15))


@settings(PROPS, max_examples=15)
@given(offset, offset, st.floats(0.0, 2.0), st.sampled_from(list(Profile)))
def test_random_preemptions_stay_continuous_and_every_goal_ends_once(mech, limits, d1, d2,
                                                                    t_switch, profile):
    run = make_runner(mech, limits, profile)
    events, plan1 = submit(run, '1', HOME + d1, 0.0, tag=1)
    if plan1 is not None:
        run.on_execution(1, 'started', '', None, now=0.1)
    start = run.start_state(t_switch)
    ev2, plan2 = submit(run, '2', HOME + d2, t_switch, tag=2)
    events += ev2
    if plan1 is not None and plan2 is not None:
        ref = plan1.trajectory.sample(start.t0 - 0.1)
        got = plan2.trajectory.sample(0.0)
        for x, y, tol in zip(got, ref, (1e-12, 1e-9, 1e-7)):
            np.testing.assert_allclose(x, y, atol=tol)
    if plan2 is not None:
        run.on_execution(2, 'started', '', None, now=start.t0)
        end = start.t0 + plan2.duration
        run.on_execution(2, 'finished', '', None, now=end)
        for k in range(7):                                       # 60 ms at the goal
            events += run.on_estimate(HOME + d2, stamp=end + 0.01 * (k + 1), now=end + 0.01 * (k + 1))
    events += run.check(1e3)
    ends = [(e.goal_id, e.state) for e in events if e.state.terminal]
    assert sorted(g for g, _ in ends) == ['1', '2']              # exactly one end each


# ---------------------------------------------------------------- path timing
def test_path_arrival_times_are_relative_to_the_header_stamp():
    assert arrival_times(100.0, [101.0, 102.5]) == (2.5, pytest.approx([1.0]))
    assert arrival_times(0.0, [0.0, 0.0]) == (None, None)
    with pytest.raises(PoseError, match='non-increasing'):
        arrival_times(0.0, [1.0, 1.0])
    with pytest.raises(PoseError, match='empty'):
        arrival_times(0.0, [])
    with pytest.raises(PoseError, match='after'):
        arrival_times(5.0, [4.0])


# ---------------------------------------------------------------- wrench capacity (docs/safety.md §17)
def _lumbar_capacity(pose, limit=250.0):
    """Independent oracle: rows of J from the paper's eq. 3 (unit leg vectors u_i and
    r_i x u_i), f = J^-T W, capacity per axis = min_i limit / |(J^-T)_{i, axis}|."""
    A = np.array([[-0.217, 0.0], [0.0, 0.0], [0.217, 0.0]])
    B = np.array([[-0.195, 0.0], [0.0, 0.0], [0.195, 0.0]])
    x, y, th = pose
    R = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
    rows = []
    for a, b in zip(A, B):
        r = R @ b
        d = np.array([x, y]) + r - a
        u = d / np.linalg.norm(d)
        rows.append([u[0], u[1], r[0] * u[1] - r[1] * u[0]])
    G = np.linalg.inv(np.array(rows).T)          # f = G W
    return np.array([limit / np.abs(G[:, k]).max() for k in range(3)])


def test_a_path_from_below_the_capacity_minimum_may_leave_it_but_not_go_deeper(mech, cfg):
    """After a capacity stop the ring rests just short of trajectory.min_wrench_capacity
    (Mz 0.9 N·m, the eq. 3 oracle): a path back towards home (capacity rising) is planned; one
    further towards the theta = 0 singularity (capacity falling) is still rejected."""
    lim = Limits.from_config(cfg, dof=3)
    need = lim.min_wrench_capacity[2]
    lo, hi = math.radians(1.0), math.radians(5.0)          # Mz capacity: ~0.5 .. ~2.4 N·m
    for _ in range(60):                                   # bisection on the oracle
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if _lumbar_capacity([0.0, 0.39, mid])[2] < need else (lo, mid)
    boundary = np.array([0.0, 0.39, lo - 1e-6])
    assert need * 0.99 < _lumbar_capacity(boundary)[2] < need
    plan = plan_motion(mech, boundary, HOME, Profile.MINIMUM_JERK, lim, duration=1.5)
    assert plan.trajectory.duration > 0.0
    with pytest.raises(PlanRejected) as err:
        plan_motion(mech, boundary, np.array([0.0, 0.39, math.radians(1.0)]), Profile.MINIMUM_JERK,
                    lim, duration=1.5)
    assert err.value.violation is Violation.CAPACITY and 'along Mz' in err.value.reason


def test_a_path_through_too_little_wrench_capacity_is_rejected_naming_where(mech, cfg):
    lim = Limits.from_config(cfg, dof=3)
    assert lim.min_wrench_capacity is not None
    goal = np.array([0.0, 0.39, math.radians(1.0)])          # towards the theta = 0 singularity
    with pytest.raises(PlanRejected) as err:
        plan_motion(mech, HOME, goal, Profile.MINIMUM_JERK, lim, duration=1.5)
    reason = err.value.reason
    assert err.value.violation is Violation.CAPACITY
    assert 'wrench capacity along' in reason and 'limited by actuator a2' in reason
    # the reported number is the capacity at the reported pose (oracle above)
    import re
    axis, value = re.search(r'capacity along (\w+) is ([0-9.e+-]+)', reason).groups()
    pose = np.array([float(v) for v in re.search(r'at pose \(([^)]*)\)', reason).group(1).split(',')])
    k = ('Fx', 'Fy', 'Mz').index(axis)
    assert float(value) == pytest.approx(_lumbar_capacity(pose)[k], rel=2e-3)
    assert float(value) < lim.min_wrench_capacity[k]


def test_an_accepted_plan_carries_its_minimum_wrench_capacity(mech, cfg):
    lim = Limits.from_config(cfg, dof=3)
    goal = HOME + [0.0, 0.01, 0.05]
    plan = plan_motion(mech, HOME, goal, Profile.MINIMUM_JERK, lim, duration=1.5)
    got = np.array([float(v) for v in plan.values['min_wrench_capacity'].split()])
    ts = np.linspace(0.0, 1.5, 400)
    want = np.min([_lumbar_capacity(p) for p in plan.trajectory.sample_many(ts)[0]], axis=0)
    np.testing.assert_allclose(got, want, rtol=2e-3)


def test_a_goal_at_the_edge_of_a_legs_reach_is_planned_within_what_the_driver_accepts():
    """3-RRR neck brace: a goal 0.1 mm inside leg 2's reach (its two links nearly straight),
    from a random-goal run (scripts/random_goals.py neck_brace_3rrr --seed 3, goal 10).
    There ``dq2/dx`` is ~200 x its value at the start and joint 2's acceleration peaks in
    the last 10 ms. The planner once read 0.77 of that peak (differences on 200 samples),
    accepted the motion, and the driver refused it ("joint 2 would accelerate at 1.03 x its
    limit"). Oracle: the motion's true joint accelerations, second differences of the
    inverse kinematics on 40 001 instants; and the driver's acceptance of what ik_node
    makes of the plan."""
    from brace_control.control.execution import PathExecutor
    from brace_control.mechanisms import mechanism_from_config
    from brace_control.trajectory.actuator import actuator_knots
    from brace_control.trajectory.knots import knots_of
    cfg = load_device_config('config/neck_brace_3rrr.yaml')
    mech = mechanism_from_config(cfg)
    limits = Limits.from_config(cfg, dof=3)
    start = np.array([0.005311679354935053, 0.014689011224469292, -0.24587389317232097])
    goal = np.array([-0.037481263337639854, 0.045833361084890514, -0.2822383339450152])
    assert np.linalg.cond(mech.jacobian(goal)) > 1000.0          # at the edge of the reach
    tr = cfg['trajectory']
    plan = plan_motion(mech, start, goal, tr['profile'], limits,
                       fitts=FittsLaw(a=tr['fitts_a'], b=tr['fitts_b'], w=tr['fitts_w']),
                       fitts_axes=(0, 1))
    T = plan.trajectory.duration
    t = np.linspace(0.0, T, 40001)
    q = np.asarray(mech.inverse_batch(plan.trajectory.sample_many(t)[0]), dtype=float)
    qdd = np.gradient(np.gradient(q, t, axis=0), t, axis=0)[5:-5]
    a_max = float(cfg['actuator']['max_acceleration'])
    v_max = float(cfg['actuator']['max_velocity'])
    peak = float(np.max(np.abs(qdd))) / a_max
    assert peak <= 1.0, f'the motion accelerates a joint at {peak:.3f} x its limit'
    assert peak <= 1.05 * limits.limit_margin, (peak, limits.limit_margin)
    ex = PathExecutor(3, v_max=v_max, a_max=a_max, period=1.0 / float(cfg['can']['sync_rate_hz']))
    ex.anchor(q[0], t=0.0)
    knots = actuator_knots(mech, knots_of(plan.trajectory))
    assert ex.load(knots, 0.0, 1, now=0.0) is None, ex.events[-1].reason


DEVICES = ('lumbar_brace', 'lumbar_brace_v2', 'neck_brace_4rpr', 'neck_brace_3rrr', 'neck_brace_2r',
           'upper_limb_trainer', 'shoulder', 'continuum')


def _random_pose(mech, rng: np.random.Generator) -> np.ndarray:
    """A pose of the device's workspace: actuator values 3-97 % of their ranges through the
    forward kinematics nearest home (a redundant device: a pose near home whose lengths are
    in range), kept when its inverse kinematics is in range (as scripts/random_goals.py)."""
    home = np.asarray(mech.home_pose, dtype=float)
    lo, hi = (np.asarray(v, dtype=float) for v in mech.actuator_limits)
    for _ in range(1000):
        try:
            if lo.size == home.size or lo.size == 1:
                pose = np.asarray(mech.forward_nearest(rng.uniform(lo + 0.03 * (hi - lo),
                                                                   hi - 0.03 * (hi - lo)), home), float)
            else:
                pose = home + np.array([0.08, 0.08, 0.6][:home.size]) * rng.uniform(-1, 1, home.size)
            q = np.asarray(mech.inverse(pose), dtype=float)
        except ValueError:
            continue
        if mech.in_workspace(pose) and np.all(q >= lo) and np.all(q <= hi):
            return pose
    raise AssertionError('no random pose found')


@pytest.mark.parametrize('device', DEVICES)
def test_every_motion_the_planner_accepts_is_one_ik_node_converts_and_the_driver_accepts(device):
    """The contract between the nodes, on random start/goal pairs across each device's
    workspace: a plan trajectory_node accepts becomes actuator knots in ik_node (every pose
    with an inverse kinematics) and passes the driver's own check of the interpolated motion
    (stroke, speed, acceleration: PathExecutor.load). A goal the planner refuses is refused
    with a reason; one it accepts must never be refused downstream ("accepted", then
    "aborted: its motion was rejected", seen on the 3-RRR and the shoulder)."""
    from brace_control.control.execution import PathExecutor
    from brace_control.mechanisms import mechanism_from_config
    from brace_control.nodes.msgs import pose_kind
    from brace_control.trajectory.actuator import actuator_knots
    from brace_control.trajectory.knots import knots_of
    cfg = load_device_config(f'config/{device}.yaml')
    mech = mechanism_from_config(cfg)
    limits = Limits.from_config(cfg, dof=mech.dof)
    tr = cfg['trajectory']
    fitts = FittsLaw(a=tr['fitts_a'], b=tr['fitts_b'], w=tr['fitts_w'])
    axes = (0, 1) if pose_kind(mech) in ('planar', 'xy') else None
    lo, hi = (np.asarray(v, dtype=float) for v in mech.actuator_limits)
    rng = np.random.default_rng(7)
    accepted = 0
    for _ in range(40):
        if accepted == 8:
            break
        start, goal = _random_pose(mech, rng), _random_pose(mech, rng)
        try:
            plan = plan_motion(mech, start, goal, tr['profile'], limits, fitts=fitts, fitts_axes=axes)
        except PlanRejected as exc:
            assert str(exc)
            continue
        accepted += 1
        knots = actuator_knots(mech, knots_of(plan.trajectory, breaks=getattr(plan.trajectory, 'breaks', None)))
        ex = PathExecutor(mech.n_actuators, v_max=cfg['actuator']['max_velocity'],
                          a_max=cfg['actuator']['max_acceleration'],
                          period=1.0 / float(cfg['can']['sync_rate_hz']))
        ex.anchor(knots.positions[0], t=0.0)
        reason = ex.load(knots, 0.0, 1, now=0.0, lo=lo, hi=hi)
        assert reason is None, (start.tolist(), goal.tolist(), reason)
    assert accepted >= 3          # (the shoulder's random pairs mostly cross a singularity)


def test_a_long_path_goal_is_planned_within_what_the_driver_accepts():
    """A nav_msgs/Path goal of many close poses (the lumbar brace, 300 poses over 50 mrad and
    a 10 mm arc): the via-point minimum-jerk motion through them bends at every via, between
    the 200 path samples. Checked by differences on those samples, a 1000-pose path was
    planned at 4.5 s and the driver refused it (joint 3 at 9.9 x its acceleration limit).
    Oracle: the driver's check of what ik_node makes of the plan."""
    from brace_control.control.execution import PathExecutor
    from brace_control.mechanisms import mechanism_from_config
    from brace_control.trajectory.actuator import actuator_knots
    from brace_control.trajectory.knots import knots_of
    cfg = load_device_config(CONFIG)
    mech = mechanism_from_config(cfg)
    limits = Limits.from_config(cfg, dof=3)
    home = np.array([0.0, 0.39, 0.0873])
    u = np.linspace(0.0, 1.0, 301)[1:]
    poses = home + np.column_stack([0.0 * u, 0.01 * np.sin(np.pi * u), 0.05 * u])
    plan = plan_motion(mech, home, poses[-1], Profile.MINIMUM_JERK, limits, via=poses[:-1],
                       fitts=FittsLaw(), fitts_axes=(0, 1))
    knots = actuator_knots(mech, knots_of(plan.trajectory, breaks=plan.trajectory.breaks))
    ex = PathExecutor(3, v_max=cfg['actuator']['max_velocity'], a_max=cfg['actuator']['max_acceleration'],
                      period=1.0 / float(cfg['can']['sync_rate_hz']))
    ex.anchor(knots.positions[0], t=0.0)
    assert ex.load(knots, 0.0, 1, now=0.0) is None, ex.events[-1].reason
