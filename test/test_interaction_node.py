"""interaction_node's own checks of a wrench goal, at the latest pose estimate, with no driver.

The node keeps only the newest ``/brace/pose`` (as received) and converts it when a goal
needs it. These tests show that the goal is judged at the estimate published last: a
platform-frame force turns with the ring (the rotation ``R(theta)`` written out here), so
the same goal is fine at theta = 0 and puts a component on the held x axis at theta = 10 deg.
"""
from __future__ import annotations

import math

import pytest
from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import PoseStamped, WrenchStamped

from brace_control.nodes import topics
from brace_control.nodes.interaction_node import InteractionNode
from ros_helpers import LUMBAR_YAML

pytestmark = pytest.mark.ros

BASE, PLATFORM = 'brace_base', 'brace_platform'


def _values(msg: DiagnosticStatus) -> dict[str, str]:
    return {kv.key: kv.value for kv in msg.values}


def _pose(y: float, theta: float, frame: str = BASE) -> PoseStamped:
    msg = PoseStamped()
    msg.header.frame_id = frame
    msg.pose.position.y = y
    msg.pose.orientation.z, msg.pose.orientation.w = math.sin(theta / 2), math.cos(theta / 2)
    return msg


def _wrench(fy: float, frame: str) -> WrenchStamped:
    msg = WrenchStamped()
    msg.header.frame_id = frame
    msg.wrench.force.y = fy
    return msg


@pytest.fixture
def rig(ros):
    import yaml
    frames = yaml.safe_load(LUMBAR_YAML.read_text())['/**']['ros__parameters']
    assert (frames['base_frame'], frames['platform_frame']) == (BASE, PLATFORM)
    node = ros.device_node(InteractionNode)
    probe = ros.node('probe_interaction_node')
    statuses = ros.collect(probe, DiagnosticStatus, topics.GOAL_STATUS, topics.STATUS_QOS)
    forwarded = ros.collect(probe, WrenchStamped, topics.INTERACTION_GOAL, topics.GOAL_QOS)
    goals = probe.create_publisher(WrenchStamped, topics.WRENCH_GOAL, topics.GOAL_QOS)
    poses = probe.create_publisher(PoseStamped, topics.POSE, topics.MEASURED_QOS)
    ros.wait_matched(goals)
    ros.wait_matched(poses)
    node._active = True          # as after the driver's interaction_start (no driver here)

    def outcome(goal: WrenchStamped) -> dict[str, str]:
        before = len(statuses)
        goals.publish(goal)
        ros.spin_until(lambda: len(statuses) > before, what='the goal status')
        return {'state': statuses[-1].message, **_values(statuses[-1])}

    def estimate(pose: PoseStamped) -> None:
        node._pose_cdr = None
        poses.publish(pose)
        ros.spin_until(lambda: node._pose_cdr is not None, what='the pose estimate')
    return outcome, estimate, forwarded


def test_a_goal_before_any_estimate_is_rejected_naming_the_topic(rig):
    outcome, _, forwarded = rig
    end = outcome(_wrench(20.0, BASE))
    assert end['state'] == 'rejected'
    assert topics.POSE in end['reason'] and 'capacity cannot be checked' in end['reason']
    assert not forwarded


def test_a_goal_is_judged_at_the_newest_estimate(ros, rig):
    outcome, estimate, forwarded = rig
    estimate(_pose(0.39, 0.0))
    end = outcome(_wrench(20.0, PLATFORM))
    assert end['state'] == 'accepted', end
    ros.spin_until(lambda: forwarded, what='the forwarded goal')
    assert forwarded[-1].header.frame_id == BASE
    assert (forwarded[-1].wrench.force.x, forwarded[-1].wrench.force.y) == pytest.approx((0.0, 20.0))

    theta = math.radians(10.0)
    estimate(_pose(0.39, theta))
    end = outcome(_wrench(20.0, PLATFORM))
    # R(theta) (0, 20): x = -20 sin(theta) = -3.47 N on the held x axis
    assert end['state'] == 'rejected', end
    assert 'axis 0' in end['reason'] and f'{-20.0 * math.sin(theta):g}' in end['reason']
    assert len(forwarded) == 1


def test_an_estimate_in_another_frame_rejects_the_goal_saying_so(rig):
    outcome, estimate, forwarded = rig
    estimate(_pose(0.39, 0.0, frame='map'))
    end = outcome(_wrench(20.0, BASE))
    assert end['state'] == 'rejected'
    assert 'unusable' in end['reason'] and "'map'" in end['reason']
    assert not forwarded


def test_the_driver_s_answer_to_each_goal_is_published_for_that_goal(ros, rig):
    """The driver names the goal it answers by the stamp of the message the node sent it:
    two goals in flight, answered in the other order (the second rejected at the driver's
    pose, the first applied), each answer goes to its own goal's name, ``applied`` with the
    driver's ``applied_ns``."""
    from brace_control.nodes.msgs import stamp_to_ns, status_msg

    outcome, estimate, forwarded = rig
    estimate(_pose(0.39, 0.0))
    first, second = outcome(_wrench(10.0, BASE)), outcome(_wrench(20.0, BASE))
    assert (first['state'], second['state']) == ('accepted', 'accepted')
    ros.spin_until(lambda: len(forwarded) == 2, what='both goals forwarded')
    probe = ros.node('probe_driver_events')
    events = probe.create_publisher(DiagnosticStatus, topics.EXECUTION_STATUS, topics.STATUS_QOS)
    statuses = ros.collect(probe, DiagnosticStatus, topics.GOAL_STATUS, topics.STATUS_QOS)
    ros.wait_matched(events)
    stamps = [stamp_to_ns(m.header.stamp) for m in forwarded]
    events.publish(status_msg('can_driver_node/interaction/1', 'goal_rejected', kind='goal_rejected',
                              reason='above the capacity at its pose', goal_stamp=stamps[1]))
    events.publish(status_msg('can_driver_node/interaction/1', 'goal_applied', kind='goal_applied',
                              reason='', goal_stamp=stamps[0], applied_ns=1234567890))
    def answers():              # (a late joiner of the goal statuses also gets the 'accepted's)
        return {(m.name.rsplit('/', 1)[-1], m.message): _values(m) for m in list(statuses)
                if m.message != 'accepted'}
    ros.spin_until(lambda: len(answers()) >= 2, what="the driver's answers as goal statuses")
    got = answers()
    assert set(got) == {('1', 'applied'), ('2', 'rejected')}, got
    assert got[('1', 'applied')]['applied_ns'] == '1234567890'
    assert got[('2', 'rejected')]['reason'] == 'the driver: above the capacity at its pose'
