"""Admittance control without ROS: the virtual mass-damper, its limits, and the loop's stability.

Oracles: the closed-form solution of ``M a + D v = e`` for a constant ``e``
(``v(t) = e / D (1 - exp(-D t / M))``); the closed-loop poles of the discrete loop
(admittance + delay + inner lag + body spring-damper), built here as a state-space matrix
from the loop's equations, independently of :func:`simulate_loop`; the lumbar brace's
inverse kinematics (seed 001, eq. 3) for the stroke.
"""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from brace_control.config import load_device_config
from brace_control.interaction import (AdmittanceController, AdmittanceParams, GoalRejected,
                                       LimitStop, LoopModel, Mode, phase_margin, simulate_loop)
from brace_control.mechanisms import load_mechanism
from rpr_oracles import lumbar_eq3

ROOT = Path(__file__).resolve().parent.parent
LUMBAR = ROOT / 'config' / 'lumbar_brace.yaml'
#: s: the drives' inner position loop as the admittance sees it: none, the command carries
#: its velocity as feed-forward (60B1h), so the CSP loop x' = v_ff + Kp (r - x) tracks it
DESIGN_LAG = 1e-6
DEVICES = ['lumbar_brace', 'lumbar_brace_v2', 'neck_brace_4rpr', 'neck_brace_3rrr',
           'neck_brace_2r', 'shoulder', 'continuum', 'upper_limb_trainer']


def controller(device: str = 'lumbar_brace', **inter: object) -> AdmittanceController:
    cfg = load_device_config(ROOT / 'config' / f'{device}.yaml')
    cfg['interaction'].update(inter)
    mech = load_mechanism(ROOT / 'config' / f'{device}.yaml')
    return AdmittanceController(mech, AdmittanceParams.from_config(cfg, mech))


def closed_loop_matrix(K: float, c: float, M: float, D: float, dt: float, delay_n: int,
                       lag: float) -> np.ndarray:
    """The discrete loop as ``z[k+1] = A z[k]`` (goal 0, body at rest), from its equations:

    W = K x + c (x - x_prev) / dt;  e = -W;  v' = p v + (1 - p) e / D;
    s_{k+1} = s_k + e dt / D + (v - e / D) (M / D) (1 - p) (the exact ZOH integral of v),
    delayed by delay_n periods;
    x' = x + a (s_delayed - x), a = 1 - exp(-dt / lag).
    State: [v, x, x_prev, s_k, s_{k-1}, ..., s_{k-delay_n}] (delay line of setpoints).
    """
    p = math.exp(-D * dt / M)
    a = 1.0 - math.exp(-dt / lag)
    n = 3 + delay_n + 1
    A = np.zeros((n, n))
    # e as a row over the state
    e = np.zeros(n)
    e[1] = -(K + c / dt)
    e[2] = c / dt
    vnew = np.zeros(n)
    vnew[0] = p
    vnew += (1.0 - p) / D * e
    A[0] = vnew
    # newest setpoint s_{k+1} = s_k + (v + v') dt / 2  -> stored in slot 3
    s_new = np.zeros(n)
    s_new[3] = 1.0
    s_new[0] += (M / D) * (1.0 - p)
    s_new += (dt / D - (M / D) * (1.0 - p) / D) * e
    A[3] = s_new
    for j in range(1, delay_n + 1):          # shift the delay line
        A[3 + j, 3 + j - 1] = 1.0
    # x' = x + a (s_{k-delay_n} - x)
    A[1, 1] = 1.0 - a
    A[1, 3 + delay_n] += a
    A[2, 1] = 1.0                             # x_prev' = x
    return A


@pytest.mark.parametrize('device', DEVICES)
@pytest.mark.parametrize('scale', [0.5, 1.0, 2.0, 4.0])
def test_the_loop_is_stable_and_settles_for_body_stiffness_half_to_four_times(device: str, scale: float) -> None:
    cfg = load_device_config(ROOT / 'config' / f'{device}.yaml')
    inter, sim = cfg['interaction'], cfg['sim']
    n = len(inter['damping'])
    K = np.reshape(sim['stiffness'], (n, n)).diagonal() * scale
    c = np.reshape(sim['damping'], (n, n)).diagonal()
    dt = 1.0 / float(inter['rate_hz'])
    lag = DESIGN_LAG
    # in the cycle: two SYNC periods (the lumbar brace's 500 Hz: 4 ms) plus 2 ms of margin
    delay = 2.0 / float(cfg['can']['sync_rate_hz']) + 0.002
    for i in range(n):
        if not inter['force_axes'][i]:
            continue
        M, D = float(inter['mass'][i]), float(inter['damping'][i])
        delay_n = round(delay / dt)
        # 1. every closed-loop pole inside the unit circle, with room (no limit cycle)
        A = closed_loop_matrix(float(K[i]), float(c[i]), M, D, dt, delay_n, lag)
        radius = float(np.max(np.abs(np.linalg.eigvals(A))))
        assert radius < 0.995, f'{device} axis {i} x{scale}: pole radius {radius:.4f}'
        # 2. a step of the goal (10 % of the capacity-limited goal or 1 unit) settles:
        #    bounded, within 2 % after 1.5 s, no ringing left (the error shrinks monotonically
        #    over the last 1 s: no limit cycle)
        model = LoopModel(float(K[i]), float(c[i]), M, D, dt, delay, lag)
        steps = int(3.0 / dt)
        goal = np.where(np.arange(steps) * dt >= 0.1, 1.0, 0.0)
        W, _ = simulate_loop(model, goal=goal, rest=np.zeros(steps))
        assert np.all(np.isfinite(W)) and np.max(np.abs(W)) < 1.5
        t = np.arange(steps) * dt
        assert np.max(np.abs(W[t > 1.6] - 1.0)) < 0.02, f'{device} axis {i} x{scale} not settled'
        tail = np.abs(W[t > 2.0] - 1.0)
        assert np.all(np.diff(tail) <= 1e-12), f'{device} axis {i} x{scale} still oscillates'
        # 3. the phase margin of (3) agrees: at least 40 deg over the range
        pm, _ = phase_margin(model)
        assert pm > 40.0, f'{device} axis {i} x{scale}: phase margin {pm:.1f} deg'


def test_an_undamped_design_is_caught_by_the_same_checks() -> None:
    """The oracle can fail: a tenth of the lumbar's vertical damping against 4 x K oscillates."""
    dt, lag, delay = 0.005, 1.0 / (2 * math.pi * 30.0), 0.03     # the ROS path's 30 ms
    A = closed_loop_matrix(16000.0, 80.0, 0.38, 76.5, dt, round(delay / dt), lag)
    assert float(np.max(np.abs(np.linalg.eigvals(A)))) > 1.0
    pm, _ = phase_margin(LoopModel(16000.0, 80.0, 0.38, 76.5, dt, delay, lag))
    assert pm < 0.0


def test_the_virtual_mass_damper_follows_its_closed_form() -> None:
    ctl = controller()
    mech = ctl.mechanism
    ctl.start(mech.home_pose)
    M, D, dt = ctl.p.mass[1], ctl.p.damping[1], ctl.p.dt
    e = 5.0                           # the body pushes the ring up with 5 N: the brace pushes -5 N
    x0 = mech.home_pose.copy()
    for k in range(1, 41):
        x, v = ctl.step([0.0, -e, 0.0])
        t = k * dt
        assert v[1] == pytest.approx(e / D * (1 - math.exp(-D * t / M)), rel=1e-9)
        exact_x = e / D * (t - M / D * (1 - math.exp(-D * t / M)))
        assert x[1] - x0[1] == pytest.approx(exact_x, rel=1e-9)
        assert v[0] == 0.0 and x[0] == x0[0]                 # x held (force_axes)
    assert v[2] == 0.0                                      # no moment: theta at rest


# docs/safety.md §19
def test_wrench_goals_on_held_axes_or_beyond_the_capacity_are_rejected() -> None:
    ctl = controller()
    ctl.start(ctl.mechanism.home_pose)
    with pytest.raises(GoalRejected, match='axis 0 holds position'):
        ctl.set_goal([1.0, 0.0, 0.0])
    with pytest.raises(GoalRejected, match='max_goal_wrench'):
        ctl.set_goal([0.0, 80.0, 0.0])
    with pytest.raises(GoalRejected, match='finite'):
        ctl.set_goal([0.0, float('nan'), 0.0])
    # the lateral capacity at home is 0.71 N: a device that force-controls x cannot take 5 N
    ctl_x = controller(force_axes=[True, True, True])
    ctl_x.start(ctl_x.mechanism.home_pose)
    with pytest.raises(GoalRejected, match='wrench capacity 0.711'):
        ctl_x.set_goal([5.0, 0.0, 0.0])
    ctl.set_goal([0.0, 30.0, 2.0])
    np.testing.assert_array_equal(ctl.goal, [0.0, 30.0, 2.0])


def test_stop_decelerates_along_the_direction_and_ends_at_rest() -> None:
    ctl = controller()
    ctl.start(ctl.mechanism.home_pose)
    for _ in range(60):
        ctl.step([0.0, -15.0, -0.15])
    v0 = ctl.v.copy()
    assert v0[1] > 0.015 and v0[2] > 0.015
    ctl.stop('test')
    xs, vs = [ctl.x.copy()], [ctl.v.copy()]
    while ctl.mode is Mode.STOPPING:
        x, v = ctl.step([0.0, -15.0, -0.15])        # the wrench no longer drives it
        xs.append(x)
        vs.append(v)
    assert ctl.mode is Mode.IDLE and not np.any(ctl.v)
    dv = np.diff(np.array(vs), axis=0) / ctl.p.dt
    assert np.all(np.abs(dv) <= ctl.p.stop_deceleration * (1 + 1e-9))
    # one direction: the velocity stays parallel to v0 (path-synchronous braking)
    for v in vs:
        assert abs(v[1] * v0[2] - v[2] * v0[1]) < 1e-12
    # no step in position: no step longer than the speed at the stop allows
    steps = np.diff(np.array(xs), axis=0)
    assert np.max(np.abs(steps)) <= np.max(np.abs(v0)) * ctl.p.dt * (1 + 1e-9)


def _brake_from_a_sway(ctl: AdmittanceController) -> tuple[np.ndarray, np.ndarray]:
    """Push the lumbar ring up and round (y and theta at once), stop, and brake to rest:
    the poses of every period from the one before the stop on, and where braking_pose said
    it would end."""
    ctl.start(ctl.mechanism.home_pose)
    before = ctl.x.copy()
    for _ in range(60):
        before = ctl.x.copy()
        ctl.step([0.0, -4.0, -0.4])
    predicted = ctl.braking_pose(ctl.x, ctl.v)
    ctl.stop('test')
    xs = [before, ctl.x.copy()]                # the period before the stop: its speed
    while ctl.mode is Mode.STOPPING:
        xs.append(ctl.step([0.0, -4.0, -0.4])[0])
    return np.array(xs), predicted


# docs/safety.md §19
def test_braking_keeps_every_actuator_within_its_acceleration_limit() -> None:
    """Pose axes braking each within its own stop_deceleration can, together, ask a leg for
    more than it may do (0.64 m/s^2 on the lumbar brace's 0.5 seen in the interaction e2e).
    The legs' lengths by eq. 3 (not the code under test), their second difference per
    period squared: within limit_margin x actuator.max_acceleration; and the ring ends where
    braking_pose predicted (a limit stop starts braking by that prediction)."""
    loose = dict(stop_deceleration=[10.0, 10.0, 100.0])      # the pose axes never bind here
    ctl = controller(**loose)
    a_lim = ctl.p.limit_margin * float(np.max(ctl.p.actuator_max_acceleration))
    xs, predicted = _brake_from_a_sway(ctl)
    assert ctl.mode is Mode.IDLE and len(xs) > 5
    q = np.array([lumbar_eq3(x) for x in xs])
    acc = np.abs(np.diff(q, n=2, axis=0)) / ctl.p.dt ** 2
    assert np.max(acc) <= a_lim * 1.02, (np.max(acc), a_lim)
    np.testing.assert_allclose(xs[-1], predicted, atol=2e-4)
    # the same sway braked on the pose axes' rates alone breaks the legs' limit: the check
    # above can fail
    free = AdmittanceController(ctl.mechanism, dataclasses.replace(ctl.p, actuator_max_acceleration=None))
    xs, _ = _brake_from_a_sway(free)
    q = np.array([lumbar_eq3(x) for x in xs])
    assert np.max(np.abs(np.diff(q, n=2, axis=0))) / free.p.dt ** 2 > 2 * a_lim


# docs/safety.md §5, §19
def test_pushing_towards_the_stroke_end_stops_inside_the_stroke() -> None:
    ctl = controller()
    mech = ctl.mechanism
    lo, hi = mech.actuator_limits
    ctl.start(mech.home_pose)
    stopped = None
    for _ in range(4000):
        try:
            ctl.step([0.0, -60.0, 0.0])           # the patient keeps pushing up, hard
        except LimitStop as exc:
            stopped = exc.reason
        if ctl.mode is Mode.IDLE:
            break
        q = lumbar_eq3(ctl.x)                     # eq. 3, not the code under test
        assert np.all(q >= lo[0] - 1e-9) and np.all(q <= hi[0] + 1e-9), q
    assert stopped is not None and stopped.startswith('workspace')
    assert ctl.mode is Mode.IDLE
    assert np.max(lumbar_eq3(ctl.x)) <= hi[0]


# docs/safety.md §19
def test_the_soft_force_limit_and_a_bad_wrench_stop_the_mode() -> None:
    ctl = controller()
    ctl.start(ctl.mechanism.home_pose)
    soft = ctl.p.soft_force_limit
    assert soft == pytest.approx(0.8 * 250.0)
    ctl.step([0.0, -10.0, 0.0], forces=[10.0, 10.0, 10.0])
    with pytest.raises(LimitStop, match='soft force limit: actuator a2 at 201.0'):
        ctl.step([0.0, -10.0, 0.0], forces=[10.0, 201.0, 10.0])
    assert ctl.mode in (Mode.STOPPING, Mode.IDLE)
    ctl = controller()
    ctl.start(ctl.mechanism.home_pose)
    with pytest.raises(LimitStop, match='not finite'):
        ctl.step([0.0, float('inf'), 0.0])


def test_the_virtual_velocity_stays_within_the_actuator_speed() -> None:
    ctl = controller()
    mech = ctl.mechanism
    ctl.start(mech.home_pose)
    limit = ctl.p.limit_margin * ctl.p.actuator_max_velocity
    for _ in range(60):
        x, v = ctl.step([0.0, -60.0, -3.0])       # drives M a + D v far beyond the speed
        qd = mech.jacobian(ctl.x - 0.5 * v * ctl.p.dt) @ v
        assert np.all(np.abs(qd) <= limit * (1 + 1e-3))
    assert ctl.velocity_limited > 0


def test_a_wrench_goal_is_tracked_as_a_ramp_at_the_goal_rate() -> None:
    """interaction.goal_rate [_, 60 N/s, 4 N·m/s]: after k periods the tracked wrench is
    min(goal, rate k dt) (a ramp, then the goal); with goal_rate 0 it is the step at once."""
    ctl = controller(goal_rate=[0.0, 60.0, 4.0])
    ctl.start(ctl.mechanism.home_pose)
    ctl.set_goal([0.0, 30.0, -2.0])
    dt = ctl.p.dt
    for k in range(1, 400):
        ctl.step(ctl.goal_now.copy())              # the body answers with what was tracked
        expect = [0.0, min(30.0, 60.0 * k * dt), -min(2.0, 4.0 * k * dt)]
        np.testing.assert_allclose(ctl.goal_now, expect, rtol=0, atol=1e-9)
    step = controller(goal_rate=[0.0])
    step.start(step.mechanism.home_pose)
    step.set_goal([0.0, 30.0, -2.0])
    step.step([0.0, 0.0, 0.0])
    np.testing.assert_array_equal(step.goal_now, [0.0, 30.0, -2.0])


def test_a_saturated_pose_moves_with_the_velocity_it_reports() -> None:
    """While speed limited, each period's pose change is the trapezoid of the reported
    velocities (the integral of a velocity that is linear over the period), so the actuator
    command's second difference stays at the velocity change: no catch-up step when the
    saturation ends (the command's 9 m/s^2 spike, test_interaction_e2e, before the fix)."""
    ctl = controller()
    ctl.start(ctl.mechanism.home_pose)
    dt = ctl.p.dt
    xs, vs, limited = [ctl.x.copy()], [ctl.v.copy()], []
    for k in range(200):
        goal = [0.0, -60.0, -3.0] if k < 100 else [0.0, -0.5, -0.02]   # saturate, then not
        before = ctl.velocity_limited
        x, v = ctl.step(goal)
        xs.append(x)
        vs.append(v)
        limited.append(ctl.velocity_limited > before)
    xs, vs = np.array(xs), np.array(vs)
    assert any(limited[:100]) and not any(limited[150:])
    for k in np.flatnonzero(limited):
        assert np.allclose(xs[k + 1] - xs[k], 0.5 * (vs[k] + vs[k + 1]) * dt, rtol=0, atol=1e-12), k
    # the pose's own acceleration (second difference) never exceeds the velocity change's
    # by more than the ZOH's curvature within a period (a few %)
    acc = np.abs(np.diff(xs, 2, axis=0)) / dt ** 2
    dv = np.abs(np.diff(vs, axis=0)) / dt
    bound = np.maximum(dv[:-1], dv[1:]) * 1.1 + 1e-9
    assert np.all(acc <= bound), np.max(acc / bound)


@pytest.mark.parametrize('device', DEVICES)
def test_every_device_follows_a_push_through_the_protocol(device: str) -> None:
    """Each mechanism's admittance moves the pose in the direction of a body push on its
    force axes (the sign convention: the brace's wrench on the body), within IK."""
    ctl = controller(device)
    mech = ctl.mechanism
    ctl.start(mech.home_pose)
    axes = np.flatnonzero(ctl.p.force_axes)
    push = np.zeros(mech.dof)
    push[axes] = -0.1 * ctl.p.max_goal_wrench[axes]      # a tenth of the largest goal
    for _ in range(20):
        x, v = ctl.step(push)
    mech.inverse(x)
    moved = x - mech.home_pose
    if hasattr(mech, 'path_direction'):
        # one crank: the handle follows the push's component along its path
        along = float(mech.path_direction(mech.home_pose) @ -push)
        assert along != 0.0 and float(moved @ -push) > 0.0, f'{device}: did not follow the push'
        return
    for i in range(mech.dof):
        if i in axes:
            assert moved[i] > 0.0, f'{device}: axis {i} did not follow the push'
        else:
            assert moved[i] == 0.0


# ------------------------------------------------------------------ the trainer: along its path
def _trainer_curve_oracle():
    """The coupler point of the trainer's four-bar for a crank angle, from the circle
    intersection written out here (the open assembly, P on AB extended by BP = L3), and
    the crank angle of the curve point nearest a point (dense grid, then golden section)."""
    from scipy.optimize import minimize_scalar
    cfg = load_device_config(ROOT / 'config' / 'upper_limb_trainer.yaml')
    m = cfg['mechanism']
    l2 = float(m['crank'])
    l1, l3, l4, bp = (float(m[k]) for k in ('ground', 'coupler', 'rocker', 'coupler_extension'))
    assert m.get('branch', 'open') == 'open'

    def point(th: float) -> np.ndarray:
        a = l2 * complex(math.cos(th), math.sin(th))
        o4 = complex(l1, 0.0)
        d = abs(o4 - a)
        x = (l3 ** 2 - l4 ** 2 + d ** 2) / (2 * d)
        u = (o4 - a) / d
        b = a + x * u + math.sqrt(l3 ** 2 - x * x) * 1j * u
        p = b + bp * (b - a) / l3
        return np.array([p.real, p.imag])

    grid = np.linspace(-math.pi, math.pi, 3601)
    pts = np.array([point(float(t)) for t in grid])

    def nearest(x: np.ndarray) -> tuple[float, float]:
        i = int(np.argmin(np.linalg.norm(pts - x, axis=1)))
        r = minimize_scalar(lambda t: float(np.linalg.norm(point(t) - x)),
                            bounds=(grid[i] - 0.01, grid[i] + 0.01), method='bounded',
                            options={'xatol': 1e-12})
        return float(r.x), float(r.fun)
    return point, nearest


def test_the_trainer_handle_moves_along_its_path_as_a_mass_damper_in_arc_length() -> None:
    """Zero-torque on the one-crank trainer: the hand pushes the handle along the coupler
    curve with a constant force F (measured: the brace's wrench on the hand, -F along the
    oracle's tangent). The handle stays on the curve (oracle: circle intersection), and
    its arc length follows M s'' + D s' = F in closed form, as a free axis would."""
    from scipy.integrate import quad
    ctl = controller('upper_limb_trainer')
    mech = ctl.mechanism
    point, nearest = _trainer_curve_oracle()
    home = np.asarray(mech.home_pose, dtype=float)
    th0, d0 = nearest(home)
    assert d0 < 1e-9
    ctl.start(home)
    M, D, dt, F = ctl.p.mass[0], ctl.p.damping[0], ctl.p.dt, 2.0
    h = 1e-6

    def tangent(th: float) -> np.ndarray:
        t = (point(th + h) - point(th - h)) / (2 * h)
        return t / np.linalg.norm(t)

    th = th0
    for k in range(1, 101):
        x, v = ctl.step(-F * tangent(th))
        th, dist = nearest(x)
        assert dist < 1e-8, f'step {k}: the handle left the coupler curve by {dist:.3g} m'
        assert abs(float(v @ tangent(th)) - np.linalg.norm(v)) < 1e-9 * max(1.0, np.linalg.norm(v))
        t = k * dt
        s_exact = F / D * (t - M / D * (1 - math.exp(-D * t / M)))
        arc = abs(quad(lambda a: float(np.linalg.norm((point(a + h) - point(a - h)) / (2 * h))), th0, th)[0])
        assert arc == pytest.approx(s_exact, rel=2e-3, abs=1e-7), f'step {k}'
        assert np.linalg.norm(v) == pytest.approx(F / D * (1 - math.exp(-D * t / M)), rel=2e-3)


def test_a_trainer_goal_is_judged_by_its_component_along_the_path() -> None:
    """The handle's capacity is a force along its path: a goal beyond it is rejected
    naming that component; a goal normal to the path asks nothing of the motor."""
    ctl = controller('upper_limb_trainer')
    mech = ctl.mechanism
    _, nearest = _trainer_curve_oracle()
    home = np.asarray(mech.home_pose, dtype=float)
    ctl.start(home)
    cap = float(ctl.capacity(home)[0])
    t = np.asarray(mech.path_direction(home))
    normal = np.array([-t[1], t[0]])
    ctl.set_goal(15.0 * normal)                      # along the path: 0
    for _ in range(50):
        x, v = ctl.step(np.zeros(2))
    assert nearest(x)[1] < 1e-8 and np.linalg.norm(x - home) < 1e-3
    small = controller('upper_limb_trainer', max_goal_wrench=[1e3, 1e3])
    small.start(home)
    with pytest.raises(GoalRejected, match='along the path exceeds the wrench capacity'):
        small.set_goal((cap + 1.0) * t)
