"""End to end on the simulated bus: pose goals into the four nodes, judged against the truth.

Real rclpy, real DDS, the simulated CiA 402 drives on a python-can virtual bus. Run with
every node in this process (:class:`BringUp`) and with each node as its own process
(:class:`ProcessBringUp`, the executables the way ``ros2 run`` starts them).

The oracle is the simulator's ground truth (``/brace/sim/*``), never the encoders or the
setpoints, and independent computations from the paper and the YAML (:class:`Device`):

* a goal reported ``succeeded`` has the TRUE ring within ``safety.pose_tolerance`` of it; a
  goal the ring cannot follow (a lateral shift against the body: the legs are nearly
  parallel) is ``aborted`` saying so, never ``succeeded``;
* while moving, the true leg forces stay within 10 N of the static forces of the planned
  path (the equilibrium of legs and body for the IK lengths of the plan): the legs stay on
  the IK manifold (issue "motion that keeps the legs consistent");
* no protective stop for goals that are statically feasible under the YAML's body;
* the estimated pose (``/brace/pose``) is within 2 mm and 0.2 deg of the true one, and
  the truth lies within 3 sigma of ``/brace/pose_with_covariance``;
* rejected goals move nothing (the true actuator lengths).

Deliberate settings, all as ROS parameters on the command line:

* ``can.channel``: a channel of its own per test (virtual buses are per process);
* every safety limit as the device file sets it (docs/safety.md §13);
* ``trajectory.fitts_a`` 1 s (Fitts' law intercept; 0.2 s in the YAML): motions of
  1.2-1.5 s instead of 0.5 s. Near the lumbar brace's theta = 0 singularity microns of
  actuator lag are millimetres of pose (at theta = 5 deg, 10 um on a2 = 3.4 mm in x);
* ``ros_helpers.BUSY_HOST_ARGS``: the trajectory node's planning budget, plan lookahead and
  driver report time-out, wall-clock settings no test here checks, widened for a busy host.
"""
from __future__ import annotations

import contextlib
import itertools
import math
import os
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseStamped, WrenchStamped
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from sensor_msgs.msg import JointState

from geometry_msgs.msg import PoseWithCovarianceStamped
from trajectory_msgs.msg import JointTrajectory

from brace_control.bag import replay
from brace_control.bringup import (BringUp, ProcessBringUp, call_trigger, wait_for_links,
                                   wait_until_ready)
from brace_control.config import load_device_config
from brace_control.nodes.spin import BackgroundSpinner
from brace_control.demo import prepare_config
from brace_control.exercise import Goal, write_goal_bag
from brace_control.nodes import topics
from brace_control.nodes.msgs import joint_knots_from_msg, pose_msg, stamp_to_ns, status_values
from ros_helpers import BUSY_HOST_ARGS, LUMBAR_YAML, RELIABLE_10, unclean_exits

pytestmark = [pytest.mark.ros, pytest.mark.e2e, pytest.mark.slow]

DEG = math.pi / 180
_channels = itertools.count()


# ----------------------------------------------------------------------------- oracles

class Device:
    """The numbers of the device file, read with yaml, not with the code under test."""

    def __init__(self, path: Path) -> None:
        cfg = load_device_config(path)
        m = cfg['mechanism']
        self.A = np.asarray(m['base_anchors'], float).reshape(3, 2)
        self.B = np.asarray(m['platform_anchors'], float).reshape(3, 2)
        self.names = list(m['actuator_names'])
        self.stroke = (float(m['stroke_min']), float(m['stroke_max']))
        a = cfg['actuator']
        self.v_max = float(a['max_velocity'])
        self.resolution = float(a['screw_lead']) / float(a['encoder_counts_per_rev'])
        self.step_margin = float(cfg['safety']['step_margin'])
        self.K = np.asarray(cfg['sim']['stiffness'], float).reshape(3, 3)
        self.rest = np.asarray(cfg['sim']['rest_pose'], float)
        self.home = np.asarray(m['home_pose'], float)
        self.k_leg = float(cfg['sim'].get('leg_stiffness', cfg['actuator']['stiffness']))
        self.tolerance = np.asarray(cfg['safety']['pose_tolerance'], float)
        self.soft_limit = 0.8 * float(cfg['safety']['force_limit'])

    def lengths(self, pose) -> np.ndarray:
        """Seed 001 inverse kinematics: l_i = |p + R(theta) b_i - a_i|."""
        x, y, th = pose
        R = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
        return np.linalg.norm(np.array([x, y]) + self.B @ R.T - self.A, axis=1)

    def ring_pose(self, q, guess) -> np.ndarray:
        """Where the ring rests for drive lengths ``q``: each leg is the drive in series with
        ``sim.leg_stiffness`` k, f = k (q - l(p)), and the legs hold the torso,
        sum f_i u_i = K (p - rest) (force and moment about P). Newton on p with a
        finite-difference Jacobian of this residual, each step halved until the residual
        shrinks; from ``guess``, else from the home and the rest pose. An equilibrium not
        found (the residual above 1e-6 N) is the oracle's failure, said as such: a burner
        run once took 50 undamped steps to a pose 49 kN from equilibrium and blamed the brace."""
        q = np.asarray(q, float)

        def residual(p):
            x, y, th = p
            R = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
            rb = self.B @ R.T
            d = np.array([x, y]) + rb - self.A
            ln = np.linalg.norm(d, axis=1)
            u = d / ln[:, None]
            f = self.k_leg * (q - ln)
            F = (f[:, None] * u).sum(axis=0)
            M = float(np.sum(f * (rb[:, 0] * u[:, 1] - rb[:, 1] * u[:, 0])))
            return np.array([F[0], F[1], M]) - self.K @ (p - self.rest)

        def newton(p):
            r = residual(p)
            for _ in range(60):
                if np.max(np.abs(r)) < 1e-9:
                    break
                h = 1e-9
                Jr = np.column_stack([(residual(p + h * e) - r) / h for e in np.eye(3)])
                step = np.linalg.solve(Jr, -r)
                for _halving in range(30):
                    trial = p + step
                    r_trial = residual(trial)
                    if np.linalg.norm(r_trial) < np.linalg.norm(r):
                        break
                    step = 0.5 * step
                else:
                    break
                p, r = trial, r_trial
            return p, float(np.max(np.abs(r)))

        tried = []
        for start in (guess, self.home, self.rest):
            p, err = newton(np.asarray(start, float).copy())
            if err < 1e-6:
                return p
            tried.append((np.round(np.asarray(start, float), 6).tolist(), err))
        raise AssertionError(f'oracle: no equilibrium of the ring found for drive lengths '
                             f'{q.tolist()} (start, residual N): {tried}')

    def static_forces(self, q, guess) -> tuple[np.ndarray, np.ndarray]:
        """The ring's rest pose for drive lengths ``q`` and the leg forces there."""
        ring = self.ring_pose(q, guess)
        return ring, self.k_leg * (np.asarray(q) - self.lengths(ring))

    def feasible(self, goal) -> bool:
        """Statically feasible: the goal's IK lengths within the stroke (5 mm margin) and
        the legs' forces holding the body there below the soft force limit."""
        q = self.lengths(goal)
        lo, hi = self.stroke
        if np.any(q < lo + 0.005) or np.any(q > hi - 0.005):
            return False
        _, f = self.static_forces(q, goal)
        return bool(np.all(np.abs(f) < self.soft_limit))

    def brace_wrench_platform(self, pose) -> np.ndarray:
        """At rest the brace holds the body: W_brace = -W_body = K (pose - rest); force in
        the platform frame (rotated by -theta), moment about the platform origin."""
        w = self.K @ (np.asarray(pose) - self.rest)
        th = pose[2]
        fx = math.cos(th) * w[0] + math.sin(th) * w[1]
        fy = -math.sin(th) * w[0] + math.cos(th) * w[1]
        return np.array([fx, fy, w[2]])


@pytest.fixture(scope='module')
def device_file(tmp_path_factory) -> Path:
    """The lumbar brace file, parked clear of the theta = 0 singularity (as the demo runs it)."""
    out = tmp_path_factory.mktemp('device')
    path, _ = prepare_config(str(LUMBAR_YAML), out)
    return path


def _extra_args() -> list[str]:
    # the truth at 100 Hz so that a short force spike cannot fall between two samples
    return ['-p', f'can.channel:=e2e{next(_channels)}', '-p', 'trajectory.fitts_a:=1.0',
            '-p', 'sim.truth_rate_hz:=100.0', *BUSY_HOST_ARGS]


# ----------------------------------------------------------------------------- probe

class Probe:
    """What the test watches, on a node of its own (spun by whoever owns the node)."""

    def __init__(self, node) -> None:
        self.node = node
        self.lock = threading.Lock()
        #: topic -> (messages received, monotonic time of the last): a failure tells a probe
        #: that heard nothing more from one that missed one sample
        self.heard: dict[str, tuple[int, float]] = {}
        self.statuses: list[tuple[float, DiagnosticStatus]] = []    # (arrival, message)
        self.driver: list[DiagnosticStatus] = []
        self.trajectories: list[JointTrajectory] = []
        self.wrenches: list[WrenchStamped] = []
        self.poses: list[PoseStamped] = []
        self.covariances: list[PoseWithCovarianceStamped] = []
        self.joints: list[JointState] = []
        self.sim_poses: list[PoseStamped] = []          # the simulator's ground truth
        self.sim_joints: list[JointState] = []
        self.faults: list[str] = []
        self.cycle = ''                                # the driver's last SYNC cycle status
        node.create_subscription(DiagnosticArray, topics.DIAGNOSTICS,
                                 self._heard(topics.DIAGNOSTICS, self._on_diagnostics), 50)
        node.create_subscription(DiagnosticStatus, topics.GOAL_STATUS,
                                 self._heard(topics.GOAL_STATUS, self._on_status), topics.STATUS_QOS)
        for typ, topic, box, qos in (
                (DiagnosticStatus, topics.DRIVER_STATE, self.driver, topics.LATCHED_QOS),
                (JointTrajectory, topics.ACTUATOR_TRAJECTORY, self.trajectories, topics.TRAJECTORY_QOS),
                (WrenchStamped, topics.WRENCH, self.wrenches, RELIABLE_10),
                (PoseStamped, topics.POSE, self.poses, RELIABLE_10),
                (PoseWithCovarianceStamped, topics.POSE_WITH_COVARIANCE, self.covariances, RELIABLE_10),
                (JointState, topics.JOINT_STATES, self.joints, RELIABLE_10),
                (PoseStamped, topics.SIM_POSE, self.sim_poses, RELIABLE_10),
                (JointState, topics.SIM_JOINT_STATES, self.sim_joints, RELIABLE_10)):
            node.create_subscription(typ, topic, self._heard(topic, self._keep(box)), qos)
        self.goal_pub = node.create_publisher(PoseStamped, topics.POSE_GOAL, topics.GOAL_QOS)

    def _heard(self, topic: str, cb):
        def counted(msg) -> None:
            n, _ = self.heard.get(topic, (0, 0.0))
            self.heard[topic] = (n + 1, time.monotonic())
            cb(msg)
        return counted

    def hearing(self) -> str:
        now = time.monotonic()
        return ', '.join(f'{topic} {n} ({now - t:.1f} s ago)' for topic, (n, t) in sorted(self.heard.items()))

    def _on_diagnostics(self, msg) -> None:
        for st in msg.status:
            if st.name.endswith('/cycle'):         # the SYNC cycle: told on a failure
                self.cycle = f'{st.message} ({", ".join(f"{kv.key} {kv.value}" for kv in st.values)})'
            if st.name.endswith('/safety') and st.level >= DiagnosticStatus.ERROR \
                    and st.message not in self.faults:
                self.faults.append(st.message)

    def _on_status(self, msg) -> None:
        with self.lock:
            self.statuses.append((time.monotonic(), msg))

    def _keep(self, box):
        def cb(msg):
            with self.lock:
                box.append(msg)
        return cb

    def forget(self) -> None:
        """Empty every record (a stack shared between tests), except the driver's current
        state: its topic is latched, a new sample comes only when it changes."""
        with self.lock:
            for box in (self.statuses, self.trajectories, self.wrenches, self.poses,
                        self.covariances, self.joints, self.sim_poses, self.sim_joints):
                box.clear()
            del self.driver[:-1]
            self.faults.clear()

    def events(self) -> list[dict]:
        with self.lock:
            return [dict(status_values(s), arrival=t) for t, s in self.statuses]

    def terminal(self) -> list[dict]:
        """The goal statuses that end a goal (not a position goal's or a wrench goal's
        ``accepted``, nor a wrench goal's ``applied``)."""
        return [e for e in self.events() if e['state'] not in ('accepted', 'applied')]

    def stops(self) -> list[str]:
        """Driver states that were a protective stop."""
        with self.lock:
            return [s.message for s in self.driver if s.message.startswith('protective stop')]

    def wait_fresh(self, box: list, count: int, timeout: float, what: str) -> None:
        """Wait until ``count`` more messages arrived in ``box`` (one of the lists above)."""
        with self.lock:
            start = len(box)
        self.wait(lambda: len(box) >= start + count, timeout, f'{count} new {what}')

    def wait(self, predicate, timeout: float, what: str) -> None:
        deadline = time.monotonic() + timeout
        while not predicate():
            if time.monotonic() > deadline:
                last = list(self.joints[-1].position) if self.joints else None
                pytest.fail(f'timed out after {timeout} s waiting for {what}; goal events: '
                            f'{[(e["goal_id"], e["state"], e["reason"]) for e in self.events()]}; '
                            f'last joint positions {last}; driver faults {self.faults}; '
                            f'driver states {[s.message for s in self.driver][-3:]}; '
                            f'SYNC cycle: {self.cycle}; heard: {self.hearing()}')
            time.sleep(0.02)

    def send(self, pose, frame='brace_base') -> None:
        self.goal_pub.publish(pose_msg(pose, frame_id=frame, kind='planar',
                                       stamp=self.node.get_clock().now().to_msg()))


def _replay_goals(node, tmp: Path, goals: list[Goal], frame: str) -> None:
    bag = write_goal_bag(tmp / f'goals{next(_channels)}', goals, frame_id=frame, storage='sqlite3')
    stats = replay(node, bag, wait_subscribers=1)
    assert stats.ok, stats.problems


def _planar(msg) -> np.ndarray:
    p = msg.pose.pose if hasattr(msg.pose, 'pose') else msg.pose
    return np.array([p.position.x, p.position.y, 2 * math.atan2(p.orientation.z, p.orientation.w)])


# ----------------------------------------------------------------------------- checks

#: ns: a truth sample older than this before a success's decision is a hole in the truth
#: stream (samples come at sim.truth_rate_hz, 20-100 Hz)
TRUTH_HOLE_NS = 100_000_000


def check_succeeded_goals_are_true(dev: Device, probe: Probe) -> int:
    """Every succeeded goal has the TRUE ring within the pose tolerance of its target, at
    the instant the node decided the success (the truth sample just before it).

    First the truth must have caught up with the last success: a driver starved for a while
    publishes the truths it missed afterwards, stamped as they were (README, "ground
    truth"), and a success can arrive before them (run 1305: the newest truth before a success
    was 0.71 s old, the rest of that time still to come)."""
    ends = [int(e['time']) for e in probe.terminal() if e['state'] == 'succeeded']

    def caught_up() -> bool:
        with probe.lock:
            return bool(probe.sim_poses) and stamp_to_ns(probe.sim_poses[-1].header.stamp) >= max(ends)
    if ends:
        probe.wait(caught_up, 10.0, 'the ground truth to reach the last success')
    with probe.lock:
        truth = [(stamp_to_ns(m.header.stamp), _planar(m)) for m in probe.sim_poses]
    stamps = np.array([t for t, _ in truth])
    n = 0
    for e in probe.terminal():
        if e['state'] != 'succeeded':
            continue
        target = np.array([float(x) for x in e['target'].split()])
        # the success was decided on an estimate at most settle_time after the end: the
        # truth at the latest sample before the node decided it (the event's ``time``; truth
        # runs on ROS time). Not before the report's arrival here: on a loaded host it came
        # a second late, after the next goal had moved the ring 10 mm on (run 711, goal 54)
        when = int(e['time'])
        i = int(np.searchsorted(stamps, when)) - 1
        assert i >= 0, 'no truth sample before the success'
        err = np.abs(truth[i][1] - target)
        if when - stamps[i] > TRUTH_HOLE_NS and i + 1 < len(truth):
            # a hole in the truth stream there (a loaded host, run 716: the last sample before
            # was from before the ring arrived): the first sample after the decision instead
            after = np.abs(truth[i + 1][1] - target)
            if np.max(after / dev.tolerance) < np.max(err / dev.tolerance):
                err = after
        assert np.all(err <= dev.tolerance), (e['goal_id'], err, dev.tolerance, (when - stamps[i]) * 1e-9)
        n += 1
    return n


def _planned(probe: Probe, names) -> list[tuple[int, np.ndarray]]:
    """Every planned actuator motion as ``(start stamp ns, dense samples)``, in start order:
    a quintic Hermite of its knots (scipy's BPoly, independent of the driver's
    interpolation) every 2 ms."""
    from scipy.interpolate import BPoly
    with probe.lock:
        trajs = [t for t in probe.trajectories if len(t.points) > 1]
    out = []
    for t in trajs:
        stamp, tk, q, qd, qdd = joint_knots_from_msg(t, names)
        spline = BPoly.from_derivatives(tk, np.stack([q, qd, qdd], axis=1))
        out.append((stamp, spline(np.linspace(tk[0], tk[-1], max(200, int((tk[-1] - tk[0]) / 0.002))))))
    return sorted(out, key=lambda p: p[0])


def _nearest_on_path(points: np.ndarray, q: np.ndarray) -> np.ndarray:
    """The point of the polyline through ``points`` nearest ``q`` (Euclidean)."""
    a, d = points[:-1], np.diff(points, axis=0)
    dd = np.maximum(np.einsum('ij,ij->i', d, d), 1e-30)
    s = np.clip(np.einsum('ij,ij->i', q - a, d) / dd, 0.0, 1.0)
    c = a + s[:, None] * d
    return c[int(np.argmin(np.einsum('ij,ij->i', c - q, c - q)))]


def check_self_stress(dev: Device, probe: Probe, bound: float = 10.0) -> float:
    """The true leg forces stay within ``bound`` N of the static forces of the planned path:
    for each true sample, the configuration nearest its lengths on the plan running then
    (the last one stamped to start at or before it; until it starts the drives stand at its
    first point), its equilibrium with the body (the legs on the IK manifold carry only the
    static load). Near the lumbar brace's parallel legs two plans may pass within microns
    of each other in actuator space at poses millimetres apart: a sample is matched to its
    own motion, never to whichever plan passes closest."""
    plans = _planned(probe, dev.names)
    assert plans, 'no planned motion seen'
    starts = np.array([s for s, _ in plans])
    with probe.lock:
        samples = [(stamp_to_ns(m.header.stamp), np.asarray(m.position), np.asarray(m.effort))
                   for m in probe.sim_joints]
    worst, checked = 0.0, 0
    guess = dev.home.copy()
    for stamp, q, f in samples[::2]:
        i = int(np.searchsorted(starts, stamp, side='right')) - 1
        if i < 0:
            continue            # before the first motion
        q_plan = _nearest_on_path(plans[i][1], q)
        if np.max(np.abs(q_plan - q)) > 2e-4:
            continue            # not on a planned motion (lagging behind a start, a stop)
        guess, static = dev.static_forces(q_plan, guess)
        worst = max(worst, float(np.max(np.abs(f - static))))
        checked += 1
    assert checked, 'no true sample on a planned motion'
    assert worst <= bound, f'leg forces {worst:.1f} N away from the static load of the planned path'
    return worst


def _estimate_excursion(err, t: int, est: dict, keys: np.ndarray, truth: list,
                        joints: list = (), sim_joints: list = ()) -> str:
    """What a failed :func:`check_estimate` saw around the truth sample ``t`` (ns): the
    estimates and truths of the 150 ms before and after, each as (ms from t, x, y in mm,
    theta in deg), and the measured and true joint states (lengths in mm, forces in N), so
    that an estimate's jump tells itself from a truth paired with the wrong SYNC or a
    reading gone wrong (a fresh-clone run saw the estimate 40 mm off in x once)."""
    def row(stamp: int, msg) -> str:
        x, y, th = _planar(msg)
        return f'{(stamp - t) / 1e6:+7.1f} ms  x {x * 1e3:8.3f}  y {y * 1e3:8.3f}  th {math.degrees(th):7.3f}'

    def joint_row(msg) -> str:
        q = ' '.join(f'{v * 1e3:8.3f}' for v in msg.position)
        f = ' '.join(f'{v:7.2f}' for v in msg.effort)
        return f'{(stamp_to_ns(msg.header.stamp) - t) / 1e6:+7.1f} ms  q {q}  f {f}'
    near = 150_000_000
    lines = [f'estimate - truth = {np.round(err, 6).tolist()} at the truth stamp {t} ns '
             f'({len(keys)} estimates, {len(truth)} truths in all)', 'estimates:']
    lines += [row(int(k), est[k]) for k in keys if abs(int(k) - t) <= near]
    lines.append('truths:')
    lines += [row(stamp_to_ns(m.header.stamp), m) for m in truth
              if abs(stamp_to_ns(m.header.stamp) - t) <= near]
    for name, box in (('joint states', joints), ('true joint states', sim_joints)):
        lines.append(f'{name}:')
        lines += [joint_row(m) for m in box if abs(stamp_to_ns(m.header.stamp) - t) <= near]
    return '\n'.join(lines)


def check_estimate(probe: Probe, *, position=0.002, angle=0.2 * DEG, share=0.99) -> None:
    """/brace/pose within ``position`` / ``angle`` of /brace/sim/pose at every truth sample
    (same SYNC stamp), the truth within 3 sigma of the covariance in ``share`` of them."""
    with probe.lock:
        est = {stamp_to_ns(m.header.stamp): m for m in probe.covariances}
        truth = list(probe.sim_poses)
        joints, sim_joints = list(probe.joints), list(probe.sim_joints)
    keys = np.array(sorted(est))
    assert len(keys) and truth
    inside, n = 0, 0
    for m in truth:
        t = stamp_to_ns(m.header.stamp)
        i = int(np.argmin(np.abs(keys - t)))
        if abs(keys[i] - t) > 2_000_000:              # no estimate of that SYNC (rates differ)
            continue
        e = est[keys[i]]
        err = _planar(e) - _planar(m)
        assert abs(err[0]) <= position and abs(err[1]) <= position and abs(err[2]) <= angle, \
            _estimate_excursion(err, t, est, keys, truth, joints, sim_joints)
        cov = np.asarray(e.pose.covariance).reshape(6, 6)
        sigma = np.sqrt(np.array([cov[0, 0], cov[1, 1], cov[5, 5]]))
        inside += bool(np.all(np.abs(err) <= 3 * sigma))
        n += 1
    assert n > 20, f'only {n} estimate/truth pairs'
    assert inside >= share * n, f'truth within 3 sigma in {inside} of {n}'


def check_no_stop(probe: Probe) -> None:
    assert probe.stops() == [], probe.stops()
    assert probe.faults == [], probe.faults


def check_still(probe: Probe, since: float, until: float) -> None:
    """The true actuator lengths did not move between two ROS times (ns)."""
    with probe.lock:
        qs = [np.asarray(m.position) for m in probe.sim_joints
              if since <= stamp_to_ns(m.header.stamp) <= until]
    assert len(qs) > 5
    assert np.ptp(np.asarray(qs), axis=0).max() < 2e-6, 'the brace moved'


# lift and turn (Fitts' law gives ~1.5 s with fitts_a = 1), a lateral shift the ring cannot
# follow (the legs are nearly parallel: 0.7 N of lateral capacity), and back. The shift is
# judged by the trajectory node at the latest settle_time + report_timeout (1.5 s) after the
# driver reports its motion (1.5 s) finished: 'back' comes 6 s after it, not 4 (CI of
# 7300779: on a loaded host the shift was accepted 0.85 s late and its end reported late;
# 'back' preempted it, cancelled, before its judgement)
GOALS = [Goal(0.2, (0.0, 0.400, 8.0 * DEG), 'lift + tilt'),
         Goal(4.0, (0.015, 0.400, 8.0 * DEG), 'lateral shift'),
         Goal(10.0, (0.0, 0.392, 6.0 * DEG), 'back')]


def check_honest_outcomes(dev: Device, probe: Probe) -> None:
    probe.wait(lambda: len(probe.terminal()) >= 3, 30, 'three goals to end')
    ends = sorted(probe.terminal(), key=lambda e: int(e['goal_id']))
    assert [e['state'] for e in ends] == ['succeeded', 'aborted', 'succeeded'], ends
    assert 'did not follow' in ends[1]['reason'] and 'x off by' in ends[1]['reason'], ends[1]
    assert check_succeeded_goals_are_true(dev, probe) == 2
    check_no_stop(probe)
    check_self_stress(dev, probe)
    check_estimate(probe)


def rejection_goals() -> list[Goal]:
    return [Goal(0.2, (0.0, 0.396, 5.5 * DEG), 'valid'),
            Goal(3.2, (0.0, 0.50, 5.5 * DEG), 'unreachable'),          # legs beyond the stroke
            Goal(3.6, (math.nan, 0.39, 5.5 * DEG), 'nan'),
            Goal(4.6, (0.0, 0.386, 6.0 * DEG), 'valid after')]


def check_rejections(dev: Device, probe: Probe) -> None:
    probe.wait(lambda: len(probe.terminal()) >= 4, 25, 'four goals to end')
    ends = sorted(probe.terminal(), key=lambda e: int(e['goal_id']))
    states = [e['state'] for e in ends]
    assert states == ['succeeded', 'rejected', 'rejected', 'succeeded'], ends
    assert 'stroke' in ends[1]['reason'] or 'unreachable' in ends[1]['reason'], ends[1]
    assert 'finite' in ends[2]['reason'] or 'nan' in ends[2]['reason'].lower(), ends[2]
    # no motion while the bad goals came and went: the true lengths stood still from the
    # first goal's end to the last goal's start
    events = probe.events()
    now_ns = probe.node.get_clock().now().nanoseconds

    def ros_time(e):
        return now_ns - round((time.monotonic() - e['arrival']) * 1e9)
    first_end = ros_time(ends[0])
    last_start = ros_time([e for e in events if e['goal_id'] == ends[3]['goal_id']][0])
    check_still(probe, first_end + 100_000_000, last_start - 50_000_000)
    check_no_stop(probe)
    assert check_succeeded_goals_are_true(dev, probe) == 2


def random_goals(dev: Device, n: int, seed: int) -> list[np.ndarray]:
    """Seeded goals from the paper's workspace (theta 3-25 deg, |x| <= 20 mm, y 365-425 mm,
    5 mm stroke margin), statically feasible under the YAML's body, each reachable from the
    one before along the straight pose path (feasible all along it)."""
    rng = np.random.default_rng(seed)
    goals, prev = [], dev.home
    while len(goals) < n:
        g = np.array([rng.uniform(-0.02, 0.02), rng.uniform(0.365, 0.425),
                      rng.uniform(3.0, 25.0) * DEG])
        if all(dev.feasible(prev + s * (g - prev)) for s in np.linspace(0.0, 1.0, 9)):
            goals.append(g)
            prev = g
    return goals


#: goals of each seeded random-goal soak: the suite runs the first ``SOAK_GOALS`` of the
#: seeded sequence (the same goals, in the same order, as the full soak's first ones);
#: ``bench/stability.sh`` runs the full 20 (``BRACE_SOAK_GOALS=20``), recorded in
#: bench/RESULTS.md. The checks and tolerances are the same for any count.
SOAK_GOALS = int(os.environ.get('BRACE_SOAK_GOALS', '6'))


def run_random_goals(dev: Device, probe: Probe, n: int = SOAK_GOALS, seed: int = 11) -> None:
    """One goal after the other (each sent once the previous ended): no protective stop, the
    legs carry only the static load, every goal exactly one end, success only where the
    truth is, the estimate within 2 mm / 0.2 deg of the truth."""
    for i, goal in enumerate(random_goals(dev, n, seed), start=1):
        probe.send(goal)
        probe.wait(lambda: any(e['goal_id'] == str(i) for e in probe.terminal()), 20,
                   f'random goal {i} to end')
    ends = probe.terminal()
    assert sorted(int(e['goal_id']) for e in ends) == list(range(1, n + 1))
    bad = [(e['goal_id'], e['state'], e['reason'][:120]) for e in ends
           if not (e['state'] == 'succeeded' or 'did not follow' in e['reason'])]
    assert not bad, bad
    check_no_stop(probe)
    check_succeeded_goals_are_true(dev, probe)
    check_self_stress(dev, probe)
    check_estimate(probe)


# ----------------------------------------------------------------------------- one process

@contextlib.contextmanager
def enabled_bring_up(device_file, extra_args):
    """All nodes in this process on a private context, homed and enabled: (bring-up, probe)."""
    ctx = Context()
    rclpy.init(context=ctx)
    b = BringUp(device_file, context=ctx, extra_args=extra_args).start()
    probe = Probe(b.helper)
    try:
        for what in ('home', 'enable'):
            ok, msg = b.call(f'/can_driver_node/{what}', timeout=15)
            assert ok, f'{what}: {msg}'
        probe.wait(lambda: probe.driver and 'enabled' in probe.driver[-1].message, 5, 'enabled state')
        yield b, probe
    finally:
        b.shutdown()
        rclpy.shutdown(context=ctx)


@pytest.fixture
def in_process(device_file):
    with enabled_bring_up(device_file, _extra_args()) as running:
        yield running


# docs/safety.md §12, §16
def test_in_process_goals_end_honestly_against_the_truth(device_file, in_process, tmp_path):
    b, probe = in_process
    _replay_goals(b.helper, tmp_path, GOALS, 'brace_base')
    check_honest_outcomes(Device(device_file), probe)


# docs/safety.md §6, §10
def test_in_process_unreachable_and_nan_goals_are_rejected_without_motion(device_file, in_process, tmp_path):
    b, probe = in_process
    _replay_goals(b.helper, tmp_path, rejection_goals(), 'brace_base')
    check_rejections(Device(device_file), probe)


def test_in_process_random_goals_keep_the_legs_consistent(device_file, in_process):
    b, probe = in_process
    run_random_goals(Device(device_file), probe, seed=11)


# ----------------------------------------------------------------------------- processes

@contextlib.contextmanager
def process_bring_up(device_file, extra_args):
    """Each node its own process (``ProcessBringUp``), homed and enabled, watched by a
    probe node in this process: (process group, probe node, probe). Checks on exit that
    no node process died and that each exited 0."""
    group = ProcessBringUp(device_file, extra_args=extra_args).start()
    ctx = Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node('e2e_probe', context=ctx)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    spinner = BackgroundSpinner(executor, 'probe-executor').start()
    probe = Probe(node)
    try:
        for what in ('home', 'enable'):
            deadline = time.monotonic() + 30
            while True:
                ok, msg = call_trigger(node, f'/can_driver_node/{what}', timeout=15, executor=executor)
                if ok or time.monotonic() > deadline or group.failed():
                    break
                time.sleep(0.2)
            assert ok, f'{what}: {msg}; ended: {group.failed()}'
        wait_for_links(node, timeout=30)      # DDS discovery between the node processes
        wait_until_ready(node, timeout=30)    # ... as each node process sees it
        probe.wait(lambda: probe.driver and 'enabled' in probe.driver[-1].message, 5, 'enabled state')
        yield group, node, probe
        assert not group.failed(), f'a node process died: {group.failed()}'
    finally:
        # this process's participant goes first: it then never delivers the node processes'
        # removal (a Fast DDS deadlock window, watchdog_plugin.TEST_LIMIT_S)
        spinner.stop()                        # no spin on a context being shut down
        executor.shutdown()
        node.destroy_node()
        rclpy.shutdown(context=ctx)
        codes = group.stop()
    assert not unclean_exits(codes), unclean_exits(codes)


@pytest.fixture
def as_processes(device_file):
    with process_bring_up(device_file, _extra_args()) as running:
        yield running


# docs/safety.md §12, §16
def test_processes_goals_end_honestly_against_the_truth(device_file, as_processes, tmp_path):
    group, node, probe = as_processes
    _replay_goals(node, tmp_path, GOALS, 'brace_base')
    check_honest_outcomes(Device(device_file), probe)
    check_late_subscriber_gets_every_outcome(node, probe)


def check_late_subscriber_gets_every_outcome(node, probe) -> None:
    """A client that subscribes after the goals ended (transient local, topics.GOAL_STATUS_QOS)
    still receives every goal's terminal status (issue 26): the same states the probe saw live."""
    ended = {e['goal_id']: e['state'] for e in probe.terminal()}
    assert ended
    late: list = []
    sub = node.create_subscription(DiagnosticStatus, topics.GOAL_STATUS, late.append, topics.GOAL_STATUS_QOS)
    try:
        def got() -> dict:
            vals = [dict(status_values(m), state=m.message) for m in list(late)]
            return {v['goal_id']: v['state'] for v in vals if v['state'] != 'accepted'}
        probe.wait(lambda: got() == ended, 10, f'the late subscriber to receive {ended}')
    finally:
        node.destroy_subscription(sub)


# docs/safety.md §6, §10
def test_processes_unreachable_and_nan_goals_are_rejected_without_motion(device_file, as_processes, tmp_path):
    group, node, probe = as_processes
    _replay_goals(node, tmp_path, rejection_goals(), 'brace_base')
    check_rejections(Device(device_file), probe)


def test_processes_random_goals_keep_the_legs_consistent(device_file, as_processes):
    group, node, probe = as_processes
    run_random_goals(Device(device_file), probe, seed=23)
