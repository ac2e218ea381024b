"""``inverse_batch`` / ``jacobian_batch`` of every mechanism against the scalar methods.

Oracles: the scalar ``inverse`` / ``jacobian`` (each tested against the papers' equations
in its own test module) pose by pose, NaN rows exactly where the scalar raises
``UnreachablePose``, central finite differences of the batch inverse for the Jacobian,
and the lumbar paper's eq. 3 (``rpr_oracles.lumbar_eq3``) for the raw lengths. Poses are
seeded random samples around each bundled device's workspace, inside and outside it.
"""
from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest
from rpr_oracles import lumbar_eq3

from brace_control.mechanisms import (Mechanism, Rpr3, Rr2, Rrr3, SingularPose, UnreachablePose,
                                      load_mechanism)
from brace_control.mechanisms.base import MechanismBase

DEVICES = ['lumbar_brace', 'neck_brace_4rpr', 'neck_brace_3rrr', 'neck_brace_2r', 'shoulder',
           'upper_limb_trainer', 'continuum']


def _trainer_poses(mech, rng: np.random.Generator, n: int) -> np.ndarray:
    """Coupler points on the curve, within the projection tolerance and beyond it."""
    th = rng.uniform(-math.pi, math.pi, n)
    p = mech.position_analysis(th)['P']
    ang = rng.uniform(0.0, 2.0 * math.pi, n)
    off = rng.choice([0.0, 1e-5, 2e-4, 4.5e-4, 6e-4, 3e-3, 1e-2], n)
    return np.column_stack([p.real, p.imag]) + off[:, None] * np.column_stack([np.cos(ang), np.sin(ang)])


SAMPLERS: dict[str, Callable[[object, np.random.Generator, int], np.ndarray]] = {
    'lumbar_brace': lambda m, rng, n: np.column_stack([rng.uniform(-0.06, 0.06, n), rng.uniform(0.33, 0.45, n),
                                                       rng.uniform(-0.35, 0.35, n)]),
    'neck_brace_4rpr': lambda m, rng, n: np.column_stack([rng.uniform(-0.16, 0.16, n), rng.uniform(-0.16, 0.16, n),
                                                          rng.uniform(-0.8, 0.8, n)]),
    'neck_brace_3rrr': lambda m, rng, n: m.home_pose + np.column_stack(
        [rng.uniform(-0.08, 0.08, n), rng.uniform(-0.08, 0.08, n), rng.uniform(-1.2, 1.2, n)]),
    'neck_brace_2r': lambda m, rng, n: np.column_stack([rng.uniform(-0.3, 0.3, n), rng.uniform(-0.1, 0.3, n)]),
    'shoulder': lambda m, rng, n: np.column_stack([rng.uniform(-1.5, 3.0, n), rng.uniform(-3.0, 1.5, n),
                                                   rng.uniform(-2.5, 2.5, n)]),
    'upper_limb_trainer': _trainer_poses,
    'continuum': lambda m, rng, n: np.column_stack([rng.uniform(-0.15, 0.15, n), rng.uniform(0.0, 0.21, n)]),
}


@pytest.fixture(scope='module')
def devices() -> dict[str, object]:
    return {name: load_mechanism(f'config/{name}.yaml') for name in DEVICES}


def sample(devices, name: str, n: int, seed: int) -> tuple[object, np.ndarray]:
    mech = devices[name]
    return mech, SAMPLERS[name](mech, np.random.default_rng(seed), n)


def scalar_or_none(fn: Callable[[np.ndarray], np.ndarray], pose: np.ndarray) -> np.ndarray | None:
    try:
        return fn(pose)
    except SingularPose:
        raise
    except UnreachablePose:
        return None


# ---------------------------------------------------------------- inverse_batch
@pytest.mark.parametrize('name', DEVICES)
def test_inverse_batch_equals_scalar_and_nan_exactly_where_scalar_raises(devices, name):
    mech, poses = sample(devices, name, 400, seed=11)
    q = mech.inverse_batch(poses)
    assert q.shape == (len(poses), mech.n_actuators)
    unreachable = 0
    for pose, row in zip(poses, q):
        expected = scalar_or_none(mech.inverse, pose)
        if expected is None:
            assert np.isnan(row).all(), f'{name}: scalar raises at {pose}, batch gave {row}'
            unreachable += 1
        else:
            assert np.isfinite(row).all()
            np.testing.assert_allclose(row, expected, rtol=0, atol=1e-12)
    # the sample covers both sides of the workspace boundary
    assert 0.1 * len(poses) < unreachable < 0.9 * len(poses)


@pytest.mark.parametrize('name', DEVICES)
def test_jacobian_batch_equals_scalar_and_nan_matrix_where_unreachable(devices, name):
    mech, poses = sample(devices, name, 200, seed=12)
    jac = mech.jacobian_batch(poses)
    assert jac.shape == (len(poses), mech.n_actuators, mech.dof)
    q = mech.inverse_batch(poses)
    # the continuum's J is itself a central difference in the elliptic modulus (step 1e-6 of
    # the branch's range): its rounding noise is ~1e-8 relative, so two evaluations at moduli
    # equal to 1e-15 agree only to that; every other model is analytic
    rtol = 1e-6 if name == 'continuum' else 1e-12
    checked = 0
    for pose, row, qrow in zip(poses, jac, q):
        if np.isnan(qrow).any():
            assert np.isnan(row).all()
            continue
        expected = mech.jacobian(pose)
        np.testing.assert_allclose(row, expected, rtol=rtol, atol=rtol * float(np.max(np.abs(expected))))
        checked += 1
    assert checked > 20


@pytest.mark.parametrize('name', DEVICES)
def test_jacobian_batch_matches_central_differences_of_the_batch_inverse(devices, name):
    mech, poses = sample(devices, name, 400, seed=13)
    if name == 'upper_limb_trainer':
        # the four-bar's J = t^T / |t|^2 is exact on the coupler curve (off it, the projection
        # has the curvature term (P - Q) . P'' as well): on-curve points only
        poses = mech.position_analysis(np.random.default_rng(13).uniform(-math.pi, math.pi, 400))['P']
        poses = np.column_stack([poses.real, poses.imag])
    q0 = mech.inverse_batch(poses)
    poses = poses[~np.isnan(q0).any(axis=1)][:60]
    # step (m or rad); 1e-5 for the four-bar: its closed form accepts points within 5e-11 m
    # of the curve, which moves the angle by up to ~1e-10 rad off it (seen by a smaller step)
    h = 1e-5 if name == 'upper_limb_trainer' else 1e-6
    jac = mech.jacobian_batch(poses)
    fd = np.empty_like(jac)
    ok = np.ones(len(poses), dtype=bool)
    for j in range(mech.dof):
        step = np.zeros(mech.dof)
        step[j] = h
        qp, qm = mech.inverse_batch(poses + step), mech.inverse_batch(poses - step)
        diff = qp - qm
        # a neighbour outside the range, or an angle wrapped by a turn between the two
        ok &= np.isfinite(diff).all(axis=1) & (np.abs(diff) < 1.0).all(axis=1)
        fd[:, :, j] = diff / (2.0 * h)
    assert ok.sum() >= 20
    for k in np.flatnonzero(ok):
        scale = float(np.max(np.abs(jac[k])))
        np.testing.assert_allclose(jac[k], fd[k], rtol=2e-5, atol=2e-5 * scale)


def test_lumbar_raw_lengths_without_the_stroke_check_are_the_papers_eq3(devices):
    brace, poses = sample(devices, 'lumbar_brace', 300, seed=14)
    raw = brace.inverse_batch(poses, limits=False)
    for pose, row in zip(poses, raw):
        np.testing.assert_allclose(row, lumbar_eq3(pose), atol=1e-15, rtol=0)
    checked = brace.inverse_batch(poses)
    inside = ~np.isnan(checked).any(axis=1)
    assert 0 < inside.sum() < len(poses)
    np.testing.assert_array_equal(checked[inside], raw[inside])
    np.testing.assert_array_equal(inside, brace.reachable_batch(poses))
    assert np.all((raw[~inside] < 0.340 - 1e-12) | (raw[~inside] > 0.440 + 1e-12), axis=1).any()


def test_singular_but_reachable_pose_is_not_a_nan_row(devices):
    brace = devices['lumbar_brace']
    pose = np.array([0.0, 0.39, 0.0])           # every theta = 0 pose of the brace is singular
    with pytest.raises(SingularPose):
        brace.check_singularity(pose)
    q = brace.inverse_batch(pose[None])[0]
    np.testing.assert_allclose(q, lumbar_eq3(pose), atol=1e-15)
    assert np.isfinite(brace.jacobian_batch(pose[None])).all()


def test_rr2_end_point_on_the_shoulder_gets_the_formula_angles_where_the_scalar_raises_singular():
    arm = Rr2([0.1, 0.1], (-math.pi, math.pi), elbow='up', home_pose=[0.1, 0.1])
    with pytest.raises(SingularPose):
        arm.inverse([0.0, 0.0])
    q = arm.inverse_batch(np.array([[0.0, 0.0], [0.1, 0.1]]))
    assert np.isfinite(q).all()
    # folded: theta2 = -pi (elbow up), the end point back on the shoulder
    assert q[0, 1] == pytest.approx(-math.pi, abs=1e-12)
    end = arm.forward(q[0])[0]
    np.testing.assert_allclose(end, [0.0, 0.0], atol=1e-12)


def test_rr2_jacobian_batch_is_non_finite_where_the_arm_is_stretched():
    arm = Rr2([0.15, 0.12], (-math.pi, math.pi), elbow='up', home_pose=[0.1, 0.1])
    stretched = np.array([[0.27, 0.0], [0.1, 0.1]])
    with pytest.raises(SingularPose):
        arm.jacobian(stretched[0])
    jac = arm.jacobian_batch(stretched)
    assert not np.isfinite(jac[0]).all()
    np.testing.assert_allclose(jac[1], arm.jacobian(stretched[1]), rtol=1e-12)


# ---------------------------------------------------------------- working modes / branches
def test_rrr3_every_working_mode_batch_equals_scalar(devices):
    mech, poses = sample(devices, 'neck_brace_3rrr', 150, seed=15)
    wide = Rrr3(mech.base_pivots, mech.proximal_lengths, mech.distal_lengths, mech.platform_anchors,
                (-math.pi, math.pi), home_pose=mech.home_pose)
    for mode in Rrr3.working_modes():
        q = wide.inverse_batch(poses, working_mode=mode)
        jac = wide.jacobian_batch(poses, working_mode=mode)
        for pose, row, jrow in zip(poses, q, jac):
            try:
                expected = wide.inverse(pose, working_mode=mode)
            except UnreachablePose:
                assert np.isnan(row).all() and np.isnan(jrow).all()
                continue
            np.testing.assert_allclose(row, expected, atol=1e-12, rtol=0)
            np.testing.assert_allclose(jrow, wide.jacobian(pose, working_mode=mode), rtol=1e-12, atol=1e-10)


def test_rr2_both_elbows_batch_equals_scalar():
    arm = Rr2([0.15, 0.12], (-math.pi, math.pi), elbow='up', home_pose=[0.05, 0.2])
    poses = np.random.default_rng(16).uniform(-0.3, 0.3, (300, 2))
    for elbow in ('up', 'down'):
        q = arm.inverse_batch(poses, elbow=elbow)
        for pose, row in zip(poses, q):
            try:
                expected = arm.inverse(pose, elbow=elbow)
            except UnreachablePose:
                assert np.isnan(row).all()
                continue
            np.testing.assert_allclose(row, expected, atol=1e-12, rtol=0)
    up, down = arm.inverse_batch(poses, elbow='up'), arm.inverse_batch(poses, elbow='down')
    both = ~np.isnan(up).any(axis=1)
    assert both.any() and np.all(up[both, 1] <= 0.0) and np.all(down[both, 1] >= 0.0)


# ---------------------------------------------------------------- the protocol, fallbacks, input errors
@pytest.mark.parametrize('name', DEVICES)
def test_every_device_follows_the_protocol_and_handles_an_empty_batch(devices, name):
    mech = devices[name]
    assert isinstance(mech, Mechanism)
    empty = np.empty((0, mech.dof))
    assert mech.inverse_batch(empty).shape == (0, mech.n_actuators)
    assert mech.jacobian_batch(empty).shape == (0, mech.n_actuators, mech.dof)


@pytest.mark.parametrize('name', DEVICES)
@pytest.mark.parametrize('method', ['inverse_batch', 'jacobian_batch'])
def test_malformed_poses_are_a_value_error_naming_what_is_wrong(devices, name, method):
    mech = devices[name]
    fn = getattr(mech, method)
    d = mech.dof
    with pytest.raises(ValueError, match=rf'poses: expected shape \(N, {d}\), got shape \(4, {d + 1}\)'):
        fn(np.zeros((4, d + 1)))
    with pytest.raises(ValueError, match=rf'poses: expected shape \(N, {d}\), got shape \({d},\)'):
        fn(mech.home_pose)
    bad = np.tile(mech.home_pose, (3, 1))
    bad[2, 0] = np.inf
    with pytest.raises(ValueError, match=r'poses: non-finite value in rows \[2\]'):
        fn(bad)
    with pytest.raises(ValueError, match='poses'):
        fn('not poses')


def test_the_loop_fallback_agrees_with_the_vectorised_models(devices):
    for name, kwargs in (('lumbar_brace', {}), ('neck_brace_3rrr', {'working_mode': (1, 1, 1)}),
                         ('continuum', {})):
        mech, poses = sample(devices, name, 80, seed=17)
        q_loop = MechanismBase.inverse_batch(mech, poses, **kwargs)
        q_vec = mech.inverse_batch(poses, **kwargs)
        np.testing.assert_array_equal(np.isnan(q_loop), np.isnan(q_vec))
        np.testing.assert_allclose(q_loop, q_vec, atol=1e-12, rtol=0)
        j_loop = MechanismBase.jacobian_batch(mech, poses, **kwargs)
        j_vec = mech.jacobian_batch(poses, **kwargs)
        np.testing.assert_array_equal(np.isnan(j_loop), np.isnan(j_vec))
        rtol = 1e-6 if name == 'continuum' else 1e-12
        np.testing.assert_allclose(j_loop, j_vec, rtol=rtol, atol=rtol)
    with pytest.raises(ValueError, match='limits=False'):
        MechanismBase.inverse_batch(devices['lumbar_brace'], np.zeros((1, 3)), limits=False)


def test_general_3rpr_random_anchors_batch_equals_scalar():
    rng = np.random.default_rng(18)
    for _ in range(5):
        base, plat = rng.uniform(-0.3, 0.3, (3, 2)), rng.uniform(-0.15, 0.15, (3, 2))
        try:
            mech = Rpr3(base, plat, (0.05, 0.6))
        except ValueError:
            continue
        poses = mech.home_pose + np.column_stack([rng.uniform(-0.3, 0.3, (200, 2)), rng.uniform(-1.0, 1.0, 200)])
        q, jac = mech.inverse_batch(poses), mech.jacobian_batch(poses)
        for pose, row, jrow in zip(poses, q, jac):
            try:
                expected = mech.inverse(pose)
            except UnreachablePose:
                assert np.isnan(row).all() and np.isnan(jrow).all()
                continue
            np.testing.assert_allclose(row, expected, atol=1e-12, rtol=0)
            np.testing.assert_allclose(jrow, mech.jacobian(pose), atol=1e-12, rtol=1e-12)
