"""The exercise bag and the run report (plot + summary), without ROS: bags written with rosbags."""
from __future__ import annotations

import math

import numpy as np
import pytest
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from brace_control.demo import prepare_config
from brace_control.demo_report import plot_run, read_run, summarise
from brace_control.exercise import NEUTRAL_TILT, build_exercise_bag, exercise_goals
from ros_helpers import LUMBAR_YAML

STORE = get_typestore(Stores.ROS2_HUMBLE)
T = STORE.types


def test_exercise_covers_shift_lift_and_rotation_to_10_deg_and_back():
    goals = exercise_goals([0.0, 0.39, 0.0])
    poses = np.array([g.pose for g in goals])
    assert poses[:, 0].max() >= 0.01 and poses[:, 0].min() <= -0.01        # lateral both ways
    assert poses[:, 1].max() - 0.39 >= 0.015                               # vertical lift
    assert math.degrees(poses[:, 2].max()) == pytest.approx(10.0)          # coronal rotation
    np.testing.assert_allclose(goals[-1].pose, goals[0].pose)              # and back
    assert all(p[2] >= NEUTRAL_TILT - 1e-12 for p in poses)                # never at theta = 0
    times = [g.t for g in goals]
    assert all(b - a >= 2.0 for a, b in zip(times, times[1:]))             # human pace


def test_exercise_bag_holds_the_goals_in_the_base_frame(tmp_path):
    path, goals = build_exercise_bag(tmp_path / 'ex', LUMBAR_YAML)
    with Reader(path) as r:
        (c,) = r.connections
        assert c.topic == '/brace/pose_goal' and c.msgtype == 'geometry_msgs/msg/PoseStamped'
        msgs = [STORE.deserialize_cdr(d, c.msgtype) for _, _, d in r.messages()]
    assert len(msgs) == len(goals)
    assert {m.header.frame_id for m in msgs} == {'brace_base'}
    for m, g in zip(msgs, goals):
        assert m.pose.position.x == pytest.approx(g.pose[0])
        assert 2 * math.atan2(m.pose.orientation.z, m.pose.orientation.w) == pytest.approx(g.pose[2])


def test_prepare_config_parks_a_singular_home_clear_of_theta_0(tmp_path):
    import yaml
    path, note = prepare_config(str(LUMBAR_YAML), tmp_path)
    params = yaml.safe_load(path.read_text())['/**']['ros__parameters']
    original = yaml.safe_load(LUMBAR_YAML.read_text())['/**']['ros__parameters']
    if original['mechanism']['home_pose'][2] == 0.0:
        assert note and params['mechanism']['home_pose'][2] == pytest.approx(NEUTRAL_TILT)
        assert params['sim']['rest_pose'][2] == pytest.approx(NEUTRAL_TILT)
        assert (tmp_path / path.name).is_file()
    else:
        assert note is None


def _pose(t_ns, x, y, th, topic_frame='brace_base'):
    return T['geometry_msgs/msg/PoseStamped'](
        header=T['std_msgs/msg/Header'](stamp=T['builtin_interfaces/msg/Time'](
            sec=t_ns // 10**9, nanosec=t_ns % 10**9), frame_id=topic_frame),
        pose=T['geometry_msgs/msg/Pose'](
            position=T['geometry_msgs/msg/Point'](x=x, y=y, z=0.0),
            orientation=T['geometry_msgs/msg/Quaternion'](x=0.0, y=0.0, z=math.sin(th / 2), w=math.cos(th / 2))))


def test_summary_and_plot_of_a_synthetic_run(tmp_path):
    """Two goals: the first reached, the second not (measured stops 5 mm short)."""
    goals = [(0.01, 0.39, 0.1), (0.03, 0.39, 0.1)]
    bag = tmp_path / 'run'
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        cg = w.add_connection('/brace/pose_goal', 'geometry_msgs/msg/PoseStamped', typestore=STORE)
        cs = w.add_connection('/brace/pose_setpoint', 'geometry_msgs/msg/PoseStamped', typestore=STORE)
        cp = w.add_connection('/brace/pose', 'geometry_msgs/msg/PoseStamped', typestore=STORE)
        cj = w.add_connection('/brace/joint_states', 'sensor_msgs/msg/JointState', typestore=STORE)
        cw = w.add_connection('/brace/wrench', 'geometry_msgs/msg/WrenchStamped', typestore=STORE)
        ser = STORE.serialize_cdr
        w.write(cg, 0, bytes(ser(_pose(0, *goals[0]), 'geometry_msgs/msg/PoseStamped')))
        w.write(cg, 2 * 10**9, bytes(ser(_pose(0, *goals[1]), 'geometry_msgs/msg/PoseStamped')))
        for k in range(400):                       # 4 s at 100 Hz
            t = k * 10_000_000
            s = k / 100
            x_sp = 0.01 * min(s / 1.0, 1.0) if s < 2 else 0.01 + 0.02 * min((s - 2) / 1.0, 1.0)
            x_meas = x_sp - 0.001 if s < 2 else min(x_sp, 0.025)
            w.write(cs, t, bytes(ser(_pose(t, x_sp, 0.39, 0.1), 'geometry_msgs/msg/PoseStamped')))
            w.write(cp, t + 1, bytes(ser(_pose(t, x_meas + (0.001 if s > 1.2 and s < 2 else 0), 0.39, 0.1),
                                         'geometry_msgs/msg/PoseStamped')))
            js = T['sensor_msgs/msg/JointState'](
                header=T['std_msgs/msg/Header'](stamp=T['builtin_interfaces/msg/Time'](sec=0, nanosec=0),
                                                frame_id=''),
                name=['a1', 'a2', 'a3'], position=np.array([0.39, 0.39, 0.39]),
                velocity=np.zeros(3), effort=np.array([10.0, -42.0 if k == 100 else 5.0, 3.0]))
            w.write(cj, t + 2, bytes(ser(js, 'sensor_msgs/msg/JointState')))
            wr = T['geometry_msgs/msg/WrenchStamped'](
                header=T['std_msgs/msg/Header'](stamp=T['builtin_interfaces/msg/Time'](sec=0, nanosec=0),
                                                frame_id='brace_platform'),
                wrench=T['geometry_msgs/msg/Wrench'](force=T['geometry_msgs/msg/Vector3'](x=1.0, y=-7.5, z=0.0),
                                                     torque=T['geometry_msgs/msg/Vector3'](x=0.0, y=0.0, z=0.25)))
            w.write(cw, t + 3, bytes(ser(wr, 'geometry_msgs/msg/WrenchStamped')))
    run = read_run(bag)
    assert run.names == ['a1', 'a2', 'a3'] and len(run.goal.t) == 2
    s = summarise(run, goals)
    assert (s.goals, s.goals_reached) == (2, 1)
    assert s.peak_force_n == pytest.approx(42.0) and s.peak_force_actuator == 'a2'
    assert s.peak_wrench == pytest.approx([1.0, 7.5, 0.25])
    assert s.max_tracking_error_m == pytest.approx(0.005, abs=2e-4)
    assert any('goals reached: 1/2' in line for line in s.lines())
    png = plot_run(run, tmp_path / 'run.png')
    assert png.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n' and png.stat().st_size > 20_000
