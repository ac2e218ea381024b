"""Planar 3-RRR (neck brace, report "Planar 3RRR") against independent oracles.

Oracles: the loop closure written out (|M_i - B_i| = r_i, |A_i - M_i| = l_i, the elbow's
side), an independently written 3-RPR forward residual over phi whose sign changes are
counted (dense sampling + brentq) for the six-mode case, central finite differences, and
the statics of two-force distal links (sum of r x F). Nothing here calls the code under
test to build an expected value.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from rpr_oracles import fk_thetas_by_sampling as count_roots

from brace_control.mechanisms import Mechanism, SingularPose, UnreachablePose, load_mechanism
from brace_control.mechanisms.rrr3 import Rrr3

# ---- the six-assembly-mode case: with q = SIX_Q the elbows land on the 3-RPR example of
# test_rpr3.py (base (0,0), (0.5,0), (0.6,-0.4); platform (0,0), (-0.4,0), (-0.8,-0.7);
# lengths 1.06, 0.86, 1.28), a known six-solution case
SIX_ELBOWS = np.array([[0.0, 0.0], [0.5, 0.0], [0.6, -0.4]])
SIX_PLATFORM = [[0.0, 0.0], [-0.4, 0.0], [-0.8, -0.7]]
SIX_DISTAL = [1.06, 0.86, 1.28]
SIX_R = 0.3
SIX_Q = np.array([0.0, math.pi / 2, math.pi])
SIX_BASE = SIX_ELBOWS - SIX_R * np.column_stack([np.cos(SIX_Q), np.sin(SIX_Q)])   # (-0.3,0), (0.5,-0.3), (0.9,-0.4)


def wrap(t):
    return np.pi - np.mod(np.pi - np.asarray(t, dtype=float), 2 * np.pi)


def platform_points(anchors, pose) -> np.ndarray:
    x, y, t = pose
    c, s = math.cos(t), math.sin(t)
    return np.array([[x + c * ax - s * ay, y + s * ax + c * ay] for ax, ay in anchors])


def elbows_of(base, r, q) -> np.ndarray:
    r = np.broadcast_to(np.asarray(r, dtype=float), (3,))
    return np.array([[bx + ri * math.cos(t), by + ri * math.sin(t)] for (bx, by), ri, t in zip(base, r, q)])


# count_roots: the independent 3-RPR forward oracle's roots (rpr_oracles.fk_thetas_by_sampling)


def check_closure(mech, pose, q, mode=None, tol=1e-9) -> None:
    """Loop closure written out: proximal and distal lengths, and the elbow side per leg."""
    m = elbows_of(mech.base_pivots, mech.proximal_lengths, q)
    a = platform_points(mech.platform_anchors, pose)
    np.testing.assert_allclose(np.linalg.norm(m - mech.base_pivots, axis=1), mech.proximal_lengths, atol=tol)
    np.testing.assert_allclose(np.linalg.norm(a - m, axis=1), mech.distal_lengths, atol=tol)
    if mode is not None:
        u, w = m - mech.base_pivots, a - m
        side = u[:, 0] * w[:, 1] - u[:, 1] * w[:, 0]
        assert np.all(np.sign(side) == np.asarray(mode)), (side, mode)


@pytest.fixture(scope='module')
def neck() -> Rrr3:
    return load_mechanism('config/neck_brace_3rrr.yaml')


@pytest.fixture(scope='module')
def free(neck) -> Rrr3:
    """The neck geometry with unlimited motor ranges (every working mode reachable)."""
    return Rrr3(neck.base_pivots, neck.proximal_lengths, neck.distal_lengths, neck.platform_anchors,
                (-math.pi, math.pi), home_pose=[0.0, 0.0, 0.0])


def six_pose_independent() -> tuple[float, float, float]:
    """One six-mode pose from the independent root finder (Cramer lift)."""
    theta = count_roots(SIX_ELBOWS, SIX_PLATFORM, SIX_DISTAL, n=20_001)[0]
    a = np.asarray(SIX_ELBOWS) - SIX_ELBOWS[0]
    b = np.asarray(SIX_PLATFORM, float) - SIX_PLATFORM[0]
    c, s = math.cos(theta), math.sin(theta)
    rows, rhs = [], []
    for i in (1, 2):
        rb = np.array([c * b[i, 0] - s * b[i, 1], s * b[i, 0] + c * b[i, 1]])
        rows.append(rb - a[i])
        rhs.append(0.5 * (SIX_DISTAL[i] ** 2 - SIX_DISTAL[0] ** 2 - a[i] @ a[i] - b[i] @ b[i] + 2 * a[i] @ rb))
    p = np.linalg.solve(np.array(rows), np.array(rhs))          # B1 - A1 (platform anchor 1 at origin)
    return (SIX_ELBOWS[0, 0] + p[0], SIX_ELBOWS[0, 1] + p[1], theta)


@pytest.fixture(scope='module')
def six() -> Rrr3:
    return Rrr3(SIX_BASE, SIX_R, SIX_DISTAL, SIX_PLATFORM, (-math.pi, math.pi), home_pose=six_pose_independent())


# ---------------------------------------------------------------- inverse kinematics
def test_all_eight_working_modes_close_the_loops(free):
    pose = (0.01, -0.008, 0.1)
    seen = []
    for mode in Rrr3.working_modes():
        q = free.inverse(pose, working_mode=mode)
        check_closure(free, pose, q, mode)
        seen.append(tuple(np.round(q, 9)))
    assert len(set(seen)) == 8


def test_round_trip_on_random_workspace_poses(neck):
    rng = np.random.default_rng(42)
    done = 0
    for _ in range(3000):
        pose = (rng.uniform(-0.03, 0.03), rng.uniform(-0.03, 0.03), rng.uniform(-0.4, 0.4))
        if not neck.in_workspace(pose):
            continue
        q = neck.inverse(pose)
        check_closure(neck, pose, q, neck.working_mode)
        sols = neck.forward(q)
        assert 1 <= len(sols) <= 6
        assert any(np.allclose(s[:2], pose[:2], atol=1e-8) and abs(wrap(s[2] - pose[2])) < 1e-8 for s in sols)
        for s in sols:                        # every assembly mode closes the loops with the same q
            check_closure(neck, s, q)
        np.testing.assert_allclose(neck.forward_nearest(q, np.add(pose, [1e-3, -1e-3, 1e-2])), pose, atol=1e-9)
        done += 1
        if done == 300:
            break
    assert done == 300


def test_leg_that_cannot_close_is_rejected_naming_the_motor(neck):
    with pytest.raises(UnreachablePose, match='leg of m3 cannot close') as info:
        neck.inverse((0.0, -0.1, 0.0))
    err = info.value
    # independent: A3 = (0, -0.1 + 0.057735) is 0.202 m from B3 = (0, 0.16); the leg reaches 0–0.16 m
    assert err.actuator == 'm3' and err.value == pytest.approx(0.16 + 0.1 - 0.057735, abs=1e-6)
    assert err.limits == (pytest.approx(0.0), pytest.approx(0.16))
    assert not neck.in_workspace((0.0, -0.1, 0.0))


def test_motor_range_violation_names_the_motor(free):
    # the neck geometry with m1 limited to +-0.5 rad (home needs -0.354 rad)
    narrow = Rrr3(free.base_pivots, free.proximal_lengths, free.distal_lengths, free.platform_anchors,
                  ([-0.5, -math.pi, -math.pi], [0.5, math.pi, math.pi]), home_pose=[0.0, 0.0, 0.0])
    pose = (0.0, 0.0, 0.5)
    with pytest.raises(UnreachablePose, match=r'm1 would need -?\d\.\d{4} rad, its range is -0\.5000–0\.5000 rad') \
            as info:
        narrow.inverse(pose)
    err = info.value
    assert err.actuator == 'm1' and err.limits == (-0.5, 0.5) and not -0.5 <= err.value <= 0.5
    # the angle it names really closes leg 1 (written-out closure)
    q = free.inverse(pose)
    assert q[0] == pytest.approx(err.value, abs=1e-12)
    check_closure(free, pose, q, (1, 1, 1))
    assert not narrow.in_workspace(pose) and free.in_workspace(pose)


# ---------------------------------------------------------------- forward kinematics: six modes
def test_six_assembly_modes_match_independent_root_count(six):
    # elbows land on the 3-RPR six-mode example
    np.testing.assert_allclose(elbows_of(SIX_BASE, SIX_R, SIX_Q), SIX_ELBOWS, atol=1e-15)
    thetas = count_roots(SIX_ELBOWS, SIX_PLATFORM, SIX_DISTAL)
    assert len(thetas) == 6
    sols = six.forward(SIX_Q)
    assert len(sols) == 6
    np.testing.assert_allclose(sorted(s[2] for s in sols), sorted(thetas), atol=1e-9)
    modes = set()
    for s in sols:
        check_closure(six, s, SIX_Q)
        # and each is the inverse kinematics of some working mode
        m = elbows_of(SIX_BASE, SIX_R, SIX_Q)
        a = platform_points(SIX_PLATFORM, s)
        u, w = m - SIX_BASE, a - m
        mode = tuple(int(v) for v in np.sign(u[:, 0] * w[:, 1] - u[:, 1] * w[:, 0]))
        np.testing.assert_allclose(wrap(six.inverse(s, working_mode=mode) - SIX_Q), 0.0, atol=1e-9)
        modes.add(mode)
    assert len(modes) == 6                  # here every assembly mode is in a different working mode


def test_forward_nearest_picks_each_of_the_six(six):
    for s in six.forward(SIX_Q):
        np.testing.assert_allclose(six.forward_nearest(SIX_Q, s + [2e-3, -2e-3, 1e-2]), s, atol=1e-12)


def test_no_assembly_mode_returns_empty_and_nearest_raises(neck):
    # cranks pointing radially outwards: elbows on a circle of radius 0.24 m, 0.416 m apart;
    # a platform joint is within 0.0577 m of P and 0.08 m from its elbow, so every elbow
    # would be within 0.138 m of P: at most 0.276 m apart. No assembly.
    q = np.radians([-150.0, -30.0, 90.0])
    m = elbows_of(neck.base_pivots, neck.proximal_lengths, q)
    assert min(np.linalg.norm(m[i] - m[j]) for i, j in ((0, 1), (1, 2), (0, 2))) > 2 * (0.0578 + 0.08)
    assert neck.forward(q) == []
    with pytest.raises(UnreachablePose, match='no assembly mode'):
        neck.forward_nearest(q, neck.home_pose)


# ---------------------------------------------------------------- Jacobian, statics
@pytest.mark.parametrize('pose', [(0.0, 0.0, 0.0), (0.012, -0.01, 0.2), (-0.015, 0.008, -0.25)])
@pytest.mark.parametrize('mode', [(1, 1, 1), (-1, 1, -1)])
def test_jacobian_matches_finite_differences(free, pose, mode):
    h = 1e-7
    fd = np.column_stack([wrap(free.inverse(np.add(pose, h * e), working_mode=mode)
                               - free.inverse(np.subtract(pose, h * e), working_mode=mode)) / (2 * h)
                          for e in np.eye(3)])
    np.testing.assert_allclose(free.jacobian(pose, working_mode=mode), fd, rtol=1e-6, atol=1e-5)
    # the report's J = A^-1 D maps motor rates to pose rates: the inverse
    np.testing.assert_allclose(free.report_jacobian(pose, working_mode=mode) @ fd, np.eye(3), atol=1e-5)


def test_wrench_matches_two_force_member_statics(six):
    rng = np.random.default_rng(4)
    for pose in six.forward(SIX_Q):
        tau = rng.normal(size=3)
        m = elbows_of(SIX_BASE, SIX_R, SIX_Q)
        a = platform_points(SIX_PLATFORM, pose)
        total = np.zeros(3)
        for i in range(3):
            u = (m[i] - SIX_BASE[i]) / SIX_R
            w = (a[i] - m[i]) / np.linalg.norm(a[i] - m[i])
            # crank i in equilibrium: tau_i + (M_i - B_i) x (-f_i w) = 0
            f = tau[i] / (SIX_R * (u[0] * w[1] - u[1] * w[0]))
            fx, fy = f * w
            rx, ry = a[i] - pose[:2]
            total += (fx, fy, rx * fy - ry * fx)
        mode = tuple(int(v) for v in np.sign([(m[i] - SIX_BASE[i])[0] * (a[i] - m[i])[1]
                                              - (m[i] - SIX_BASE[i])[1] * (a[i] - m[i])[0] for i in range(3)]))
        np.testing.assert_allclose(six.wrench(pose, tau, working_mode=mode), total, rtol=1e-9, atol=1e-9)


def test_wrench_is_virtual_work_dual(neck):
    pose, tau, xdot = (0.01, 0.0, 0.1), np.array([0.5, -0.2, 0.3]), np.array([0.01, -0.02, 0.3])
    assert tau @ (neck.jacobian(pose) @ xdot) == pytest.approx(neck.wrench(pose, tau) @ xdot, rel=1e-12)


def test_stretched_leg_is_a_serial_singularity(free):
    # put A1 exactly r + l from B1 along the ray at -150 deg: leg 1 stretched
    b1 = free.base_pivots[0]
    d = 0.16 / np.linalg.norm(b1)
    target = b1 * (1 - d)                       # 0.16 m from B1 towards the centre
    pose = (target[0] - free.platform_anchors[0, 0], target[1] - free.platform_anchors[0, 1], 0.0)
    assert np.linalg.norm(platform_points(free.platform_anchors, pose)[0] - b1) == pytest.approx(0.16)
    with pytest.raises(SingularPose, match='m1 is stretched or folded'):
        free.jacobian(pose)
    assert free.condition(pose) == math.inf
    assert not free.in_workspace(pose)


def test_concurrent_distal_lines_are_a_parallel_singularity():
    # build a 3-RRR whose distal lines all pass through C at the pose P: A singular
    plat = np.array([[-0.05, -0.03], [0.05, -0.03], [0.0, 0.06]])
    pose = (0.01, 0.02, 0.3)
    a = platform_points(plat, pose)
    c = np.array([0.2, 0.5])
    l, r = 0.09, 0.07
    m = np.array([ai + l * (c - ai) / np.linalg.norm(c - ai) for ai in a])
    base = np.array([mi + r * np.array([math.cos(k), math.sin(k)]) for mi, k in zip(m, (0.4, 2.0, -1.7))])
    # the working mode of this assembly, from the elbow side (written out)
    u, w = m - base, a - m
    mode = tuple(int(v) for v in np.sign(u[:, 0] * w[:, 1] - u[:, 1] * w[:, 0]))
    mech = Rrr3(base, r, l, plat, (-math.pi, math.pi), home_pose=pose, working_mode=mode)
    assert mech.condition(pose) > 1e8
    with pytest.raises(SingularPose, match='cond'):
        mech.check_singularity(pose)
    assert not mech.in_workspace(pose)


# ---------------------------------------------------------------- validation, config
BAD = [[np.nan, 0.0, 0.0], [0.0, np.inf, 0.0], [0.0, 0.0], [0.0, 0.0, 0.0, 1.0], 'abc', [[0.0, 0.0, 0.0]]]


@pytest.mark.parametrize('bad', BAD, ids=['nan', 'inf', 'short', 'long', 'str', 'nested'])
@pytest.mark.parametrize('method', ['inverse', 'forward', 'jacobian', 'condition', 'in_workspace',
                                    'wrench_pose', 'wrench_tau', 'nearest_q', 'nearest_hint'])
def test_malformed_input_raises_value_error(neck, bad, method):
    good = [0.0, 0.0, 0.0]
    q = list(neck.inverse(good))
    calls = {
        'inverse': lambda: neck.inverse(bad), 'forward': lambda: neck.forward(bad),
        'jacobian': lambda: neck.jacobian(bad), 'condition': lambda: neck.condition(bad),
        'in_workspace': lambda: neck.in_workspace(bad),
        'wrench_pose': lambda: neck.wrench(bad, [1.0, 1.0, 1.0]), 'wrench_tau': lambda: neck.wrench(good, bad),
        'nearest_q': lambda: neck.forward_nearest(bad, good), 'nearest_hint': lambda: neck.forward_nearest(q, bad),
    }
    with pytest.raises(ValueError, match=r'(pose|q|forces|hint_pose).*(expected|non-finite)'):
        calls[method]()


@pytest.mark.parametrize('kwargs, match', [
    (dict(base_pivots=[[0, 0], [1, 0]]), 'base_pivots'),
    (dict(proximal_lengths=[0.08, -0.08, 0.08]), 'proximal_lengths'),
    (dict(distal_lengths=[0.08, np.nan, 0.08]), 'distal_lengths'),
    (dict(joint_range=(1.0, -1.0)), 'joint_range'),
    (dict(working_mode=(1, 0, 1)), 'working_mode'),
    (dict(working_mode=(1, 1)), 'working_mode'),
    (dict(actuator_names=('m1', 'm1', 'm3')), 'actuator_names'),
    (dict(home_pose=[0.0, -0.2, 0.0]), 'cannot close'),
])
def test_constructor_rejects_bad_arguments(neck, kwargs, match):
    args = dict(base_pivots=neck.base_pivots, proximal_lengths=0.08, distal_lengths=0.08,
                platform_anchors=neck.platform_anchors, joint_range=(-math.pi, math.pi))
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        Rrr3(args.pop('base_pivots'), args.pop('proximal_lengths'), args.pop('distal_lengths'),
             args.pop('platform_anchors'), args.pop('joint_range'), **args)


def test_load_mechanism_neck_brace_3rrr(neck):
    assert isinstance(neck, Rrr3) and isinstance(neck, Mechanism)
    assert neck.dof == 3 and neck.n_actuators == 3 and neck.working_mode == (1, 1, 1)
    home = neck.home_pose
    assert neck.in_workspace(home) and neck.condition(home) < 100
    check_closure(neck, home, neck.inverse(home), (1, 1, 1))
    # the report's equilateral platform: side d = 0.10 m, end effector at the centroid
    pa = neck.platform_anchors
    np.testing.assert_allclose([np.linalg.norm(pa[i] - pa[j]) for i, j in ((0, 1), (1, 2), (0, 2))], 0.1, atol=1e-5)
    np.testing.assert_allclose(pa.mean(axis=0), 0.0, atol=1e-6)


_c = st.floats(-0.4, 0.4, allow_nan=False)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much])
@given(base=st.lists(_c, min_size=6, max_size=6), plat=st.lists(_c, min_size=6, max_size=6),
       r=st.floats(0.1, 0.5), q=st.lists(st.floats(-math.pi, math.pi), min_size=3, max_size=3),
       x=_c, y=_c, phi=st.floats(-math.pi, math.pi))
def test_property_fk_contains_the_pose_of_random_architectures(base, plat, r, q, x, y, phi):
    # build the mechanism around a pose: elbows from q, distal lengths from the pose
    base = np.reshape(base, (3, 2))
    plat = np.reshape(plat, (3, 2))
    pose = (x, y, phi)
    m = elbows_of(base, r, q)
    a = platform_points(plat, pose)
    dist = np.linalg.norm(a - m, axis=1)
    apart = min(np.linalg.norm(plat[i] - plat[j]) + np.linalg.norm(m[i] - m[j]) for i, j in ((0, 1), (0, 2), (1, 2)))
    if np.min(dist) < 0.02 or np.min(np.linalg.norm(a - base, axis=1)) < 0.02 or apart < 0.05:
        return
    try:
        mech = Rrr3(base, r, dist, plat, (-math.pi, math.pi), home_pose=pose)
        if mech.condition(pose) > 1e5:
            return
        sols = mech.forward(q)
    except SingularPose:
        return
    assert any(np.allclose(s[:2], pose[:2], atol=1e-6) and abs(wrap(s[2] - phi)) < 1e-6 for s in sols)
    for s in sols:
        check_closure(mech, s, q)
    assert len(sols) <= 6
