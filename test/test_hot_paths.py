"""The per-cycle fast paths give what the general computations give (bench/RESULTS.md,
"Driver and kinetics at rest, per thread").

Each fast path is checked against the computation it replaces, run on the same state, or
against an independent oracle: the lumbar brace's eq. 3 (seed paper 001, test/rpr_oracles.py)
and its Jacobian by central differences, CiA 402-2 table 30 written out here, the rotation
of a planar force. No rclpy: the node helpers are called as plain functions.
"""
from __future__ import annotations

import inspect
import itertools
import math
import os
from pathlib import Path

import numpy as np
import pytest

from brace_control.can.cia402 import Controlword, State402, controlword_towards, decode_state
from brace_control.can.plan import pdo_mapping_writes
from brace_control.mechanisms import load_mechanism
from brace_control.mechanisms.planar_floats import PlanarRprFloats
from brace_control.mechanisms.pose_estimate import MeasurementModel, PoseEstimator
from brace_control.nodes.kinetics_node import platform_frame_wrench
from brace_control.nodes.msgs import joint_state, pose_covariance_6x6, pose_with_covariance_msg
from brace_control.nodes.timers import timer_callback
from brace_control.safety import PlatformWrench
from brace_control.sim import SimulatedBrace
from drive_frames import FrameMaster
from rpr_oracles import eq3_jacobian, lumbar_eq3

ROOT = Path(__file__).resolve().parent.parent
CFG = ROOT / 'config' / 'lumbar_brace.yaml'
CPM = 8192 / 0.001
_ids = itertools.count()


def enabled_brace() -> tuple[SimulatedBrace, FrameMaster]:
    """The simulated lumbar brace, no bus: homed, CSP, OPERATION ENABLED, frame by frame."""
    sim = SimulatedBrace(CFG, channel=f'hot-{os.getpid()}-{next(_ids)}', start=False)
    fm = FrameMaster(sim.drives)
    q0 = sim.mechanism.inverse(sim.mechanism.home_pose)
    fm.enable_csp([round(q * CPM) for q in q0], configure=lambda nid: [
        (w.index, w.subindex, w.fmt, w.value) for w in pdo_mapping_writes(nid)])
    return sim, fm


# ---------------------------------------------------------------------- simulated drive

_LOOP_STATE = ('length_m', 'velocity_mps', '_seg_t', '_at_hard_stop', '_demand_m')


def test_csp_step_at_rest_is_the_position_loop_bit_for_bit() -> None:
    """At every SYNC of a hold, a motion and the hold after it, ``_csp_step`` leaves the
    drive in exactly the state the sub-step loop ``_csp_loop`` leaves it in from the same
    state (the at-rest shortcut changes nothing but the cost); and the shortcut is taken
    during the holds (the drive sits on its reference: zero error)."""
    sim, fm = enabled_brace()
    drive = sim.drives[1]
    q0 = sim.mechanism.inverse(sim.mechanism.home_pose)
    on_reference = 0
    dts = np.random.default_rng(2).uniform(0.0005, 0.012, 900)
    for k in range(900):
        if 300 <= k < 500:                  # a 1 mm move of leg 2 with feed-forward
            s = (k - 300) / 200
            fm.rpdo1(drive.node_id, 0x0F, round((q0[1] + 0.001 * s) * CPM))
            fm.rpdo2(drive.node_id, round(0.005 * CPM))
        elif k == 500:
            fm.rpdo2(drive.node_id, 0)
        dt = float(dts[k])                   # SYNC intervals as a loaded host makes them
        saved = {name: getattr(drive, name) for name in _LOOP_STATE}
        drive._csp_loop(dt)
        by_loop = [repr(getattr(drive, name)) for name in _LOOP_STATE]
        for name, value in saved.items():
            setattr(drive, name, value)
        at_rest = (drive.velocity_mps == 0.0 and drive._seg_from_m == drive._seg_to_m
                   and (math.floor(drive.length_m * CPM) + 0.5) / CPM == drive._seg_to_m)
        drive._csp_step(dt)
        assert [repr(getattr(drive, name)) for name in _LOOP_STATE] == by_loop, k
        on_reference += at_rest
        for name, value in saved.items():       # the SYNC itself, as the brace runs it
            setattr(drive, name, value)
        fm.sync(dt)
    assert on_reference > 500, on_reference


def test_brace_at_rest_reports_the_held_equilibrium_each_sync() -> None:
    """At rest the physics reuses its equilibrium: every SYNC's truth still has the wrench
    ``J^T f`` (J of eq. 3 by differences), the same lengths and pose, fresh noise in the
    load cells, and arrays of its own (a consumer changing one changes no other SYNC's)."""
    sim, _ = enabled_brace()
    for _ in range(400):
        sim._on_sync(0.002)                 # what the bus's SYNC runs: motion, physics, TPDOs
    truths = []
    for _ in range(50):
        sim._on_sync(0.002)
        truths.append(sim.truth())
    assert truths[-1].sync_count - truths[0].sync_count == 49
    first = truths[0]
    jac = eq3_jacobian(first.pose)
    for t in truths:
        np.testing.assert_allclose(t.brace_wrench, jac.T @ t.forces, atol=1e-6)
        np.testing.assert_array_equal(t.lengths, first.lengths)
        np.testing.assert_array_equal(t.pose, first.pose)
        assert not np.any(t.velocities)
    assert len({tuple(t.load_cell_counts) for t in truths}) > 1          # the noise is drawn
    for a, b in itertools.combinations(truths, 2):
        for field in ('lengths', 'velocities', 'pose', 'brace_wrench', 'load_cell_counts'):
            assert not np.shares_memory(getattr(a, field), getattr(b, field)), field


def test_truth_at_is_the_truth_of_the_nearest_stamp() -> None:
    """``truth_at`` (a walk back from the newest truth) picks the truth that a search of the
    whole history for the least ``|stamp - asked|`` picks (the oldest of equals): stamps a
    period apart, repeated stamps (SYNCs no later than the one before), asked for before,
    inside, between and after the history."""
    sim, _ = enabled_brace()
    rng = np.random.default_rng(7)
    for _ in range(300):
        sim._on_sync(0.002)
        sim.host.last_sync_stamp = round(sim.host.last_sync_stamp + rng.choice([0.0, 0.002, 0.005]), 3) \
            if sim.host.last_sync_stamp else 1000.0
    history = list(sim._history)
    stamps = np.array([t.stamp for t in history])
    assert np.all(np.diff(stamps) >= 0) and np.any(np.diff(stamps) == 0) and len(history) > 30
    asked = np.concatenate([stamps, stamps + 0.001, stamps - 0.0015, stamps + 0.0025,
                            [stamps[0] - 1.0, stamps[-1] + 1.0], rng.uniform(stamps[0], stamps[-1], 200)])
    for s in asked:
        expected = min(history, key=lambda t: abs(t.stamp - s))        # the first of equals
        assert sim.truth_at(float(s)) is expected, s


# ---------------------------------------------------------------------- CiA 402 codes

#: CiA 402-2 table 30, written out: (mask, value) -> state
_TABLE_30 = [(0x4F, 0x00, State402.NOT_READY_TO_SWITCH_ON), (0x4F, 0x40, State402.SWITCH_ON_DISABLED),
             (0x6F, 0x21, State402.READY_TO_SWITCH_ON), (0x6F, 0x23, State402.SWITCHED_ON),
             (0x6F, 0x27, State402.OPERATION_ENABLED), (0x6F, 0x07, State402.QUICK_STOP_ACTIVE),
             (0x4F, 0x0F, State402.FAULT_REACTION_ACTIVE), (0x4F, 0x08, State402.FAULT)]


def test_decode_state_is_table_30_for_every_statusword() -> None:
    for sw in range(0x10000):
        want = next((st for mask, value, st in _TABLE_30 if sw & mask == value), State402.UNKNOWN)
        assert decode_state(sw) is want, hex(sw)


def test_controlword_towards_enabled_steps_through_the_state_machine() -> None:
    """CiA 402-2 transitions 2, 3, 4 (and 12 out of QUICK STOP ACTIVE); the word that keeps a
    drive where it is; none from FAULT."""
    en = State402.OPERATION_ENABLED
    assert controlword_towards(State402.SWITCH_ON_DISABLED, en) == Controlword.SHUTDOWN == 0x06
    assert controlword_towards(State402.READY_TO_SWITCH_ON, en) == 0x07
    assert controlword_towards(State402.SWITCHED_ON, en) == 0x0F
    assert controlword_towards(State402.QUICK_STOP_ACTIVE, en) == 0x00
    assert controlword_towards(en, en) == 0x0F
    assert controlword_towards(State402.QUICK_STOP_ACTIVE, State402.QUICK_STOP_ACTIVE) == 0x02
    assert controlword_towards(State402.SWITCH_ON_DISABLED, State402.SWITCH_ON_DISABLED) == 0x00
    assert controlword_towards(State402.FAULT, State402.FAULT) is None
    assert controlword_towards(State402.FAULT, en) is None
    assert all(type(controlword_towards(s, en)) is int for s in
               (State402.SWITCH_ON_DISABLED, State402.READY_TO_SWITCH_ON, State402.SWITCHED_ON, en))


# ---------------------------------------------------------------------- planar legs in floats

def test_float_legs_are_eq3_and_its_jacobian() -> None:
    mech = load_mechanism(str(CFG))
    legs = PlanarRprFloats.of(mech)
    assert legs is not None
    rng = np.random.default_rng(11)
    home = np.asarray(mech.home_pose, dtype=float)
    for pose in [home, home * np.array([1, 1, 0])] + [home + rng.normal(0, [0.01, 0.01, 0.1]) for _ in range(50)]:
        lengths, rows = legs.lengths_and_rows(*pose.tolist())
        np.testing.assert_allclose(lengths, lumbar_eq3(pose), rtol=0, atol=1e-12)
        np.testing.assert_allclose(legs.lengths(*pose.tolist()), lumbar_eq3(pose), rtol=0, atol=1e-12)
        np.testing.assert_allclose(rows, eq3_jacobian(pose), rtol=0, atol=1e-6)
        f = rng.normal(0, 100.0, 3)
        np.testing.assert_allclose(legs.wrench(rows, f.tolist()), eq3_jacobian(pose).T @ f, atol=1e-4)


def test_float_legs_only_for_a_planar_rpr_that_agrees_with_its_model() -> None:
    assert PlanarRprFloats.of(load_mechanism(str(ROOT / 'config' / 'neck_brace_4rpr.yaml'))) is not None
    for other in ('neck_brace_3rrr', 'upper_limb_trainer', 'shoulder'):
        assert PlanarRprFloats.of(load_mechanism(str(ROOT / 'config' / f'{other}.yaml'))) is None, other
    mech = load_mechanism(str(CFG))

    class Shifted(type(mech)):           # a model whose lengths are not the anchors' (1 um longer)
        def inverse(self, pose):
            return super().inverse(pose) + 1e-6
    shifted = Shifted.__new__(Shifted)
    shifted.__dict__.update(mech.__dict__)
    assert PlanarRprFloats.of(shifted) is None


# ---------------------------------------------------------------------- pose estimate

@pytest.mark.parametrize('device', ['lumbar_brace', 'neck_brace_4rpr'])
def test_estimates_with_float_geometry_are_those_of_the_model_geometry(device: str) -> None:
    """The same readings (a loaded sway through the lumbar brace's singular theta = 0, a
    jump, a reading without forces) through the estimator with the float geometry and with
    the model's own: the same poses to 1e-12 m (rad), the same covariance to 1e-9
    relative, the same verdicts (exact, iterations, step limited, reacquired)."""
    mech = load_mechanism(str(ROOT / 'config' / f'{device}.yaml'))
    model = MeasurementModel(stiffness=1e6, resolution=0.001 / 8192, force_noise=0.05, stiffness_rel_std=0.05,
                             force_resolution=0.01, force_limit=250.0)
    fast, slow = PoseEstimator(mech, model), PoseEstimator(mech, model, fast_geometry=False)
    assert fast._floats is not None and slow._floats is None
    rng = np.random.default_rng(5)
    home = np.asarray(mech.home_pose, dtype=float)
    cable = getattr(mech, 'actuation', None) == 'cable'
    for k in range(400):
        pose = home + np.array([0.004 * math.sin(k / 40), 0.003 * math.sin(k / 70), 0.05 * math.sin(k / 55)])
        f = rng.normal(30.0, 10.0, mech.n_actuators) * (-1.0 if cable else 1.0)
        q = np.asarray(mech.inverse(pose)) + f / 1e6 + rng.normal(0, 5e-8, mech.n_actuators)
        if k == 250:
            q = q + 0.002
        forces = None if k % 50 == 7 else np.round(f / 0.01) * 0.01
        a, b = fast.update(q, forces), slow.update(q, forces)
        np.testing.assert_allclose(a.pose, b.pose, rtol=0, atol=1e-12)
        np.testing.assert_allclose(a.covariance, b.covariance, rtol=1e-9, atol=0)
        assert (a.exact, a.iterations, a.step_limited, a.reacquired, a.slack) == \
               (b.exact, b.iterations, b.step_limited, b.reacquired, b.slack), k
        if forces is not None:
            np.testing.assert_allclose(fast.wrench(a.pose, forces), slow.wrench(a.pose, forces), atol=1e-9)


def test_estimator_float_geometry_leaves_unreachable_poses_to_the_model() -> None:
    """Where the model raises (a pose beyond the widened stroke), the float path raises the
    model's error too: the solver's trial steps fail the same way."""
    mech = load_mechanism(str(CFG))
    est = PoseEstimator(mech, MeasurementModel(stiffness=1e6, resolution=1e-7, force_noise=0.05,
                                               stiffness_rel_std=0.05))
    far = np.asarray(mech.home_pose, dtype=float) + np.array([0.0, 0.5, 0.0])
    with pytest.raises(ValueError) as fast_error:
        est._inverse(far)
    with pytest.raises(ValueError) as model_error:
        est.geometry.inverse(far)
    assert str(fast_error.value) == str(model_error.value)
    with pytest.raises(ValueError):
        est._inverse(np.array([0.0, math.nan, 0.0]))


# ---------------------------------------------------------------------- driver and kinetics nodes

class _CountingMechanism:
    """The lumbar model, counting its forward kinematics."""

    def __init__(self) -> None:
        self.mech = load_mechanism(str(CFG))
        self.forward_calls = 0

    def __getattr__(self, name):
        return getattr(self.mech, name)

    def forward_nearest(self, q, hint):
        self.forward_calls += 1
        return self.mech.forward_nearest(q, hint)


def test_wrench_check_solves_forward_kinematics_again_only_for_new_inputs() -> None:
    """The cycle's wrench check (brace_control.safety.PlatformWrench, every sample): ``J^T f``
    at ``forward_nearest(q, last pose)``, the pose reused while ``q`` repeats bit for bit
    (``pose_period=0``: a new ``q`` is solved at once)."""
    counting = _CountingMechanism()
    mech = counting.mech
    platform = PlatformWrench(counting, pose_period=0.0, legs=PlanarRprFloats.of(mech))
    rng = np.random.default_rng(3)
    q = np.asarray(mech.inverse(np.asarray(mech.home_pose) + np.array([0.002, -0.001, 0.03])))
    pose = mech.forward_nearest(q, mech.home_pose)
    for k in range(6):
        f = rng.normal(0, 50.0, 3)
        w = platform(q, f, 0.002 * k)
        np.testing.assert_allclose(w, mech.wrench(pose, f), rtol=0, atol=1e-9)
        np.testing.assert_allclose(w, eq3_jacobian(pose).T @ f, atol=1e-4)
    assert counting.forward_calls == 1           # from the home pose, then reused
    q2 = q + np.array([1e-6, 0.0, 0.0])
    platform(q2, f, 0.02)
    assert counting.forward_calls == 2
    np.testing.assert_array_equal(platform.pose, mech.forward_nearest(q2, pose))


def test_platform_frame_wrench_rotates_the_force_into_the_platform() -> None:
    for theta in (0.0, 0.3, -2.5, math.pi):
        w = np.array([12.0, -7.0, 0.8])
        got = platform_frame_wrench(np.array([0.01, 0.39, theta]), w, 'planar')
        c, s = math.cos(theta), math.sin(theta)
        np.testing.assert_allclose(got[:2], np.array([[c, -s], [s, c]]).T @ w[:2], rtol=0, atol=1e-12)
        assert got[2] == w[2] and w.tolist() == [12.0, -7.0, 0.8]        # input untouched
    assert platform_frame_wrench(np.zeros(3), w, 'spherical') is w


def test_joint_state_carries_the_exact_doubles() -> None:
    v = np.array([0.1, -0.0, 1e-300])
    msg = joint_state(('a', 'b', 'c'), position=v, velocity=[1, 2, 3], effort=(0.5, 0.25, 0.125))
    assert msg.position.tobytes() == v.tobytes() and msg.position.typecode == 'd'
    assert list(msg.velocity) == [1.0, 2.0, 3.0] and list(msg.effort) == [0.5, 0.25, 0.125]
    with pytest.raises(ValueError, match='position: 2 values for 3 names'):
        joint_state(('a', 'b', 'c'), position=np.zeros(2))


def test_pose_covariance_layout_and_symmetry_check() -> None:
    cov = np.array([[4.0, 1.0, 0.5], [1.0, 9.0, 0.25], [0.5, 0.25, 16.0]])
    out = pose_covariance_6x6([0.0, 0.39, 0.1], cov, kind='planar', unobserved_variance=7.0)
    want = np.diag([7.0] * 6)
    for i, a in enumerate((0, 1, 5)):
        for j, b in enumerate((0, 1, 5)):
            want[a, b] = cov[i, j]
    np.testing.assert_array_equal(out, want)
    msg = pose_with_covariance_msg([0.0, 0.39, 0.1], cov, frame_id='brace_base', kind='planar',
                                   unobserved_variance=7.0)
    assert list(msg.pose.covariance) == want.ravel().tolist() and msg.header.frame_id == 'brace_base'
    assert msg.pose.pose.position.y == 0.39 and msg.pose.pose.orientation.z == math.sin(0.05)
    nearly = cov.copy()
    nearly[0, 2] *= 1 + 1e-12                      # within the 1e-9 tolerance: accepted
    pose_covariance_6x6([0.0, 0.39, 0.1], nearly, kind='planar')
    nearly[0, 2] *= 1 + 1e-6
    with pytest.raises(ValueError, match='not symmetric'):
        pose_covariance_6x6([0.0, 0.39, 0.1], nearly, kind='planar')


def test_timer_callback_has_no_parameters_and_calls_through() -> None:
    calls = []
    cb = timer_callback(lambda: calls.append(1))
    assert inspect.signature(cb).parameters == {} and cb() is None and calls == [1]
    assert inspect.signature(cb) is inspect.signature(cb)          # precomputed, not rebuilt
    with pytest.raises(TypeError, match='takes arguments'):
        timer_callback(lambda info: None)


def test_stamped_after_is_every_item_stamped_later_in_order() -> None:
    """``stamped_after`` (a walk back from the newest) gives what a filter of the whole record
    gives: stamps in order with repeats, asked before, inside, on and after the record."""
    from collections import deque
    from types import SimpleNamespace

    from brace_control.can.sync import stamped_after
    stamps = [1.0, 1.0, 1.5, 2.0, 2.0, 2.0, 3.25]
    kept = deque(SimpleNamespace(stamp=s, i=i) for i, s in enumerate(stamps))
    for asked in (0.0, 1.0, 1.2, 2.0, 3.0, 3.25, 9.0):
        assert stamped_after(kept, asked) == [x for x in kept if x.stamp > asked], asked
