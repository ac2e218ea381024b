"""Message conversions (brace_control/nodes/msgs.py): no node, no DDS."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from brace_control.nodes.msgs import (MalformedMessage, joint_state, joint_state_arrays,
                                      ns_to_stamp, pose_from_msg, pose_msg, quaternion_from_rotvec,
                                      quaternion_yaw, rotvec_from_quaternion, sec_to_stamp,
                                      stamp_to_ns, stamp_to_sec, wrench_msg, yaw_quaternion)


def test_stamps_round_trip_and_normalise_nanoseconds():
    assert stamp_to_ns(ns_to_stamp(12_345_678_901)) == 12_345_678_901
    s = ns_to_stamp(-1)                      # one ns before the epoch
    assert (s.sec, s.nanosec) == (-1, 999_999_999)
    assert stamp_to_sec(sec_to_stamp(3.25)) == 3.25


@pytest.mark.parametrize('theta', [0.0, 0.3, -2.0, math.pi - 1e-9])
def test_yaw_quaternion_round_trip(theta):
    assert quaternion_yaw(yaw_quaternion(theta)) == pytest.approx(theta)


def test_planar_pose_round_trip_in_frame():
    msg = pose_msg([0.01, 0.39, 0.1], frame_id='brace_base')
    assert msg.pose.orientation.z == pytest.approx(math.sin(0.05))     # half-angle
    np.testing.assert_allclose(pose_from_msg(msg, dof=3, frame_id='brace_base'), [0.01, 0.39, 0.1])


@pytest.mark.parametrize('mutate, reason', [
    (lambda m: setattr(m.header, 'frame_id', 'map'), 'frame'),
    (lambda m: setattr(m.pose.position, 'x', math.nan), 'non_finite'),
    (lambda m: setattr(m.pose.position, 'z', 0.01), 'non_planar'),
    (lambda m: setattr(m.pose.orientation, 'x', 0.2), 'quaternion'),   # not unit any more
    (lambda m: setattr(m.pose.orientation, 'w', math.inf), 'non_finite'),
])
# docs/safety.md §6
def test_malformed_planar_pose_is_rejected_with_reason(mutate, reason):
    msg = pose_msg([0.0, 0.39, 0.0], frame_id='brace_base')
    mutate(msg)
    with pytest.raises(MalformedMessage) as err:
        pose_from_msg(msg, dof=3, frame_id='brace_base')
    assert err.value.reason == reason


def test_roll_quaternion_is_not_planar():
    msg = pose_msg([0.0, 0.39, 0.0], frame_id='b')
    o = msg.pose.orientation
    o.x, o.w = math.sin(0.1), math.cos(0.1)
    with pytest.raises(MalformedMessage, match='not a rotation about z') as err:
        pose_from_msg(msg, dof=3)
    assert err.value.reason == 'non_planar'


def test_path_and_xy_kinds():
    np.testing.assert_allclose(pose_from_msg(pose_msg([0.2], frame_id='b'), dof=1), [0.2])
    np.testing.assert_allclose(pose_from_msg(pose_msg([0.2, 0.1], frame_id='b'), dof=2), [0.2, 0.1])
    bad = pose_msg([0.2, 0.1, 0.3], frame_id='b')
    with pytest.raises(MalformedMessage):
        pose_from_msg(bad, kind='xy')                      # a rotation on a 2-DOF device


def test_spherical_rotation_vector_round_trip():
    rv = np.array([0.1, -0.2, 0.3])
    q = quaternion_from_rotvec(rv)
    assert np.linalg.norm(q) == pytest.approx(1.0)
    np.testing.assert_allclose(rotvec_from_quaternion(q), rv, atol=1e-12)
    msg = pose_msg(rv, frame_id='shoulder', kind='spherical')
    np.testing.assert_allclose(pose_from_msg(msg, kind='spherical'), rv, atol=1e-12)


def test_joint_state_by_name_any_order_extra_joints():
    msg = joint_state(['x', 'a3', 'a1', 'a2'], position=[9, 3, 1, 2], effort=[0, 30, 10, 20])
    out = joint_state_arrays(msg, ['a1', 'a2', 'a3'], ('position', 'effort', 'velocity'),
                             optional=('velocity',))
    np.testing.assert_array_equal(out['position'], [1, 2, 3])
    np.testing.assert_array_equal(out['effort'], [10, 20, 30])
    assert out['velocity'] is None


@pytest.mark.parametrize('msg, match', [
    (joint_state(['a1', 'a2'], position=[1, 2]), 'lacks'),
    (joint_state(['a1', 'a1', 'a2'], position=[1, 1, 2]), 'twice'),
    (joint_state(['a1', 'a2'], position=[1, math.nan]), r"\['a2'\] is not finite"),
])
def test_bad_joint_state_names_the_problem(msg, match):
    with pytest.raises(MalformedMessage, match=match):
        joint_state_arrays(msg, ['a1', 'a2'] if 'lacks' not in match else ['a1', 'a2', 'a3'])


def test_joint_state_length_mismatch():
    msg = joint_state(['a1', 'a2'], position=[1, 2])
    msg.velocity = [1.0]
    with pytest.raises(MalformedMessage, match='velocity has 1 values for 2 names'):
        joint_state_arrays(msg, ['a1', 'a2'], ('velocity',))
    with pytest.raises(ValueError):
        joint_state(['a1'], position=[1, 2])


def test_wrench_planar_components():
    w = wrench_msg([1.0, 2.0, 3.0], frame_id='brace_platform')
    assert (w.wrench.force.x, w.wrench.force.y, w.wrench.torque.z) == (1.0, 2.0, 3.0)
    assert (w.wrench.force.z, w.wrench.torque.x, w.wrench.torque.y) == (0.0, 0.0, 0.0)
    assert w.header.frame_id == 'brace_platform'


def test_every_mechanism_declares_its_pose_kind_and_it_fits_its_dof():
    """The pose kind (how a pose maps onto a geometry_msgs/Pose) is the mechanism's own
    declaration, one of base.POSE_KINDS, with the dof that kind has: nothing infers it from
    the dof (issue 25, "the pose-kind switch moved onto the mechanism")."""
    from brace_control.config import load_device_config
    from brace_control.mechanisms import mechanism_from_config
    from brace_control.mechanisms.base import POSE_KINDS
    from brace_control.nodes.msgs import pose_kind
    devices = sorted(p.stem for p in (Path(__file__).resolve().parents[1] / 'config').glob('*.yaml'))
    assert len(devices) >= 7, devices
    for device in devices:
        mech = mechanism_from_config(load_device_config(device))
        assert mech.pose_kind in POSE_KINDS and POSE_KINDS[mech.pose_kind] == mech.dof, (device, mech.pose_kind)
        assert pose_kind(mech) == mech.pose_kind

    class NoKind:
        dof = 3
    with pytest.raises(TypeError, match='declares no pose_kind'):
        pose_kind(NoKind())
