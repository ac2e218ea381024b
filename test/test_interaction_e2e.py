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
import yaml
from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import PoseStamped, WrenchStamped

from brace_control import bag
from brace_control.bringup import BringUp
from brace_control.nodes import topics
from brace_control.nodes.msgs import pose_msg, status_values
from ros_helpers import BUSY_HOST_ARGS, cycle_evidence, home_and_enable, stack_in_process, wait_until as wait
from seed001 import leg_lengths as legs, leg_matrix

ROOT = Path(__file__).resolve().parent.parent
LUMBAR = ROOT / 'config' / 'lumbar_brace.yaml'
PARAMS = yaml.safe_load(LUMBAR.read_text())['/**']['ros__parameters']
_channels = itertools.count()
#: the truth readers' depth: a reader the host starved for seconds still takes every sample
#: the simulator kept for it (``topics.truth_qos``: 20 s), not the newest 10
TRUTH_DEPTH = bag.RECORD_DEPTH
#: Hz of the simulator's truth in this file's stack (the stack fixture says why not 100)
TRUTH_HZ = 50.0
#: m/s: the speed the admittance may command (trajectory.limit_margin x actuator.max_velocity)
V_ALLOWED = PARAMS['trajectory']['limit_margin'] * PARAMS['actuator']['max_velocity']
#: share of V_ALLOWED a sway may need: the ring lags the trunk and catches up a little faster
SPEED_HEADROOM = 0.9
STROKE = (PARAMS['mechanism']['stroke_min'], PARAMS['mechanism']['stroke_max'])
#: the admittance keeps 2 % of the stroke clear (brace_control.interaction.admittance.STROKE_MARGIN)
STROKE_CLEAR = 0.02 * (STROKE[1] - STROKE[0])
MIN_CAPACITY = np.asarray(PARAMS['trajectory']['min_wrench_capacity'], dtype=float)
STOP_DECEL = np.asarray(PARAMS['interaction']['stop_deceleration'], dtype=float)
DAMPING = np.asarray(PARAMS['interaction']['damping'], dtype=float)
K_BODY = np.diag(np.reshape(PARAMS['sim']['stiffness'], (3, 3)))


# ------------------------------------------------------------------ feasibility (the oracle)
# From the YAML's anchors alone (not the mechanism code): legs and G(pose), test/seed001.py.

def capacity(pose: np.ndarray) -> np.ndarray:
    """Wrench capacity (Fx, Fy N, Mz N·m) with |f| <= actuator.max_force: ``W = G f`` so
    ``f = G^-1 W``; axis i alone holds ``f_max / max_j |(G^-1)_ji|``."""
    return PARAMS['actuator']['max_force'] / np.max(np.abs(np.linalg.inv(leg_matrix(pose))), axis=0)


def sway_feasibility(centre: np.ndarray, amplitude: np.ndarray) -> tuple[float, str]:
    """``(f_max, why_not)`` for a trunk at ``centre + A sin(2 pi f t)``: the leg speeds scale
    with ``f`` (``dL/dt = (dL/dpose) A 2 pi f cos``), so ``f_max`` = V_ALLOWED over the peak
    leg speed per Hz (central differences of :func:`legs` over one period at 1 Hz).
    ``why_not`` (empty if fine): a pose of the sway at ``f_max``, or its braking pose (the
    admittance's check: ``x + v T / 2``, ``T = max |v_i| / stop_deceleration_i``), within the
    stroke's cleared 2 % or below trajectory.min_wrench_capacity."""
    t = np.linspace(0.0, 1.0, 4001)
    w = 2.0 * math.pi
    poses = centre[None, :] + amplitude[None, :] * np.sin(w * t)[:, None]
    L = np.array([legs(p) for p in poses])
    speed_per_hz = float(np.max(np.abs(np.gradient(L, t, axis=0))))
    f_max = V_ALLOWED / speed_per_hz
    rates = amplitude[None, :] * w * f_max * np.cos(w * t)[:, None]
    for p, v in zip(poses, rates):
        ahead = p + 0.5 * v * float(np.max(np.abs(v) / STOP_DECEL))
        for q in (p, ahead):
            lq = legs(q)
            if np.any(lq < STROKE[0] + STROKE_CLEAR) or np.any(lq > STROKE[1] - STROKE_CLEAR):
                return f_max, f'legs {np.round(lq * 1e3, 1).tolist()} mm at pose {np.round(q, 4).tolist()}'
            cap = capacity(q)
            if np.any(cap < MIN_CAPACITY):
                return f_max, f'capacity {np.round(cap, 2).tolist()} at pose {np.round(q, 4).tolist()}'
    return f_max, ''


#: (tag, trunk centre, amplitude, highest frequency asked for): the issue's sway ±10 mm
#: vertically and ±5 deg, 0.2-0.5 Hz; each run at the highest frequency (in 0.05 Hz steps,
#: at most the one asked for) whose leg speed stays within SPEED_HEADROOM x V_ALLOWED.
#: Centres: the paper's 100 mm stroke has no room for the sway at its 5 deg home (at 3 deg
#: and below the moment capacity falls under 0.9 N·m); y = 390 mm, theta = 8 deg keeps a1
#: 10 mm clear at 13 deg; the combined sway (in phase) needs y = 380 mm (a3 at 390 mm, 13 deg)
SWAYS = (('y', (0.0, 0.390, math.radians(8.0)), (0.0, 0.010, 0.0), 0.5),
         ('theta', (0.0, 0.390, math.radians(8.0)), (0.0, 0.0, math.radians(5.0)), 0.5),
         ('y+theta', (0.0, 0.380, math.radians(8.0)), (0.0, 0.010, math.radians(5.0)), 0.5))


def run_frequency(centre, amplitude, f_asked: float) -> float:
    f_max, why_not = sway_feasibility(np.asarray(centre, float), np.asarray(amplitude, float))
    assert not why_not, f'sway about {centre} of {amplitude} leaves the workspace: {why_not}'
    return min(f_asked, math.floor(SPEED_HEADROOM * f_max / 0.05 + 1e-9) * 0.05)


def test_the_sways_feasibility_oracle() -> None:
    """The oracle's numbers (hand check of the paper's geometry, Table II's 65 mm/s at 80 %):
    the combined sway at 0.5 Hz needs ~85 mm/s (f_max ~0.31 Hz), the rotation alone ~53 mm/s
    (just over 52: f_max ~0.49 Hz), the vertical alone ~31 mm/s (0.5 Hz is fine); the
    rotation about theta = 5 deg dips under the moment capacity's 0.9 N·m."""
    f = {tag: sway_feasibility(np.asarray(c, float), np.asarray(a, float)) for tag, c, a, _ in SWAYS}
    assert f['y+theta'][0] == pytest.approx(0.31, abs=0.01) and not f['y+theta'][1]
    assert f['theta'][0] == pytest.approx(0.49, abs=0.01) and not f['theta'][1]
    assert f['y'][0] > 0.8 and not f['y'][1]
    assert 'capacity' in sway_feasibility(np.array([0.0, 0.390, math.radians(5.0)]),
                                          np.array([0.0, 0.0, math.radians(5.0)]))[1]
    assert [run_frequency(c, a, fa) for _, c, a, fa in SWAYS] == pytest.approx([0.5, 0.4, 0.25])


class Truth:
    """The simulator's truth and the interaction events, as (arrival time, value)."""

    def __init__(self, node, driver=None) -> None:
        self.lock = threading.Lock()
        #: the stack's CAN driver node (its cycle's evidence when the truth stalls)
        self.driver = driver
        self.pose: list[tuple[float, np.ndarray]] = []
        self.body: list[tuple[float, np.ndarray]] = []
        self.wrench: list[tuple[float, np.ndarray]] = []
        #: the wrench again, at the simulator's own sample time (header stamp, wall clock)
        self.wrench_sampled: list[tuple[float, np.ndarray]] = []
        self.status: list[DiagnosticStatus] = []
        #: the same samples by their header stamp (ns): the simulator stamps the ring's and the
        #: trunk's pose of one sample alike; pairing by arrival order mismatched them by tens of
        #: samples when one topic's delivery ran behind the other's
        self.pose_at: dict[int, tuple[float, np.ndarray]] = {}
        self.body_at: dict[int, tuple[float, np.ndarray]] = {}
        node.create_subscription(PoseStamped, topics.SIM_POSE, self._pose(self.pose, self.pose_at), TRUTH_DEPTH)
        node.create_subscription(PoseStamped, topics.SIM_BODY_POSE, self._pose(self.body, self.body_at),
                                 TRUTH_DEPTH)
        node.create_subscription(WrenchStamped, topics.SIM_WRENCH, self._on_wrench, TRUTH_DEPTH)
        node.create_subscription(DiagnosticStatus, topics.GOAL_STATUS, self._on_status, topics.STATUS_QOS)

    def _pose(self, box, by_stamp):
        def cb(msg: PoseStamped) -> None:
            q = msg.pose.orientation
            th = 2.0 * math.atan2(q.z, q.w)
            value = np.array([msg.pose.position.x, msg.pose.position.y, th])
            now = time.monotonic()
            with self.lock:
                box.append((now, value))
                by_stamp[msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec] = (now, value)
        return cb

    def ring_and_trunk(self, t0: float, t1: float) -> tuple[np.ndarray, np.ndarray]:
        """The ring's and the trunk's true poses of the identical stamps, sampled (the
        simulator's stamp, wall clock) from ``t0`` to ``t1``."""
        lo, hi = round(t0 * 1e9), round(t1 * 1e9)
        with self.lock:
            pairs = [(p, self.body_at[s][1]) for s, (_, p) in sorted(self.pose_at.items())
                     if lo <= s <= hi and s in self.body_at]
        return np.array([p for p, _ in pairs]), np.array([b for _, b in pairs])

    def pose_sampled_at(self, t: float) -> np.ndarray:
        """The ring's true pose of the first sample stamped ``t`` or later."""
        at = round(t * 1e9)
        with self.lock:
            return self.pose_at[min(s for s in self.pose_at if s >= at)][1]

    def sampled(self, t0: float, t1: float) -> np.ndarray:
        """The wrenches the simulator sampled (its stamp, wall clock) from ``t0`` to ``t1``."""
        with self.lock:
            return np.array([w for t, w in self.wrench_sampled if t0 <= t <= t1])

    def wait_sampled_until(self, t1: float, timeout: float) -> None:
        """Wait until the wrench, the ring's and the trunk's samples stamped ``t1`` or later
        arrived: the record up to ``t1`` is then whole, however late this process reads."""
        hi = round(t1 * 1e9)

        def whole() -> bool:
            with self.lock:
                return (bool(self.wrench_sampled) and self.wrench_sampled[-1][0] >= t1
                        and max(self.pose_at, default=0) >= hi and max(self.body_at, default=0) >= hi)
        wait(whole, timeout, f'the truth sampled after {t1:.3f}', self.evidence)

    def wait_trunk_at(self, pose: np.ndarray, since: float, timeout: float) -> float:
        """Wait until the trunk's true pose (``/brace/sim/body_pose``) is ``pose``; the stamp
        (s, wall clock) of its first sample there stamped ``since`` or later."""
        at, lo = np.asarray(pose, float), round(since * 1e9)

        def first() -> float | None:
            with self.lock:
                there = [s for s, (_, b) in self.body_at.items()
                         if s >= lo and np.allclose(b, at, atol=1e-6)]
            return min(there) * 1e-9 if there else None
        wait(lambda: first() is not None, timeout, f'the trunk at {at}', self.evidence)
        return first()

    def evidence(self) -> str:
        with self.lock:
            newest = max(self.pose_at, default=0) * 1e-9
        return (f'newest truth sample stamped {time.time() - newest:.1f} s ago; '
                + (cycle_evidence(self.driver) if self.driver is not None else ''))

    def _on_wrench(self, msg: WrenchStamped) -> None:
        # platform frame -> base: R(theta) (the ring's true theta of the same sample)
        with self.lock:
            th = self.pose[-1][1][2] if self.pose else 0.0
            f, t = msg.wrench.force, msg.wrench.torque
            c, s = math.cos(th), math.sin(th)
            w = np.array([c * f.x - s * f.y, s * f.x + c * f.y, t.z])
            self.wrench.append((time.monotonic(), w))
            self.wrench_sampled.append((msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec, w))

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


@pytest.fixture(scope='module')
def stack(tmp_path_factory):
    # the truth at TRUTH_HZ: this process runs the whole stack and reads three truth topics;
    # at 100 Hz, beside two other workers, the driver's truth publisher fell seconds behind
    # (runs 1110, 1201: the newest sample 12-15 s old, past its 5 s backlog: holes; runs 910,
    # 1016: half the sway's samples unpaired)
    extra = ['-p', f'can.channel:=inter{next(_channels)}', '-p', 'can.sync_spin_us:=0',
             '-p', f'sim.truth_rate_hz:={TRUTH_HZ}', *BUSY_HOST_ARGS]
    with stack_in_process(LUMBAR, tmp_path_factory.mktemp('device'), extra) as b:
        truth = Truth(b.helper, b.node('can_driver_node'))
        home_and_enable(b)
        yield b, truth


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
    # the driver's command at every SYNC (the in-cycle admittance's output), the wall time of
    # every SYNC cycle (the simulated world advances one SYNC period per SYNC, so a loaded
    # host that skips cycles stops the world meanwhile) and when each wrench goal reached the
    # cycle (wall clock, the truth's stamps' clock): settling is counted from there
    # (docs/interaction.md), not from this process's publish, two DDS hops earlier (tens of ms
    # on a loaded host). The master's cycle trace, taken from the control cycle's process.
    master = b.node('can_driver_node').master
    commands: list[list[float]] = []
    cycles: list[float] = []
    goal_arrivals: list[float] = []

    def take_trace() -> None:
        got = master.take_cycle_trace()
        cycles.extend(got['cycles'])
        commands.extend(q for _, q in got['commands'])
        goal_arrivals.extend(got['goals'])
    master.trace_cycles(True)
    period = 1.0 / float(b.config['can']['sync_rate_hz'])
    ok, msg = trigger(b, 'start')
    assert ok, msg
    truth.wait_status(lambda s: s.message == 'started', 2, 'started')
    report: dict[str, float] = {}

    # the patient leans to the first sway's centre over 2 s; the brace follows (x is held:
    # no lateral capacity)
    current = np.asarray(sim.rest_pose, dtype=float)
    t0 = time.monotonic()
    bounds: dict[str, float] = {}
    for tag, centre, amp, f_asked in SWAYS:
        centre, amp = np.asarray(centre, float), np.asarray(amp, float)
        if np.any(centre != current):
            t_lean = time.time()
            move_body(b, rest_pub, current, centre, 2.0)
            current = centre
            # the ring's pose 1.5 s after the trunk got there, by the simulator's stamps,
            # however late this process reads them: by arrival time, a reader the host served
            # late had nothing from the last 0.3 s (run 703) or only poses from before the
            # lean (run 701). And from the trunk's arrival, not from this process's last
            # publish: the trunk plays the stream on the simulated clock, which a loaded host
            # slows (SYNCs skipped: the world stands still; CI of 7300779, 1.5 s after the
            # publish the ring had moved 0.1 mm of the 10 mm lean)
            t_check = truth.wait_trunk_at(centre, t_lean, 15) + 1.5
            truth.wait_sampled_until(t_check, 10)
            pose = truth.pose_sampled_at(t_check)
            assert abs(pose[2] - centre[2]) < math.radians(0.3), np.degrees(pose)
            assert abs(pose[1] - centre[1]) < 0.002, pose
        f_hz = run_frequency(centre, amp, f_asked)
        tag = f'{tag} {f_hz:.2f} Hz'
        periods = 3 if f_hz >= 0.4 else 1.5
        # the sway's window by the simulator's own stamps (wall clock), not by when this
        # process read the samples: a test process the host served late read the start's
        # transient after its arrival-time window had begun (run 614: max |Fy| 6.03 N)
        t_start = time.time()
        sim.set_sway(amp, f_hz)
        time.sleep(periods / f_hz)
        t_end = time.time()
        sim.set_sway([0.0, 0.0, 0.0], 0.0)
        t_skip = t_start + 0.25 / f_hz                   # the start's transient
        truth.wait_sampled_until(t_end, 10)
        w = truth.sampled(t_skip, t_end)
        pose, body = truth.ring_and_trunk(t_skip, t_end)
        # at least half the truth's samples of the sway paired (the same stamp) with the trunk's
        assert len(pose) > TRUTH_HZ / 2 * periods / f_hz, f'{tag}: {len(pose)} pose samples paired with the trunk'
        err = np.abs(pose - body)
        report[f'{tag} max |Fy| N'] = float(np.max(np.abs(w[:, 1])))
        report[f'{tag} max |Mz| N.m'] = float(np.max(np.abs(w[:, 2])))
        report[f'{tag} max |y_ring - y_body| mm'] = float(np.max(err[:, 1]) * 1e3)
        report[f'{tag} max |th_ring - th_body| deg'] = float(np.degrees(np.max(err[:, 2])))
        # the ring lags the trunk by ~ D v / K: following at A w costs D A w of wrench, which
        # the trunk's stiffness turns into D A w / K of lag (docs/interaction.md, "The price")
        lag_deg = math.degrees(DAMPING[2] * amp[2] * 2.0 * math.pi * f_hz / K_BODY[2])
        # issue target 0.3 deg; where the 45 deg phase-margin damping (D_theta = 1.43 N·m·s/rad
        # for 4 x the body's stiffness) makes the lag alone larger than 0.8 x 0.3 deg, the
        # bound is 1.3 x that lag (theta at 0.4 Hz: lag 0.45 deg, measured 0.4-0.5 deg)
        bounds[tag] = 0.3 if lag_deg < 0.24 else 1.3 * lag_deg
        report[f'{tag} predicted theta lag deg'] = lag_deg
        time.sleep(1.0)
    report['lean_max_moment'] = float(np.max(np.abs(truth.since(truth.wrench, t0)[1][:, 2])))
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
        take_trace()
        t_goal, n_arrived = time.time(), len(goal_arrivals)
        goal_pub.publish(msg)
        truth.wait_status(lambda s: '/wrench_goal/' in s.name and s.message == 'accepted'
                          and float(status_values(s)['goal'].split(',')[axis]) == value,
                          2, f'{name} accepted')
        # 2 s of the step from the goal's arrival in the cycle, two DDS hops after the
        # acceptance (the final clone of the twelfth session: more than 2 s later, and a fixed
        # 2 s from the acceptance left no sample after it), its record whole
        wait(lambda: (take_trace(), len(goal_arrivals) > n_arrived)[1], 10, f'{name} in the cycle',
             truth.evidence)
        truth.wait_sampled_until(goal_arrivals[n_arrived] + 2.0, 15)
        take_trace()
        # the goal reached the cycle once; or twice within 0.1 s, the same goal delivered
        # again (run 915: 8 ms apart, one publish): settling counts from the first
        arrivals = goal_arrivals[n_arrived:]
        assert arrivals and arrivals[-1] - arrivals[0] < 0.1, f'{name}: the driver got {arrivals}'
        arrived = arrivals[0]
        tw, w = truth.since(truth.wrench_sampled, arrived)
        comp = w[:, axis]
        # each sample's time on the simulated world's clock: the SYNCs since the goal reached
        # the cycle (a sample's stamp is its SYNC's send time, just after that cycle's step)
        walls = np.array(cycles)
        t_rel = (np.searchsorted(walls, tw, side='right') - np.searchsorted(walls, arrived, side='right')) * period
        report[f'{name} delivery s'] = arrived - t_goal
        report[f'{name} wall-clock stretch'] = float((tw[-1] - arrived) / t_rel[-1])
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
    take_trace()
    master.trace_cycles(False)
    # continuity: the driver's command (the admittance in the SYNC cycle) never steps or
    # accelerates beyond the actuator limits (docs/safety.md §7: no jump at start, goal or stop)
    cmd = np.array(commands)
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
    for tag, bound in bounds.items():
        assert report[f'{tag} max |Fy| N'] < 5.0, report
        assert report[f'{tag} max |Mz| N.m'] < 0.5, report
        assert report[f'{tag} max |y_ring - y_body| mm'] < 2.0, report
        assert report[f'{tag} max |th_ring - th_body| deg'] < bound, (tag, bound, report)
    for name in ('Fy 30 N', 'Mz 2 N.m'):
        assert report[f'{name} settling s (5 %)'] <= 1.0, report
        assert report[f'{name} overshoot %'] <= 10.0, report
