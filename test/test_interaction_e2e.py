"""Zero-torque mode and wrench goals on the simulated bus (lumbar brace), against the truth.

The whole stack in this process (:class:`~brace_control.bringup.BringUp`: trajectory, IK,
CAN driver with the simulated brace, kinetics, interaction), homed and enabled. The
patient is the simulator's (:mod:`brace_control.sim.brace`, "The patient"); every number is
measured on ``/brace/sim/*`` (the ring's true pose and wrench, the trunk's wanted pose),
never on the setpoints. Targets (issue 14) and what the design can promise are in
docs/interaction.md; the measured numbers are printed (``-s``) and asserted against the
bounds the loop model predicts.
"""
from __future__ import annotations

import itertools
import math
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import PoseStamped, WrenchStamped
from rclpy.context import Context

from brace_control.bringup import BringUp, call_trigger
from brace_control.demo import prepare_config
from brace_control.nodes import topics
from brace_control.nodes.msgs import pose_msg, status_values

ROOT = Path(__file__).resolve().parent.parent
LUMBAR = ROOT / 'config' / 'lumbar_brace.yaml'
_channels = itertools.count()
RELIABLE_10 = 10
#: the sway's centre: y 380 mm, theta 8 deg. In phase, +-10 mm and +-5 deg keep every leg
#: 5.3 mm inside the 340-440 mm stroke and the capacity above trajectory.min_wrench_capacity
#: (Mz >= 1.5 N·m at 3 deg); the paper's brace has no room for the sway at its 5 deg home
WORK = (0.0, 0.380, math.radians(8.0))


class Truth:
    """The simulator's truth and the interaction events, as (arrival time, value)."""

    def __init__(self, node) -> None:
        self.lock = threading.Lock()
        self.pose: list[tuple[float, np.ndarray]] = []
        self.body: list[tuple[float, np.ndarray]] = []
        self.wrench: list[tuple[float, np.ndarray]] = []
        self.status: list[DiagnosticStatus] = []
        node.create_subscription(PoseStamped, topics.SIM_POSE, self._pose(self.pose), RELIABLE_10)
        node.create_subscription(PoseStamped, topics.SIM_BODY_POSE, self._pose(self.body), RELIABLE_10)
        node.create_subscription(WrenchStamped, topics.SIM_WRENCH, self._on_wrench, RELIABLE_10)
        node.create_subscription(DiagnosticStatus, topics.GOAL_STATUS, self._on_status, topics.STATUS_QOS)

    def _pose(self, box):
        def cb(msg: PoseStamped) -> None:
            q = msg.pose.orientation
            th = 2.0 * math.atan2(q.z, q.w)
            with self.lock:
                box.append((time.monotonic(), np.array([msg.pose.position.x, msg.pose.position.y, th])))
        return cb

    def _on_wrench(self, msg: WrenchStamped) -> None:
        # platform frame -> base: R(theta) (the ring's true theta of the same sample)
        with self.lock:
            th = self.pose[-1][1][2] if self.pose else 0.0
            f, t = msg.wrench.force, msg.wrench.torque
            c, s = math.cos(th), math.sin(th)
            self.wrench.append((time.monotonic(), np.array([c * f.x - s * f.y, s * f.x + c * f.y, t.z])))

    def _on_status(self, msg: DiagnosticStatus) -> None:
        with self.lock:
            self.status.append(msg)

    def since(self, box, t0: float) -> tuple[np.ndarray, np.ndarray]:
        with self.lock:
            rows = [(t, v) for t, v in box if t >= t0]
        return np.array([t for t, _ in rows]), np.array([v for _, v in rows])

    def wait_status(self, pred, timeout: float, what: str) -> DiagnosticStatus:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with self.lock:
                for st in self.status:
                    if pred(st):
                        return st
            time.sleep(0.02)
        with self.lock:
            seen = [(s.name, s.message, status_values(s).get('reason', '')) for s in self.status]
        raise AssertionError(f'no {what} within {timeout} s; statuses: {seen}')


def wait(pred, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not pred():
        if time.monotonic() > deadline:
            raise AssertionError(f'timed out waiting for {what}')
        time.sleep(0.02)


@pytest.fixture(scope='module')
def stack(tmp_path_factory):
    out = tmp_path_factory.mktemp('device')
    path, _ = prepare_config(str(LUMBAR), out)
    ctx = Context()
    rclpy.init(context=ctx)
    extra = ['-p', f'can.channel:=inter{next(_channels)}', '-p', 'can.sync_spin_us:=0',
             '-p', 'sim.truth_rate_hz:=100.0']
    b = BringUp(path, context=ctx, extra_args=extra).start()
    try:
        truth = Truth(b.helper)
        for what in ('home', 'enable'):
            ok, msg = b.call(f'/can_driver_node/{what}', timeout=15)
            assert ok, f'{what}: {msg}'
        yield b, truth
    finally:
        b.shutdown()
        rclpy.shutdown(context=ctx)


def trigger(b: BringUp, name: str) -> tuple[bool, str]:
    return b.call(f'/interaction_node/{name}', timeout=5)


def move_body(b: BringUp, pub, start: np.ndarray, goal: np.ndarray, duration: float) -> None:
    """The patient moves their trunk's rest pose (``/brace/sim/body_rest``) smoothly."""
    n = int(duration * 50)
    for k in range(1, n + 1):
        u = k / n
        s = u * u * u * (10 - 15 * u + 6 * u * u)
        pub.publish(pose_msg(start + s * (goal - start), frame_id='brace_base', mechanism=None))
        time.sleep(0.02)


def test_zero_torque_mode_follows_a_swaying_patient_and_holds_wrench_goals(stack) -> None:
    b, truth = stack
    sim = b.node('can_driver_node').sim
    rest_pub = b.helper.create_publisher(PoseStamped, topics.SIM_BODY_REST, topics.STATE_QOS)
    goal_pub = b.helper.create_publisher(WrenchStamped, topics.WRENCH_GOAL, topics.GOAL_QOS)
    wait(lambda: len(truth.pose) > 5 and len(truth.wrench) > 5, 10, 'the truth topics')
    # the driver's command at every SYNC (the in-cycle admittance's output)
    executor = b.node('can_driver_node').master.executor
    commands: list[np.ndarray] = []
    step = executor.step

    def recording_step(t: float):
        q, v = step(t)
        if executor.source is not None:
            commands.append(q)
        return q, v
    executor.step = recording_step
    ok, msg = trigger(b, 'start')
    assert ok, msg
    truth.wait_status(lambda s: s.message == 'started', 2, 'started')
    report: dict[str, float] = {}

    # the patient settles lower and leans to 8 deg over 2 s; the brace follows (x is held:
    # no lateral capacity)
    rest0 = np.asarray(sim.rest_pose, dtype=float)
    work = np.array(WORK)
    t0 = time.monotonic()
    move_body(b, rest_pub, rest0, work, 2.0)
    time.sleep(1.5)
    tt, pose = truth.since(truth.pose, time.monotonic() - 0.3)
    assert abs(pose[-1][2] - work[2]) < math.radians(0.3), np.degrees(pose[-1])
    assert abs(pose[-1][1] - work[1]) < 0.002, pose[-1]
    _, w = truth.since(truth.wrench, t0)
    report['lean_max_moment'] = float(np.max(np.abs(w[:, 2])))

    # sway +-10 mm vertically and +-5 deg at 0.5 Hz, then 0.2 Hz. At 0.5 Hz one at a time: in
    # phase (or any phase) the two need 62-85 mm/s of leg speed, beyond the paper's actuators
    # (0.065 m/s, Table II; 0.052 m/s with trajectory.limit_margin); the rotation alone needs
    # 53 mm/s (a1, a3: the ring is speed limited for a moment at the sine's zero crossings)
    for f_hz, periods, amp, tag in ((0.5, 3, [0.0, 0.010, 0.0], '0.5 Hz y'),
                                    (0.5, 3, [0.0, 0.0, math.radians(5.0)], '0.5 Hz theta'),
                                    (0.2, 1.5, [0.0, 0.010, math.radians(5.0)], '0.2 Hz')):
        sim.set_sway(amp, f_hz)
        t_start = time.monotonic()
        time.sleep(periods / f_hz)
        sim.set_sway([0.0, 0.0, 0.0], 0.0)
        t_skip = t_start + 0.25 / f_hz                   # the start's transient
        _, w = truth.since(truth.wrench, t_skip)
        tp, pose = truth.since(truth.pose, t_skip)
        tb, body = truth.since(truth.body, t_skip)
        m = min(len(pose), len(body))
        err = np.abs(pose[:m] - body[:m])
        report[f'{tag} max |Fy| N'] = float(np.max(np.abs(w[:, 1])))
        report[f'{tag} max |Mz| N.m'] = float(np.max(np.abs(w[:, 2])))
        report[f'{tag} max |y_ring - y_body| mm'] = float(np.max(err[:, 1]) * 1e3)
        report[f'{tag} max |th_ring - th_body| deg'] = float(np.degrees(np.max(err[:, 2])))
        time.sleep(1.0)
    # the brace stayed in interaction mode throughout (no limit, no fault)
    assert not [s for s in truth.status if s.message in ('aborted', 'stopping')], \
        [(s.message, status_values(s).get('reason')) for s in truth.status]

    # wrench goals: 30 N vertical, then 2 N·m
    for axis, value, name in ((1, 30.0, 'Fy 30 N'), (2, 2.0, 'Mz 2 N.m')):
        msg = WrenchStamped()
        msg.header.frame_id = 'brace_base'
        if axis == 1:
            msg.wrench.force.y = value
        else:
            msg.wrench.torque.z = value
        t_goal = time.monotonic()
        goal_pub.publish(msg)
        truth.wait_status(lambda s: '/wrench_goal/' in s.name and s.message == 'accepted'
                          and float(status_values(s)['goal'].split(',')[axis]) == value,
                          2, f'{name} accepted')
        time.sleep(2.0)
        tw, w = truth.since(truth.wrench, t_goal)
        comp = w[:, axis]
        t_rel = tw - t_goal
        inside = np.abs(comp - value) <= 0.05 * abs(value)
        outside = np.flatnonzero(~inside)
        settle = float(t_rel[outside[-1] + 1]) if outside.size and outside[-1] + 1 < len(t_rel) else \
            (0.0 if not outside.size else float('inf'))
        report[f'{name} settling s (5 %)'] = settle
        report[f'{name} overshoot %'] = float(max(0.0, (np.max(comp * np.sign(value)) - abs(value))
                                                   / abs(value) * 100))
        # back to zero-torque
        zero = WrenchStamped()
        zero.header.frame_id = 'brace_base'
        goal_pub.publish(zero)
        time.sleep(1.5)

    print('\ninteraction e2e (truth), before the stop:', {k: round(v, 3) for k, v in report.items()})
    ok, msg = trigger(b, 'stop')
    assert ok, msg
    truth.wait_status(lambda s: s.message == 'stopped', 5, 'stopped')
    # continuity: the driver's command (the admittance in the SYNC cycle) never steps or
    # accelerates beyond the actuator limits (SAFETY 7: no jump at start, goal or stop)
    cmd = np.array(commands)
    period = 1.0 / float(b.config['can']['sync_rate_hz'])
    vel = np.diff(cmd, axis=0) / period
    report['max command speed mm/s'] = float(np.max(np.abs(vel)) * 1e3)
    acc = np.abs(np.diff(vel, axis=0)) / period
    report['max command acceleration m/s2'] = float(np.max(acc))
    k = int(np.argmax(np.max(acc, axis=1)))
    print('max acceleration at command', k, 'of', len(cmd), np.round(vel[max(0, k - 3):k + 4] * 1e3, 2))
    print('\ninteraction e2e (truth):')
    for k, v in report.items():
        print(f'  {k}: {v:.3f}')
    v_max = float(b.config['actuator']['max_velocity'])
    a_max = float(b.config['actuator']['max_acceleration'])
    assert report['max command speed mm/s'] <= v_max * 1e3, report
    assert report['max command acceleration m/s2'] <= a_max * 1.001, report
    # issue 14's targets (docs/interaction.md, "Measured")
    for tag in ('0.5 Hz y', '0.5 Hz theta', '0.2 Hz'):
        assert report[f'{tag} max |Fy| N'] < 5.0, report
        assert report[f'{tag} max |Mz| N.m'] < 0.5, report
        assert report[f'{tag} max |y_ring - y_body| mm'] < 2.0, report
        # target 0.3 deg, not reachable with 45 deg of phase margin at 4 x the body's
        # stiffness: following at w A costs D_theta w A = 1.43 x 0.274 = 0.39 N·m, which the
        # trunk's 40 N·m/rad turns into 0.56 deg (0.3 deg needs D_theta < 0.77, i.e. < 30 deg
        # at 4 x K even with no delay jitter; docs/interaction.md, "The trade-off")
        assert report[f'{tag} max |th_ring - th_body| deg'] < 0.8, report
    for name in ('Fy 30 N', 'Mz 2 N.m'):
        assert report[f'{name} settling s (5 %)'] <= 1.0, report
        assert report[f'{name} overshoot %'] <= 10.0, report
