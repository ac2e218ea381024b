"""Planar 3-RPR (lumbar brace) kinematics and kinetics against independent oracles.

Oracles: the paper's equations written out here (eq. 3, eqs. 6-13, eqs. 14-20 with their
errata), central finite differences, an r x F sum, and an independently written
forward-kinematics residual over theta whose sign changes (dense sampling) and brentq
roots count and locate the assembly modes. Nothing here calls the code under test to
build an expected value.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from rpr_oracles import R1, R2, fk_residual, fk_thetas_by_sampling, lumbar_eq3

from brace_control.mechanisms import Mechanism, Rpr3, SingularPose, UnreachablePose, load_mechanism

LO, HI = 0.340, 0.440            # installed length range (m)

# A general 3-RPR with six real assembly modes (found by a search script over rounded
# architectures; the six theta roots are at least 0.8 rad apart). Units: m.
SIX_BASE = [[0.0, 0.0], [0.5, 0.0], [0.6, -0.4]]
SIX_PLATFORM = [[0.0, 0.0], [-0.4, 0.0], [-0.8, -0.7]]
SIX_LENGTHS = [1.06, 0.86, 1.28]


@pytest.fixture(scope='module')
def brace() -> Rpr3:
    return Rpr3([[-R1, 0.0], [0.0, 0.0], [R1, 0.0]], [[-R2, 0.0], [0.0, 0.0], [R2, 0.0]], (LO, HI),
                home_pose=[0.0, 0.39, 0.1])


@pytest.fixture(scope='module')
def six() -> Rpr3:
    return Rpr3(SIX_BASE, SIX_PLATFORM, (0.0, 3.0), home_pose=[0.0, 0.0, 0.0])


# ---------------------------------------------------------------- independent oracles
def lengths_general(base, plat, pose) -> np.ndarray:
    x, y, t = pose
    c, s = math.cos(t), math.sin(t)
    return np.array([math.hypot(x + c * bx - s * by - ax, y + s * bx + c * by - ay)
                     for (ax, ay), (bx, by) in zip(base, plat)])


# fk_residual, fk_thetas_by_sampling: the independent forward oracle, in rpr_oracles.py


def wrap(t: float) -> float:
    return math.pi - (math.pi - t) % (2 * math.pi)


def same_pose(p, q, tol=1e-7) -> bool:
    return abs(p[0] - q[0]) < tol and abs(p[1] - q[1]) < tol and abs(wrap(p[2] - q[2])) < tol


# ---------------------------------------------------------------- inverse kinematics
def test_inverse_matches_paper_eq3(brace):
    rng = np.random.default_rng(3)
    for _ in range(200):
        pose = (rng.uniform(-0.05, 0.05), rng.uniform(0.36, 0.42), rng.uniform(-0.5, 0.5))
        expected = lumbar_eq3(pose)
        if np.all((expected >= LO) & (expected <= HI)):
            np.testing.assert_allclose(brace.inverse(pose), expected, atol=1e-15, rtol=0)
        np.testing.assert_allclose(brace.inverse_batch(np.array([pose]), limits=False)[0], expected, atol=1e-15, rtol=0)


def test_inverse_batch_and_reachable_mask_agree_with_scalar_inverse(brace):
    rng = np.random.default_rng(4)
    poses = np.column_stack([rng.uniform(-0.1, 0.1, 500), rng.uniform(0.3, 0.45, 500), rng.uniform(-0.6, 0.6, 500)])
    q = brace.inverse_batch(poses, limits=False)
    mask = brace.reachable_batch(poses)
    for pose, qi, ok in zip(poses, q, mask):
        np.testing.assert_allclose(qi, lumbar_eq3(pose), atol=1e-15)
        assert ok == bool(np.all((qi >= LO) & (qi <= HI)))
        if ok:
            np.testing.assert_allclose(brace.inverse(pose), qi, atol=1e-15)
        else:
            with pytest.raises(UnreachablePose):
                brace.inverse(pose)
    assert 0 < mask.sum() < mask.size


def test_unreachable_pose_names_actuator_length_and_stroke(brace):
    pose = (0.0, 0.50, 0.0)          # l2 = 0.5 m > 0.44 m
    with pytest.raises(UnreachablePose) as info:
        brace.inverse(pose)
    err = info.value
    assert isinstance(err, ValueError)
    assert err.actuator == 'a1'        # a1 is checked first and is also too long (0.5005 m)
    assert err.value == pytest.approx(lumbar_eq3(pose)[0])
    assert err.limits == (pytest.approx(LO), pytest.approx(HI))
    msg = str(err)
    assert 'a1' in msg and '0.5005' in msg and '0.3400' in msg and '0.4400' in msg
    # per-actuator strokes: only a2 (0.30 m < 0.34 m) is out of range
    with pytest.raises(UnreachablePose, match='a2 would need 0.3000 m'):
        Rpr3([[-R1, 0.0], [0.0, 0.0], [R1, 0.0]], [[-R2, 0.0], [0.0, 0.0], [R2, 0.0]],
             ([0.2, 0.34, 0.2], [0.44, 0.44, 0.44]), home_pose=[0.0, 0.39, 0.1]).inverse((0.0, 0.30, 0.0))


# ---------------------------------------------------------------- forward kinematics: the brace
def paper_fk_candidates(l1: float, l2: float, l3: float) -> list[tuple[float, float, float]]:
    """Paper eqs. 6, 9-13 written out; every sign combination, verified against all lengths."""
    v1 = (2 * l2 ** 2 + 2 * R2 ** 2 + 2 * R1 ** 2 - l1 ** 2 - l3 ** 2) / (4 * R1 * R2)      # eq. 6
    out: list[tuple[float, float, float]] = []
    if abs(v1) > 1.0:
        return out
    for t in (math.acos(v1), -math.acos(v1)):
        a, b, c, d = (l3 ** 2 - l1 ** 2) / 4, R2 * math.cos(t) - R1, R2 * math.sin(t), l2
        disc = (a * b) ** 2 - (b ** 2 + c ** 2) * (a ** 2 - (c * d) ** 2)                  # eq. 9
        if disc < -1e-18:
            continue
        disc = max(disc, 0.0)
        for x in ((a * b + math.sqrt(disc)) / (b ** 2 + c ** 2), (a * b - math.sqrt(disc)) / (b ** 2 + c ** 2)):
            for y in (math.sqrt(l2 ** 2 - x ** 2), -math.sqrt(l2 ** 2 - x ** 2)):            # eq. 7
                if np.max(np.abs(lumbar_eq3((x, y, t)) - [l1, l2, l3])) < 1e-9:
                    out.append((x, y, t))
    return out


def test_brace_is_detected_as_the_aligned_closed_form_case(brace):
    assert brace.architecture == 'aligned'


def test_brace_four_solutions_when_l1_lt_l2_lt_l3(brace):
    q = (0.357, 0.390, 0.425)
    sols = brace.forward(q)
    expected = paper_fk_candidates(*q)
    assert len(expected) == 4 and len(sols) == 4
    for e in expected:
        assert sum(same_pose(s, e, 1e-9) for s in sols) == 1
    for s in sols:
        np.testing.assert_allclose(lumbar_eq3(s), q, atol=1e-12)
        assert -math.pi < s[2] <= math.pi
    # the paper pairs theta >= 0 with y >= 0 (eqs. 10-11) and theta < 0 with y < 0
    # (eqs. 12-13); here every theta has one solution of each sign of y, so the pairing
    # does not hold: check the true mirror structure (x, y, t) <-> (x, -y, -t) instead
    for s in sols:
        assert sum(same_pose(o, (s[0], -s[1], -s[2]), 1e-9) for o in sols) == 1
    assert sum(1 for s in sols if s[1] > 0) == 2
    # a concrete counterexample to the pairing, at the brace's home (theta = 5 deg):
    # the second y > 0 mode has theta < 0
    home = brace.forward(lumbar_eq3((0.0, 0.39, math.radians(5))))
    assert any(s[1] > 0 and s[2] < 0 for s in home)


def test_brace_l1_lt_l2_lt_l3_is_not_always_four_solutions(brace):
    # the paper: "assume l1 < l2 < l3, four solutions". With l1 + l3 = 2 l2 the quadratic
    # eq. 9 has a double root (two assembly modes merge: a singular configuration), and
    # some l1 < l2 < l3 have no solution at all.
    q = (0.36, 0.39, 0.42)
    expected = paper_fk_candidates(*q)
    sols = brace.forward(q)
    assert len(sols) == 2
    for e in expected:
        assert any(same_pose(s, e, 1e-6) for s in sols)
    for s in sols:
        np.testing.assert_allclose(lumbar_eq3(s), q, atol=1e-9)
    assert brace.forward((0.345, 0.400, 0.435)) == [] == paper_fk_candidates(0.345, 0.400, 0.435)


def test_brace_round_trip_on_ten_thousand_workspace_poses(brace):
    rng = np.random.default_rng(2024)
    n = 40_000            # P sampled in leg 2's half annulus, theta in [-30, 30] deg
    rho, phi = np.sqrt(rng.uniform(LO ** 2, HI ** 2, n)), rng.uniform(0.0, math.pi, n)
    poses = np.column_stack([rho * np.cos(phi), rho * np.sin(phi),
                             rng.uniform(-math.radians(30), math.radians(30), n)])
    poses = poses[brace.in_workspace_batch(poses)][:10_000]
    assert len(poses) == 10_000
    worst = 0.0
    for pose in poses:
        q = lumbar_eq3(pose)
        sols = brace.forward(q)
        assert 1 <= len(sols) <= 4
        assert any(same_pose(s, pose, 1e-7) for s in sols), (pose, sols)
        for s in sols:
            worst = max(worst, float(np.max(np.abs(lumbar_eq3(s) - q))))
    assert worst <= 1e-9


def test_brace_singular_theta_zero_still_solved(brace):
    q = lumbar_eq3((0.01, 0.39, 0.0))
    sols = brace.forward(q)
    assert len(sols) == 2
    assert any(same_pose(s, (0.01, 0.39, 0.0), 1e-9) for s in sols)
    assert all(np.max(np.abs(lumbar_eq3(s) - q)) < 1e-9 for s in sols)


def test_brace_no_solution_returns_empty_and_forward_nearest_raises(brace):
    q = (0.34, 0.44, 0.34)     # cos t = (2*0.44^2 + 2 r2^2 + 2 r1^2 - 2*0.34^2) / (4 r1 r2) > 1
    assert (2 * 0.44 ** 2 + 2 * R2 ** 2 + 2 * R1 ** 2 - 2 * 0.34 ** 2) / (4 * R1 * R2) > 1
    assert brace.forward(q) == []
    with pytest.raises(UnreachablePose, match='no assembly mode'):
        brace.forward_nearest(q, (0.0, 0.39, 0.0))


def test_forward_nearest_follows_the_hint_branch(brace):
    pose = np.array([0.02, 0.40, math.radians(8)])
    q = lumbar_eq3(pose)
    np.testing.assert_allclose(brace.forward_nearest(q, pose + [0.003, -0.002, 0.01]), pose, atol=1e-12)
    mirror = np.array([pose[0], -pose[1], -pose[2]])
    np.testing.assert_allclose(brace.forward_nearest(q, mirror), mirror, atol=1e-12)
    # along a path, each step continues the previous branch
    prev = pose
    for k in range(1, 30):
        true = pose + k * np.array([0.001, -0.0005, -0.01])
        got = brace.forward_nearest(lumbar_eq3(true), prev)
        np.testing.assert_allclose(got, true, atol=1e-10)
        prev = got


# ---------------------------------------------------------------- forward kinematics: general
def test_general_six_assembly_modes_match_independent_root_count(six):
    assert six.architecture == 'general'
    thetas = fk_thetas_by_sampling(SIX_BASE, SIX_PLATFORM, SIX_LENGTHS)
    assert len(thetas) == 6
    sols = six.forward(SIX_LENGTHS)
    assert len(sols) == 6
    got = sorted(s[2] for s in sols)
    np.testing.assert_allclose(got, sorted(thetas), atol=1e-9)
    for s in sols:
        np.testing.assert_allclose(lengths_general(SIX_BASE, SIX_PLATFORM, s), SIX_LENGTHS, atol=1e-9)


def test_general_round_trip_and_root_count_on_random_architectures():
    rng = np.random.default_rng(11)
    counts: dict[int, int] = {}
    for _ in range(60):
        base = rng.normal(size=(3, 2)) * 0.3
        plat = rng.normal(size=(3, 2)) * 0.3 * rng.uniform(0.3, 1.5)
        mech = Rpr3(base, plat, (0.0, 5.0), home_pose=[0.0, 0.0, 0.0])
        pose = (rng.normal() * 0.4, rng.normal() * 0.4, rng.uniform(-math.pi, math.pi))
        q = lengths_general(base, plat, pose)
        sols = mech.forward(q)
        assert any(same_pose(s, pose, 1e-7) for s in sols)
        for s in sols:
            np.testing.assert_allclose(lengths_general(base, plat, s), q, atol=1e-9)
        assert len(sols) == len(fk_thetas_by_sampling(base, plat, q, n=40_001))
        counts[len(sols)] = counts.get(len(sols), 0) + 1
    assert set(counts) <= {2, 4, 6} and len(counts) >= 2


def test_root_at_theta_pi_is_found():
    # theta = pi is where a tan-half-angle substitution loses its root
    base = [[0.0, 0.0], [0.6, 0.1], [0.2, 0.7]]
    plat = [[0.1, -0.1], [0.5, 0.2], [-0.2, 0.4]]
    mech = Rpr3(base, plat, (0.0, 5.0), home_pose=[0.0, 0.0, 0.0])
    for pose in ((0.3, 0.9, math.pi), (0.3, 0.9, -math.pi), (-0.2, 0.5, math.pi - 1e-12)):
        sols = mech.forward(lengths_general(base, plat, pose))
        assert any(same_pose(s, pose, 1e-8) for s in sols)
        assert all(-math.pi < s[2] <= math.pi for s in sols)


def test_mirror_degenerate_architecture_round_trip():
    # platform triangle = base triangle mirrored: the Cramer determinant vanishes for all theta
    base = [[0.0, 0.0], [0.4, 0.0], [0.12, 0.2]]
    plat = [[0.0, 0.0], [0.4, 0.0], [0.12, -0.2]]
    mech = Rpr3(base, plat, (0.0, 5.0), home_pose=[0.1, 0.5, 0.3])
    assert mech.architecture == 'mirror'
    rng = np.random.default_rng(5)
    for _ in range(100):
        pose = (rng.normal() * 0.3, rng.normal() * 0.3, rng.uniform(-math.pi, math.pi))
        q = lengths_general(base, plat, pose)
        sols = mech.forward(q)
        assert any(same_pose(s, pose, 1e-7) for s in sols)
        for s in sols:
            np.testing.assert_allclose(lengths_general(base, plat, s), q, atol=1e-9)


def test_self_motion_raises_singular_pose():
    # congruent base and platform, equal legs: the platform translates on a circle
    tri = [[0.0, 0.0], [0.3, 0.0], [0.1, 0.25]]
    mech = Rpr3(tri, tri, (0.0, 1.0), home_pose=[0.0, 0.4, 0.0])
    with pytest.raises(SingularPose, match='self-motion'):
        mech.forward([0.4, 0.4, 0.4])
    # aligned class with r1 = r2 (parallelogram-like): at theta = 0 with equal legs
    par = Rpr3([[-0.2, 0.0], [0.0, 0.0], [0.2, 0.0]], [[-0.2, 0.0], [0.0, 0.0], [0.2, 0.0]], (0.0, 1.0),
               home_pose=[0.0, 0.4, 0.1])
    with pytest.raises(SingularPose, match='self-motion'):
        par.forward([0.4, 0.4, 0.4])
    assert len(par.forward(lengths_general(par.base_anchors, par.platform_anchors, (0.05, 0.38, 0.2)))) >= 1


def test_general_forward_nearest_picks_each_mode(six):
    sols = six.forward(SIX_LENGTHS)
    for s in sols:
        np.testing.assert_allclose(six.forward_nearest(SIX_LENGTHS, s + [1e-3, -1e-3, 1e-2]), s, atol=1e-12)


# ---------------------------------------------------------------- differential kinematics and kinetics
@pytest.mark.parametrize('pose', [(0.0, 0.39, 0.2), (0.03, 0.37, -0.4), (-0.05, 0.41, 0.5)])
def test_jacobian_matches_central_finite_differences(brace, pose):
    h = 1e-6
    fd = np.column_stack([(lumbar_eq3(np.add(pose, h * e)) - lumbar_eq3(np.subtract(pose, h * e))) / (2 * h)
                          for e in np.eye(3)])
    np.testing.assert_allclose(brace.jacobian(pose), fd, atol=1e-8)


def test_general_jacobian_matches_finite_differences(six):
    pose = six.forward(SIX_LENGTHS)[2]
    h = 1e-6
    fd = np.column_stack([(lengths_general(SIX_BASE, SIX_PLATFORM, pose + h * e)
                           - lengths_general(SIX_BASE, SIX_PLATFORM, pose - h * e)) / (2 * h) for e in np.eye(3)])
    np.testing.assert_allclose(six.jacobian(pose), fd, atol=1e-8)


def paper_eq20(pose, forces, *, squared_denominator: bool) -> np.ndarray:
    """Paper eqs. 14-20 as printed (squared_denominator=True) or with unit vectors."""
    x, y, t = pose
    f1, f2, f3 = forces
    c, s = math.cos(t), math.sin(t)
    vecs = [(x - R2 * c + R1, y - R2 * s), (x, y), (x + R2 * c - R1, y + R2 * s)]
    dirs = []
    for vx, vy in vecs:
        den = vx ** 2 + vy ** 2
        den = den if squared_denominator else math.sqrt(den)
        dirs.append((vx / den, vy / den))
    (ca, sa), (cb, sb), (cg, sg) = dirs
    f1x, f1y, f2x, f2y, f3x, f3y = f1 * ca, f1 * sa, f2 * cb, f2 * sb, f3 * cg, f3 * sg
    return np.array([f1x + f2x + f3x, f1y + f2y + f3y,
                     (f1y - f3y) * R2 * c + (f3x - f1x) * R2 * s])


def test_wrench_matches_eq20_with_errata(brace):
    pose, forces = (0.02, 0.39, 0.3), (120.0, -40.0, 75.0)
    w = brace.wrench(pose, forces)
    eq20 = paper_eq20(pose, forces, squared_denominator=False)
    np.testing.assert_allclose(w[:2], eq20[:2], rtol=1e-12)
    np.testing.assert_allclose(w[2], -eq20[2], rtol=1e-12)      # erratum 2: opposite sign
    # erratum 1: as printed (squared length in the denominator) the forces are wrong
    printed = paper_eq20(pose, forces, squared_denominator=True)
    assert not np.allclose(printed[:2], w[:2], rtol=0.1)


def test_wrench_matches_independent_r_cross_f_sum(six):
    pose = six.forward(SIX_LENGTHS)[4]
    forces = np.array([30.0, -12.0, 55.0])
    x, y, t = pose
    c, s = math.cos(t), math.sin(t)
    total = np.zeros(3)
    for (ax, ay), (bx, by), f in zip(SIX_BASE, SIX_PLATFORM, forces):
        rx, ry = c * bx - s * by, s * bx + c * by          # P -> B_i
        dx, dy = x + rx - ax, y + ry - ay                  # A_i -> B_i
        n = math.hypot(dx, dy)
        fx, fy = f * dx / n, f * dy / n
        total += (fx, fy, rx * fy - ry * fx)
    np.testing.assert_allclose(six.wrench(pose, forces), total, rtol=1e-12, atol=1e-12)


def test_wrench_is_virtual_work_dual_of_jacobian(brace):
    pose, forces = np.array([0.01, 0.4, 0.2]), np.array([10.0, 20.0, -5.0])
    xdot = np.array([0.003, -0.002, 0.05])
    qdot = brace.jacobian(pose) @ xdot
    assert forces @ qdot == pytest.approx(brace.wrench(pose, forces) @ xdot, rel=1e-12)


# ---------------------------------------------------------------- singularity and workspace
def test_brace_theta_zero_is_singular_leg_lines_concurrent(brace):
    x, y = 0.02, 0.39
    # independent: legs 1 and 3 meet at k (x, y), k = r1 / (r1 - r2), a point of leg 2's line
    k = R1 / (R1 - R2)
    for ax, bx in ((-R1, x - R2), (R1, x + R2)):
        cross = (bx - ax) * (k * y) - y * (k * x - ax)
        assert abs(cross) < 1e-12
    with pytest.raises(SingularPose, match='cond'):
        brace.check_singularity((x, y, 0.0))
    assert not brace.in_workspace((x, y, 0.0))
    assert brace.in_workspace((x, y, math.radians(10)))
    brace.check_singularity((x, y, math.radians(10)))
    assert brace.condition((x, y, math.radians(10))) < brace.singularity_condition_max


def test_in_workspace_respects_stroke(brace):
    assert brace.in_workspace((0.0, 0.39, 0.2))
    assert not brace.in_workspace((0.0, 0.50, 0.2))
    assert not brace.in_workspace((0.0, 0.30, 0.2))


# ---------------------------------------------------------------- input validation
BAD = [[np.nan, 0.39, 0.0], [0.0, np.inf, 0.0], [0.0, 0.39], [0.0, 0.39, 0.0, 1.0], 'abc', [[0.0, 0.39, 0.0]]]


@pytest.mark.parametrize('bad', BAD, ids=['nan', 'inf', 'short', 'long', 'str', 'nested'])
@pytest.mark.parametrize('method', ['inverse', 'jacobian', 'condition', 'check_singularity', 'in_workspace',
                                    'forward', 'wrench_pose', 'wrench_forces', 'nearest_q', 'nearest_hint'])
def test_malformed_input_raises_value_error_with_message(brace, bad, method):
    good = [0.0, 0.39, 0.2]
    q = list(lumbar_eq3(good))
    calls = {
        'inverse': lambda: brace.inverse(bad),
        'jacobian': lambda: brace.jacobian(bad),
        'condition': lambda: brace.condition(bad),
        'check_singularity': lambda: brace.check_singularity(bad),
        'in_workspace': lambda: brace.in_workspace(bad),
        'forward': lambda: brace.forward(bad),
        'wrench_pose': lambda: brace.wrench(bad, [1.0, 2.0, 3.0]),
        'wrench_forces': lambda: brace.wrench(good, bad),
        'nearest_q': lambda: brace.forward_nearest(bad, good),
        'nearest_hint': lambda: brace.forward_nearest(q, bad),
    }
    with pytest.raises(ValueError, match=r'(pose|q|forces|hint_pose).*(expected|non-finite)'):
        calls[method]()


def test_batch_input_validation(brace):
    with pytest.raises(ValueError, match=r'shape \(N, 3\)'):
        brace.inverse_batch(np.zeros((4, 2)))
    with pytest.raises(ValueError, match='non-finite'):
        brace.inverse_batch(np.array([[0.0, 0.39, 0.0], [np.nan, 0.39, 0.0]]))


def test_negative_lengths_rejected(brace):
    with pytest.raises(ValueError, match='>= 0'):
        brace.forward([-0.1, 0.39, 0.39])


@pytest.mark.parametrize('kwargs, match', [
    (dict(base_anchors=[[0, 0], [1, 0]]), 'base_anchors'),
    (dict(platform_anchors=[[0, 0], [1, 0], [np.nan, 0]]), 'platform_anchors'),
    (dict(stroke=(0.44, 0.34)), 'stroke'),
    (dict(stroke=(0.3, [0.4, 0.5])), 'stroke'),
    (dict(actuator_names=('a1', 'a1', 'a3')), 'actuator_names'),
    (dict(singularity_condition_max=float('nan')), 'singularity_condition_max'),
    (dict(home_pose=[0.0, 0.6, 0.0]), 'a1 would need'),
    (dict(base_anchors=[[0, 0], [0, 0], [1, 0]], platform_anchors=[[0, 0], [0, 0], [1, 0]]), 'same leg'),
])
def test_constructor_rejects_bad_arguments(kwargs, match):
    args = dict(base_anchors=[[-R1, 0.0], [0.0, 0.0], [R1, 0.0]], platform_anchors=[[-R2, 0.0], [0.0, 0.0], [R2, 0.0]],
                stroke=(LO, HI), home_pose=[0.0, 0.39, 0.1])
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        Rpr3(args.pop('base_anchors'), args.pop('platform_anchors'), args.pop('stroke'), **args)


def test_contract_attributes(brace):
    assert isinstance(brace, Mechanism)
    assert brace.dof == 3 and brace.n_actuators == 3 and brace.actuator_names == ('a1', 'a2', 'a3')
    lo, hi = brace.actuator_limits
    assert lo.shape == hi.shape == (3,)
    np.testing.assert_array_equal(lo, [LO] * 3)
    lo[0] = 0.0                      # a copy: the model is not mutated
    assert brace.actuator_limits[0][0] == LO
    np.testing.assert_array_equal(brace.home_pose, [0.0, 0.39, 0.1])


def test_load_mechanism_lumbar_brace():
    mech = load_mechanism('config/lumbar_brace.yaml')
    assert isinstance(mech, Rpr3) and mech.architecture == 'aligned'
    pose = (0.01, 0.395, math.radians(12))
    np.testing.assert_allclose(mech.inverse(pose), lumbar_eq3(pose), atol=1e-15)


# ---------------------------------------------------------------- property-based round trip
from hypothesis import HealthCheck, assume, example, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

_coord = st.floats(-0.5, 0.5, allow_nan=False, allow_infinity=False)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(base=st.lists(_coord, min_size=6, max_size=6), plat=st.lists(_coord, min_size=6, max_size=6),
       x=_coord, y=_coord, theta=st.floats(-math.pi, math.pi))
# found by a CI run (cond(J) 1205): a double root came out as two poses 6e-8 m apart, seven in all
@example(base=[-0.125, 0.0, 0.0, 0.0, 0.3125, 0.078125], plat=[-0.125, 0.0, 0.0, 0.09375, 0.3125, 0.078125],
         x=0.0, y=-0.5, theta=0.009765625)
def test_property_fk_of_ik_contains_the_pose_for_any_architecture(base, plat, x, y, theta):
    base = np.reshape(base, (3, 2))
    plat = np.reshape(plat, (3, 2))
    # keep architectures that are a mechanism (anchors apart) and poses away from singularities
    assume(min(np.linalg.norm(base[i] - base[j]) + np.linalg.norm(plat[i] - plat[j])
               for i, j in ((0, 1), (0, 2), (1, 2))) > 0.05)
    pose = (x, y, theta)
    q = lengths_general(base, plat, pose)
    assume(np.min(q) > 1e-3)
    mech = Rpr3(base, plat, (0.0, 5.0), home_pose=pose)
    assume(mech.condition(pose) < 1e5)
    try:
        sols = mech.forward(q)
    except SingularPose:
        # a genuine self-motion: the independent residual vanishes for every theta
        th = np.linspace(-math.pi, math.pi, 97)
        scale = np.max(np.abs(fk_residual(base, plat, q + 0.01, th)))
        assert np.max(np.abs(fk_residual(base, plat, q, th))) <= 1e-9 * scale
        return
    assert any(same_pose(s, pose, 1e-6) for s in sols), (mech.architecture, sols)
    for s in sols:
        np.testing.assert_allclose(lengths_general(base, plat, s), q, atol=1e-9)
    assert len(sols) <= 6
