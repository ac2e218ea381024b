"""Zero-torque mode on the upper-limb trainer (one crank, the handle on the coupler curve),
on the simulated bus, against the truth.

The whole stack in this process (:class:`~brace_control.bringup.BringUp`), homed and
enabled, ``/interaction_node/start``. The user's hand (the simulator's patient: a spring
``sim.stiffness`` about a rest point) moves its rest point along the trainer's straight
stroke and back, as a minimum-jerk motion. Everything is measured on ``/brace/sim/*``:

* the handle follows: within 1 s of the hand's rest coming to a stop it is within 1 mm of
  it, at the far end and back home, having travelled the stroke;
* the hand is not loaded: the true force stays below what the virtual damper must cost
  (``D v`` at the hand's peak speed, with 2x for the loop's lag and 0.5 N of noise floor);
* the mode ran throughout (no stop, no abort) and stops cleanly on ``~/stop``.
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
from brace_control.nodes import topics
from brace_control.nodes.msgs import status_values
from ros_helpers import BUSY_HOST_ARGS, home_and_enable, stack_in_process, wait_until as wait

pytestmark = [pytest.mark.ros, pytest.mark.slow]

ROOT = Path(__file__).resolve().parent.parent
TRAINER = ROOT / 'config' / 'upper_limb_trainer.yaml'
PARAMS = yaml.safe_load(TRAINER.read_text())['/**']['ros__parameters']
DAMPING = float(PARAMS['interaction']['damping'][0])
BASE = PARAMS['base_frame']
_channels = itertools.count()


class Truth:
    """The simulator's handle, hand and force, and the goal statuses (arrival time, value)."""

    def __init__(self, node) -> None:
        self.lock = threading.Lock()
        self.pose: list[tuple[float, np.ndarray]] = []
        self.body: list[tuple[float, np.ndarray]] = []
        self.force: list[tuple[float, np.ndarray]] = []
        self.status: list[DiagnosticStatus] = []
        node.create_subscription(PoseStamped, topics.SIM_POSE, self._xy(self.pose), bag.RECORD_DEPTH)
        node.create_subscription(PoseStamped, topics.SIM_BODY_POSE, self._xy(self.body), bag.RECORD_DEPTH)
        node.create_subscription(WrenchStamped, topics.SIM_WRENCH, self._on_wrench, bag.RECORD_DEPTH)
        node.create_subscription(DiagnosticStatus, topics.GOAL_STATUS, self._on_status, topics.STATUS_QOS)

    def _xy(self, box):
        def cb(msg: PoseStamped) -> None:
            with self.lock:
                box.append((time.monotonic(), np.array([msg.pose.position.x, msg.pose.position.y])))
        return cb

    def _on_wrench(self, msg: WrenchStamped) -> None:
        with self.lock:
            self.force.append((time.monotonic(), np.array([msg.wrench.force.x, msg.wrench.force.y])))

    def _on_status(self, msg: DiagnosticStatus) -> None:
        with self.lock:
            self.status.append(msg)

    def since(self, box, t0: float) -> np.ndarray:
        with self.lock:
            return np.array([v for t, v in box if t >= t0])

    def events(self) -> list[tuple[str, str]]:
        with self.lock:
            return [(s.message, status_values(s).get('reason', '')) for s in self.status]


@pytest.fixture(scope='module')
def stack(tmp_path_factory):
    extra = ['-p', f'can.channel:=trainer_inter{next(_channels)}', '-p', 'sim.truth_rate_hz:=100.0', *BUSY_HOST_ARGS]
    with stack_in_process(TRAINER, tmp_path_factory.mktemp('device'), extra) as b:
        truth = Truth(b.helper)
        home_and_enable(b)
        yield b, truth


def _rest(x: np.ndarray, stamp_ns: int) -> PoseStamped:
    msg = PoseStamped()
    msg.header.frame_id = BASE
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
    msg.pose.position.x, msg.pose.position.y = float(x[0]), float(x[1])
    msg.pose.orientation.w = 1.0
    return msg


def settled_gap(truth: Truth, still_s: float = 0.3, within_s: float = 1.0, timeout: float = 15.0) -> float:
    """The handle's distance from the hand's rest ``within_s`` after the rest came to a
    stop (no sample of the last ``still_s`` farther than 10 um from the newest): the
    simulated world runs on SYNC-counted time, so on a loaded host the hand ends its
    motion later than the test's clock says."""
    deadline = time.monotonic() + timeout

    def still() -> bool:
        body = truth.since(truth.body, time.monotonic() - still_s)
        return len(body) > 5 and float(np.max(np.linalg.norm(body - body[-1], axis=1))) < 1e-5
    wait(still, timeout, "the hand's rest to stop")
    t_still = time.monotonic()
    gap = math.inf
    while time.monotonic() < min(t_still + within_s, deadline) and gap >= 1e-3:
        time.sleep(0.05)
        gap = float(np.linalg.norm(truth.since(truth.pose, 0.0)[-1] - truth.since(truth.body, 0.0)[-1]))
    return gap


def test_zero_torque_follows_the_hand_along_the_straight_stroke(stack) -> None:
    b, truth = stack
    mech = b.node('can_driver_node').mechanism
    rest_pub = b.helper.create_publisher(PoseStamped, topics.SIM_BODY_REST, topics.STATE_QOS)
    wait(lambda: len(truth.pose) > 5 and len(truth.force) > 5, 10, 'the truth topics')
    ok, msg = b.call('/interaction_node/start', timeout=5)
    assert ok, msg
    wait(lambda: any(m == 'started' for m, _ in truth.events()), 2, 'started')

    # the hand's rest along the straight stroke (crank 90 -> 125 deg) and back, each a
    # minimum-jerk motion of T seconds; the rest points are the curve's own (a hand that
    # moves along the path: a transparent trainer carries no load). Each sample is stamped
    # with its instant of the motion: the simulator plays the stream out at the stamps' rate,
    # so the hand's motion is the planned one whatever the publisher's timing
    start = truth.since(truth.pose, 0.0)[-1]
    th0 = float(mech.inverse(start)[0])
    th1 = th0 + math.radians(35.0)
    T, rate = 2.0, 50
    stroke = float(np.linalg.norm(mech.forward_branch(th1) - start))
    assert stroke > 0.03, stroke
    v_peak = 0.0
    t_move = time.monotonic()
    n = int(T * rate)
    for leg, (a, b_) in enumerate(((th0, th1), (th1, th0))):
        prev = mech.forward_branch(a)
        leg_ns, leg_mono = b.helper.get_clock().now().nanoseconds, time.monotonic()
        for k in range(1, n + 1):
            u = k / (T * rate)
            s = u * u * u * (10 - 15 * u + 6 * u * u)
            p = mech.forward_branch(a + s * (b_ - a))
            v_peak = max(v_peak, float(np.linalg.norm(p - prev)) * rate)
            prev = p
            # published a little ahead of its instant (the simulator plays it 0.1 s after it)
            time.sleep(max(0.0, leg_mono + k / rate - 0.05 - time.monotonic()))
            rest_pub.publish(_rest(p, leg_ns + round(1e9 * k / rate)))
        if leg == 0:
            gap_far = settled_gap(truth)
            travelled = float(np.linalg.norm(truth.since(truth.pose, 0.0)[-1] - start))
    gap_home = settled_gap(truth)
    force = truth.since(truth.force, t_move)
    peak = float(np.max(np.linalg.norm(force, axis=1)))
    bound = 2.0 * DAMPING * v_peak + 0.5
    report = {'stroke mm': stroke * 1e3, 'handle travelled mm': travelled * 1e3,
              'gap at the far end mm': gap_far * 1e3,
              'gap back home mm': gap_home * 1e3,
              'hand peak speed mm/s': v_peak * 1e3, 'peak |F| on the hand N': peak,
              'bound N (2 D v + 0.5)': bound}
    print('\ntrainer zero-torque (truth):', {k: round(v, 3) for k, v in report.items()})
    assert not [e for e in truth.events() if e[0] in ('aborted', 'stopping')], truth.events()
    assert travelled > 0.9 * stroke, report
    assert gap_far < 1e-3 and gap_home < 1e-3, report
    assert peak < bound, report

    ok, msg = b.call('/interaction_node/stop', timeout=5)
    assert ok, msg
    wait(lambda: any(m == 'stopped' for m, _ in truth.events()), 5, 'stopped')
