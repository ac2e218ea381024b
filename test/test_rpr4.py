"""Planar 4-RPR (neck brace, report §"FOUR RPR") against independent oracles.

Oracles: the report's eqs. 5-6 written out (anchors (x_n, y_n), radius r, angles delta_n),
central finite differences, a sum of r x F, scipy's linear programming for the
feasibility of ``J^T f = W`` within the force bounds (and the ends of the feasible
segment), ``scipy.linalg.null_space``, and a scipy least-squares fit for the forward
residual. Nothing here calls the code under test to build an expected value.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.linalg import null_space
from scipy.optimize import least_squares, linprog

from brace_control.mechanisms import Mechanism, SingularPose, UnreachablePose, load_mechanism
from brace_control.mechanisms.rpr4 import InconsistentLengths, InfeasibleWrench, Rpr4, report_anchors

ANCHORS = [(0.18, 0.18), (-0.18, 0.18), (-0.18, -0.18), (0.18, -0.18)]
RADIUS = 0.075
DELTA = np.radians([75.0, 105.0, 255.0, 285.0])
T_MIN, T_MAX = 5.0, 120.0


def eq6(pose) -> np.ndarray:
    x, y, psi = pose
    return np.array([math.sqrt((x + RADIUS * math.cos(psi + d) - xn) ** 2 + (y + RADIUS * math.sin(psi + d) - yn) ** 2)
                     for (xn, yn), d in zip(ANCHORS, DELTA)])


def eq5(pose) -> np.ndarray:
    x, y, psi = pose
    return np.array([math.atan2(y + RADIUS * math.sin(psi + d) - yn, x + RADIUS * math.cos(psi + d) - xn)
                     for (xn, yn), d in zip(ANCHORS, DELTA)])


def jt_independent(pose) -> np.ndarray:
    """J^T (3, 4) from the statics: columns (u_n, rho_n x u_n), u_n unit A_n -> B_n."""
    x, y, psi = pose
    cols = []
    for (xn, yn), d in zip(ANCHORS, DELTA):
        rx, ry = RADIUS * math.cos(psi + d), RADIUS * math.sin(psi + d)
        ux, uy = x + rx - xn, y + ry - yn
        n = math.hypot(ux, uy)
        ux, uy = ux / n, uy / n
        cols.append((ux, uy, rx * uy - ry * ux))
    return np.array(cols).T


def lp_feasible(pose, wrench, lo, hi) -> bool:
    res = linprog(np.zeros(4), A_eq=jt_independent(pose), b_eq=wrench, bounds=[(lo, hi)] * 4, method='highs')
    return res.status == 0


def same_pose(p, q, tol=1e-7) -> bool:
    d = math.pi - (math.pi - (p[2] - q[2])) % (2 * math.pi)
    return abs(p[0] - q[0]) < tol and abs(p[1] - q[1]) < tol and abs(d) < tol


@pytest.fixture(scope='module')
def neck() -> Rpr4:
    return load_mechanism('config/neck_brace_4rpr.yaml')


@pytest.fixture(scope='module')
def poses(neck) -> np.ndarray:
    rng = np.random.default_rng(8)
    cand = np.column_stack([rng.uniform(-0.06, 0.06, 800), rng.uniform(-0.06, 0.06, 800),
                            rng.uniform(-0.4, 0.4, 800)])
    good = [p for p in cand if neck.in_workspace(p)]
    assert len(good) > 200
    return np.array(good[:200])


# ---------------------------------------------------------------- inverse kinematics (eqs. 5-6)
def test_inverse_matches_report_eq6_and_eq5(neck, poses):
    for p in poses:
        np.testing.assert_allclose(neck.inverse(p), eq6(p), atol=1e-15)
        np.testing.assert_allclose(neck.leg_angles(p), eq5(p), atol=1e-14)
    np.testing.assert_allclose(neck.inverse_batch(poses), [eq6(p) for p in poses], atol=1e-15)


def test_report_anchor_layout(neck):
    np.testing.assert_allclose(neck.platform_anchors,
                               [[RADIUS * math.cos(d), RADIUS * math.sin(d)] for d in DELTA], atol=1e-15)
    np.testing.assert_allclose(report_anchors(RADIUS, DELTA), neck.platform_anchors, atol=1e-15)


def test_unreachable_pose_names_the_cable(neck):
    with pytest.raises(UnreachablePose) as info:
        neck.inverse((0.15, 0.15, 0.0))
    err = info.value
    q = eq6((0.15, 0.15, 0.0))
    i = int(np.flatnonzero((q < 0.10) | (q > 0.30))[0])
    assert err.actuator == f'c{i + 1}' and err.value == pytest.approx(q[i])
    assert err.limits == (pytest.approx(0.10), pytest.approx(0.30))
    assert f'c{i + 1} would need {q[i]:.4f} m' in str(err) and '0.1000–0.3000 m' in str(err)
    assert not neck.in_workspace((0.15, 0.15, 0.0))


# ---------------------------------------------------------------- forward kinematics, residual
def test_forward_round_trip_with_zero_residual(neck, poses):
    for p in poses[:100]:
        q = eq6(p)
        sols = neck.forward(q)
        assert sols and same_pose(sols[0], p, 1e-9), (p, sols)
        for s in sols:
            assert np.max(np.abs(eq6(s) - q)) <= neck.residual_max
        pose, res = neck.forward_with_residual(q)
        assert same_pose(pose, p, 1e-9) and res < 1e-12
        np.testing.assert_allclose(neck.forward_nearest(q, p + [1e-3, 1e-3, 1e-2]), p, atol=1e-9)


def test_forward_residual_matches_independent_least_squares(neck):
    p = np.array([0.02, -0.015, 0.15])
    q = eq6(p) + np.array([0.0004, -0.0003, 0.0002, 0.0005])      # measurement noise
    fit = least_squares(lambda z: eq6(z) - q, p, xtol=1e-15, ftol=1e-15, gtol=1e-15)
    pose, res = neck.forward_with_residual(q)
    np.testing.assert_allclose(pose, fit.x, atol=1e-9)
    assert res == pytest.approx(np.linalg.norm(fit.fun), rel=1e-6)
    assert res < neck.residual_max
    np.testing.assert_allclose(neck.forward(q)[0], fit.x, atol=1e-9)


@pytest.mark.parametrize('cable', [0, 1, 2, 3])
def test_slack_cable_makes_the_residual_grow_and_is_flagged(neck, cable):
    p = np.array([0.01, 0.02, -0.1])
    q = eq6(p)
    residuals = []
    for slack in (0.0, 0.002, 0.005, 0.01, 0.02):
        ql = q.copy()
        ql[cable] += slack          # the motor paid out more cable than the geometry takes up
        residuals.append(neck.forward_with_residual(ql)[1])
    assert residuals[0] < 1e-12
    assert all(b > a for a, b in zip(residuals, residuals[1:])), residuals
    # independent sensitivity: residual = |n_k| / |n| * slack (n spans the null space of J^T)
    n = null_space(jt_independent(p))[:, 0]
    assert residuals[1] == pytest.approx(abs(n[cable]) / np.linalg.norm(n) * 0.002, rel=0.05)
    ql = q.copy()
    ql[cable] += 0.02
    assert neck.forward(ql) == []
    with pytest.raises(InconsistentLengths, match='slack or broken') as info:
        neck.forward_nearest(ql, p)
    assert info.value.residual > neck.residual_max and isinstance(info.value, UnreachablePose)


def test_forward_rejects_negative_and_malformed_lengths(neck):
    with pytest.raises(ValueError, match='>= 0'):
        neck.forward([0.2, -0.1, 0.2, 0.2])
    with pytest.raises(ValueError, match='q'):
        neck.forward([0.2, 0.2, 0.2])


# ---------------------------------------------------------------- Jacobian, wrench
def test_jacobian_matches_finite_differences(neck, poses):
    h = 1e-7
    for p in poses[:20]:
        fd = np.column_stack([(eq6(p + h * e) - eq6(p - h * e)) / (2 * h) for e in np.eye(3)])
        jac = neck.jacobian(p)
        assert jac.shape == (4, 3)
        np.testing.assert_allclose(jac, fd, atol=1e-7)


def test_wrench_matches_r_cross_f_sum(neck, poses):
    rng = np.random.default_rng(2)
    for p in poses[:20]:
        f = rng.normal(size=4) * 30
        x, y, psi = p
        total = np.zeros(3)
        for (xn, yn), d, fn in zip(ANCHORS, DELTA, f):
            rx, ry = RADIUS * math.cos(psi + d), RADIUS * math.sin(psi + d)
            dx, dy = x + rx - xn, y + ry - yn
            n = math.hypot(dx, dy)
            fx, fy = fn * dx / n, fn * dy / n
            total += (fx, fy, rx * fy - ry * fx)
        np.testing.assert_allclose(neck.wrench(p, f), total, atol=1e-10)


def test_cable_tension_pulls_the_platform_towards_the_anchor(neck):
    # one cable in tension, the others slack: the force points from B_1 to A_1
    p = (0.0, 0.0, 0.0)
    w = neck.wrench(p, [-10.0, 0.0, 0.0, 0.0])
    b1 = np.array([RADIUS * math.cos(DELTA[0]), RADIUS * math.sin(DELTA[0])])
    to_anchor = (np.array(ANCHORS[0]) - b1) / np.linalg.norm(np.array(ANCHORS[0]) - b1)
    np.testing.assert_allclose(w[:2], 10.0 * to_anchor, atol=1e-12)


# ---------------------------------------------------------------- redundancy resolution
def test_rod_forces_are_minimum_norm(neck, poses):
    rng = np.random.default_rng(3)
    for p in poses[:20]:
        w = rng.normal(size=3) * [20, 20, 1.5]
        f = neck.actuator_forces(p, w, 'rod')
        np.testing.assert_allclose(jt_independent(p) @ f, w, atol=1e-9)
        ref = np.linalg.lstsq(jt_independent(p), w, rcond=None)[0]     # minimum-norm solution
        # force_max = 120 N in the YAML: the minimum-norm forces stay within it here
        if np.max(np.abs(ref)) <= 120.0:
            np.testing.assert_allclose(f, ref, atol=1e-9)


def test_rod_without_bound_is_pinv():
    mech = Rpr4(ANCHORS, report_anchors(RADIUS, DELTA), (0.1, 0.3), actuation='rod', home_pose=[0, 0, 0])
    w = np.array([300.0, -500.0, 40.0])
    np.testing.assert_allclose(mech.actuator_forces((0.0, 0.0, 0.0), w),
                               np.linalg.pinv(jt_independent((0.0, 0.0, 0.0))) @ w, atol=1e-9)


def test_cable_centre_and_min_norm_against_lp_segment(neck):
    p = np.array([0.01, -0.02, 0.1])
    w = np.array([8.0, -5.0, 0.4])
    jt = jt_independent(p)
    n = null_space(jt)[:, 0]
    # the feasible segment of tensions, independently: extreme values of n . t over the polytope
    ends = [linprog(sign * n, A_eq=jt, b_eq=-w, bounds=[(T_MIN, T_MAX)] * 4, method='highs') for sign in (1, -1)]
    assert all(e.status == 0 for e in ends)
    t_a, t_b = ends[0].x, ends[1].x
    centre = neck.cable_tensions(p, w, method='centre')
    np.testing.assert_allclose(centre, 0.5 * (t_a + t_b), atol=1e-6)
    least = neck.cable_tensions(p, w, method='min_norm')
    # minimum norm over the segment, by dense sampling
    s = np.linspace(0.0, 1.0, 20001)[:, None]
    seg = t_a + s * (t_b - t_a)
    best = seg[np.argmin(np.linalg.norm(seg, axis=1))]
    np.testing.assert_allclose(least, best, atol=1e-3)
    for t in (centre, least):
        assert np.all(t >= T_MIN - 1e-9) and np.all(t <= T_MAX + 1e-9)
        np.testing.assert_allclose(neck.wrench(p, -t), w, atol=1e-9)


def test_infeasible_wrench_is_flagged_with_a_reason(neck):
    p = (0.0, 0.0, 0.0)
    w = (200.0, 0.0, 0.0)                     # more than the cables can pull
    assert not lp_feasible(p, (-np.array(w)).tolist(), T_MIN, T_MAX)
    d = neck.distribute(p, w)
    assert not d.feasible and d.forces is None and d.tensions is None
    assert 'infeasible' in d.reason and '> max' in d.reason
    with pytest.raises(InfeasibleWrench, match=r'c\d = [\d.]+ N \(> max\)'):
        neck.cable_tensions(p, w)
    # a modest pull is feasible; the same 200 N is feasible for rods without a force bound
    assert neck.distribute(p, (10.0, 10.0, 0.0)).feasible
    rods = Rpr4(ANCHORS, report_anchors(RADIUS, DELTA), (0.1, 0.3), actuation='rod', home_pose=[0, 0, 0])
    assert rods.distribute(p, w).feasible


def test_non_wrench_closure_pose_cannot_be_pretensioned():
    # every platform joint rotated the same way: all cables turn the platform the same way,
    # no positive tension balances itself (independent: the null vector has mixed signs)
    delta = np.radians([75.0, 165.0, 255.0, 345.0])
    mech = Rpr4(ANCHORS, report_anchors(RADIUS, delta), (0.05, 0.4), tension_min=T_MIN, tension_max=T_MAX,
                home_pose=[0.0, 0.0, 0.0])
    p = (0.0, 0.0, 0.0)
    jac = mech.jacobian(p)
    n = null_space(jac.T)[:, 0]
    assert np.min(n) < 0 < np.max(n)
    assert not mech.distribute(p, (0.0, 0.0, 0.0)).feasible
    assert not mech.in_workspace(p)
    assert mech.distribute(p, (0.0, 0.0, 0.0), mode='rod').feasible


_f = st.floats(-60.0, 60.0, allow_nan=False)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(i=st.integers(0, 199), fx=_f, fy=_f, m=st.floats(-4.0, 4.0), method=st.sampled_from(['centre', 'min_norm']))
def test_property_cable_tensions_never_negative_and_agree_with_lp(neck, poses, i, fx, fy, m, method):
    p, w = poses[i], np.array([fx, fy, m])
    d = neck.distribute(p, w, method=method)
    feasible = lp_feasible(p, -w, T_MIN, T_MAX)
    if d.feasible:
        t = d.tensions
        assert t is not None and np.all(t >= T_MIN - 1e-9) and np.all(t <= T_MAX + 1e-9)
        assert np.all(t >= 0.0)
        np.testing.assert_allclose(neck.wrench(p, d.forces), w, atol=1e-8)
        np.testing.assert_allclose(d.forces, -t)
        assert feasible
    else:
        assert d.reason and not feasible
        with pytest.raises(InfeasibleWrench):
            neck.actuator_forces(p, w)


def test_wrench_feasible_workspace_matches_pointwise_lp(neck):
    xs = np.linspace(-0.08, 0.08, 9)
    ys = np.linspace(-0.08, 0.08, 7)
    wrenches = np.array([[15.0, 0.0, 0.0], [0.0, -15.0, 0.0], [0.0, 0.0, 1.0], [-10.0, 10.0, -0.5]])
    mask = neck.wrench_feasible_workspace(xs, ys, 0.1, wrenches)
    assert mask.shape == (7, 9)
    assert 0 < mask.sum() < mask.size
    lo, hi = neck.actuator_limits
    for j, y in enumerate(ys):
        for i, x in enumerate(xs):
            p = (x, y, 0.1)
            q = eq6(p)
            expected = bool(np.all((q >= lo) & (q <= hi))) and all(
                lp_feasible(p, -w, T_MIN, T_MAX) for w in wrenches)
            assert mask[j, i] == expected, (p, mask[j, i])


def test_singular_pose_distribution_infeasible():
    # anchors radial (delta_n = the base anchors' angles): at the centre all cables meet at P
    mech = Rpr4(ANCHORS, report_anchors(RADIUS, np.radians([45.0, 135.0, 225.0, 315.0])), (0.05, 0.4),
                home_pose=[0.01, 0.0, 0.0], tension_min=T_MIN, tension_max=T_MAX)
    p = (0.0, 0.0, 0.0)
    assert np.linalg.matrix_rank(jt_independent_radial(p)) == 2
    with pytest.raises(SingularPose, match='cond'):
        mech.check_singularity(p)
    d = mech.distribute(p, (1.0, 0.0, 0.0))
    assert not d.feasible and 'singular' in d.reason
    assert not mech.wrench_feasible_batch(np.array([p]), np.zeros((1, 3)))[0]


def jt_independent_radial(pose) -> np.ndarray:
    x, y, psi = pose
    cols = []
    for (xn, yn), d in zip(ANCHORS, np.radians([45.0, 135.0, 225.0, 315.0])):
        rx, ry = RADIUS * math.cos(psi + d), RADIUS * math.sin(psi + d)
        ux, uy = x + rx - xn, y + ry - yn
        n = math.hypot(ux, uy)
        cols.append((ux / n, uy / n, (rx * uy - ry * ux) / n))
    return np.array(cols).T


# ---------------------------------------------------------------- validation, config
BAD = [[np.nan, 0.0, 0.0], [0.0, np.inf, 0.0], [0.0, 0.0], [0.0, 0.0, 0.0, 1.0], 'abc', [[0.0, 0.0, 0.0]]]


@pytest.mark.parametrize('bad', BAD, ids=['nan', 'inf', 'short', 'long', 'str', 'nested'])
@pytest.mark.parametrize('method', ['inverse', 'jacobian', 'condition', 'in_workspace', 'wrench_pose',
                                    'distribute_pose', 'distribute_wrench', 'nearest_hint'])
def test_malformed_input_raises_value_error(neck, bad, method):
    good = [0.0, 0.0, 0.0]
    q = list(eq6(good))
    calls = {
        'inverse': lambda: neck.inverse(bad), 'jacobian': lambda: neck.jacobian(bad),
        'condition': lambda: neck.condition(bad), 'in_workspace': lambda: neck.in_workspace(bad),
        'wrench_pose': lambda: neck.wrench(bad, [1.0] * 4),
        'distribute_pose': lambda: neck.distribute(bad, [1.0, 0.0, 0.0]),
        'distribute_wrench': lambda: neck.distribute(good, bad),
        'nearest_hint': lambda: neck.forward_nearest(q, bad),
    }
    with pytest.raises(ValueError, match=r'(pose|q|wrench|hint_pose).*(expected|non-finite)'):
        calls[method]()


@pytest.mark.parametrize('bad', [[np.nan, 0.2, 0.2, 0.2], [0.2, 0.2, 0.2], 'abcd'])
def test_malformed_lengths_and_forces(neck, bad):
    with pytest.raises(ValueError, match=r'(q|forces).*(expected|non-finite)'):
        neck.forward(bad)
    with pytest.raises(ValueError, match=r'forces.*(expected|non-finite)'):
        neck.wrench([0.0, 0.0, 0.0], bad)


@pytest.mark.parametrize('kwargs, match', [
    (dict(base_anchors=[[0, 0], [1, 0], [0, 1]]), 'base_anchors'),
    (dict(stroke=(0.3, 0.1)), 'stroke'),
    (dict(actuation='chain'), 'actuation'),
    (dict(tension_min=50.0, tension_max=10.0), 'tension_min'),
    (dict(tension_min=-1.0), 'tension_min'),
    (dict(distribution='median'), 'distribution'),
    (dict(residual_max=0.0), 'residual_max'),
    (dict(actuator_names=('c1', 'c2', 'c3')), 'actuator_names'),
    (dict(home_pose=[0.2, 0.2, 0.0]), 'would need'),
])
def test_constructor_rejects_bad_arguments(kwargs, match):
    args = dict(base_anchors=ANCHORS, platform_anchors=report_anchors(RADIUS, DELTA), stroke=(0.1, 0.3),
                home_pose=[0.0, 0.0, 0.0])
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        Rpr4(args.pop('base_anchors'), args.pop('platform_anchors'), args.pop('stroke'), **args)


def test_load_mechanism_neck_brace_4rpr(neck):
    assert isinstance(neck, Rpr4) and isinstance(neck, Mechanism)
    assert neck.dof == 3 and neck.n_actuators == 4 and neck.actuator_names == ('c1', 'c2', 'c3', 'c4')
    assert neck.actuation == 'cable' and (neck.tension_min, neck.tension_max) == (T_MIN, T_MAX)
    home = neck.home_pose
    assert neck.in_workspace(home) and neck.condition(home) < 100
    # unloaded at home: equal tensions (symmetry), within the bounds
    t = neck.cable_tensions(home, (0.0, 0.0, 0.0))
    np.testing.assert_allclose(t, t[0])
    assert T_MIN <= t[0] <= T_MAX
