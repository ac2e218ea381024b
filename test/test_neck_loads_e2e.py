"""The 4-RPR neck brace (cables) against the simulated head, judged on the simulator's truth.

All nodes in this process (``test_e2e.enabled_bring_up``, every safety limit as the YAML
sets it unless a test says otherwise). The head is a stiffness about its rest pose
(``sim.stiffness``: 1500 N/m in x and y); the oracle for the load on it is ``K (pose -
rest)`` at the TRUE head pose (``/brace/sim/pose``), with K and rest read from the YAML.

* A goal whose load on the head stays below ``safety.max_wrench`` (40 N) succeeds, one
  whose load would pass it is braked on the way (the soft tier of the wrench limit) and
  aborted naming it, nothing latches, the TRUE load never passes 40 N, and the brace goes
  on to the next goal. Before, it pressed on until the hard limit latched a protective stop.
* After a loaded protective stop and its relief the cables hang slack; ``~/enable`` takes
  the slack up, and the next goal succeeds. Before, the slack lengths fit no pose, and every
  later goal was refused ("its start is 25 mm from the command").
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from geometry_msgs.msg import PoseStamped

from brace_control.config import load_device_config
from brace_control.nodes import topics
from brace_control.nodes.msgs import pose_msg, stamp_to_ns
from rpr_oracles import cable_lengths_4rpr
from test_e2e import _extra_args, _planar, enabled_bring_up

pytestmark = [pytest.mark.ros, pytest.mark.e2e, pytest.mark.slow]

DEVICE = Path(__file__).resolve().parents[1] / 'config' / 'neck_brace_4rpr.yaml'


def _head_load(cfg, poses) -> np.ndarray:
    """|K (pose - rest)| per axis for TRUE poses (N, N, N·m)."""
    K = np.asarray(cfg['sim']['stiffness'], float).reshape(3, 3)
    rest = np.asarray(cfg['sim']['rest_pose'], float)
    return np.abs((np.asarray(poses) - rest) @ K.T)


def _same_sync(probe, since: int):
    """The newest true head pose (of ``probe.sim_poses[since:]``) and the joint state of the
    same SYNC (the same stamp: the simulator's truth and the measurements of one SYNC carry
    its send time), or None. After the take-up the head still settles: samples of two SYNCs
    would differ by its motion in between (run of 2026-11-29: 40 um)."""
    with probe.lock:
        joints = {stamp_to_ns(m.header.stamp): m for m in probe.joints[-200:]}
        for pose in reversed(probe.sim_poses[since:][-200:]):
            js = joints.get(stamp_to_ns(pose.header.stamp))
            if js is not None:
                return pose, js
    return None


def _end_of(probe, k: int, what: str) -> dict:
    probe.wait(lambda: len(probe.terminal()) >= k, 30, what)
    return probe.terminal()[-1]


def test_a_goal_past_the_wrench_limit_is_braked_softly_and_nothing_latches():
    cfg = load_device_config(DEVICE)
    home = np.asarray(cfg['mechanism']['home_pose'], float)
    limit = float(cfg['safety']['max_wrench'][0])
    below, beyond = home + (0.022, 0.0, 0.0), home + (0.045, 0.0, 0.0)
    assert _head_load(cfg, [below])[0, 0] < 0.9 * limit < 1.5 * limit < _head_load(cfg, [beyond])[0, 0]
    with enabled_bring_up(DEVICE, _extra_args()) as (b, probe):
        probe.send(below)
        end = _end_of(probe, 1, 'the goal below the limit to end')
        assert end['state'] == 'succeeded', end
        probe.send(beyond)
        end = _end_of(probe, 2, 'the goal beyond the limit to end')
        assert end['state'] == 'aborted' and 'soft wrench limit' in end['reason'], end
        assert 'Fx' in end['reason'] and 'max_wrench' in end['reason'], end
        probe.wait_fresh(probe.sim_poses, 20, 5, 'true poses at rest')
        probe.send(home)
        end = _end_of(probe, 3, 'the way back home to end')
        assert end['state'] == 'succeeded', end
        with probe.lock:
            true = np.array([_planar(m) for m in probe.sim_poses])
        peak = _head_load(cfg, true)[:, 0].max()
        assert 0.6 * limit < peak <= limit, f'TRUE load on the head peaked at {peak:.1f} N'
        assert probe.stops() == [], probe.stops()


def test_cables_slack_after_a_relief_are_taken_up_on_enable_and_goals_run_again():
    """The head's rest moves 22 mm while the brace holds (33 N): the cables pass a force
    limit of 15 N (this test's: ~13 mm of slack for the take-up's ~1 mm/s; 40 mm on 25 N
    left 27 mm, 33 s of test) and a protective stop latches; relieve pays them out (the
    head then rests near its new rest, cables hanging slack: longer than the TRUE head pose's
    lengths, written out in rpr_oracles); recover, enable: the slack taken up, every cable
    is taut at the TRUE head pose again, holding tension_min; and a goal 5 mm back towards
    home from where the head TRULY is succeeds, the TRUE head ending within pose_tolerance."""
    cfg = load_device_config(DEVICE)
    rest = np.asarray(cfg['sim']['rest_pose'], float)
    tol = np.asarray(cfg['safety']['pose_tolerance'], float)
    extra = _extra_args() + ['-p', 'safety.force_limit:=15.0', '-p', 'safety.soft_force_limit:=12.0',
                             '-p', 'safety.release_force:=5.0']
    with enabled_bring_up(DEVICE, extra) as (b, probe):
        node = b.helper
        pub = node.create_publisher(PoseStamped, topics.SIM_BODY_REST, topics.STATE_QOS)
        probe.wait(lambda: pub.get_subscription_count() > 0, 10, 'the simulator on body_rest')
        pub.publish(pose_msg(rest + (0.022, 0.0, 0.0), frame_id='brace_base', kind='planar',
                             stamp=node.get_clock().now().to_msg()))
        probe.wait(lambda: probe.stops() != [], 10, 'a protective stop')
        ok, msg = b.call('/can_driver_node/relieve', timeout=40)
        assert ok and 'relieved' in msg, (msg, probe.stops())
        ok, msg = b.call('/can_driver_node/recover', timeout=15)
        assert ok, msg
        with probe.lock:
            true = _planar(probe.sim_poses[-1])
            lengths = np.asarray(probe.joints[-1].position, float)
        slack = lengths - cable_lengths_4rpr(cfg, true)
        assert slack.max() > 0.005, f'premise: cables hang slack after the relief: {slack} m'
        ok, msg = b.call('/can_driver_node/enable', timeout=60)
        assert ok, msg
        since = len(probe.sim_poses)
        probe.wait(lambda: probe.driver and probe.driver[-1].message == 'enabled', 5, 'enabled state')
        probe.wait_fresh(probe.joints, 5, 5, 'joint states after the take-up')
        probe.wait_fresh(probe.sim_poses, 5, 5, 'true poses')
        probe.wait(lambda: _same_sync(probe, since) is not None, 5, 'a true pose and a joint state of one SYNC')
        pose, js = _same_sync(probe, since)
        here = _planar(pose)
        lengths = np.asarray(js.position, float)
        tension = -np.asarray(js.effort, float)
        # taut again: each cable's length is its length at the TRUE head pose, short by its
        # stretch under its tension (sim.leg_stiffness), within two encoder counts
        stretch = np.maximum(tension, 0.0) / float(cfg['sim']['leg_stiffness'])
        count = float(cfg['actuator']['screw_lead']) / float(cfg['actuator']['encoder_counts_per_rev'])
        np.testing.assert_allclose(lengths + stretch, cable_lengths_4rpr(cfg, here), atol=2 * count + 2e-5)
        assert np.all(tension >= float(cfg['mechanism']['tension_min']) - 0.3), tension
        goal = here - np.array([0.005, 0.0, 0.0])
        k = len(probe.terminal())
        probe.send(goal)
        end = _end_of(probe, k + 1, 'the goal to end')
        assert end['state'] == 'succeeded', end
        probe.wait_fresh(probe.sim_poses, 5, 5, 'true poses at rest')
        with probe.lock:
            true = _planar(probe.sim_poses[-1])
        assert np.all(np.abs(true - goal) <= tol), (true, goal)
