"""``wrench_capacity`` / ``wrench_capacity_batch`` against a brute-force oracle and published numbers.

Oracle (written here, no call into the capacity code): the wrench map ``G`` of the pose —
for the planar n-RPR from the leg geometry (columns ``(u_i, rho_i x u_i)``), for the
others from the public ``wrench`` probed with unit efforts (its convention is tested in
each model's own module) — then the largest ``w`` such that both ``+w e_axis`` and
``-w e_axis`` are ``G (f - b)`` for efforts ``f`` in the box (a cable: the half box
``[-limit, 0]``): feasibility by bounded least squares (``scipy.optimize.lsq_linear``,
BVLS), the largest feasible ``w`` by doubling then bisection. Published numbers: the
lumbar brace's leg forces for 10 N sideways at x = 0, y = 390 mm (the issue).
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.optimize import lsq_linear

from brace_control.mechanisms import Rpr3, UnreachablePose, load_mechanism
from brace_control.mechanisms.rpr4 import Rpr4

LUMBAR_LIMIT = 250.0           # N, actuator.max_force of config/lumbar_brace.yaml


# ---------------------------------------------------------------- the oracle
def rpr_wrench_map(base: np.ndarray, plat: np.ndarray, pose) -> np.ndarray:
    """``G = J^T`` (3, n) of a planar n-RPR: column i = (u_i, rho_i x u_i), u_i unit A_i -> B_i."""
    x, y, t = pose
    c, s = math.cos(t), math.sin(t)
    cols = []
    for (ax, ay), (bx, by) in zip(base, plat):
        rx, ry = c * bx - s * by, s * bx + c * by
        dx, dy = x + rx - ax, y + ry - ay
        n = math.hypot(dx, dy)
        ux, uy = dx / n, dy / n
        cols.append((ux, uy, rx * uy - ry * ux))
    return np.array(cols).T


def probed_wrench_map(mech, pose) -> tuple[np.ndarray, np.ndarray]:
    """``(G, b)`` from the public ``wrench``: b = the unloaded efforts, columns wrench(b + e_i) - wrench(b)."""
    bias = np.asarray(mech.unloaded_forces(mech.inverse(pose)), dtype=float)
    w0 = mech.wrench(pose, bias)
    eye = np.eye(mech.n_actuators)
    return np.column_stack([mech.wrench(pose, bias + eye[i]) - w0 for i in range(mech.n_actuators)]), bias


def feasible(g: np.ndarray, lo: np.ndarray, hi: np.ndarray, target: np.ndarray) -> bool:
    res = lsq_linear(g, target, bounds=(lo, hi), method='bvls', tol=1e-13)
    return float(np.linalg.norm(g @ res.x - target)) <= 1e-9 * (1.0 + float(np.linalg.norm(target)))


def oracle_capacity(g: np.ndarray, lo: np.ndarray, hi: np.ndarray, axis: int, *,
                    bias: np.ndarray | None = None) -> float:
    """Largest w with both +-w e_axis feasible (doubling, then 50 bisections)."""
    b = np.zeros(g.shape[1]) if bias is None else bias
    lo_c, hi_c = lo - b, hi - b
    e = np.zeros(g.shape[0])
    e[axis] = 1.0

    def ok(w: float) -> bool:
        return feasible(g, lo_c, hi_c, w * e) and feasible(g, lo_c, hi_c, -w * e)

    if not ok(0.0):
        return 0.0
    w_lo, w_hi = 0.0, 1e-3
    while ok(w_hi):
        w_lo, w_hi = w_hi, 2.0 * w_hi
        assert w_hi < 1e9
    for _ in range(50):
        mid = 0.5 * (w_lo + w_hi)
        w_lo, w_hi = (mid, w_hi) if ok(mid) else (w_lo, mid)
    return 0.5 * (w_lo + w_hi)


def assert_matches_oracle(mech, pose, limits, g, *, cable: bool = False, bias=None, rtol=1e-6):
    lim = np.broadcast_to(np.asarray(limits, dtype=float), (g.shape[1],))
    lo, hi = -lim, (np.zeros_like(lim) if cable else lim)
    cap = mech.wrench_capacity(pose, limits)
    for a in range(g.shape[0]):
        expected = oracle_capacity(g, lo, hi, a, bias=bias)
        assert cap[a] == pytest.approx(expected, rel=rtol, abs=1e-7 * float(np.max(lim))), (pose, a, cap, expected)
    return cap


@pytest.fixture(scope='module')
def lumbar() -> Rpr3:
    return load_mechanism('config/lumbar_brace.yaml')


# ---------------------------------------------------------------- the lumbar brace: published numbers
@pytest.mark.parametrize('theta_deg, forces', [(5.0, (1770.0, -3515.0, 1751.0)), (10.0, (800.0, -1579.0, 782.0)),
                                               (30.0, (127.0, -232.0, 108.0))])
def test_leg_forces_for_10_n_sideways_are_the_published_ones(lumbar, theta_deg, forces):
    """The oracle's statics reproduce the issue's numbers (base-frame Fx, push positive)."""
    pose = (0.0, 0.390, math.radians(theta_deg))
    g = rpr_wrench_map(lumbar.base_anchors, lumbar.platform_anchors, pose)
    f = np.linalg.solve(g, [10.0, 0.0, 0.0])
    np.testing.assert_allclose(f, forces, atol=1.0)


@pytest.mark.parametrize('theta_deg, leg2_force', [(5.0, 3515.0), (10.0, 1579.0)])
def test_lumbar_lateral_capacity_with_250_n_actuators(lumbar, theta_deg, leg2_force):
    pose = (0.0, 0.390, math.radians(theta_deg))
    cap, limiting = lumbar.wrench_capacity(pose, LUMBAR_LIMIT, return_limiting=True)
    # the published leg forces for 10 N: the middle leg binds first
    assert cap[0] == pytest.approx(LUMBAR_LIMIT * 10.0 / leg2_force, rel=5e-4)
    assert lumbar.actuator_names[limiting[0]] == 'a2'
    assert_matches_oracle(lumbar, pose, LUMBAR_LIMIT,
                          rpr_wrench_map(lumbar.base_anchors, lumbar.platform_anchors, pose))


def test_lumbar_30_deg_is_outside_the_stroke_and_the_geometry_gives_10_8_n(lumbar):
    pose = (0.0, 0.390, math.radians(30.0))
    with pytest.raises(UnreachablePose, match='a1'):       # a1 would need 0.296 m < 0.340 m
        lumbar.wrench_capacity(pose, LUMBAR_LIMIT)
    assert np.isnan(lumbar.wrench_capacity_batch(np.array([pose]), LUMBAR_LIMIT)).all()
    wide = Rpr3(lumbar.base_anchors, lumbar.platform_anchors, (0.2, 0.6), home_pose=lumbar.home_pose)
    cap, limiting = wide.wrench_capacity(pose, LUMBAR_LIMIT, return_limiting=True)
    assert cap[0] == pytest.approx(LUMBAR_LIMIT * 10.0 / 232.0, rel=5e-4)
    assert limiting[0] == 1


def test_lumbar_singular_pose_has_zero_capacity_along_the_unsupported_directions(lumbar):
    """theta = 0: the legs meet at the rings' homothety centre, above P on the y axis when x = 0."""
    pose = (0.0, 0.390, 0.0)
    g = rpr_wrench_map(lumbar.base_anchors, lumbar.platform_anchors, pose)
    cap, limiting = lumbar.wrench_capacity(pose, LUMBAR_LIMIT, return_limiting=True)
    assert cap[0] == 0.0 and cap[2] == 0.0 and limiting[0] == limiting[2] == -1
    lim = np.full(3, LUMBAR_LIMIT)
    assert oracle_capacity(g, -lim, lim, 0) < 1e-6 and oracle_capacity(g, -lim, lim, 2) < 1e-6
    assert cap[1] == pytest.approx(oracle_capacity(g, -lim, lim, 1), rel=1e-6)
    assert cap[1] == pytest.approx(749.2, abs=0.1)                 # all three legs push, x cancels
    # off the axis the vertical force misses the centre too
    off = (0.01, 0.390, 0.0)
    np.testing.assert_array_equal(lumbar.wrench_capacity(off, LUMBAR_LIMIT), [0.0, 0.0, 0.0])
    batch = lumbar.wrench_capacity_batch(np.array([pose, off]), LUMBAR_LIMIT)
    np.testing.assert_allclose(batch, [cap, [0.0, 0.0, 0.0]], rtol=1e-9)


def test_raising_the_limiting_actuator_raises_the_capacity_and_no_other_does(lumbar):
    pose = (0.01, 0.385, math.radians(12.0))
    base = np.full(3, LUMBAR_LIMIT)
    cap, limiting = lumbar.wrench_capacity(pose, base, return_limiting=True)
    for a in range(3):
        for i in range(3):
            raised = base.copy()
            raised[i] *= 1.01
            new = lumbar.wrench_capacity(pose, raised)[a]
            if i == limiting[a]:
                assert new == pytest.approx(1.01 * cap[a], rel=1e-9)
            else:
                assert new == pytest.approx(cap[a], rel=1e-12)


# ---------------------------------------------------------------- other devices against the oracle
def test_general_3rpr_random_anchors_match_the_oracle():
    rng = np.random.default_rng(21)
    done = 0
    while done < 4:
        base, plat = rng.uniform(-0.3, 0.3, (3, 2)), rng.uniform(-0.15, 0.15, (3, 2))
        try:
            mech = Rpr3(base, plat, (0.05, 0.6))
        except ValueError:
            continue
        pose = mech.home_pose + np.array([*rng.uniform(-0.02, 0.02, 2), rng.uniform(-0.2, 0.2)])
        if not mech.in_workspace(pose):
            continue
        limits = rng.uniform(50.0, 300.0, 3)
        assert_matches_oracle(mech, pose, limits, rpr_wrench_map(base, plat, pose))
        done += 1


@pytest.fixture(scope='module')
def neck() -> Rpr4:
    return load_mechanism('config/neck_brace_4rpr.yaml')


@pytest.mark.parametrize('actuation', ['cable', 'rod'])
def test_4rpr_cables_and_rods_match_the_oracle(neck, actuation):
    mech = neck if actuation == 'cable' else Rpr4(neck.base_anchors, neck.platform_anchors, (0.1, 0.3),
                                                  actuation='rod', force_max=120.0)
    rng = np.random.default_rng(22)
    for pose in [mech.home_pose, (0.01, -0.02, 0.1), (-0.03, 0.01, -0.2)] + \
            [tuple(rng.uniform(-0.04, 0.04, 2)) + (float(rng.uniform(-0.3, 0.3)),) for _ in range(2)]:
        g = rpr_wrench_map(mech.base_anchors, mech.platform_anchors, pose)
        cap = assert_matches_oracle(mech, pose, 120.0, g, cable=(actuation == 'cable'))
        batch = mech.wrench_capacity_batch(np.array([pose]), 120.0)[0]
        np.testing.assert_allclose(batch, cap, rtol=1e-7)


def test_cables_hold_less_than_rods_of_the_same_rating(neck):
    rods = Rpr4(neck.base_anchors, neck.platform_anchors, (0.1, 0.3), actuation='rod')
    poses = neck.home_pose + np.random.default_rng(23).uniform(-0.03, 0.03, (50, 3))
    cable, rod = neck.wrench_capacity_batch(poses, 120.0), rods.wrench_capacity_batch(poses, 120.0)
    ok = np.isfinite(cable).all(axis=1)
    assert ok.sum() > 30
    assert np.all(cable[ok] <= rod[ok] * (1 + 1e-9))
    assert np.any(cable[ok] < 0.9 * rod[ok])


def test_shoulder_moments_match_the_oracle():
    mech = load_mechanism('config/shoulder.yaml')
    rng = np.random.default_rng(24)
    poses = [mech.home_pose, np.radians([30.0, -20.0, 10.0])]
    while len(poses) < 5:
        p = np.array([rng.uniform(-0.17, 1.5), rng.uniform(-1.5, 0.3), rng.uniform(-0.7, 0.8)])
        if mech.in_workspace(p):
            poses.append(p)
    for pose in poses:
        g, _ = probed_wrench_map(mech, pose)
        assert_matches_oracle(mech, pose, 25.0, g)


def test_upper_limb_trainer_force_along_the_path_is_torque_over_path_speed():
    """One DOF: T2 theta2_dot = F_s s_dot, so F_s = T2 / |dP/dtheta2|; |dP/dtheta2| by a central
    difference of the coupler point."""
    mech = load_mechanism('config/upper_limb_trainer.yaml')
    assert mech.wrench_axes == ('F_path',)
    for th in np.radians([-40.0, 0.0, 90.0, 150.0, 200.0, 260.0]):
        pose = mech.forward_branch(th)
        h = 1e-6
        speed = np.linalg.norm(mech.forward_branch(th + h) - mech.forward_branch(th - h)) / (2 * h)
        cap, limiting = mech.wrench_capacity(pose, 5.0, return_limiting=True)
        assert cap.shape == (1,) and limiting[0] == 0
        assert cap[0] == pytest.approx(5.0 / speed, rel=1e-7)
        # the oracle on the probed map (the wrench projected on the path)
        g, _ = probed_wrench_map(mech, pose)
        t_hat = g[:, 0] / np.linalg.norm(g[:, 0])
        assert cap[0] == pytest.approx(oracle_capacity(t_hat[None] @ g, np.array([-5.0]), np.array([5.0]), 0),
                                       rel=1e-6)


def test_continuum_capacity_accounts_for_the_bars_push():
    mech = load_mechanism('config/continuum.yaml')
    for y in (0.05, 0.10, mech.y0, 0.17):
        pose = np.array([0.0, y])
        g, bias = probed_wrench_map(mech, pose)
        cap = assert_matches_oracle(mech, pose, 50.0, g, bias=bias)
        # Fx: both sliders push the same way, each with 50 N less its share of the bars' push
        assert cap[0] == pytest.approx(2.0 * (50.0 - abs(bias[0])), rel=1e-9)


def test_stretched_arm_holds_any_radial_force_and_the_moment_arm_limits_the_other():
    """Serial singularity (the scalar wrench map is infinite there): a force along the
    stretched arm needs no torque; across it, tau1 = (l1 + l2) F and tau2 = l2 F."""
    from brace_control.mechanisms import Rr2
    arm = Rr2([0.15, 0.12], (-math.pi, math.pi), elbow='up', home_pose=[0.1, 0.1])
    cap, limiting = arm.wrench_capacity([0.27, 0.0], 6.0, return_limiting=True)
    assert math.isinf(cap[0]) and limiting[0] == -1
    assert cap[1] == pytest.approx(6.0 / 0.27, rel=1e-12) and limiting[1] == 0
    np.testing.assert_allclose(arm.wrench_capacity_batch(np.array([[0.27, 0.0]]), 6.0)[0], cap, rtol=1e-12)


# ---------------------------------------------------------------- batch == scalar, unreachable rows, errors
CONFIGS = ['lumbar_brace', 'neck_brace_4rpr', 'neck_brace_3rrr', 'neck_brace_2r', 'shoulder',
           'upper_limb_trainer', 'continuum']


@pytest.mark.parametrize('name', CONFIGS)
def test_batch_equals_scalar_and_nan_where_unreachable(name):
    import yaml
    mech = load_mechanism(f'config/{name}.yaml')
    doc = yaml.safe_load(open(f'config/{name}.yaml'))
    limit = float(doc['/**']['ros__parameters']['actuator']['max_force'])
    rng = np.random.default_rng(25)
    home = mech.home_pose
    spread = {'shoulder': 0.8, 'neck_brace_2r': 0.1, 'continuum': 0.08}.get(name, 0.06)
    poses = home + rng.uniform(-spread, spread, (120, mech.dof))
    if name == 'upper_limb_trainer':
        p = mech.position_analysis(rng.uniform(-math.pi, math.pi, 120))['P']
        poses = np.column_stack([p.real, p.imag])
    cap, which = mech.wrench_capacity_batch(poses, limit, return_limiting=True)
    assert cap.shape == which.shape == (len(poses), len(mech.wrench_axes))
    # the continuum's Jacobian is a finite difference (~1e-8 rounding, see test_batch_kinematics)
    rtol = {'continuum': 1e-6, 'neck_brace_4rpr': 1e-7}.get(name, 1e-9)
    reachable = 0
    for pose, row, wrow in zip(poses, cap, which):
        try:
            expected, limiting = mech.wrench_capacity(pose, limit, return_limiting=True)
        except UnreachablePose:
            assert np.isnan(row).all() and np.all(wrow == -1)
            continue
        reachable += 1
        np.testing.assert_allclose(row, expected, rtol=rtol)
        # where the two name different actuators (a tie, e.g. the continuum's two sliders),
        # the batch's is binding too: lowering its limit alone lowers the capacity
        for a in range(len(row)):
            if wrow[a] != limiting[a]:
                assert wrow[a] >= 0
                lowered = np.full(mech.n_actuators, limit)
                lowered[wrow[a]] *= 0.99
                assert mech.wrench_capacity(pose, lowered)[a] < row[a] * (1 - 1e-3)
    assert 10 <= reachable


def test_force_limit_errors_name_the_parameter(lumbar):
    pose = lumbar.home_pose
    for bad in (0.0, -250.0, float('nan'), [250.0, 250.0], 'lots'):
        with pytest.raises(ValueError, match='force_limits'):
            lumbar.wrench_capacity(pose, bad)
        with pytest.raises(ValueError, match='force_limits'):
            lumbar.wrench_capacity_batch(pose[None], bad)
    with pytest.raises(ValueError, match=r'poses: expected shape \(N, 3\)'):
        lumbar.wrench_capacity_batch(pose, LUMBAR_LIMIT)
    with pytest.raises(ValueError, match='pose'):
        lumbar.wrench_capacity([0.0, float('inf'), 0.1], LUMBAR_LIMIT)
    # an unbounded actuator: the capacity is unbounded, nothing limits it
    cap, limiting = lumbar.wrench_capacity(pose, [250.0, math.inf, 250.0], return_limiting=True)
    assert np.isfinite(cap).all()           # the other two legs still bind every axis here
    cap, limiting = lumbar.wrench_capacity(pose, math.inf, return_limiting=True)
    assert np.all(np.isinf(cap)) and np.all(limiting == -1)
