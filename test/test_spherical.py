"""Spherical 3-RRR (the shoulder joint, seed paper 004) against independent oracles.

Oracles written here, not taken from the code under test: the rotation from
``scipy.spatial.transform.Rotation`` (intrinsic 'YXZ'), the leg geometry (Gosselin's
unit vectors) written out, the closure ``w_i . v_i = cos alpha2_i``, central finite
differences, virtual work, and a multi-start Newton search on SO(3) (a different
formulation: three leg equations in a rotation increment) that counts the assembly modes.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from brace_control.mechanisms import SingularPose, UnreachablePose, load_mechanism
from brace_control.mechanisms.spherical import (PAPER_DESIGN_DEG, WORKING_MODES, Spherical3Rrr,
                                                design_from_degrees)
from brace_control.tools import spm_study

DES = design_from_degrees(PAPER_DESIGN_DEG)
RANGES = np.radians([[-10, 90], [-90, 20], [-40, 50]])


@pytest.fixture(scope='module')
def shoulder() -> Spherical3Rrr:
    return Spherical3Rrr(DES['gamma'], DES['beta'], DES['alpha1'], DES['alpha2'], DES['delta'],
                         working_mode='++-')


def q_of(pose) -> np.ndarray:
    """Independent: Q = R_y(a) R_x(-f) R_z(-r) via scipy (intrinsic YXZ)."""
    return Rotation.from_euler('YXZ', [pose[0], -pose[1], -pose[2]]).as_matrix()


def legs():
    """Independent: Gosselin's unit vectors, as documented (u_i, e1_i, e2_i, v_i^P)."""
    g, b, d = DES['gamma'], DES['beta'], DES['delta']
    u = np.array([[math.cos(di) * math.sin(g), math.sin(di) * math.sin(g), -math.cos(g)] for di in d])
    z = np.array([0.0, 0.0, 1.0])
    e1 = np.array([z - (ui @ z) * ui for ui in u])
    e1 /= np.linalg.norm(e1, axis=1)[:, None]
    e2 = np.cross(u, e1)
    vp = np.array([[math.cos(di) * math.sin(b), math.sin(di) * math.sin(b), math.cos(b)] for di in d])
    return u, e1, e2, vp


def elbow(theta):
    u, e1, e2, _ = legs()
    a1 = DES['alpha1']
    return np.array([math.cos(a1[i]) * u[i] + math.sin(a1[i]) * (math.cos(theta[i]) * e1[i]
                                                                 + math.sin(theta[i]) * e2[i]) for i in range(3)])


def random_poses(n, seed):
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(lo, hi, n) for lo, hi in RANGES])


# ---------------------------------------------------------------- orientation conventions
def test_rotation_and_quaternion_helpers_match_scipy(shoulder):
    for pose in random_poses(50, 1):
        np.testing.assert_allclose(shoulder.rotation_matrix(pose), q_of(pose), atol=1e-14)
        quat = shoulder.quaternion_from_pose(pose)
        ref = Rotation.from_matrix(q_of(pose)).as_quat()      # (x, y, z, w)
        ref = ref if ref[3] >= 0 else -ref
        np.testing.assert_allclose(quat, ref, atol=1e-12)
        np.testing.assert_allclose(shoulder.pose_from_quaternion(quat), pose, atol=1e-10)
        np.testing.assert_allclose(shoulder.pose_from_matrix(q_of(pose)), pose, atol=1e-12)
    # anatomy: abduction swings the hanging arm (+z) out to +x (lateral), flexion (negative) forward (-y)
    arm = shoulder.rotation_matrix([math.radians(90), 0, 0])[:, 2]
    np.testing.assert_allclose(arm, [1, 0, 0], atol=1e-15)
    arm = shoulder.rotation_matrix([0, math.radians(-90), 0])[:, 2]
    np.testing.assert_allclose(arm, [0, -1, 0], atol=1e-15)
    with pytest.raises(ValueError, match='norm'):
        shoulder.pose_from_quaternion([0.0, 0.0, 0.0, 2.0])


# ---------------------------------------------------------------- inverse kinematics
def test_each_of_the_8_working_modes_closes_every_leg(shoulder):
    u, e1, e2, vp = legs()
    for pose in random_poses(60, 2):
        all_q = shoulder.inverse_all(pose)
        assert all_q.shape == (8, 3)
        v = vp @ q_of(pose).T
        a, b, c = shoulder.ik_quadratic(pose)
        for mode, th in zip(WORKING_MODES, all_q):
            w = elbow(th)
            np.testing.assert_allclose(np.einsum('ij,ij->i', w, v), np.cos(DES['alpha2']), atol=1e-12)
            np.testing.assert_allclose(np.einsum('ij,ij->i', w, u), np.cos(DES['alpha1']), atol=1e-12)
            # the label is the sign of Kq_ii = (u_i x w_i) . v_i
            kq = np.einsum('ij,ij->i', np.cross(u, w), v)
            assert ''.join('+' if k > 0 else '-' for k in kq) == mode
            # the slides' quadratic in T = tan(theta / 2)
            t = np.tan(th / 2)
            np.testing.assert_allclose((a * t ** 2 + b * t + c) / (1 + t ** 2), 0.0, atol=1e-12)
        # 8 distinct solutions (2 per leg)
        assert len({tuple(np.round(q, 9)) for q in all_q}) == 8


def test_inverse_uses_the_configured_working_mode_and_limits(shoulder):
    pose = np.radians([30.0, -40.0, 10.0])
    np.testing.assert_allclose(shoulder.inverse(pose), shoulder.inverse_all(pose)[WORKING_MODES.index('++-')])
    lo, hi = shoulder.actuator_limits
    q = shoulder.inverse(pose)
    assert np.all((lo <= q) & (q < lo + 2 * math.pi))


def test_unreachable_orientation_names_the_leg(shoulder):
    with pytest.raises(UnreachablePose) as info:
        shoulder.inverse(np.radians([0.0, 0.0, 180.0]))      # platform turned half a turn
    err = info.value
    assert err.actuator in shoulder.actuator_names
    assert f'leg {err.actuator} cannot close' in str(err) and 'deg apart' in str(err)
    tight = Spherical3Rrr(DES['gamma'], DES['beta'], DES['alpha1'], DES['alpha2'], DES['delta'],
                          joint_limits=(-1.6, -1.3))           # home (0, 0, 0) is inside
    with pytest.raises(UnreachablePose, match=r'actuator m\d would need .* rad, its range is -1.6000') as info:
        tight.inverse([0.5, 0.0, 0.0])
    assert info.value.limits == (pytest.approx(-1.6), pytest.approx(-1.3))


# ---------------------------------------------------------------- forward kinematics
def newton_modes(q, starts=400, seed=0):
    """Independent FK: Newton on SO(3) (Q <- exp(delta) Q) from random orientations."""
    _, _, _, vp = legs()
    w = elbow(q)
    c2 = np.cos(DES['alpha2'])
    rots = Rotation.random(starts, random_state=seed).as_matrix()
    for _ in range(40):
        v = np.einsum('nij,kj->nki', rots, vp)
        f = np.einsum('nki,ki->nk', v, w) - c2
        jac = np.cross(v, w[None])                 # d f_k / d delta = v_k x w_k
        ok = np.abs(np.linalg.det(jac)) > 1e-10
        step = np.zeros((starts, 3))
        step[ok] = -np.linalg.solve(jac[ok], f[ok][:, :, None])[:, :, 0]
        step = np.clip(step, -0.5, 0.5)
        rots = Rotation.from_rotvec(step).as_matrix() @ rots
    v = np.einsum('nij,kj->nki', rots, vp)
    f = np.max(np.abs(np.einsum('nki,ki->nk', v, w) - c2), axis=1)
    found = []
    for r in rots[f < 1e-12]:
        if not any(np.max(np.abs(r - o)) < 1e-6 for o in found):
            found.append(r)
    return found


def test_ik_fk_round_trip_true_orientation_among_the_forward_solutions(shoulder):
    counts = []
    for pose in random_poses(150, 3):
        q = shoulder.inverse(pose)
        mats = shoulder.forward_matrices(q)
        counts.append(len(mats))
        assert any(np.max(np.abs(m - q_of(pose))) < 1e-9 for m in mats)
        assert any(np.max(np.abs(p - pose)) < 1e-9 for p in shoulder.forward(q))
        if shoulder.dexterity(pose) < 100:     # near a parallel singularity two modes merge
            np.testing.assert_allclose(shoulder.forward_nearest(q, pose + 0.005), pose, atol=1e-9)
        assert len(mats) <= 8 and len(mats) % 2 == 0
    assert max(counts) >= 6


@pytest.mark.parametrize('seed', [5, 6, 7])
def test_forward_finds_every_assembly_mode_of_an_independent_search(shoulder, seed):
    pose = random_poses(1, seed)[0]
    q = shoulder.inverse(pose)
    ours = shoulder.forward_matrices(q)
    theirs = newton_modes(q, seed=seed)
    assert len(ours) == len(theirs) >= 2
    for r in theirs:
        assert any(np.max(np.abs(r - m)) < 1e-8 for m in ours)


def test_forward_on_random_motor_angles_closes_every_leg(shoulder):
    rng = np.random.default_rng(8)
    _, _, _, vp = legs()
    total = 0
    for _ in range(40):
        q = rng.uniform(-math.pi, math.pi, 3)
        w = elbow(q)
        mats = shoulder.forward_matrices(q)
        total += len(mats)
        for m in mats:
            np.testing.assert_allclose(np.einsum('ij,ij->i', vp @ m.T, w), np.cos(DES['alpha2']), atol=1e-9)
            np.testing.assert_allclose(m.T @ m, np.eye(3), atol=1e-12)
            assert np.linalg.det(m) == pytest.approx(1.0)
        if mats and len(mats) < 8:
            assert len(newton_modes(q, starts=300, seed=1)) == len(mats)
    assert total > 0


# ---------------------------------------------------------------- differential kinematics
def test_angular_jacobian_matches_finite_differences(shoulder):
    h = 1e-6
    for pose in random_poses(20, 9):
        jac = shoulder.angular_jacobian(pose)
        q0 = q_of(pose)
        num = np.zeros((3, 3))
        for j in range(3):
            om = np.zeros(3)
            om[j] = h
            qp = shoulder.pose_from_matrix(Rotation.from_rotvec(om).as_matrix() @ q0)
            qm = shoulder.pose_from_matrix(Rotation.from_rotvec(-om).as_matrix() @ q0)
            dq = np.angle(np.exp(1j * (shoulder.inverse(qp) - shoulder.inverse(qm))))
            num[:, j] = dq / (2 * h)
        np.testing.assert_allclose(jac, num, atol=1e-6 * max(1.0, np.abs(num).max()))
        jx, kq = shoulder.velocity_matrices(pose)
        np.testing.assert_allclose(kq @ jac, jx, atol=1e-12)


def test_pose_rate_jacobian_matches_finite_differences(shoulder):
    h = 1e-6
    for pose in random_poses(20, 10):
        jac = shoulder.jacobian(pose)
        num = np.column_stack([np.angle(np.exp(1j * (shoulder.inverse(pose + h * e) - shoulder.inverse(pose - h * e))))
                               / (2 * h) for e in np.eye(3)])
        np.testing.assert_allclose(jac, num, atol=1e-6 * max(1.0, np.abs(num).max()))


def test_dexterity_torques_and_wrench_by_virtual_work(shoulder):
    rng = np.random.default_rng(11)
    for pose in random_poses(20, 12):
        jac = shoulder.angular_jacobian(pose)
        sv = np.linalg.svd(jac, compute_uv=False)
        inv = np.linalg.inv(jac)
        assert shoulder.dexterity(pose) == pytest.approx(np.linalg.norm(jac, 2) * np.linalg.norm(inv, 2), rel=1e-9)
        assert shoulder.dexterity(pose) == pytest.approx(sv[0] / sv[-1], rel=1e-9)
        moment = rng.normal(size=3)
        tau = shoulder.joint_torques(pose, moment)
        omega = rng.normal(size=3)
        assert tau @ (jac @ omega) + moment @ omega == pytest.approx(0.0, abs=1e-9)    # tau.q_dot + M.omega = 0
        # the motors' moment on the platform (platform frame) balances the external one
        np.testing.assert_allclose(shoulder.wrench(pose, tau), -q_of(pose).T @ moment, atol=1e-9)
    # the arm's weight: zero moment hanging, sum F*l when horizontal (abduction 90 deg)
    s = float(np.dot(shoulder.load_forces, shoulder.load_lever_arms))
    np.testing.assert_allclose(shoulder.load_moment([0, 0, 0]), 0.0, atol=1e-15)
    assert np.linalg.norm(shoulder.load_moment([math.pi / 2, 0, 0])) == pytest.approx(s)


def test_serial_singularity_at_the_edge_of_reach_is_detected(shoulder):
    # along abduction (flexion = rotation = 0) leg m1's reach ends near 75 deg, where
    # a^2 + b^2 = c^2: its two elbow solutions merge, Kq_11 -> 0 (bisection on an
    # independent closure test). (The 10-deg study grid steps over this sliver: 70 and 80 deg
    # are reachable.)
    u, e1, e2, vp = legs()

    def margin(a_deg):
        v = vp @ q_of(np.radians([a_deg, 0.0, 0.0])).T
        s1 = np.sin(DES['alpha1'])
        a, b = s1 * np.einsum('ij,ij->i', e1, v), s1 * np.einsum('ij,ij->i', e2, v)
        c = np.cos(DES['alpha2']) - np.cos(DES['alpha1']) * np.einsum('ij,ij->i', u, v)
        return np.min(np.hypot(a, b) - np.abs(c))
    lo, hi = 60.0, 75.0
    assert margin(lo) > 0 > margin(hi)
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if margin(mid) > 0 else (lo, mid)
    edge = np.radians([lo, 0.0, 0.0])
    kinds = shoulder.singularity(edge, tol=1e-5)
    assert 'serial:m1' in kinds
    assert shoulder.dexterity(edge) > 1e3
    with pytest.raises(SingularPose):
        shoulder.check_singularity(edge)
    assert not shoulder.in_workspace(edge)


def test_malformed_inputs_raise_value_error(shoulder):
    for bad in ([math.nan, 0, 0], [0, 0], [[0, 0, 0]], 'abc', [0, math.inf, 0]):
        with pytest.raises(ValueError):
            shoulder.inverse(bad)
        with pytest.raises(ValueError):
            shoulder.forward(bad)
        with pytest.raises(ValueError):
            shoulder.jacobian(bad)
        with pytest.raises(ValueError):
            shoulder.in_workspace(bad)
    with pytest.raises(ValueError, match='working_mode'):
        Spherical3Rrr(DES['gamma'], DES['beta'], DES['alpha1'], DES['alpha2'], DES['delta'], working_mode='+x+')
    with pytest.raises(ValueError, match='alpha1'):
        Spherical3Rrr(DES['gamma'], DES['beta'], [1.0, 1.0], DES['alpha2'], DES['delta'])


# ---------------------------------------------------------------- config and design study
def test_load_mechanism_on_the_shoulder_yaml():
    mech = load_mechanism('config/shoulder.yaml')
    assert isinstance(mech, Spherical3Rrr)
    assert mech.pose_kind == 'spherical' and mech.dof == 3 and mech.n_actuators == 3
    np.testing.assert_allclose(np.degrees([mech.gamma, mech.beta]), [73.97034, 74.02084], atol=1e-9)
    np.testing.assert_allclose(np.degrees(mech.delta), PAPER_DESIGN_DEG['delta'], atol=1e-9)
    home = mech.home_pose
    assert mech.in_workspace(home)
    assert mech.dexterity(home) < 10
    np.testing.assert_allclose(mech.forward_nearest(mech.inverse(home), home), home, atol=1e-9)
    np.testing.assert_allclose(mech.load_lever_arms, [0.25, 0.60, 0.65])


def test_design_study_g1_matches_an_independent_reach_count():
    u, e1, e2, vp = legs()
    for step in (30.0, 10.0):
        poses = spm_study.motion_grid(step)
        count = 0
        for pose in poses:
            v = vp @ q_of(pose).T
            s1 = np.sin(DES['alpha1'])
            a, b = s1 * np.einsum('ij,ij->i', e1, v), s1 * np.einsum('ij,ij->i', e2, v)
            c = np.cos(DES['alpha2']) - np.cos(DES['alpha1']) * np.einsum('ij,ij->i', u, v)
            count += bool(np.all(a * a + b * b >= c * c))      # discriminant B^2 - 4AC >= 0 per leg
        res = spm_study.evaluate_design(DES, poses, working_mode='++-', load_moment_nm=10.0)
        assert res.g1 == count
    assert poses.shape == (1320, 3) and res.g1 == 1320           # the paper's g1 at 10 deg
    assert 0.7 < res.g2 <= 1.0
    assert np.isfinite(res.g3) and res.g3 > 0


def test_design_study_cli_runs_and_writes_the_pareto_plot(tmp_path, capsys):
    rc = spm_study.main(['config/shoulder.yaml', '--out', str(tmp_path), '--optimise',
                         '--maxiter', '1', '--popsize', '1'])
    assert rc == 0
    out = capsys.readouterr().out
    assert 'g1' in out and '1320' in out
    assert (tmp_path / 'spm_pareto.png').stat().st_size > 1000
    assert (tmp_path / 'spm_study.json').is_file()


@pytest.mark.parametrize('leg', [0, 1])
def test_forward_keeps_a_solution_at_the_half_angle_infinity(shoulder, leg, monkeypatch):
    # put the true v_1 (or v_2) exactly at t = pi on its cone: tan(t/2) = inf, where the
    # resultant's degree drops (t1) or the back-substitution divides by zero (t2)
    pose = np.radians([30.0, -40.0, 10.0])
    q = shoulder.inverse(pose)
    w = elbow(q)
    v = legs()[3] @ q_of(pose).T
    orig = Spherical3Rrr._cone_basis

    def basis(wi):
        if np.allclose(wi, w[leg], atol=1e-12):
            perp = v[leg] - (v[leg] @ wi) * wi
            a = -perp / np.linalg.norm(perp)
            return a, np.cross(wi, a)
        return orig(wi)
    expected = len(shoulder.forward_matrices(q))
    monkeypatch.setattr(shoulder, '_cone_basis', basis)
    mats = shoulder.forward_matrices(q)
    assert len(mats) == expected
    assert any(np.max(np.abs(m - q_of(pose))) < 1e-9 for m in mats)
