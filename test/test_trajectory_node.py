"""trajectory_node with real rclpy and DDS: goals, paths, rejections, cancel, status.

The lumbar brace's configured home (0, 0.39, 0) is singular for its collinear 3-RPR
(see test_trajectory.py), so the node runs with ``mechanism.home_pose`` tilted to 0.1 rad.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.interpolate import CubicSpline
from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path
from std_srvs.srv import Trigger

from brace_control.nodes.msgs import pose_msg, sec_to_stamp, stamp_to_sec
from brace_control.nodes.trajectory_node import (GOAL_TOPIC, PATH_TOPIC, STATUS_TOPIC,
                                                 TrajectoryNode)
from ros_helpers import RELIABLE_10, ros  # noqa: F401
from rpr_oracles import lumbar_eq3

pytestmark = pytest.mark.ros

HOME = np.array([0.0, 0.39, 0.1])
OVERRIDES = {'mechanism.home_pose': '[0.0, 0.39, 0.1]'}
FRAME = 'brace_base'


def start(ros, **overrides):
    node = ros.device_node(TrajectoryNode, **(OVERRIDES | overrides))
    client = ros.node('trajectory_test_client')
    setpoints = ros.collect(client, PoseStamped, '/brace/pose_setpoint')
    status = ros.collect(client, DiagnosticStatus, STATUS_TOPIC,
                         qos=type(RELIABLE_10)(depth=50, reliability=RELIABLE_10.reliability))
    goal_pub = client.create_publisher(PoseStamped, GOAL_TOPIC, RELIABLE_10)
    path_pub = client.create_publisher(Path, PATH_TOPIC, RELIABLE_10)
    ros.wait_matched(goal_pub)
    ros.wait_matched(path_pub)
    ros.spin_until(lambda: node.count_subscribers('/brace/pose_setpoint') >= 1
                   and node.count_subscribers(STATUS_TOPIC) >= 1, what='test subscriptions')
    return node, client, setpoints, status, goal_pub, path_pub


def states(status, goal_id=None):
    return [(s.values[0].value, s.message) for s in status
            if goal_id is None or s.values[0].value == goal_id]


def value(msg: DiagnosticStatus, key: str) -> str:
    return {kv.key: kv.value for kv in msg.values}[key]


def pose_of(msg: PoseStamped) -> np.ndarray:
    q = msg.pose.orientation
    return np.array([msg.pose.position.x, msg.pose.position.y, 2 * math.atan2(q.z, q.w)])


def test_goal_streams_setpoints_at_the_rate_and_ends_at_the_goal(ros):
    node, _, setpoints, status, goal_pub, _ = start(ros)
    goal = HOME + [0.004, 0.0, 0.02]
    goal_pub.publish(pose_msg(goal, frame_id=FRAME))
    ros.spin_until(lambda: ('1', 'succeeded') in states(status), timeout=10.0, what='goal succeeded')
    assert states(status) == [('1', 'accepted'), ('1', 'succeeded')]
    ros.spin_until(lambda: len(setpoints) >= 60, what='setpoints')
    final = pose_of(setpoints[-1])
    np.testing.assert_allclose(final, goal, atol=1e-9)
    stamps = np.array([stamp_to_sec(m.header.stamp) for m in setpoints])
    period = np.median(np.diff(stamps))
    assert period == pytest.approx(1.0 / 200.0, rel=0.1)
    # starts from home (no measured pose, no earlier setpoint), no jump at the start
    assert np.linalg.norm(pose_of(setpoints[0]) - HOME) < 1e-3
    assert all(m.header.frame_id == FRAME for m in setpoints)
    accepted = status[0]
    assert value(accepted, 'source') == 'pose_goal' and float(value(accepted, 'duration')) > 0


def test_unreachable_goal_is_rejected_with_its_reason_and_nothing_moves(ros):
    node, _, setpoints, status, goal_pub, _ = start(ros)
    goal_pub.publish(pose_msg(HOME + [0.0, 0.2, 0.0], frame_id=FRAME))
    ros.spin_until(lambda: len(status) >= 1, what='a status')
    assert states(status) == [('1', 'rejected')]
    assert status[0].level == DiagnosticStatus.WARN
    assert 'actuator a' in value(status[0], 'reason')
    ros.spin_for(0.2)
    assert setpoints == []


def test_bad_input_is_rejected_with_a_message(ros):
    node, _, setpoints, status, goal_pub, path_pub = start(ros)
    goal_pub.publish(pose_msg([math.nan, 0.39, 0.1], frame_id=FRAME))
    goal_pub.publish(pose_msg(HOME, frame_id='world'))
    empty = Path()
    empty.header.frame_id = FRAME
    path_pub.publish(empty)
    stamps = (1.0, 1.0)
    path = Path()
    path.header.frame_id = FRAME
    for t, pose in zip(stamps, (HOME + [0.002, 0, 0.01], HOME + [0.004, 0, 0.02])):
        path.poses.append(pose_msg(pose, frame_id=FRAME, stamp=sec_to_stamp(t)))
    path_pub.publish(path)
    ros.spin_until(lambda: len(status) >= 4, what='four statuses')
    assert sorted(value(s, 'goal_id') for s in status) == ['1', '2', '3', '4']
    assert all(s.message == 'rejected' for s in status)
    reasons = ' | '.join(value(s, 'reason') for s in status)   # topics are not ordered
    for expected in ('not finite', "frame 'world'", 'empty path', 'non-increasing'):
        assert expected in reasons
    ros.spin_for(0.1)
    assert setpoints == []


def test_path_passes_its_via_point_at_its_stamp(ros):
    node, _, setpoints, status, _, path_pub = start(ros)
    via, goal = HOME + [0.003, 0.002, 0.01], HOME + [0.005, 0.0, 0.02]
    path = Path()
    path.header.frame_id = FRAME                       # header stamp 0: relative times
    path.poses = [pose_msg(via, frame_id=FRAME, stamp=sec_to_stamp(0.3)),
                  pose_msg(goal, frame_id=FRAME, stamp=sec_to_stamp(0.6))]
    path_pub.publish(path)
    ros.spin_until(lambda: ('1', 'succeeded') in states(status), timeout=10.0, what='path done')
    ps = np.array([pose_of(m) for m in setpoints])
    t = np.array([stamp_to_sec(m.header.stamp) for m in setpoints])
    # passes the via point. Each setpoint is the path sampled at its stamp, but a loaded
    # machine can drop timer ticks, so the samples' polyline may cut the corner: rebuild
    # the path from the samples by a cubic spline in the stamps (interpolation error
    # ~ h^4 |p''''| < 1e-7 m here even with ticks dropped) and measure its distance.
    keep = np.concatenate([[True], np.diff(t) > 0])
    spline = CubicSpline(t[keep], ps[keep])
    dense = spline(np.linspace(t[0], t[-1], 20000))
    assert np.min(np.linalg.norm(dense - via, axis=1)) < 1e-5
    np.testing.assert_allclose(ps[-1], goal, atol=1e-9)
    assert float(value(status[0], 'duration')) == pytest.approx(0.6)


def test_cancel_decelerates_smoothly_and_holds(ros):
    node, client, setpoints, status, goal_pub, _ = start(ros, **{'trajectory.profile': 'scurve'})
    goal = HOME + [0.03, 0.0, 0.08]
    goal_pub.publish(pose_msg(goal, frame_id=FRAME))
    ros.spin_until(lambda: len(setpoints) >= 80, what='moving')
    cancel = client.create_client(Trigger, '/trajectory_node/cancel')
    assert cancel.wait_for_service(timeout_sec=5.0)
    future = cancel.call_async(Trigger.Request())
    ros.spin_until(future.done, what='cancel response')
    assert future.result().success
    ros.spin_until(lambda: ('1', 'cancelled') in states(status), what='cancelled status')
    n_cancel = len(setpoints)
    ros.spin_until(lambda: len(setpoints) >= n_cancel + 200, what='setpoints after cancel')
    ps = np.array([pose_of(m) for m in setpoints])
    steps = np.linalg.norm(np.diff(ps[:, :2], axis=0), axis=1)
    t = np.array([stamp_to_sec(m.header.stamp) for m in setpoints])
    dt = np.diff(t)
    velocity = np.diff(ps[:, :2], axis=0) / dt[:, None]   # by the stamps (= sample instants)
    speed = np.linalg.norm(velocity, axis=1)
    # no jump in velocity across the cancel: the brake starts from the running state
    # (a change of at most a few times the S-curve's acceleration limit over one step)
    dv = np.linalg.norm(np.diff(velocity, axis=0), axis=1)
    dt_mid = (dt[:-1] + dt[1:]) / 2.0                      # between the two mean velocities
    amax = 0.1                                             # trajectory.max_acceleration x, y
    accel = dv / dt_mid
    assert accel[n_cancel - 3:].max() <= 4.0 * amax, (n_cancel, np.argmax(accel), accel.max())
    # the brake carries the start acceleration over (jerk is finite): the speed may rise
    # briefly, then falls to rest; it stays far below the actuators' 65 mm/s
    assert speed[n_cancel:].max() <= 0.065
    peak = n_cancel + int(np.argmax(speed[n_cancel:]))
    assert np.all(np.diff(speed[peak:]) <= 1e-4)    # 0.3 % of the speed: stamp rounding
    # at rest, holding, short of the goal
    assert np.all(steps[-50:] < 1e-12)
    assert np.linalg.norm(ps[-1, :2] - goal[:2]) > 1e-3
    assert states(status) == [('1', 'accepted'), ('1', 'cancelled')]


def test_platform_limits_of_the_wrong_length_fail_at_start_up(ros):
    from brace_control.config import ConfigError
    with pytest.raises(ConfigError, match='max_jerk needs 3 values'):
        ros.device_node(TrajectoryNode, **(OVERRIDES | {'trajectory.max_jerk': '[1.0, 1.0]'}))


def test_first_goal_starts_from_a_fresh_measured_pose_and_tracking_error_aborts(ros):
    from brace_control.nodes.trajectory_node import POSE_TOPIC
    node, client, setpoints, status, goal_pub, _ = start(ros, **{'safety.tracking_latency': 0.1})
    measured_pub = client.create_publisher(PoseStamped, POSE_TOPIC, RELIABLE_10)
    ros.wait_matched(measured_pub)
    measured = HOME + [0.002, 0.001, 0.01]
    measured_pub.publish(pose_msg(measured, frame_id=FRAME))
    ros.spin_until(lambda: node._measured is not None, what='measured pose received')
    goal_pub.publish(pose_msg(HOME + [0.03, 0.0, 0.08], frame_id=FRAME))
    ros.spin_until(lambda: len(setpoints) >= 1, what='first setpoint')
    np.testing.assert_allclose(pose_of(setpoints[0]), measured, atol=1e-6)
    # the brace does not follow (the measured pose stays put): beyond 5 mm of actuator
    # length (paper eq. 3) from every setpoint of the last tracking_latency -> aborted
    window = int(node.runner.tracking_latency * 200.0) + 10      # setpoints at 200 Hz, + margin
    ros.spin_until(lambda: len(setpoints) > window and min(
        np.abs(lumbar_eq3(pose_of(m)) - lumbar_eq3(measured)).max() for m in setpoints[-window:]) > 0.006,
        timeout=10.0, what='setpoints 6 mm of actuator length away')
    measured_pub.publish(pose_msg(measured, frame_id=FRAME))
    ros.spin_until(lambda: ('1', 'aborted') in states(status), what='aborted status')
    aborted = [s for s in status if s.message == 'aborted'][0]
    assert aborted.level == DiagnosticStatus.ERROR
    assert 'tracking error' in value(aborted, 'reason')
    assert states(status) == [('1', 'accepted'), ('1', 'aborted')]
