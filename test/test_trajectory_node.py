"""trajectory_node with real rclpy and DDS: planned motions out, honest goal outcomes.

The node's peers are played by the test (:class:`FakeStack`): the driver's latched state,
its execution events, and the pose estimate. Oracles: the minimum-jerk motion of thesis 002
eq. (2.2) and the paper's eq. 3 for actuator lengths (rpr_oracles), not the node's code.

The lumbar brace's home is tilted to 0.1 rad here (clear of the theta = 0 singularity).
"""
from __future__ import annotations

import math
import time

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path
from std_srvs.srv import Trigger
from trajectory_msgs.msg import MultiDOFJointTrajectory

from brace_control.nodes import topics
from brace_control.nodes.msgs import (pose_knots_from_msg, pose_msg, sec_to_stamp, stamp_to_ns,
                                      status_msg, status_values)
from brace_control.nodes.trajectory_node import PLAN_LOOKAHEAD_S, TrajectoryNode
from brace_control.trajectory import KnotTrajectory
from rpr_oracles import lumbar_eq3

pytestmark = pytest.mark.ros

HOME = np.array([0.0, 0.39, 0.1])
OVERRIDES = {'mechanism.home_pose': '[0.0, 0.39, 0.1]'}
FRAME = 'brace_base'
DEEP = topics.STATUS_QOS


class FakeStack:
    """The driver and the estimator as the node sees them, driven by the test."""

    def __init__(self, ros, node):
        self.ros = ros
        self.client = ros.node('trajectory_test_client')
        c = self.client
        self.trajectories: list[MultiDOFJointTrajectory] = []
        self.status: list[DiagnosticStatus] = []
        c.create_subscription(MultiDOFJointTrajectory, topics.POSE_TRAJECTORY,
                              self.trajectories.append, DEEP)
        c.create_subscription(DiagnosticStatus, topics.GOAL_STATUS, self.status.append, DEEP)
        self.goal_pub = c.create_publisher(PoseStamped, topics.POSE_GOAL, topics.GOAL_QOS)
        self.path_pub = c.create_publisher(Path, topics.POSE_PATH, topics.GOAL_QOS)
        self.state_pub = c.create_publisher(DiagnosticStatus, topics.DRIVER_STATE, topics.LATCHED_QOS)
        self.exec_pub = c.create_publisher(DiagnosticStatus, topics.EXECUTION_STATUS, topics.STATUS_QOS)
        self.pose_pub = c.create_publisher(PoseStamped, topics.POSE, topics.STATE_QOS)
        for pub in (self.goal_pub, self.path_pub, self.state_pub, self.exec_pub, self.pose_pub):
            ros.wait_matched(pub)
        ros.spin_until(lambda: node.count_subscribers(topics.POSE_TRAJECTORY) >= 1
                       and node.count_subscribers(topics.GOAL_STATUS) >= 1, what='test subscriptions')
        self.node = node

    def driver(self, enabled: bool, message: str, pose=HOME, execution='hold'):
        self.state_pub.publish(status_msg('can_driver_node/state', message, state=message,
                                          enabled=str(enabled).lower(), execution=execution,
                                          command=list(lumbar_eq3(pose))))
        self.ros.spin_until(lambda: self.node.runner.driver_reason == message, what='driver state')

    def event(self, traj: MultiDOFJointTrajectory, kind: str, reason: str = '', pose=None):
        tag = stamp_to_ns(traj.header.stamp)
        self.exec_pub.publish(status_msg(f'can_driver_node/trajectory/{tag}', kind, stamp=tag,
                                         kind=kind, reason=reason,
                                         positions=[] if pose is None else list(lumbar_eq3(pose))))

    def estimate(self, pose):
        self.pose_pub.publish(pose_msg(pose, frame_id=FRAME,
                                       stamp=self.client.get_clock().now().to_msg()))

    def states(self, goal_id=None):
        return [(value(s, 'goal_id'), s.message) for s in self.status
                if goal_id is None or value(s, 'goal_id') == goal_id]

    def wait_state(self, goal_id, state, timeout=5.0):
        self.ros.spin_until(lambda: (goal_id, state) in self.states(), timeout=timeout,
                            what=f'goal {goal_id} {state}')

    def knots(self, traj) -> KnotTrajectory:
        _, t, P, V, A = pose_knots_from_msg(traj, frame_id=FRAME)
        return KnotTrajectory(t, P, V, A)


def start(ros, enabled=True, **overrides):
    node = ros.device_node(TrajectoryNode, **(OVERRIDES | overrides))
    stack = FakeStack(ros, node)
    if enabled:
        stack.driver(True, 'enabled')
    return node, stack


def value(msg: DiagnosticStatus, key: str) -> str:
    return status_values(msg)[key]


def eq_2_2(x0, xf, tf, t):
    """Thesis 002 eq. (2.2): the minimum-jerk position at t."""
    tau = np.clip(t / tf, 0.0, 1.0)[:, None]
    return x0 + (xf - x0) * (10 * tau ** 3 - 15 * tau ** 4 + 6 * tau ** 5)


def test_a_goal_is_published_once_whole_and_succeeds_only_at_the_goal(ros):
    node, stack = start(ros)
    goal = HOME + [0.004, 0.0, 0.02]
    sent = ros.nodes[0].get_clock().now()
    stack.goal_pub.publish(pose_msg(goal, frame_id=FRAME, stamp=sent.to_msg()))
    stack.wait_state('1', 'accepted')
    ros.spin_until(lambda: len(stack.trajectories) == 1, what='the planned motion')
    traj = stack.trajectories[0]
    # when it takes over: the lookahead after the goal came in
    start_s = (stamp_to_ns(traj.header.stamp) - sent.nanoseconds) * 1e-9
    assert PLAN_LOOKAHEAD_S - 0.01 < start_s < PLAN_LOOKAHEAD_S + 0.5
    assert traj.header.frame_id == FRAME and list(traj.joint_names) == ['brace_platform']
    # the knots rebuild the minimum-jerk motion from the hold (IK(HOME), the driver's
    # command) to the goal, eq. (2.2), with the duration the status reports
    knots = stack.knots(traj)
    assert knots.duration == pytest.approx(float(value(stack.status[0], 'duration')), abs=1e-4)
    duration = knots.duration
    t = np.linspace(0.0, duration, 500)
    np.testing.assert_allclose(knots.sample_many(t)[0], eq_2_2(HOME, goal, duration, t), atol=1e-7)
    np.testing.assert_allclose(knots.velocities[-1], 0.0, atol=0.0)     # ends exactly at rest
    # no success without the driver and the estimate: finished, but the ring is 3 mm off
    stack.event(traj, 'started')
    stack.event(traj, 'finished', pose=goal)
    ros.spin_for(0.1)
    stack.estimate(goal + [0.003, 0.0, 0.0])
    ros.spin_for(0.2)
    assert stack.states('1') == [('1', 'accepted')]
    # the estimate (kinetics_node, 100 Hz) at the goal: success once it stayed there 50 ms
    deadline = time.monotonic() + 5.0
    inside_from = node.get_clock().now().nanoseconds
    while ('1', 'succeeded') not in stack.states('1') and time.monotonic() < deadline:
        stack.estimate(goal + [0.0008, 0.0, 0.001])
        ros.spin_for(0.01)
    stack.wait_state('1', 'succeeded')
    assert stack.states() == [('1', 'accepted'), ('1', 'succeeded')]
    done = stack.status[-1]
    assert value(done, 'stamp') == str(sent.nanoseconds) and value(done, 'source') == 'pose_goal'
    # when the node decided it: after 50 ms of estimates inside the tolerance, not later than now
    assert inside_from + 50_000_000 <= int(value(done, 'time')) <= node.get_clock().now().nanoseconds
    assert len(stack.trajectories) == 1


def test_goals_are_rejected_while_the_drives_are_not_enabled(ros):
    node, stack = start(ros, enabled=False)
    stack.goal_pub.publish(pose_msg(HOME + [0.0, 0.005, 0.0], frame_id=FRAME))
    stack.wait_state('1', 'rejected')
    assert 'not enabled' in value(stack.status[0], 'reason')
    stack.driver(False, 'protective stop: a2: force limit: load-cell force 254 N')
    stack.goal_pub.publish(pose_msg(HOME + [0.0, 0.005, 0.0], frame_id=FRAME))
    stack.wait_state('2', 'rejected')
    assert 'force limit' in value(stack.status[-1], 'reason')
    ros.spin_for(0.2)
    assert stack.trajectories == []


def test_a_goal_with_no_ik_node_listening_is_rejected_not_lost(ros):
    """Nothing subscribes to /brace/pose_trajectory (no ik node): the plan would be lost on
    a topic that keeps no history, and the goal would end in "the driver did not start";
    it is rejected at once, naming the topic."""
    node = ros.device_node(TrajectoryNode, **OVERRIDES)
    client = ros.node('trajectory_alone_client')
    status: list[DiagnosticStatus] = []
    client.create_subscription(DiagnosticStatus, topics.GOAL_STATUS, status.append, DEEP)
    goal_pub = client.create_publisher(PoseStamped, topics.POSE_GOAL, topics.GOAL_QOS)
    state_pub = client.create_publisher(DiagnosticStatus, topics.DRIVER_STATE, topics.LATCHED_QOS)
    for pub in (goal_pub, state_pub):
        ros.wait_matched(pub)
    state_pub.publish(status_msg('can_driver_node/state', 'enabled', state='enabled', enabled='true',
                                 execution='hold', command=list(lumbar_eq3(HOME))))
    ros.spin_until(lambda: node.runner.driver_enabled, what='driver state')
    goal_pub.publish(pose_msg(HOME + [0.0, 0.005, 0.0], frame_id=FRAME))
    ros.spin_until(lambda: any(m.message == 'rejected' for m in status), what='the rejection')
    reason = value(next(m for m in status if m.message == 'rejected'), 'reason')
    assert topics.POSE_TRAJECTORY in reason and 'ik_node' in reason


def test_unreachable_goal_is_rejected_with_its_reason_and_nothing_moves(ros):
    node, stack = start(ros)
    stack.goal_pub.publish(pose_msg(HOME + [0.0, 0.2, 0.0], frame_id=FRAME))
    stack.wait_state('1', 'rejected')
    assert stack.status[0].level == DiagnosticStatus.WARN
    assert 'actuator a' in value(stack.status[0], 'reason')
    ros.spin_for(0.2)
    assert stack.trajectories == []


def test_bad_input_is_rejected_with_a_message(ros):
    node, stack = start(ros, **{'trajectory.max_path_poses': 3})
    stack.goal_pub.publish(pose_msg([math.nan, 0.39, 0.1], frame_id=FRAME))
    stack.goal_pub.publish(pose_msg(HOME, frame_id='world'))
    empty = Path()
    empty.header.frame_id = FRAME
    stack.path_pub.publish(empty)
    path = Path()
    path.header.frame_id = FRAME
    for t, pose in zip((1.0, 1.0), (HOME + [0.002, 0, 0.01], HOME + [0.004, 0, 0.02])):
        path.poses.append(pose_msg(pose, frame_id=FRAME, stamp=sec_to_stamp(t)))
    stack.path_pub.publish(path)
    big = Path()
    big.header.frame_id = FRAME
    big.poses = [pose_msg(HOME, frame_id=FRAME) for _ in range(4)]
    stack.path_pub.publish(big)
    ros.spin_until(lambda: len(stack.status) >= 5, what='five statuses')
    assert sorted(value(s, 'goal_id') for s in stack.status) == ['1', '2', '3', '4', '5']
    assert all(s.message == 'rejected' for s in stack.status)
    reasons = ' | '.join(value(s, 'reason') for s in stack.status)
    for expected in ('not finite', "frame 'world'", 'empty path', 'non-increasing',
                     'more than trajectory.max_path_poses = 3'):
        assert expected in reasons
    ros.spin_for(0.1)
    assert stack.trajectories == []


def test_path_passes_its_via_point_at_its_stamp(ros):
    node, stack = start(ros)
    via, goal = HOME + [0.003, 0.002, 0.01], HOME + [0.005, 0.0, 0.02]
    path = Path()
    path.header.frame_id = FRAME                       # header stamp 0: relative times
    path.poses = [pose_msg(via, frame_id=FRAME, stamp=sec_to_stamp(0.3)),
                  pose_msg(goal, frame_id=FRAME, stamp=sec_to_stamp(0.6))]
    stack.path_pub.publish(path)
    ros.spin_until(lambda: len(stack.trajectories) == 1, what='the planned motion')
    stack.wait_state('1', 'accepted')
    knots = stack.knots(stack.trajectories[0])
    assert knots.duration == pytest.approx(0.6)
    np.testing.assert_allclose(knots.sample(0.3)[0], via, atol=1e-9)
    np.testing.assert_allclose(knots.positions[-1], goal, atol=1e-12)
    assert value(stack.status[0], 'source') == 'pose_path'


def test_cancel_stops_the_running_motion_and_the_next_starts_where_it_stopped(ros):
    node, stack = start(ros)
    stack.goal_pub.publish(pose_msg(HOME + [0.0, 0.02, 0.05], frame_id=FRAME))
    ros.spin_until(lambda: len(stack.trajectories) == 1, what='moving')
    first = stack.trajectories[0]
    stack.event(first, 'started')
    cancel = stack.client.create_client(Trigger, '/trajectory_node/cancel')
    assert cancel.wait_for_service(timeout_sec=5.0)
    future = cancel.call_async(Trigger.Request())
    ros.spin_until(future.done, what='cancel response')
    assert future.result().success
    stack.wait_state('1', 'cancelled')
    # the stop: an empty trajectory naming the running one (the driver brakes along it)
    ros.spin_until(lambda: len(stack.trajectories) == 2, what='the stop')
    stop = stack.trajectories[1]
    assert len(stop.points) == 0 and stop.header.stamp == first.header.stamp
    # a goal sent while the brace is braking waits for the driver's report ...
    stack.goal_pub.publish(pose_msg(HOME + [0.0, -0.01, 0.0], frame_id=FRAME))
    ros.spin_for(0.3)
    assert len(stack.trajectories) == 2
    # ... then starts exactly where the driver says the motion stopped
    where = stack.knots(first).sample(0.3)[0]
    stack.event(first, 'stopped', 'cancel requested (empty trajectory)', pose=where)
    ros.spin_until(lambda: len(stack.trajectories) == 3, what='the next motion')
    np.testing.assert_allclose(stack.knots(stack.trajectories[2]).positions[0], where, atol=1e-9)
    assert stack.states('1') == [('1', 'accepted'), ('1', 'cancelled')]


def test_a_goal_during_interaction_ends_the_mode_and_starts_where_the_driver_stopped(ros):
    """The driver's in-cycle admittance moved the command away from the node's hold: a goal
    then sends the stop (an empty trajectory), waits for the interaction's end event and is
    planned from the positions it reports (not from the stale hold: the splice would fail)."""
    node, stack = start(ros)
    stack.exec_pub.publish(status_msg('can_driver_node/interaction/1', 'started', stamp=1,
                                      kind='started', reason='', positions=list(lumbar_eq3(HOME))))
    ros.spin_until(lambda: node.runner.interacting, what='interaction seen')
    stack.goal_pub.publish(pose_msg(HOME + [0.0, -0.01, 0.0], frame_id=FRAME))
    ros.spin_until(lambda: len(stack.trajectories) == 1, what='the stop')
    assert len(stack.trajectories[0].points) == 0
    ros.spin_for(0.3)
    assert len(stack.trajectories) == 1                  # waits for the driver's report
    moved = HOME + np.array([0.0, 0.008, 0.02])           # where the admittance came to rest
    stack.exec_pub.publish(status_msg('can_driver_node/interaction/1', 'aborted', stamp=1,
                                      kind='aborted', reason='a position goal arrived (empty trajectory)',
                                      positions=list(lumbar_eq3(moved))))
    ros.spin_until(lambda: len(stack.trajectories) == 2, what='the goal\'s motion')
    np.testing.assert_allclose(stack.knots(stack.trajectories[1]).positions[0], moved, atol=1e-7)
    assert not node.runner.interacting


def test_a_platform_that_does_not_follow_is_aborted_with_the_error(ros):
    node, stack = start(ros, **{'safety.settle_time': 0.3})
    goal = HOME + [0.01, 0.0, 0.0]
    stack.goal_pub.publish(pose_msg(goal, frame_id=FRAME))
    ros.spin_until(lambda: len(stack.trajectories) == 1, what='the planned motion')
    stack.event(stack.trajectories[0], 'started')
    stack.event(stack.trajectories[0], 'finished', pose=goal)
    for _ in range(5):
        ros.spin_for(0.05)
        stack.estimate(HOME + [0.0003, 0.0, 0.0])        # the ring stayed where it was
    stack.wait_state('1', 'aborted')
    aborted = stack.status[-1]
    assert aborted.level == DiagnosticStatus.ERROR
    assert 'did not follow' in value(aborted, 'reason') and 'x off by 9.70 mm' in value(aborted, 'reason')


def test_a_protective_stop_aborts_the_running_goal_with_the_drivers_reason(ros):
    node, stack = start(ros)
    stack.goal_pub.publish(pose_msg(HOME + [0.0, 0.02, 0.05], frame_id=FRAME))
    ros.spin_until(lambda: len(stack.trajectories) == 1, what='moving')
    stack.event(stack.trajectories[0], 'started')
    stack.driver(False, 'protective stop: a1: following error')
    stack.wait_state('1', 'aborted')
    assert 'following error' in value(stack.status[-1], 'reason')
    # the stop's own execution event does not report it a second time
    stack.event(stack.trajectories[0], 'stopped', 'protective stop', pose=HOME)
    ros.spin_for(0.2)
    assert stack.states('1') == [('1', 'accepted'), ('1', 'aborted')]


def test_a_goal_flood_coalesces_and_every_goal_gets_exactly_one_end(ros):
    node, stack = start(ros)
    n = 200
    for i in range(n):                                 # as fast as rclpy publishes (> 1 kHz)
        stack.goal_pub.publish(pose_msg(HOME + [0.0, 0.0001 * (i % 20), 0.0], frame_id=FRAME))
    ros.spin_until(lambda: len({value(s, 'goal_id') for s in stack.status
                                if s.message != 'accepted'}) >= n - 1
                   and (str(n), 'accepted') in stack.states(), timeout=20.0,
                   what='an end for every goal but the newest, which runs')
    ids = [value(s, 'goal_id') for s in stack.status]
    assert set(ids) == {str(i) for i in range(1, n + 1)}, sorted(
        {str(i) for i in range(1, n + 1)} - set(ids), key=int)
    for gid in {str(i) for i in range(1, n + 1)}:
        events = stack.states(gid)
        assert events[0][1] in ('accepted', 'rejected')           # accepted or rejected first
        ends = [e for _, e in events if e != 'accepted']
        assert len(ends) <= 1
    superseded = [s for s in stack.status if 'superseded by goal' in value(s, 'reason')]
    assert len(superseded) > n / 2                                # planned far fewer than sent
    # the newest goal is the one that runs
    assert stack.states(str(n))[-1] == (str(n), 'accepted')


def test_platform_limits_of_the_wrong_length_fail_at_start_up(ros):
    from brace_control.config import ConfigError
    with pytest.raises(ConfigError, match='max_jerk needs 3 values'):
        ros.device_node(TrajectoryNode, **(OVERRIDES | {'trajectory.max_jerk': '[1.0, 1.0]'}))


def test_ros2_param_set_is_refused_with_a_reason_and_changes_nothing(ros):
    """Parameters are read once, at start-up (README, "Parameters"): a set at run time that
    would be accepted and ignored is refused instead, saying so, and the value stays."""
    from rclpy.parameter import Parameter
    node = ros.device_node(TrajectoryNode, **OVERRIDES)
    before = {n: node.get_parameter(n).value for n in ('trajectory.fitts_a', 'trajectory.profile')}
    results = node.set_parameters([Parameter('trajectory.fitts_a', value=5.0),
                                   Parameter('trajectory.profile', value='scurve')])
    for r in results:
        assert not r.successful and 'read-only' in r.reason, r.reason
    assert {n: node.get_parameter(n).value for n in before} == before


def test_a_refused_late_splice_is_planned_again_from_the_running_motion_then_aborted(ros):
    """Goal 2 preempts goal 1 while it moves; the driver refuses goal 2's motion ("more than
    the splice tolerance": it came after its takeover time). Goal 2 is not aborted: it is
    planned again, starting where motion 1 (the one that goes on) is at the new takeover,
    up to LATE_SPLICE_REPLANS times; refused once more, it is aborted with the driver's
    reason, and it ends exactly once."""
    from brace_control.nodes.trajectory_node import LATE_SPLICE_REPLANS
    node, stack = start(ros)
    stack.goal_pub.publish(pose_msg(HOME + [0.0, 0.02, 0.0], frame_id=FRAME))
    ros.spin_until(lambda: len(stack.trajectories) == 1, what='motion 1')
    motion1 = stack.knots(stack.trajectories[0])
    t1 = stamp_to_ns(stack.trajectories[0].header.stamp)
    stack.event(stack.trajectories[0], 'started')
    stack.goal_pub.publish(pose_msg(HOME + [0.0, -0.01, 0.0], frame_id=FRAME))
    ros.spin_until(lambda: len(stack.trajectories) == 2, what='motion 2')
    why = ('its start is 9.240 mm (or mrad) from the command on joint 3, more than the splice '
           'tolerance 5.000; the running motion continues')
    for k in range(LATE_SPLICE_REPLANS):
        stack.event(stack.trajectories[-1], 'rejected', why)
        ros.spin_until(lambda: len(stack.trajectories) == 3 + k, what=f'motion 2 planned again ({k + 1})')
        again = stack.trajectories[-1]
        # from motion 1 at its takeover (the motion the driver goes on with)
        t = (stamp_to_ns(again.header.stamp) - t1) * 1e-9
        want = motion1.sample(min(t, motion1.duration))[0]
        np.testing.assert_allclose(stack.knots(again).positions[0], want, atol=1e-6)
        assert [s for g, s in stack.states('2') if s != 'accepted'] == []
    stack.event(stack.trajectories[-1], 'rejected', why)
    stack.wait_state('2', 'aborted')
    assert 'splice tolerance' in value(stack.status[-1], 'reason')
    ros.spin_for(0.2)
    assert [s for _, s in stack.states('2')] == ['accepted'] * (1 + LATE_SPLICE_REPLANS) + ['aborted']
    assert [s for _, s in stack.states('1')] == ['accepted', 'cancelled']


def test_a_refused_late_splice_with_a_newer_goal_waiting_is_superseded_not_aborted(ros):
    """Goal 2 preempts goal 1 while it moves and the driver refuses goal 2's motion while
    goal 3 already waits to be planned (a flood on a loaded host, run 902): goal 2 is not
    planned again (goal 3 is, from the motion that goes on) and ends ``cancelled: superseded
    by goal 3``, the driver's reason kept; it is not counted as a failure of its own."""
    from brace_control.trajectory import GoalEvent, GoalRequest, GoalState
    node, stack = start(ros)
    stack.goal_pub.publish(pose_msg(HOME + [0.0, 0.02, 0.0], frame_id=FRAME))
    ros.spin_until(lambda: len(stack.trajectories) == 1, what='motion 1')
    stack.event(stack.trajectories[0], 'started')
    stack.goal_pub.publish(pose_msg(HOME + [0.0, -0.01, 0.0], frame_id=FRAME))
    ros.spin_until(lambda: len(stack.trajectories) == 2, what='motion 2')
    why = ('its motion was rejected: its start is 7.276 mm (or mrad) from the command on joint 3, '
           'more than the splice tolerance 5.000; the running motion continues')
    waiting = (GoalRequest('3', np.asarray(HOME, float)), {})
    with node._lock:                     # goal 3 waits: the planner has not taken it yet
        node._pending = waiting
        out = node._plan_late_splices_again([GoalEvent('2', GoalState.ABORTED, why)])
        assert node._pending is waiting and '2' not in node._replans
        node._pending = None
    assert [(e.goal_id, e.state) for e in out] == [('2', GoalState.CANCELLED)], out
    assert out[0].reason.startswith('superseded by goal 3: ') and 'splice tolerance' in out[0].reason
