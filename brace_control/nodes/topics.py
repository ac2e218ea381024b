"""Every topic name and QoS profile of the stack, in one place.

Nodes, bring-up, the demo, its report and the tests import them from here (ARCHITECTURE.md,
"Data flow"). Each QoS choice says why.
"""
from __future__ import annotations

import math

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

__all__ = [
    'POSE_GOAL', 'POSE_PATH', 'POSE_TRAJECTORY', 'ACTUATOR_TRAJECTORY', 'POSE_SETPOINT',
    'ACTUATOR_SETPOINT', 'JOINT_STATES', 'POSE', 'POSE_WITH_COVARIANCE', 'WRENCH',
    'GOAL_STATUS', 'EXECUTION_STATUS', 'DRIVER_STATE', 'DIAGNOSTICS', 'SIM_JOINT_STATES',
    'SIM_POSE', 'SIM_WRENCH', 'WRENCH_GOAL', 'INTERACTION_GOAL', 'SIM_BODY_REST', 'SIM_BODY_POSE',
    'BRINGUP',
    'GOAL_QOS', 'TRAJECTORY_QOS', 'SETPOINT_QOS', 'STATE_QOS', 'TRUTH_QOS', 'TRUTH_KEPT_S', 'truth_qos',
    'BODY_REST_QOS',
    'MEASURED_QOS', 'STATUS_QOS',
    'GOAL_STATUS_QOS', 'GOAL_STATUS_DEPTH',
    'LATCHED_QOS', 'DIAGNOSTICS_QOS',
]

# ----------------------------------------------------------------------------- goals
#: ``geometry_msgs/PoseStamped``: go to this pose
POSE_GOAL = '/brace/pose_goal'
#: ``nav_msgs/Path``: pass the poses, stop at the last
POSE_PATH = '/brace/pose_path'
#: ``geometry_msgs/WrenchStamped``: the wrench the interaction mode holds on the body
WRENCH_GOAL = '/brace/wrench_goal'
#: ``geometry_msgs/WrenchStamped``: interaction_node -> the driver's in-cycle admittance: the
#: checked goal in the pose axes' components (planar: force.x, force.y base frame, torque.z)
INTERACTION_GOAL = '/brace/interaction/goal'

# ------------------------------------------------------------------------- motion
#: ``trajectory_msgs/MultiDOFJointTrajectory``: a planned motion, once, whole (pose knots)
POSE_TRAJECTORY = '/brace/pose_trajectory'
#: ``trajectory_msgs/JointTrajectory``: the same motion in actuator coordinates
ACTUATOR_TRAJECTORY = '/brace/actuator_trajectory'
#: ``geometry_msgs/PoseStamped`` stream (teleoperation, interaction mode)
POSE_SETPOINT = '/brace/pose_setpoint'
#: ``sensor_msgs/JointState`` stream: position (m or rad), velocity (feed-forward)
ACTUATOR_SETPOINT = '/brace/actuator_setpoint'

# ------------------------------------------------------------------ measurement
#: ``sensor_msgs/JointState``: position, velocity, effort = load-cell N / torque N·m
JOINT_STATES = '/brace/joint_states'
#: ``geometry_msgs/PoseStamped``: the estimated platform pose (load aware)
POSE = '/brace/pose'
#: ``geometry_msgs/PoseWithCovarianceStamped``: the same with its covariance
POSE_WITH_COVARIANCE = '/brace/pose_with_covariance'
#: ``geometry_msgs/WrenchStamped``: the wrench the brace applies to the body
WRENCH = '/brace/wrench'

# -------------------------------------------------------------------- status
#: ``diagnostic_msgs/DiagnosticStatus``: one message per goal event
GOAL_STATUS = '/brace/goal_status'
#: ``diagnostic_msgs/DiagnosticStatus``: what happened to each trajectory (ik node, driver)
EXECUTION_STATUS = '/brace/execution_status'
#: ``diagnostic_msgs/DiagnosticStatus``: the driver's state, latched (disabled, enabled,
#: halted, protective stop with its reasons)
DRIVER_STATE = '/brace/driver_state'
#: ``diagnostic_msgs/DiagnosticArray`` from every node
DIAGNOSTICS = '/diagnostics'
#: ``diagnostic_msgs/DiagnosticStatus``, latched, one per running ``brace-bringup``: when it
#: started, its process, host, namespace and nodes (of two that run the same nodes, the later
#: one stops)
BRINGUP = '/brace/bringup'

# ------------------------------------------------------------------- simulation
#: the simulator's ground truth (``can.sim`` only), same conventions as the measured topics
SIM_JOINT_STATES = '/brace/sim/joint_states'
SIM_POSE = '/brace/sim/pose'
SIM_WRENCH = '/brace/sim/wrench'
#: ``geometry_msgs/PoseStamped``: where the simulated body rests (a test moves the patient)
SIM_BODY_REST = '/brace/sim/body_rest'
#: ``geometry_msgs/PoseStamped``: where the simulated patient's trunk wants to be now (the rest
#: pose plus the sway), the truth a zero-torque test compares the ring's pose with
SIM_BODY_POSE = '/brace/sim/body_pose'

# -------------------------------------------------------------------------- QoS
#: Goals: reliable, keep all. No goal may be lost without a status, even in a flood: the
#: node takes every sample and coalesces them itself (the newest preempts, the others are
#: reported superseded), so no history depth can overflow.
GOAL_QOS = QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE)
#: Planned motions: reliable, keep all, volatile. Each is sent once; a late subscriber needs
#: none of the past ones. None may be dropped on the way: a preempting motion is planned from
#: the one before it (which the driver may not have started yet), so a chain of preemptions
#: (a goal flood) that loses a link makes the driver refuse the next one, too far from its
#: command (a keep-last 10 history did, with the ik node behind on a busy host).
TRAJECTORY_QOS = QoSProfile(history=HistoryPolicy.KEEP_ALL,
                            reliability=ReliabilityPolicy.RELIABLE,
                            durability=DurabilityPolicy.VOLATILE)
#: Setpoint streams: reliable, depth 10. A best-effort depth-1 stream would let DDS drop a
#: setpoint whenever a callback runs late and the driver's step check (docs/safety.md §7) would
#: see a double step; 10 samples absorb jitter without a backlog the staleness check
#: would miss (stale setpoints stop the stream, docs/safety.md §1).
SETPOINT_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                          reliability=ReliabilityPolicy.RELIABLE,
                          durability=DurabilityPolicy.VOLATILE)
#: Measured state (joint_states, pose, wrench): reliable, depth 10 (a slow callback loses
#: no sample of the 100 Hz stream; recorded bags are complete).
STATE_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                       reliability=ReliabilityPolicy.RELIABLE)
#: The simulator's ground truth (``/brace/sim/*``): as :data:`STATE_QOS`, deeper. A publisher
#: that fell behind publishes the samples it missed at once, each with its own stamp
#: (can_driver_node); 100 keeps 5 s of the default 20 Hz for a reader as deep. At a higher
#: ``sim.truth_rate_hz`` the driver keeps :data:`TRUTH_KEPT_S` of it (:func:`truth_qos`).
TRUTH_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                       reliability=ReliabilityPolicy.RELIABLE)
#: s of ground truth a publisher keeps for a reader that did not acknowledge it yet (a
#: recorder starved for a second on a loaded host lost 100 samples of a 100 Hz truth kept
#: 100 deep: the interaction demo's report found a hole in its step window); as long as the
#: catch-up a starved driver publishes at once (``can.process.TRUTH_BACKLOG``)
TRUTH_KEPT_S = 20.0

#: The driver's reader of the simulated patient's trunk (``/brace/sim/body_rest``): reliable,
#: 250 deep (5 s of a 50 Hz stream). The simulator plays a stream of rest poses out by their
#: stamps, and a gap between stamps longer than ``sim.brace.REST_STREAM_GAP_S`` is a new
#: motion: a step to the new pose. A reader 10 deep lost the older samples of whatever
#: arrived while the driver's executor stood still for more than 0.2 s, and the trunk jumped
#: 9 mm in one SYNC (the interaction-limits tests' force steps of 6-12 N on a loaded host).
#: Publishers keep :data:`STATE_QOS`: the samples wait in the reader's history, which DDS
#: fills whatever the executor does. With writers 250 deep as well, the interaction demo's
#: recorder (another reader of the topic) stopped receiving anything mid-session in 1 run
#: of 4 beside two busy loops (and in a quiet fresh-clone run); with only the reader deep,
#: 0 of 6.
BODY_REST_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=250,
                           reliability=ReliabilityPolicy.RELIABLE)


def truth_qos(rate_hz: float) -> QoSProfile:
    """:data:`TRUTH_QOS`, at least :data:`TRUTH_KEPT_S` of samples at ``rate_hz`` deep."""
    return QoSProfile(history=TRUTH_QOS.history,
                      depth=max(TRUTH_QOS.depth, math.ceil(TRUTH_KEPT_S * rate_hz)),
                      reliability=TRUTH_QOS.reliability)


#: A subscriber that needs only the latest measurement: best effort matches any publisher.
MEASURED_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                          reliability=ReliabilityPolicy.BEST_EFFORT)
#: Events (goal and execution status): reliable, keep all. A goal flood makes hundreds of
#: events at once; a keep-last history would overwrite some before they are delivered.
STATUS_QOS = QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE)
#: Goal outcomes (``/brace/goal_status``): reliable, and transient local with the last
#: :data:`GOAL_STATUS_DEPTH` events kept, so a client that joins late, or whose reader matched
#: after an event was written, still gets the outcome of every recent goal (subscribe with
#: ``GOAL_STATUS_QOS``: a volatile subscriber gets only what is written after it matched).
#: The depth covers a flood of goals: each goal has 2-3 events, and the goal queue holds one.
GOAL_STATUS_DEPTH = 1000
GOAL_STATUS_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=GOAL_STATUS_DEPTH,
                             reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
#: State that a late subscriber must see at once (the driver's state): transient local,
#: the last sample kept.
LATCHED_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                         reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
DIAGNOSTICS_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                             reliability=ReliabilityPolicy.RELIABLE)
