"""The load tiers of brace_control.safety (docs/safety.md §8, §14): the platform wrench and
its prediction as plain logic, then evaluated in the master's SYNC cycle against the
simulated brace.

Oracles: the lumbar brace's Jacobian from the paper's eq. 3 (``rpr_oracles``), the
mechanisms' own statics evaluated directly (the affine map must reproduce them), hand
computed ramps for the prediction, and the simulator's true forces.
"""
from __future__ import annotations

import math
import time

import numpy as np
import pytest

from brace_control.can import ActuatorTrajectory, FaultKind, MasterState
from brace_control.config import load_device_config, resolve_device_file
from brace_control.mechanisms import mechanism_from_config
from brace_control.mechanisms.planar_floats import PlanarRprFloats
from brace_control.safety import Action, ForcePrediction, LoadPrediction, PlatformWrench, WrenchTiers
from rpr_oracles import eq3_jacobian, min_jerk
from test_can_master import _rig_with, wait_for

DEVICES = ('lumbar_brace', 'neck_brace_4rpr', 'neck_brace_3rrr', 'neck_brace_2r', 'shoulder',
           'upper_limb_trainer', 'continuum')


def _mech(device):
    return mechanism_from_config(load_device_config(resolve_device_file(device)))


class _Counting:
    """A mechanism that counts its forward solutions."""

    def __init__(self, mech):
        self.mech, self.forward_calls = mech, 0

    def __getattr__(self, name):
        return getattr(self.mech, name)

    def forward_nearest(self, q, hint):
        self.forward_calls += 1
        return self.mech.forward_nearest(q, hint)


def _near_home(mech, rng, scale=0.3):
    """A reachable pose near home and its actuator coordinates."""
    home = np.asarray(mech.home_pose, dtype=float)
    for _ in range(200):
        pose = home + rng.normal(0.0, 1.0, home.size) * np.where(np.abs(home) > 1.0, 0.02, 0.01) * scale
        try:
            q = np.asarray(mech.inverse(pose), dtype=float)
            return np.asarray(mech.forward_nearest(q, home), dtype=float), q
        except ValueError:
            continue
    raise AssertionError('no reachable pose near home')


# docs/safety.md §8
@pytest.mark.parametrize('device', DEVICES)
def test_the_per_sample_wrench_is_the_mechanism_s_statics_at_the_pose(device):
    """At a fixed pose the statics are affine in the forces: the map built once per pose
    gives what the mechanism's ``wrench`` gives for every force sample."""
    mech = _mech(device)
    rng = np.random.default_rng(11)
    pose, q = _near_home(mech, rng)
    platform = PlatformWrench(mech)
    for k in range(5):
        f = rng.normal(0.0, 20.0 if mech.actuator_limits[0][0] < 1.0 else 2.0, mech.n_actuators)
        w = platform(q, f, now=0.001 * k)
        np.testing.assert_allclose(w, np.asarray(mech.wrench(platform.pose, f), float), rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(platform.pose, pose, atol=1e-9)


def test_the_lumbar_wrench_is_j_transpose_f_of_the_paper_s_eq3():
    mech = _mech('lumbar_brace')
    platform = PlatformWrench(mech, legs=PlanarRprFloats.of(mech))
    pose, q = _near_home(mech, np.random.default_rng(3))
    f = np.array([40.0, -25.0, 60.0])
    np.testing.assert_allclose(platform(q, f, 0.0), eq3_jacobian(pose).T @ f, atol=1e-4)


def test_forward_kinematics_is_solved_again_only_for_new_positions_and_at_most_every_pose_period():
    counting = _Counting(_mech('lumbar_brace'))
    mech = counting.mech
    pose, q = _near_home(mech, np.random.default_rng(5))
    platform = PlatformWrench(counting, pose_period=0.01, legs=PlanarRprFloats.of(mech))
    rng = np.random.default_rng(3)
    for k in range(6):                              # the same q, new forces: no new solution
        f = rng.normal(0, 50.0, 3)
        np.testing.assert_allclose(platform(q, f, 0.002 * k), eq3_jacobian(pose).T @ f, atol=1e-4)
    assert counting.forward_calls == 1
    q2 = q + np.array([1e-6, 0.0, 0.0])
    platform(q2, f, 0.005)                         # new q, but the pose is 5 ms old: kept
    assert counting.forward_calls == 1
    platform(q2, f, 0.5)                            # later: solved again, from the last pose
    assert counting.forward_calls == 2
    assert platform._period >= 0.01                 # never shorter than pose_period
    np.testing.assert_array_equal(platform.pose, mech.forward_nearest(q2, pose))
    assert platform(q + np.nan, f, 1.0) is None and platform(q, f * np.nan, 1.0) is None


def test_positions_no_pose_fits_are_solved_again_only_every_pose_period_too():
    """A cable brace's slack cables (lengths that fit no pose, by more than the 4-RPR's
    residual_max): no wrench to judge by (None), and the failed solution -- the global
    least-squares search over every branch, milliseconds -- is retried at most once per pose
    period, not at every SYNC (it overran the cycle at 250 Hz during a take-up and once
    held the master's heartbeat back past the drives' consumer time). A consistent q
    afterwards gives the statics again."""
    counting = _Counting(_mech('neck_brace_4rpr'))
    mech = counting.mech
    pose, q = _near_home(mech, np.random.default_rng(7))
    slack = q + np.array([0.012, 0.0, 0.0, 0.012])          # two cables paid out 12 mm
    with pytest.raises(ValueError, match='inconsistent'):
        mech.forward_nearest(slack, pose)                   # premise: no pose fits
    platform = PlatformWrench(counting, pose_period=0.01)
    f = np.array([-1.0, -5.0, -5.0, -1.0])
    for k in range(50):                                     # 250 Hz for 0.2 s, taking up
        assert platform(slack - np.array([1e-5 * k, 0.0, 0.0, 1e-5 * k]), f, 0.004 * k) is None
    assert 1 <= counting.forward_calls <= 0.2 / 0.01 + 1, counting.forward_calls
    # taut again: solved at the next period, the mechanism's own statics there
    w = platform(q, f, 1.0)
    np.testing.assert_allclose(platform.pose, pose, atol=1e-9)
    np.testing.assert_allclose(w, np.asarray(mech.wrench(pose, f), float), rtol=1e-9, atol=1e-9)


def test_the_prediction_extrapolates_the_rise_per_displacement_to_the_motion_s_end():
    """A load rising 2 N per mm with 10 mm to go from 60 N reaches 80 N: past a 75 N limit
    (hit), not past a 90 N one; below half the limit nothing is looked at; a flat load, or a
    motion that did not move, predicts nothing."""
    def run(limit, start=60.0, slope=2.0, togo=0.010, moved=True):
        pred = LoadPrediction(floor=0.5, window_s=0.05, rise=0.01)
        out = None
        for k in range(30):                          # 500 Hz, 0.1 mm per sample
            q = np.array([1e-4 * k if moved else 0.0])
            load = np.array([start + slope * (q[0] * 1e3 if moved else 0.0)])
            out = pred(0.002 * k, load, np.array([limit]), q, lambda: togo)
            if out:
                return out
        return out

    hit = run(75.0)
    assert hit is not None and hit[0] == 0
    j, load, rise, moved, ahead, further = hit
    assert further == 0.010                     # 10 mm to go, within ten times the 2.5 mm seen
    assert ahead == pytest.approx(load + rise / moved * 0.010, rel=1e-9)
    assert rise / moved == pytest.approx(2000.0, rel=1e-6)         # 2 N per mm
    assert run(90.0, togo=0.010) is None                           # 60 + 2.6 .. + 20 < 90
    assert run(200.0) is None                                      # below half the limit
    assert run(75.0, slope=0.0) is None
    assert run(75.0, moved=False) is None
    assert run(75.0, togo=0.0) is None                             # at its end: nothing ahead


def test_a_start_transient_is_not_carried_far_beyond_the_stroke_it_was_seen_over():
    """Run 906 (the 4-RPR neck brace's way home after a soft stop at 33 N of a 40 N limit): at a
    motion's start the stroke is microns while the load cells feel the drives' acceleration.
    Here the static load falls 1.5 N per mm (the head's stiffness, moving home), the measured
    load carries a transient rising to 0.6 N over the first 60 ms, and the motion starts as a
    minimum-jerk one (stroke ~ t^3) with 34 mm to go. Carried over the whole way to go (the
    old arithmetic: premise) that rise made a load of hundreds of newtons; it is carried at most
    SOFT_AHEAD (10) times the stroke seen: nothing predicted, and the load stays below its limit
    all the way."""
    from brace_control.safety.wrench import SOFT_AHEAD
    assert SOFT_AHEAD == 10.0
    total, T = 0.034, 1.2                                   # 34 mm home in 1.2 s

    def hits(ahead):
        pred, out, loads = LoadPrediction(floor=0.5, window_s=0.05, rise=0.01, ahead=ahead), [], []
        for k in range(300):                                # 500 Hz, 0.6 s
            t = 0.002 * k
            s = t / T
            x = total * (10 * s**3 - 15 * s**4 + 6 * s**5)  # minimum jerk
            load = 33.3 - 1500.0 * x + 0.6 * min(t / 0.06, 1.0)
            loads.append(load)
            hit = pred(t, [load], [40.0], [x], lambda: total - x)
            if hit:
                out.append(hit)
        assert max(loads) < 40.0
        return out

    old = hits(math.inf)
    assert old and old[0][4] > 100.0, old[:1]               # premise: the start transient braked
    assert hits(SOFT_AHEAD) == []


def test_the_hard_tier_latches_above_max_wrench_and_its_cause_is_solved_afresh():
    mech = _mech('lumbar_brace')
    tiers = WrenchTiers(PlatformWrench(mech, legs=PlanarRprFloats.of(mech)), [150.0, 150.0, 30.0])
    pose, q = _near_home(mech, np.random.default_rng(7))
    big = np.linalg.lstsq(eq3_jacobian(pose).T, np.array([0.0, 160.0, 0.0]), rcond=None)[0]
    v = tiers.check(0.0, q, big, lambda: None)
    assert v.action is Action.PROTECTIVE_STOP and 'safety.max_wrench' in v.reason and '[1]' in v.reason
    assert tiers.exceeds(q, big) and not tiers.exceeds(q, big * 0.9)
    assert tiers.check(0.002, q, big * 0.9, lambda: None).ok


def test_force_prediction_names_the_actuator():
    pred = ForcePrediction(('a1', 'a2'), 100.0, 'N')
    v = None
    for k in range(40):
        q = np.array([0.0, 1e-4 * k])
        v = pred.check(0.002 * k, q, [5.0, 55.0 + 3000.0 * q[1]], lambda: 0.02)
        if not v.ok:
            break
    assert v.action is Action.SOFT_STOP and "a2's load cell" in v.reason and 'safety.force_limit' in v.reason


# ---------------------------------------------------------------- in the SYNC cycle

def _rig(device):
    """A master and the simulated ``device``, booted, homed, enabled (test_can_master's rig)."""
    return _rig_with({}, load_device_config(resolve_device_file(device)))


# docs/safety.md §8
def test_a_wrench_step_latches_within_two_sync_periods():
    """Three legs each under the 250 N actuator limit, together a platform force above
    safety.max_wrench (150 N): the master latches in the SYNC cycle, counted in SYNCs sent
    between the step on the simulated bus and the latch (the node's 100 Hz timer took up to
    five); recover is refused while the load is there and succeeds once it is gone."""
    sim, master = _rig('lumbar_brace')
    try:
        latched_at = []
        react = master.supervisor._on_fault

        def on_fault(fault):
            latched_at.append((fault.kind, master.clock.index))
            react(fault)
        master.supervisor._on_fault = on_fault
        k0 = master.clock.index
        for node_id in (1, 2, 3):
            sim.faults.set_load_cell(node_id, 120.0)
        wait_for(lambda: master.supervisor.has(FaultKind.WRENCH_LIMIT), 2.0, 'the wrench stop')
        kind, k = latched_at[0]
        assert kind is FaultKind.WRENCH_LIMIT and k - k0 <= 2, (k - k0, latched_at)
        assert 'safety.max_wrench' in master.supervisor.summary()
        assert any(f.kind is FaultKind.WRENCH_LIMIT for f in master.recover())     # still there
        for node_id in (1, 2, 3):
            sim.faults.set_load_cell(node_id, None)
        wait_for(lambda: not master.recover(), 2.0, 'recover once the load is gone')
    finally:
        master.shutdown()
        sim.shutdown()


def _crank_goal(master, sim, q1, T):
    """A minimum-jerk crank motion to ``q1`` (rad) over ``T``; the true crank torque's peak."""
    before = len(master.execution_events())
    assert master.execute(ActuatorTrajectory(*min_jerk(master.feedback().position[0], q1, T, 121)),
                          start=time.perf_counter() + 0.02, tag=7) is None
    peak = 0.0
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < T + 5.0:
        peak = max(peak, float(np.abs(sim.truth().forces).max()))
        events = master.execution_events()[before:]
        if any(e.kind in ('finished', 'stopped', 'aborted') for e in events) and not master.moving:
            return events, peak
        time.sleep(0.001)
    pytest.fail('the crank motion did not end')


# docs/safety.md §14
def test_the_trainer_s_crank_against_the_arm_is_braked_before_the_hard_torque_limit():
    """The upper-limb trainer (5 N·m at the crank, the arm a 300 N/m spring at the handle):
    a reach to crank 10° from home (90°) loads the crank past the limit. The prediction
    brakes it: the motion is reported stopped by the soft tier, the TRUE crank torque stays
    under 5 N·m, nothing latches; a reach to crank 60° then succeeds."""
    sim, master = _rig('upper_limb_trainer')
    try:
        events, peak = _crank_goal(master, sim, math.radians(10.0), 0.6)
        assert events[-1].kind == 'stopped' and 'soft' in events[-1].reason, events
        assert peak < 5.0, peak
        assert not master.supervisor.latched and master.state is MasterState.ENABLED
        events, peak = _crank_goal(master, sim, math.radians(60.0), 0.6)
        assert events[-1].kind == 'finished', events
        assert not master.supervisor.latched
        assert abs(float(sim.truth().lengths[0]) - math.radians(60.0)) < 0.02
    finally:
        master.shutdown()
        sim.shutdown()
