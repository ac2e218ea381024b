"""kinetics_node with real rclpy and DDS: joint states in; the load-aware pose estimate, its
covariance and the wrench out.

Oracles from the seed's eq. 3 and kinetics (leg vectors, W = sum f_i u_i: test/seed001.py) and
the leg model f = k (q - l(p)): a ring at pose p with leg forces f reads q = l(p) + f / k.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped, WrenchStamped
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import JointState

from brace_control.config import load_device_config
from brace_control.nodes.kinetics_node import KineticsNode
from brace_control.mechanisms import UnreachablePose, load_mechanism
from brace_control.nodes.msgs import (joint_state, planar_pose_from_msg, pose_covariance_6x6,
                                      sec_to_stamp, stamp_to_ns)
from ros_helpers import LUMBAR_YAML, RELIABLE_10, REPO
from seed001 import leg_lengths as lengths, leg_matrix

pytestmark = pytest.mark.ros

CFG = load_device_config(LUMBAR_YAML)
NAMES = list(CFG['mechanism']['actuator_names'])
K_LEG = float(CFG['actuator']['stiffness'])
DEG = math.pi / 180.0


def rot(th: float) -> np.ndarray:
    return np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])


def encoders(pose, forces) -> np.ndarray:
    """What the encoders read when the ring is at ``pose`` and the legs carry ``forces``
    (push positive): each leg is the drive in series with k, f = k (q - l(p))."""
    return lengths(pose) + np.asarray(forces, float) / K_LEG


def jacobian(pose) -> np.ndarray:
    """Rows (u_i, (R b_i) x u_i): dl_i = J (dx, dy, dtheta)."""
    return leg_matrix(pose).T


def expected_covariance(pose, forces) -> np.ndarray:
    """The YAML's error budget per leg (encoder quantum 1 mm / 8192 read and homed, load cell
    noise and count, stiffness known to 5 %), through the weighted least squares."""
    act, kin = CFG['actuator'], CFG['kinetics']
    res = act['screw_lead'] / act['encoder_counts_per_rev']
    var = (res ** 2 / 6.0 + (kin['load_cell_noise'] ** 2 + act['load_cell_n_per_count'] ** 2 / 12.0) / K_LEG ** 2
           + (np.asarray(forces) * kin['stiffness_rel_std'] / K_LEG) ** 2)
    j = jacobian(pose)
    return np.linalg.inv(j.T @ np.diag(1.0 / var) @ j)


def body_wrench_platform_frame(pose, forces) -> np.ndarray:
    """Oracle (seed 001, kinetics): thrust f_i along each leg pushes the platform;
    F = sum f_i u_i, M = sum (R b_i) x f_i u_i about P; F expressed in the platform frame."""
    w = leg_matrix(pose) @ np.asarray(forces, float)
    return np.array([*(rot(pose[2]).T @ w[:2]), w[2]])


@pytest.fixture
def rig(ros):
    kin = ros.device_node(KineticsNode)
    test = ros.node('kinetics_test')
    poses = ros.collect(test, PoseStamped, '/brace/pose')
    wrenches = ros.collect(test, WrenchStamped, '/brace/wrench')
    diags = ros.collect(test, DiagnosticArray, '/diagnostics')
    ros.covariances = ros.collect(test, PoseWithCovarianceStamped, '/brace/pose_with_covariance')
    pub = test.create_publisher(JointState, '/brace/joint_states', RELIABLE_10)
    ros.wait_matched(pub)
    ros.spin_until(lambda: kin._pose_pub.get_subscription_count() >= 1
                   and kin._pose_cov_pub.get_subscription_count() >= 1
                   and kin._wrench_pub.get_subscription_count() >= 1, what='kinetics -> test')
    return ros, kin, pub, poses, wrenches, diags


def _statuses(diags, level=None):
    return [s for d in diags for s in d.status if s.name == 'brace_control/kinetics_node'
            and (level is None or s.level == level)]


def test_pose_covariance_and_wrench_from_lengths_and_load_cells(rig):
    ros, kin, pub, poses, wrenches, _ = rig
    pose = np.array([0.0, 0.37, 0.17])
    forces = [40.0, -25.0, 60.0]
    # actuators listed in another order than the YAML: matched by name
    order = [2, 0, 1]
    q = encoders(pose, forces)
    pub.publish(joint_state([NAMES[i] for i in order], position=q[order],
                            velocity=[0.0] * 3, effort=np.asarray(forces)[order],
                            stamp=sec_to_stamp(7.25)))
    ros.spin_until(lambda: poses and wrenches and ros.covariances, what='pose, covariance and wrench')
    assert poses[0].header.frame_id == 'brace_base'
    np.testing.assert_allclose(planar_pose_from_msg(poses[0]), pose, atol=1e-9)
    w = wrenches[0]
    assert w.header.frame_id == 'brace_platform'
    got = [w.wrench.force.x, w.wrench.force.y, w.wrench.torque.z]
    np.testing.assert_allclose(got, body_wrench_platform_frame(pose, forces), rtol=1e-9, atol=1e-9)
    assert (w.wrench.force.z, w.wrench.torque.x, w.wrench.torque.y) == (0.0, 0.0, 0.0)
    c = ros.covariances[0]
    assert c.header.frame_id == 'brace_base'
    for m in (poses[0], w, c):                                  # the joint state's stamp, all three
        assert stamp_to_ns(m.header.stamp) == 7_250_000_000
    assert c.pose.pose == poses[0].pose
    cov = np.asarray(c.pose.covariance).reshape(6, 6)           # (x, y, z, rot x, rot y, rot z)
    xy_yaw = [0, 1, 5]
    np.testing.assert_allclose(cov[np.ix_(xy_yaw, xy_yaw)], expected_covariance(pose, forces), rtol=1e-6)
    np.testing.assert_allclose(np.diag(cov)[[2, 3, 4]], CFG['kinetics'].get('unobserved_variance', 1e6))
    off = np.ones((6, 6), bool)
    off[np.ix_(xy_yaw, xy_yaw)] = False
    np.fill_diagonal(off, False)
    assert np.all(cov[off] == 0.0)
    assert np.all(np.linalg.eigvalsh(cov[np.ix_(xy_yaw, xy_yaw)]) > 0.0)


def test_loaded_ring_pose_is_the_legs_not_the_encoders(rig):
    """Near the singular theta = 0 the encoder lengths of a loaded brace are millimetres of
    pose away from the ring: the node publishes the ring's pose (and the wrench there)."""
    ros, kin, pub, poses, wrenches, _ = rig
    pose = np.array([0.004, 0.395, 3.0 * DEG])
    forces = np.array([-180.0, 90.0, -240.0])
    q = encoders(pose, forces)
    try:                                                       # the old answer: none, or mm off
        naive = load_mechanism(LUMBAR_YAML).forward_nearest(q, pose)
        assert np.max(np.abs(naive - pose)[:2]) > 1e-3
    except UnreachablePose:
        pass
    pub.publish(joint_state(NAMES, position=q, effort=forces, stamp=sec_to_stamp(3.0)))
    ros.spin_until(lambda: poses and wrenches, what='pose and wrench')
    np.testing.assert_allclose(planar_pose_from_msg(poses[0]), pose, atol=1e-8)
    w = wrenches[0]
    np.testing.assert_allclose([w.wrench.force.x, w.wrench.force.y, w.wrench.torque.z],
                               body_wrench_platform_frame(pose, forces), rtol=1e-6, atol=1e-6)
    assert kin.estimate.exact and kin.diagnostics.values['solution'] == 'exact'


def test_lengths_that_cannot_close_give_a_least_squares_pose_and_a_warning(rig):
    """Dead load cells on a brace stopped under load: the encoder lengths cannot close
    (legs 1 and 3, 250 um short). A pose is still published, flagged least squares, the
    residual in /diagnostics and on the node."""
    ros, kin, pub, poses, _, diags = rig
    start = np.array([0.0, 0.392, 3.0 * DEG])
    pub.publish(joint_state(NAMES, position=lengths(start), effort=[0.0] * 3))
    ros.spin_until(lambda: len(poses) == 1, what='first pose')
    bad = lengths(start) + np.array([-250e-6, 60e-6, -250e-6])
    c2 = 0.5 * (bad[0] ** 2 + bad[2] ** 2 - 2 * bad[1] ** 2)  # parallelogram law: cos(theta) > 1
    assert (0.217 ** 2 + 0.195 ** 2 - c2) / (2 * 0.217 * 0.195) > 1.0
    for k in range(30):
        pub.publish(joint_state(NAMES, position=bad, effort=[0.0] * 3, stamp=sec_to_stamp(1 + 0.01 * k)))
        ros.spin_until(lambda: len(poses) == k + 2, what=f'pose {k + 2}')
    ros.spin_until(lambda: any('least squares' in s.message for s in _statuses(diags, DiagnosticStatus.WARN)),
                   what='least-squares WARN')
    assert not kin.estimate.exact and kin.failed == 0
    np.testing.assert_allclose(kin.residual, bad - lengths(kin.estimate.pose), atol=1e-12)
    assert np.max(np.abs(kin.residual)) > 1e-6
    assert kin.diagnostics.values['solution'] == 'least squares'
    assert planar_pose_from_msg(poses[-1])[1] > 0.3             # the brace's assembly mode


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
    """Without load cells the leg deflection is only bounded by the force limit: the pose of
    the encoder lengths, with that in its covariance."""
    ros, kin, pub, poses, wrenches, _ = rig
    pose = [0.0, 0.37, 0.17]
    pub.publish(joint_state(NAMES, position=lengths(pose)))
    ros.spin_until(lambda: poses and ros.covariances, what='pose')
    ros.spin_for(0.1)
    assert wrenches == []
    np.testing.assert_allclose(planar_pose_from_msg(poses[0]), pose, atol=1e-9)
    cov = np.asarray(ros.covariances[0].pose.covariance).reshape(6, 6)
    assert cov[0, 0] > 100.0 * expected_covariance(pose, [0.0] * 3)[0, 0]


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


@pytest.mark.parametrize('device', sorted(p.stem for p in (REPO / 'config').glob('*.yaml')))
def test_every_device_file_gives_its_estimator_and_a_pose(ros, device):
    """The node reads actuator.stiffness, the encoder quantum and kinetics.* from each
    device file, and estimates the home pose from the home lengths."""
    path = REPO / 'config' / f'{device}.yaml'
    cfg = load_device_config(path)
    act = cfg['actuator']
    kin = ros.device_node(KineticsNode, path)
    test = ros.node('kinetics_test')
    got = ros.collect(test, PoseWithCovarianceStamped, '/brace/pose_with_covariance')
    pub = test.create_publisher(JointState, '/brace/joint_states', RELIABLE_10)
    ros.wait_matched(pub)
    ros.spin_until(lambda: kin._pose_cov_pub.get_subscription_count() >= 1, what='kinetics -> test')
    model = kin.estimator.model
    assert model.stiffness == act['stiffness'] and model.force_noise == cfg['kinetics']['load_cell_noise']
    rotary = act.get('kind') == 'rotary'
    quantum = (2 * math.pi / (act['encoder_counts_per_rev'] * act.get('gear_ratio', 1.0)) if rotary
               else act['screw_lead'] / act['encoder_counts_per_rev'])
    assert model.resolution == pytest.approx(quantum, rel=1e-12) and kin.estimator.rotary == rotary
    mech = kin.mechanism
    home = np.asarray(mech.home_pose, float)
    pub.publish(joint_state(mech.actuator_names, position=mech.inverse(home),
                            effort=[0.0] * mech.n_actuators))
    ros.spin_until(lambda: got, what='pose with covariance')
    np.testing.assert_allclose(kin.estimate.pose, home, atol=1e-9)
    cov = np.asarray(got[0].pose.covariance).reshape(6, 6)
    assert np.all(np.isfinite(cov)) and np.all(np.diag(cov) > 0.0)


# ----------------------------------------------------------------------------- message covariance

def test_covariance_placement_for_xy_and_path_poses():
    cov2 = np.array([[4.0, 1.0], [1.0, 9.0]])
    out = pose_covariance_6x6([0.1, 0.2], cov2, kind='xy', unobserved_variance=1e6)
    np.testing.assert_array_equal(out[:2, :2], cov2)
    np.testing.assert_array_equal(np.diag(out)[2:], [1e6] * 4)
    out = pose_covariance_6x6([0.3], np.array([[2.5]]), kind='path')
    assert out[0, 0] == 2.5 and np.count_nonzero(out - np.diag(np.diag(out))) == 0
    with pytest.raises(ValueError, match='covariance'):
        pose_covariance_6x6([0.1, 0.2, 0.3], cov2, kind='planar')
    with pytest.raises(ValueError, match='symmetric'):
        pose_covariance_6x6([0.1, 0.2], np.array([[1.0, 0.5], [0.0, 1.0]]), kind='xy')


def test_spherical_covariance_is_about_the_base_frame_axes():
    """The shoulder's motion angles -> rotations about the fixed axes: G from the model's
    rotation matrices (scipy's rotation vector of R(p + h e_i) R(p)^T), independent of
    the quaternion path in msgs."""
    mech = load_mechanism(REPO / 'config' / 'shoulder.yaml')
    pose = np.array([0.3, -0.2, 0.4])
    cov = np.diag([1e-6, 4e-6, 9e-6]) + 1e-7
    h = 1e-6
    g = np.column_stack([
        (Rotation.from_matrix(mech.rotation_matrix(pose + h * e) @ mech.rotation_matrix(pose).T).as_rotvec()
         - Rotation.from_matrix(mech.rotation_matrix(pose - h * e) @ mech.rotation_matrix(pose).T).as_rotvec())
        / (2 * h) for e in np.eye(3)])
    out = pose_covariance_6x6(pose, cov, mechanism=mech)
    np.testing.assert_allclose(out[3:, 3:], g @ cov @ g.T, rtol=1e-6)
    np.testing.assert_array_equal(np.diag(out)[:3], [1e6] * 3)


# ------------------------------------------------------------------ at rest (issue 27)
REST_PERIOD = float(CFG['kinetics'].get('rest_period', 0.05))
RES = CFG['actuator']['screw_lead'] / CFG['actuator']['encoder_counts_per_rev']


def test_rest_gate_is_due_on_motion_on_a_new_load_and_after_its_period():
    from brace_control.nodes.kinetics_node import RestGate
    gate = RestGate(np.full(3, 1e-6), np.full(3, 0.25), 0.05)
    q, f = np.array([0.37, 0.38, 0.39]), np.array([10.0, -5.0, 3.0])
    assert gate.due(q, f, 1.0)                                  # nothing taken yet
    gate.took(q, f, 1.0)
    assert not gate.due(q, f, 1.01)                             # the same readings
    assert not gate.due(q + 0.9e-6, f - 0.24, 1.02)             # within the bands
    assert gate.due(q + [0.0, 1.1e-6, 0.0], f, 1.02)            # one encoder moved
    assert gate.due(q, f + [0.0, 0.0, 0.26], 1.02)              # one load cell moved
    assert gate.due(q, None, 1.02)                              # the load cells went silent
    assert gate.due(q, f, 1.05)                                 # the period is over
    assert gate.due(q, f, 0.5)                                  # a stamp from before (bag again)
    assert gate.skipped == 2
    gate.reset()
    assert gate.due(q, f, 1.01)
    assert all(RestGate(np.full(3, 1.0), np.full(3, 1.0), 0.0).due(q, f, t) for t in (1.0, 1.0, 1.001))


def test_at_rest_the_estimate_is_renewed_every_rest_period_and_at_once_when_a_reading_moves(rig):
    """Readings that do not move beyond their noise are not a new pose on every joint state:
    the newest is estimated and published every kinetics.rest_period, on its stamp. A reading
    that moves (two encoder counts, a load change) is published with its own stamp at once."""
    ros, kin, pub, poses, wrenches, _ = rig
    pose, forces = np.array([0.0, 0.37, 0.17]), np.array([40.0, -25.0, 60.0])
    q = encoders(pose, forces)
    rng = np.random.default_rng(27)
    n = 30
    for k in range(n):                                          # 0.3 s at 100 Hz, load-cell noise
        noisy = forces + rng.normal(0.0, CFG['kinetics']['load_cell_noise'], 3)
        pub.publish(joint_state(NAMES, position=q, effort=noisy, stamp=sec_to_stamp(1 + 0.01 * k)))
        ros.spin_until(lambda: kin.received == k + 1, what=f'joint state {k}')
    ros.spin_until(lambda: poses and len(wrenches) == len(poses), what='the poses at rest')
    stamps = np.array([stamp_to_ns(m.header.stamp) for m in poses]) * 1e-9
    assert stamps[0] == 1.0
    gaps = np.diff(stamps)
    assert np.all(gaps >= REST_PERIOD - 1e-6) and np.all(gaps <= REST_PERIOD + 0.01 + 1e-6), gaps
    assert len(poses) <= n * 0.01 / REST_PERIOD + 1 < n
    sigma = np.sqrt(np.diag(expected_covariance(pose, forces)))     # the noise's, through the legs
    for m in poses:
        assert np.all(np.abs(planar_pose_from_msg(m) - pose) <= 5.0 * sigma)
    # two encoder counts on leg 2 (one is within the band: a holding drive dithers by one),
    # then a 1 N load change on leg 3: each at once, on its stamp
    moved_q = q + np.array([0.0, 2 * RES, 0.0])
    pub.publish(joint_state(NAMES, position=moved_q, effort=forces, stamp=sec_to_stamp(1.301)))
    ros.spin_until(lambda: stamp_to_ns(poses[-1].header.stamp) == 1_301_000_000, what='the moved encoder')
    loaded = forces + np.array([0.0, 0.0, 1.0])
    pub.publish(joint_state(NAMES, position=moved_q, effort=loaded, stamp=sec_to_stamp(1.302)))
    ros.spin_until(lambda: stamp_to_ns(wrenches[-1].header.stamp) == 1_302_000_000, what='the new load')
    w = wrenches[-1]
    est = planar_pose_from_msg(poses[-1])
    np.testing.assert_allclose([w.wrench.force.x, w.wrench.force.y, w.wrench.torque.z],
                               body_wrench_platform_frame(est, loaded), rtol=1e-6, atol=1e-6)
    assert kin.rest_gate.skipped >= n - len(stamps)


def test_a_topic_nobody_reads_is_not_made_and_a_reader_that_joins_gets_the_next(ros):
    """Volatile outputs are made only while something subscribes them: the estimate (and
    the wrench the node keeps) follows every joint state either way, and a reader that
    subscribes later gets the next sample, with the oracle's wrench."""
    kin = ros.device_node(KineticsNode)
    test = ros.node('kinetics_lazy')
    made = {'pose': 0, 'cov': 0, 'wrench': 0}
    for key, pub in (('pose', kin._pose_pub), ('cov', kin._pose_cov_pub), ('wrench', kin._wrench_pub)):
        publish = pub.publish

        def counted(msg, key=key, publish=publish):
            made[key] += 1
            publish(msg)
        pub.publish = counted
    js = test.create_publisher(JointState, '/brace/joint_states', RELIABLE_10)
    ros.wait_matched(js)
    pose = np.array([0.0, 0.37, 0.17])
    for k, forces in enumerate(([40.0, -25.0, 60.0], [30.0, -20.0, 50.0])):
        js.publish(joint_state(NAMES, position=encoders(pose, forces), effort=forces,
                               stamp=sec_to_stamp(1.0 + k)))
        ros.spin_until(lambda k=k: kin.received == k + 1, what=f'joint state {k + 1} taken')
        np.testing.assert_allclose(kin.pose, pose, atol=1e-9)
        np.testing.assert_allclose(kin.wrench, body_wrench_platform_frame(pose, forces), atol=1e-9)
    assert made == {'pose': 0, 'cov': 0, 'wrench': 0}
    wrenches = ros.collect(test, WrenchStamped, '/brace/wrench')
    ros.spin_until(lambda: kin._wrench_pub.get_subscription_count() >= 1, what='the reader matched')
    forces = [20.0, -10.0, 45.0]
    js.publish(joint_state(NAMES, position=encoders(pose, forces), effort=forces,
                           stamp=sec_to_stamp(3.0)))
    ros.spin_until(lambda: wrenches, what='the wrench for the reader that joined')
    w = wrenches[0]
    np.testing.assert_allclose([w.wrench.force.x, w.wrench.force.y, w.wrench.torque.z],
                               body_wrench_platform_frame(pose, forces), atol=1e-9)
    assert made['wrench'] == 1 and made['pose'] == 0 and made['cov'] == 0
