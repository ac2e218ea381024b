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
from ros_helpers import LUMBAR_YAML, RELIABLE_10, ros  # noqa: F401

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
def rig(ros):  # noqa: F811
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
        while time.monotonic() < t0 + (k + 1) * period:
            ros.executor.spin_once(timeout_sec=0.001)
    ros.spin_until(lambda: len(out) == n, timeout=10, what=f'{n} setpoints')
    stamps = [stamp_to_ns(m.header.stamp) for m in out]
    assert stamps == sorted(stamps) and len(set(stamps)) == n


def test_out_of_range_parameter_fails_at_start_up(ros):  # noqa: F811
    with pytest.raises(ConfigError, match='trajectory.rate_hz'):
        ros.device_node(IkNode, **{'trajectory.rate_hz': 0.0})
