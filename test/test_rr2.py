"""Planar serial 2R (neck brace, report "Planar RR") against independent oracles.

Oracles: the report's forward kinematics and Jacobian written out here, the elbow's side
of the base -> end-point line, central finite differences, and the statics of the links
(each joint torque balances the end-point force's moment about that joint, an r x F).
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from brace_control.mechanisms import Mechanism, SingularPose, UnreachablePose, load_mechanism
from brace_control.mechanisms.rr2 import Rr2, angle_into_range

L1, L2 = 0.15, 0.12
FULL = (-math.pi, math.pi)


def report_fk(t1: float, t2: float, base=(0.0, 0.0)) -> np.ndarray:
    """The report's (x_EE, y_EE): translation [l1 0] rotated by theta1, [l2 0] by theta1 + theta2."""
    return np.array([base[0] + L1 * math.cos(t1) + L2 * math.cos(t1 + t2),
                     base[1] + L1 * math.sin(t1) + L2 * math.sin(t1 + t2)])


def report_jacobian(t1: float, t2: float) -> np.ndarray:
    return np.array([[-L1 * math.sin(t1) - L2 * math.sin(t1 + t2), -L2 * math.sin(t1 + t2)],
                     [L1 * math.cos(t1) + L2 * math.cos(t1 + t2), L2 * math.cos(t1 + t2)]])


def wrap(t: float) -> float:
    return math.pi - (math.pi - t) % (2 * math.pi)


@pytest.fixture(scope='module')
def up() -> Rr2:
    return Rr2([L1, L2], FULL, elbow='up', home_pose=[0.05, 0.2])


@pytest.fixture(scope='module')
def down() -> Rr2:
    return Rr2([L1, L2], FULL, elbow='down', home_pose=[0.05, 0.2])


# ---------------------------------------------------------------- forward / inverse
def test_forward_matches_report(up):
    rng = np.random.default_rng(1)
    for t1, t2 in rng.uniform(-math.pi, math.pi, (200, 2)):
        sols = up.forward([t1, t2])
        assert len(sols) == 1
        np.testing.assert_allclose(sols[0], report_fk(t1, t2), atol=1e-15)


@pytest.mark.parametrize('branch', ['up', 'down'])
def test_round_trip_both_branches_on_random_annulus_points(branch, up, down):
    mech = up if branch == 'up' else down
    rng = np.random.default_rng(7)
    r = rng.uniform(abs(L1 - L2) + 1e-3, L1 + L2 - 1e-3, 500)
    phi = rng.uniform(-math.pi, math.pi, 500)
    for p in np.column_stack([r * np.cos(phi), r * np.sin(phi)]):
        q = mech.inverse(p)
        np.testing.assert_allclose(report_fk(*q), p, atol=1e-13)
        # branch by the sign of theta2 and, independently, the elbow's side of base -> end
        elbow = np.array([L1 * math.cos(q[0]), L1 * math.sin(q[0])])
        side = p[0] * elbow[1] - p[1] * elbow[0]          # (end - base) x (elbow - base)
        if branch == 'up':
            assert q[1] <= 0.0 and side >= -1e-15          # elbow counter-clockwise of the line
        else:
            assert q[1] >= 0.0 and side <= 1e-15
        # the other branch through the keyword gives the mirror elbow, same end point
        other = mech.inverse(p, elbow='down' if branch == 'up' else 'up')
        np.testing.assert_allclose(report_fk(*other), p, atol=1e-13)
        assert other[1] == pytest.approx(-q[1], abs=1e-12)


def test_inverse_of_forward_recovers_joint_angles_in_range():
    mech = load_mechanism('config/neck_brace_2r.yaml')
    lo, hi = mech.actuator_limits
    rng = np.random.default_rng(3)
    for q in rng.uniform(lo, hi, (300, 2)):
        p = mech.forward(q)[0]
        np.testing.assert_allclose(mech.inverse(p), q, atol=1e-10)


def test_angles_moved_into_ranges_beyond_pi():
    # shoulder range -200..20 deg: an end point at 190 deg needs theta1 near -170 deg +-
    mech = Rr2([L1, L2], ([-math.radians(200), -math.pi], [math.radians(20), math.pi]), elbow='down',
               home_pose=report_fk(-0.5, 1.0))
    q_true = (math.radians(-195), 0.8)
    q = mech.inverse(report_fk(*q_true))
    np.testing.assert_allclose(q, q_true, atol=1e-12)
    assert angle_into_range(3.0, -4.0, -2.0) == pytest.approx(3.0 - 2 * math.pi)
    assert angle_into_range(-3.0, 2.0, 4.0) == pytest.approx(2 * math.pi - 3.0)
    assert angle_into_range(0.5, 1.0, 2.0) == 0.5           # none fits: the nearest representative


# ---------------------------------------------------------------- unreachable / invalid
def test_outside_annulus_rejected_with_distance_and_reach(up):
    for p, r in (((0.3, 0.0), 0.3), ((0.0, 0.01), 0.01)):
        with pytest.raises(UnreachablePose) as info:
            up.inverse(p)
        err = info.value
        assert err.actuator is None and err.value == pytest.approx(r)
        assert err.limits == (pytest.approx(0.03), pytest.approx(0.27))
        assert f'{r:.4f}' in str(err) and '0.0300' in str(err) and '0.2700' in str(err)
        assert not up.in_workspace(p)


def test_joint_range_violation_names_the_joint():
    mech = load_mechanism('config/neck_brace_2r.yaml')      # j1 0..180 deg
    p = report_fk(math.radians(-30), -1.0)
    msg = r'j1 would need -0\.5236 rad, its range is 0\.0000–3\.1416 rad'
    with pytest.raises(UnreachablePose, match=msg) as info:
        mech.inverse(p)
    assert info.value.actuator == 'j1' and info.value.value == pytest.approx(math.radians(-30))
    assert not mech.in_workspace(p)
    # the elbow-down branch is outside j2's range (-170..-10 deg)
    with pytest.raises(UnreachablePose, match='j2 would need'):
        mech.inverse(mech.home_pose, elbow='down')


BAD = [[np.nan, 0.1], [0.1, np.inf], [0.1], [0.1, 0.1, 0.0], 'ab', [[0.1, 0.1]]]


@pytest.mark.parametrize('bad', BAD, ids=['nan', 'inf', 'short', 'long', 'str', 'nested'])
@pytest.mark.parametrize('method', ['inverse', 'forward', 'jacobian', 'condition', 'in_workspace',
                                    'wrench_pose', 'wrench_torque', 'nearest_q', 'nearest_hint'])
def test_malformed_input_raises_value_error(up, bad, method):
    good = [0.05, 0.2]
    calls = {
        'inverse': lambda: up.inverse(bad), 'forward': lambda: up.forward(bad),
        'jacobian': lambda: up.jacobian(bad), 'condition': lambda: up.condition(bad),
        'in_workspace': lambda: up.in_workspace(bad),
        'wrench_pose': lambda: up.wrench(bad, [1.0, 1.0]), 'wrench_torque': lambda: up.wrench(good, bad),
        'nearest_q': lambda: up.forward_nearest(bad, good), 'nearest_hint': lambda: up.forward_nearest([0.1, 0.1], bad),
    }
    with pytest.raises(ValueError, match=r'(pose|q|forces|hint_pose).*(expected|non-finite)'):
        calls[method]()


@pytest.mark.parametrize('kwargs, match', [
    (dict(link_lengths=[0.0, 0.1]), 'link_lengths'),
    (dict(joint_range=(1.0, 0.0)), 'joint_range'),
    (dict(joint_range=(-4.0, 4.0)), 'joint_range'),
    (dict(elbow='sideways'), 'elbow'),
    (dict(actuator_names=('a', 'a')), 'actuator_names'),
    (dict(singularity_condition_max=0.5), 'singularity_condition_max'),
    (dict(home_pose=[0.5, 0.0]), 'annulus'),
])
def test_constructor_rejects_bad_arguments(kwargs, match):
    args = dict(link_lengths=[L1, L2], joint_range=FULL)
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        Rr2(args.pop('link_lengths'), args.pop('joint_range'), **args)


# ---------------------------------------------------------------- differential kinematics, statics
@pytest.mark.parametrize('p', [(0.05, 0.2), (-0.1, 0.12), (0.2, -0.05), (0.04, 0.03)])
def test_jacobian_is_inverse_of_report_jacobian_and_matches_finite_differences(up, p):
    q = up.inverse(p)
    jac = up.jacobian(p)
    np.testing.assert_allclose(jac @ report_jacobian(*q), np.eye(2), atol=1e-10)
    np.testing.assert_allclose(up.serial_jacobian(q), report_jacobian(*q), atol=1e-15)
    h = 1e-7
    fd = np.column_stack([[wrap(a - b) / (2 * h) for a, b in zip(up.inverse(np.add(p, h * e)),
                                                                 up.inverse(np.subtract(p, h * e)))]
                          for e in np.eye(2)])
    np.testing.assert_allclose(jac, fd, rtol=1e-6, atol=1e-6)


def test_wrench_balances_joint_torques_r_cross_f(up):
    rng = np.random.default_rng(5)
    for _ in range(50):
        q = (rng.uniform(-math.pi, math.pi), -rng.uniform(0.2, 2.9))
        p = report_fk(*q)
        tau = rng.normal(size=2)
        fx, fy = up.wrench(p, tau)
        elbow = np.array([L1 * math.cos(q[0]), L1 * math.sin(q[0])])
        # statics: the force F at the end point is balanced by each joint's torque about it
        assert p[0] * fy - p[1] * fx == pytest.approx(tau[0], abs=1e-9)
        assert (p[0] - elbow[0]) * fy - (p[1] - elbow[1]) * fx == pytest.approx(tau[1], abs=1e-9)
        xdot = rng.normal(size=2)
        assert tau @ (up.jacobian(p) @ xdot) == pytest.approx(np.array([fx, fy]) @ xdot, rel=1e-9, abs=1e-12)


def test_stretched_arm_is_singular(up):
    p = (L1 + L2, 0.0)
    assert up.condition(p) == math.inf
    with pytest.raises(SingularPose):
        up.jacobian(p)
    with pytest.raises(SingularPose, match='cond'):
        up.check_singularity(p)
    assert not up.in_workspace(p)
    near = (0.9999 * (L1 + L2), 0.0)
    assert up.condition(near) > 50


def test_forward_nearest_returns_the_end_point(up):
    np.testing.assert_allclose(up.forward_nearest([0.3, -0.4], [9.0, 9.0]), report_fk(0.3, -0.4), atol=1e-15)


# ---------------------------------------------------------------- config
def test_load_mechanism_neck_brace_2r():
    mech = load_mechanism('config/neck_brace_2r.yaml')
    assert isinstance(mech, Rr2) and isinstance(mech, Mechanism)
    assert mech.dof == 2 and mech.n_actuators == 2 and mech.actuator_names == ('j1', 'j2')
    assert mech.elbow == 'up' and mech.reach == (pytest.approx(0.03), pytest.approx(0.27))
    home = mech.home_pose
    assert mech.in_workspace(home) and mech.condition(home) < 10
    np.testing.assert_allclose(report_fk(*mech.inverse(home)), home, atol=1e-14)


@settings(max_examples=200, deadline=None)
@given(t1=st.floats(-math.pi, math.pi), t2=st.floats(0.05, math.pi - 0.05), sign=st.sampled_from([-1, 1]))
def test_property_ik_of_fk_on_both_branches(t1, t2, sign):
    mech = Rr2([L1, L2], FULL, elbow='up' if sign < 0 else 'down', home_pose=[0.05, 0.2])
    q = mech.inverse(report_fk(t1, sign * t2))
    assert wrap(q[0] - t1) == pytest.approx(0.0, abs=1e-9)
    assert q[1] == pytest.approx(sign * t2, abs=1e-9)
