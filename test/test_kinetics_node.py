"""kinetics_node with real rclpy and DDS: joint states in, measured pose and wrench out."""
from __future__ import annotations

import math

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseStamped, WrenchStamped
from sensor_msgs.msg import JointState

from brace_control.config import load_device_config
from brace_control.nodes.kinetics_node import KineticsNode
from brace_control.nodes.msgs import joint_state, planar_pose_from_msg, sec_to_stamp, stamp_to_ns
from ros_helpers import LUMBAR_YAML, RELIABLE_10, ros  # noqa: F401

pytestmark = pytest.mark.ros

CFG = load_device_config(LUMBAR_YAML)
A = np.asarray(CFG['mechanism']['base_anchors'], float).reshape(3, 2)
B = np.asarray(CFG['mechanism']['platform_anchors'], float).reshape(3, 2)
NAMES = list(CFG['mechanism']['actuator_names'])


def rot(th: float) -> np.ndarray:
    return np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])


def legs(pose):
    """Leg vectors a_i -> b_i (world) and platform anchors in world orientation."""
    rb = B @ rot(pose[2]).T
    return np.asarray(pose[:2]) + rb - A, rb


def lengths(pose) -> np.ndarray:
    return np.linalg.norm(legs(pose)[0], axis=1)


def body_wrench_platform_frame(pose, forces) -> np.ndarray:
    """Oracle (seed 001, kinetics): thrust f_i along each leg pushes the platform;
    F = sum f_i u_i, M = sum (R b_i) x f_i u_i about P; F expressed in the platform frame."""
    d, rb = legs(pose)
    u = d / np.linalg.norm(d, axis=1)[:, None]
    fvec = np.asarray(forces)[:, None] * u
    force = fvec.sum(axis=0)
    moment = float(np.sum(rb[:, 0] * fvec[:, 1] - rb[:, 1] * fvec[:, 0]))
    return np.array([*(rot(pose[2]).T @ force), moment])


@pytest.fixture
def rig(ros):  # noqa: F811
    kin = ros.device_node(KineticsNode)
    test = ros.node('kinetics_test')
    poses = ros.collect(test, PoseStamped, '/brace/pose')
    wrenches = ros.collect(test, WrenchStamped, '/brace/wrench')
    diags = ros.collect(test, DiagnosticArray, '/diagnostics')
    pub = test.create_publisher(JointState, '/brace/joint_states', RELIABLE_10)
    ros.wait_matched(pub)
    ros.spin_until(lambda: kin._pose_pub.get_subscription_count() >= 1
                   and kin._wrench_pub.get_subscription_count() >= 1, what='kinetics -> test')
    return ros, kin, pub, poses, wrenches, diags


def _statuses(diags, level=None):
    return [s for d in diags for s in d.status if s.name == 'brace_control/kinetics_node'
            and (level is None or s.level == level)]


def test_pose_and_wrench_from_lengths_and_load_cells(rig):
    ros, kin, pub, poses, wrenches, _ = rig
    pose = np.array([0.0, 0.37, 0.17])
    forces = [40.0, -25.0, 60.0]
    # actuators listed in another order than the YAML: matched by name
    order = [2, 0, 1]
    q = lengths(pose)
    pub.publish(joint_state([NAMES[i] for i in order], position=q[order],
                            velocity=[0.0] * 3, effort=np.asarray(forces)[order],
                            stamp=sec_to_stamp(7.25)))
    ros.spin_until(lambda: poses and wrenches, what='pose and wrench')
    assert poses[0].header.frame_id == 'brace_base'
    assert stamp_to_ns(poses[0].header.stamp) == 7_250_000_000
    np.testing.assert_allclose(planar_pose_from_msg(poses[0]), pose, atol=1e-9)
    w = wrenches[0]
    assert w.header.frame_id == 'brace_platform'
    got = [w.wrench.force.x, w.wrench.force.y, w.wrench.torque.z]
    np.testing.assert_allclose(got, body_wrench_platform_frame(pose, forces), rtol=1e-9, atol=1e-9)
    assert (w.wrench.force.z, w.wrench.torque.x, w.wrench.torque.y) == (0.0, 0.0, 0.0)


def test_branch_is_tracked_along_a_motion(rig):
    ros, kin, pub, poses, _, _ = rig
    path = [np.array([0.0, 0.37, 0.17]) + k * np.array([0.001, 0.0005, -0.004]) for k in range(20)]
    for k, p in enumerate(path):
        pub.publish(joint_state(NAMES, position=lengths(p), effort=[0.0] * 3,
                                stamp=sec_to_stamp(1 + 0.01 * k)))
        ros.spin_until(lambda: len(poses) == k + 1, what=f'pose {k}')
    got = np.array([planar_pose_from_msg(m) for m in poses])
    np.testing.assert_allclose(got, np.array(path), atol=1e-8)


def test_no_effort_gives_pose_but_no_wrench(rig):
    ros, kin, pub, poses, wrenches, _ = rig
    pub.publish(joint_state(NAMES, position=lengths([0.0, 0.37, 0.17])))
    ros.spin_until(lambda: poses, what='pose')
    ros.spin_for(0.1)
    assert wrenches == []


def test_malformed_joint_state_is_reported_and_not_used(rig):
    ros, kin, pub, poses, wrenches, diags = rig
    pub.publish(joint_state(NAMES, position=[0.39, math.nan, 0.39], effort=[0.0] * 3))
    pub.publish(joint_state(['a1', 'a2'], position=[0.39, 0.39]))
    ros.spin_until(lambda: kin.failed == 2, what='two failures')
    ros.spin_until(lambda: _statuses(diags, DiagnosticStatus.ERROR), what='ERROR diagnostic')
    ros.spin_for(0.05)
    assert poses == [] and wrenches == []
    assert 'a3' in kin.diagnostics.message


def test_near_singular_pose_is_reported(rig):
    ros, kin, pub, poses, _, diags = rig
    # theta = 0: the three leg lines meet in the homothety centre of the two collinear
    # anchor rows -> parallel singularity (seed 001 geometry); cond(J) is huge.
    pose = [0.004, 0.39, 0.0005]
    pub.publish(joint_state(NAMES, position=lengths(pose), effort=[0.0] * 3))
    ros.spin_until(lambda: poses, what='pose')
    ros.spin_until(lambda: any('singular' in s.message or 'ambiguous' in s.message
                               for s in _statuses(diags, DiagnosticStatus.WARN)),
                   what='WARN diagnostic')


def test_well_conditioned_pose_is_ok(rig):
    ros, kin, pub, poses, _, diags = rig
    pub.publish(joint_state(NAMES, position=lengths([0.0, 0.37, 0.17]), effort=[0.0] * 3))
    ros.spin_until(lambda: poses, what='pose')
    ros.spin_until(lambda: _statuses(diags, DiagnosticStatus.OK)
                   and kin.diagnostics.message == 'tracking', what='OK diagnostic')


def test_positions_outside_the_stroke_are_not_turned_into_a_pose(rig):
    """Incremental encoders read 0 before homing: a WARN, no pose, no error spam."""
    ros, kin, pub, poses, wrenches, diags = rig
    pub.publish(joint_state(NAMES, position=[0.0, 0.0, 0.0], effort=[0.0] * 3))
    ros.spin_until(lambda: _statuses(diags, DiagnosticStatus.WARN), what='WARN diagnostic')
    ros.spin_for(0.05)
    assert poses == [] and 'not homed' in kin.diagnostics.message
