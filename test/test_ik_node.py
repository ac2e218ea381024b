"""ik_node with real rclpy and DDS: pose setpoints in, actuator setpoints out, rejections."""
from __future__ import annotations

import math
import time

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import JointState

from brace_control.config import ConfigError, load_device_config
from brace_control.nodes.ik_node import IkNode
from brace_control.nodes.msgs import pose_msg, sec_to_stamp, stamp_to_ns
from ros_helpers import LUMBAR_YAML, RELIABLE_10

pytestmark = pytest.mark.ros

CFG = load_device_config(LUMBAR_YAML)
A = np.asarray(CFG['mechanism']['base_anchors'], float).reshape(3, 2)
B = np.asarray(CFG['mechanism']['platform_anchors'], float).reshape(3, 2)


def lengths(pose) -> np.ndarray:
    """Independent oracle: l_i = |p + R(theta) b_i - a_i| (seed 001, inverse kinematics)."""
    x, y, th = pose
    c, s = math.cos(th), math.sin(th)
    return np.array([math.hypot(x + c * b[0] - s * b[1] - a[0], y + s * b[0] + c * b[1] - a[1])
                     for a, b in zip(A, B)])


def setpoint(pose, t: float = 100.0, frame: str = 'brace_base') -> PoseStamped:
    return pose_msg(pose, frame_id=frame, stamp=sec_to_stamp(t), kind='planar')


@pytest.fixture
def rig(ros):
    ik = ros.device_node(IkNode)
    test = ros.node('ik_test')
    out = ros.collect(test, JointState, '/brace/actuator_setpoint')
    diags = ros.collect(test, DiagnosticArray, '/diagnostics')
    pub = test.create_publisher(PoseStamped, '/brace/pose_setpoint', RELIABLE_10)
    ros.wait_matched(pub)
    ros.spin_until(lambda: test.count_publishers('/brace/actuator_setpoint') >= 1)
    # wait until ik's publisher has matched our subscription as well
    ros.spin_until(lambda: ik._pub.get_subscription_count() >= 1, what='ik -> test match')
    return ros, ik, pub, out, diags


def test_setpoint_gives_ik_lengths_named_as_in_the_yaml(rig):
    ros, ik, pub, out, _ = rig
    pose = [0.01, 0.39, 0.03]
    pub.publish(setpoint(pose, t=12.5))
    ros.spin_until(lambda: len(out) == 1, what='actuator setpoint')
    msg = out[0]
    assert list(msg.name) == list(CFG['mechanism']['actuator_names'])
    np.testing.assert_allclose(msg.position, lengths(pose), atol=1e-12)
    assert list(msg.velocity) == [0.0, 0.0, 0.0]          # first setpoint: no rate yet
    assert stamp_to_ns(msg.header.stamp) == 12_500_000_000  # the setpoint's stamp is kept


def test_velocity_is_the_rate_of_the_lengths_between_setpoints(rig):
    ros, ik, pub, out, _ = rig
    p0, dt = np.array([0.01, 0.39, 0.03]), 0.005
    xdot = np.array([0.02, -0.01, 0.1])                   # m/s, m/s, rad/s
    p1 = p0 + xdot * dt
    pub.publish(setpoint(p0, t=1.0))
    pub.publish(setpoint(p1, t=1.0 + dt))
    ros.spin_until(lambda: len(out) == 2, what='two actuator setpoints')
    # oracle: central difference of the independent IK about the midpoint
    h = 1e-7
    qdot = (lengths(p0 + 0.5 * dt * xdot + h * xdot) - lengths(p0 + 0.5 * dt * xdot - h * xdot)) / (2 * h)
    np.testing.assert_allclose(out[1].velocity, qdot, rtol=2e-3, atol=1e-6)
    np.testing.assert_allclose(out[1].position, lengths(p1), atol=1e-12)


@pytest.mark.parametrize('bad, reason', [
    (lambda: setpoint([math.nan, 0.39, 0.0]), 'non_finite'),
    (lambda: setpoint([0.01, 0.39, 0.03], frame='map'), 'frame'),
    (lambda: _tilted(setpoint([0.01, 0.39, 0.03])), 'non_planar'),
    (lambda: setpoint([0.0, 0.50, 0.0]), 'unreachable'),   # all legs beyond 0.440 m
])
def test_bad_setpoint_is_rejected_with_reason_and_the_next_valid_one_passes(rig, bad, reason):
    ros, ik, pub, out, diags = rig
    pub.publish(setpoint([0.01, 0.39, 0.03], t=1.0))
    ros.spin_until(lambda: len(out) == 1)
    pub.publish(bad())
    ros.spin_until(lambda: ik.rejected == 1, what='the rejection')
    ros.spin_until(lambda: any(reason in s.message for d in diags for s in d.status
                               if s.name == 'brace_control/ik_node'), what='diagnostic')
    ros.spin_for(0.1)
    assert len(out) == 1                                     # nothing published for it
    assert reason in ik.last_rejection
    pub.publish(setpoint([0.012, 0.39, 0.03], t=1.005))
    ros.spin_until(lambda: len(out) == 2, what='the following valid setpoint')
    np.testing.assert_allclose(out[1].position, lengths([0.012, 0.39, 0.03]), atol=1e-12)


def _tilted(msg: PoseStamped) -> PoseStamped:
    o = msg.pose.orientation
    o.x, o.y, o.z, o.w = math.sin(0.05), 0.0, 0.0, math.cos(0.05)   # roll: not planar
    return msg


def test_no_setpoint_dropped_at_200_hz(rig):
    ros, ik, pub, out, _ = rig
    n, period = 400, 0.005
    t0 = time.monotonic()
    for k in range(n):
        pose = [0.01 + 0.01 * math.sin(k / 50), 0.39, 0.03]
        pub.publish(setpoint(pose, t=10.0 + k * period))
        # 200 Hz, but never more than 5 ahead of what came out: the queues hold 10 (the
        # rate a loaded host can sustain is a benchmark's question, not this test's)
        deadline = time.monotonic() + 5.0
        while (time.monotonic() < t0 + (k + 1) * period or len(out) < k + 1 - 5) \
                and time.monotonic() < deadline:
            ros.executor.spin_once(timeout_sec=0.001)
    ros.spin_until(lambda: len(out) == n, timeout=10, what=f'{n} setpoints')
    stamps = [stamp_to_ns(m.header.stamp) for m in out]
    assert stamps == sorted(stamps) and len(set(stamps)) == n


def test_out_of_range_parameter_fails_at_start_up(ros):
    with pytest.raises(ConfigError, match='trajectory.rate_hz'):
        ros.device_node(IkNode, **{'trajectory.rate_hz': 0.0})


# ---------------------------------------------------------------------------- planned motions
def _plan(t):
    """A minimum-jerk motion (thesis 002 eq. 2.2) with its exact derivatives."""
    p0, p1, T = np.array([0.0, 0.39, 0.1]), np.array([0.008, 0.40, 0.16]), 1.2
    s = np.clip(t / T, 0.0, 1.0)[:, None]
    d = p1 - p0
    return (p0 + d * (10 * s**3 - 15 * s**4 + 6 * s**5), d * (30 * s**2 - 60 * s**3 + 30 * s**4) / T,
            d * (60 * s - 180 * s**2 + 120 * s**3) / T**2)


@pytest.fixture
def motion_rig(ros):
    return _motion_rig(ros, LUMBAR_YAML, 'ik_motion_test')


def _motion_rig(ros, path, name: str):
    """ik_node of the device file ``path``; a test node ``name`` publishing pose trajectories
    and collecting the actuator trajectories and the execution events."""
    from diagnostic_msgs.msg import DiagnosticStatus
    from trajectory_msgs.msg import JointTrajectory, MultiDOFJointTrajectory

    from brace_control.nodes import topics
    ik = ros.device_node(IkNode, path)
    test = ros.node(name)
    out = ros.collect(test, JointTrajectory, topics.ACTUATOR_TRAJECTORY, topics.TRAJECTORY_QOS)
    events = ros.collect(test, DiagnosticStatus, topics.EXECUTION_STATUS, topics.STATUS_QOS)
    pub = test.create_publisher(MultiDOFJointTrajectory, topics.POSE_TRAJECTORY, topics.TRAJECTORY_QOS)
    ros.wait_matched(pub)
    ros.spin_until(lambda: ik._traj_pub.get_subscription_count() >= 1
                   and ik._status_pub.get_subscription_count() >= 1, what='ik -> test match')
    return ros, ik, pub, out, events


def test_a_planned_motion_becomes_actuator_knots_within_1_um_of_the_ik(motion_rig):
    """Sampled at SYNC times (2 ms), the actuator motion rebuilt from the knots by quintic
    Hermite interpolation (scipy's BPoly, independent of the code) equals the IK of the
    planned poses (seed 001 eq. 3 written out above) within 1 um; its rates are those of
    the IK along the plan."""
    from scipy.interpolate import BPoly

    from brace_control.nodes.msgs import joint_knots_from_msg, pose_trajectory_msg
    ros, ik, pub, out, _ = motion_rig
    t = np.linspace(0.0, 1.2, 25)                      # the trajectory node's coarse knots
    P, V, A_ = _plan(t)
    pub.publish(pose_trajectory_msg(t, P, V, A_, frame_id='brace_base', joint_name='brace_platform',
                                    stamp=sec_to_stamp(42.5), kind='planar'))
    ros.spin_until(lambda: len(out) == 1, what='the actuator trajectory')
    msg = out[0]
    assert stamp_to_ns(msg.header.stamp) == 42_500_000_000
    assert list(msg.joint_names) == list(CFG['mechanism']['actuator_names'])
    _, tk, Q, QD, QDD = joint_knots_from_msg(msg, msg.joint_names)
    spline = BPoly.from_derivatives(tk, np.stack([Q, QD, QDD], axis=1))
    ts = np.arange(0.0, 1.2, 0.002)
    truth = np.array([lengths(p) for p in _plan(ts)[0]])
    assert np.max(np.abs(spline(ts) - truth)) < 1e-6
    h = 1e-5
    inner = ts[(ts > h) & (ts < 1.2 - h)]
    rate = (np.array([lengths(p) for p in _plan(inner + h)[0]])
            - np.array([lengths(p) for p in _plan(inner - h)[0]])) / (2 * h)
    assert np.max(np.abs(spline(inner, 1) - rate)) < 1e-6
    np.testing.assert_array_equal(QD[-1], 0.0)          # ends at rest, exactly
    np.testing.assert_array_equal(QDD[-1], 0.0)


# docs/safety.md §10
def test_a_motion_through_an_unreachable_pose_is_rejected_with_its_stamp(motion_rig):
    from brace_control.nodes.msgs import pose_trajectory_msg, status_values
    ros, ik, pub, out, events = motion_rig
    t = np.linspace(0.0, 1.0, 11)
    P = np.array([[0.0, 0.39 + 0.12 * s, 0.1] for s in t / t[-1]])   # legs beyond 0.440 m
    pub.publish(pose_trajectory_msg(t, P, np.zeros_like(P), np.zeros_like(P), frame_id='brace_base',
                                    joint_name='brace_platform', stamp=sec_to_stamp(7.0), kind='planar'))
    ros.spin_until(lambda: len(events) == 1, what='the rejection')
    values = status_values(events[0])
    assert events[0].message == 'rejected' and values['stamp'] == str(7_000_000_000)
    assert 'no inverse kinematics' in values['reason']
    ros.spin_for(0.1)
    assert out == []


def test_an_empty_trajectory_is_passed_on_as_a_stop(motion_rig):
    from trajectory_msgs.msg import MultiDOFJointTrajectory
    ros, ik, pub, out, _ = motion_rig
    stop = MultiDOFJointTrajectory()
    stop.header.frame_id = 'brace_base'
    stop.header.stamp = sec_to_stamp(3.25)
    stop.joint_names = ['brace_platform']
    pub.publish(stop)
    ros.spin_until(lambda: len(out) == 1, what='the stop')
    assert len(out[0].points) == 0 and stamp_to_ns(out[0].header.stamp) == 3_250_000_000


def test_a_motion_with_no_driver_listening_is_rejected_not_lost(ros):
    """Nothing subscribes to /brace/actuator_trajectory (no driver): the converted motion
    would be lost on a topic that keeps no history; it is rejected with the reason instead."""
    from diagnostic_msgs.msg import DiagnosticStatus
    from trajectory_msgs.msg import MultiDOFJointTrajectory

    from brace_control.nodes import topics
    from brace_control.nodes.msgs import pose_trajectory_msg, status_values
    ik = ros.device_node(IkNode)
    test = ros.node('ik_no_driver_test')
    events = ros.collect(test, DiagnosticStatus, topics.EXECUTION_STATUS, topics.STATUS_QOS)
    pub = test.create_publisher(MultiDOFJointTrajectory, topics.POSE_TRAJECTORY, topics.TRAJECTORY_QOS)
    ros.wait_matched(pub)
    ros.spin_until(lambda: ik._status_pub.get_subscription_count() >= 1, what='ik -> test match')
    assert ik._traj_pub.get_subscription_count() == 0
    t = np.linspace(0.0, 1.2, 25)
    P, V, A_ = _plan(t)
    pub.publish(pose_trajectory_msg(t, P, V, A_, frame_id='brace_base', joint_name='brace_platform',
                                    stamp=sec_to_stamp(9.5), kind='planar'))
    ros.spin_until(lambda: len(events) == 1, what='the rejection')
    values = status_values(events[0])
    assert events[0].message == 'rejected' and values['stamp'] == str(9_500_000_000)
    assert topics.ACTUATOR_TRAJECTORY in values['reason'] and 'can_driver_node' in values['reason']


# ------------------------------------------------------------------ a cable brace's workspace
NECK4 = load_device_config(LUMBAR_YAML.parent / 'neck_brace_4rpr.yaml')


def _cable_null_direction(pose) -> np.ndarray:
    """The 4-RPR's self-stress: tensions ``t`` with ``sum_n t_n (u_n; b_n x u_n) = 0`` (no
    wrench on the ring), from the YAML geometry written out (report "FOUR RPR": cable n from
    the ring's anchor ``B_n`` to the base's ``A_n``). Unloaded cables can hold the pose only
    when this direction has one sign (every cable pulls); the test's own statics, not the
    code's."""
    m = NECK4['mechanism']
    A = np.asarray(m['base_anchors'], float).reshape(4, 2)
    r, d = float(m['platform_radius']), np.asarray(m['anchor_angles'], float)
    x, y, psi = pose
    b = np.column_stack([r * np.cos(d + psi), r * np.sin(d + psi)])
    u = A - (np.array([x, y]) + b)
    u /= np.linalg.norm(u, axis=1)[:, None]
    W = np.vstack([u[:, 0], u[:, 1], b[:, 0] * u[:, 1] - b[:, 1] * u[:, 0]])   # 3 x 4
    return np.linalg.svd(W)[2][-1]


# docs/safety.md §10
def test_a_cable_brace_setpoint_its_cables_cannot_hold_is_rejected_naming_them(ros):
    """The cable-driven 4-RPR neck brace at 40 deg of rotation: within the stroke and far from
    a singularity, but the ring can only be held there with a cable pushing (its self-stress
    has mixed signs). The trajectory planner refuses such a pose; a setpoint of it is refused
    as well, its reason naming the cables, and nothing is published. A pose whose self-stress
    has one sign passes, with the cable lengths of the YAML geometry."""
    from rpr_oracles import cable_lengths_4rpr
    bad, good = [0.0, 0.0, 0.7], [0.0, 0.0, 0.1]
    n_bad, n_good = _cable_null_direction(bad), _cable_null_direction(good)
    assert np.min(n_bad) < 0 < np.max(n_bad), n_bad                # a cable would push
    assert np.all(n_good > 0) or np.all(n_good < 0), n_good
    ik = ros.device_node(IkNode, LUMBAR_YAML.parent / 'neck_brace_4rpr.yaml')
    test = ros.node('ik_cable_test')
    out = ros.collect(test, JointState, '/brace/actuator_setpoint')
    diags = ros.collect(test, DiagnosticArray, '/diagnostics')
    pub = test.create_publisher(PoseStamped, '/brace/pose_setpoint', RELIABLE_10)
    ros.wait_matched(pub)
    ros.spin_until(lambda: ik._pub.get_subscription_count() >= 1, what='ik -> test match')
    pub.publish(setpoint(bad, t=5.0))
    ros.spin_until(lambda: any('cables cannot hold' in s.message for a in diags for s in a.status),
                   what='the rejection naming the cables')
    pub.publish(setpoint(good, t=5.1))
    ros.spin_until(lambda: len(out) == 1, what='the next valid setpoint')
    assert stamp_to_ns(out[0].header.stamp) == 5_100_000_000          # the bad one never went out
    np.testing.assert_allclose(out[0].position, cable_lengths_4rpr(NECK4, good), atol=1e-12)


def test_a_cable_brace_pose_trajectory_through_a_pose_its_cables_cannot_hold_is_rejected(ros):
    """A pose trajectory published straight to ik_node, rotating the cable brace's ring from
    0.1 to 0.7 rad: the knots beyond the cables' reach (the test's own statics) make it a
    rejection with its stamp and the cables named; no actuator trajectory goes out."""
    from brace_control.nodes.msgs import pose_trajectory_msg, status_values
    t = np.linspace(0.0, 1.0, 11)
    P = np.array([[0.0, 0.0, 0.1 + 0.6 * s] for s in t])
    mixed = [bool(np.min(n) < 0 < np.max(n)) for n in map(_cable_null_direction, P)]
    assert mixed[-1] and not mixed[0], mixed
    ros, ik, pub, out, events = _motion_rig(ros, LUMBAR_YAML.parent / 'neck_brace_4rpr.yaml',
                                            'ik_cable_motion_test')
    pub.publish(pose_trajectory_msg(t, P, np.zeros_like(P), np.zeros_like(P), frame_id='brace_base',
                                    joint_name='brace_platform', stamp=sec_to_stamp(9.0), kind='planar'))
    ros.spin_until(lambda: len(events) == 1, what='the rejection')
    values = status_values(events[0])
    assert events[0].message == 'rejected' and values['stamp'] == str(9_000_000_000)
    assert 'cables cannot hold' in values['reason'], values['reason']
    ros.spin_for(0.1)
    assert out == []
