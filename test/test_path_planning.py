"""Goals anywhere on the upper-limb trainer's coupler curve: planned along the curve.

The Hoeken four-bar has one crank: its handle moves on the coupler curve only. A straight
pose-space profile between two curve points leaves the curve wherever it bends (the return
stroke), so such goals used to be rejected as unreachable. The planner now runs the
profile in the curve's arc length (brace_control.trajectory.path). Oracles here are
independent of the code under test:

* the coupler point of a crank angle by the loop closure written out in this file
  (circle intersection, the open assembly), not the mechanism's ``_curve_batch``;
* the arc length as the length of a dense polyline of those points;
* the minimum-jerk speed profile of Flash and Hogan, ``s_dot = S/T 30 tau^2 (1 - tau)^2``.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from brace_control.config import load_device_config
from brace_control.mechanisms import mechanism_from_config
from brace_control.trajectory import Limits, PlanRejected, plan_motion

CONFIG = Path(__file__).resolve().parents[1] / 'config' / 'upper_limb_trainer.yaml'
DEG = math.pi / 180


@pytest.fixture(scope='module')
def trainer():
    cfg = load_device_config(CONFIG)
    return cfg, mechanism_from_config(cfg), Limits.from_config(cfg, dof=2)


def coupler_point(cfg, crank: float) -> np.ndarray:
    """P of the open Hoeken four-bar at a crank angle: |B - O4| = L4, |B - A| = L3, B left of
    the line A -> O4, P = A + (L3 + BP) / L3 (B - A)."""
    m = cfg['mechanism']
    l1, l2, l3, l4, bp = (float(m[k]) for k in ('ground', 'crank', 'coupler', 'rocker',
                                                 'coupler_extension'))
    a = np.array([l2 * math.cos(crank), l2 * math.sin(crank)])
    d = np.array([l1, 0.0]) - a
    dist = float(np.linalg.norm(d))
    x = (l3 ** 2 - l4 ** 2 + dist ** 2) / (2 * dist)
    u = d / dist
    n = np.array([-u[1], u[0]])
    b = a + x * u + math.sqrt(l3 ** 2 - x ** 2) * n        # left of A -> O4
    return a + (l3 + bp) / l3 * (b - a)


def distance_to_oracle_curve(cfg, points: np.ndarray, th_lo: float, th_hi: float) -> float:
    """Largest distance of ``points`` to a dense polyline of the oracle curve over the crank
    interval (the polyline's chord error at 20000 samples is below 0.1 um)."""
    th = np.linspace(th_lo, th_hi, 20001)
    curve = np.array([coupler_point(cfg, t) for t in th])
    seg0, seg = curve[:-1], np.diff(curve, axis=0)
    worst = 0.0
    for p in points:
        w = p - seg0
        t = np.clip(np.sum(w * seg, axis=1) / np.sum(seg * seg, axis=1), 0.0, 1.0)
        worst = max(worst, float(np.min(np.linalg.norm(w - t[:, None] * seg, axis=1))))
    return worst


def arc_length(cfg, th0: float, th1: float, n: int = 20001) -> float:
    th = np.linspace(th0, th1, n)
    pts = np.array([coupler_point(cfg, t) for t in th])
    return float(np.sum(np.linalg.norm(np.diff(pts, axis=0), axis=1)))


# crank angles of the goals: the return stroke (-50..90 deg) and the straight one (90..270)
GOAL_CRANKS = [-40.0, -10.0, 20.0, 45.0, 70.0, 150.0, 230.0, 300.0]


@pytest.mark.parametrize('goal_deg', GOAL_CRANKS)
def test_goal_on_the_curve_is_planned_on_the_curve(trainer, goal_deg):
    cfg, mech, limits = trainer
    home = np.asarray(cfg['mechanism']['home_pose'], float)       # crank 90 deg
    goal = coupler_point(cfg, goal_deg * DEG)
    plan = plan_motion(mech, home, goal, 'minimum_jerk', limits)
    ts = np.linspace(0.0, plan.duration, 301)
    P, V, _ = plan.trajectory.sample_many(ts)
    lo, hi = sorted((90.0 * DEG, goal_deg * DEG))
    # every sample on the curve, between the two crank angles (the crank's own way)
    assert distance_to_oracle_curve(cfg, P, lo - 0.01, hi + 0.01) < 1e-6
    np.testing.assert_allclose(P[0], home, atol=1e-9)
    np.testing.assert_allclose(P[-1], goal, atol=1e-9)
    # minimum jerk in arc length: the hand's speed is the bell S/T 30 tau^2 (1 - tau)^2
    S = arc_length(cfg, lo, hi)
    T = plan.duration
    tau = ts / T
    bell = S / T * 30 * tau ** 2 * (1 - tau) ** 2
    np.testing.assert_allclose(np.linalg.norm(V, axis=1), bell, atol=2e-3 * S / T)


@pytest.mark.parametrize('goal_deg', [120.0, 280.0])       # back, on round
def test_a_moving_start_goes_on_along_the_curve_continuously(trainer, goal_deg):
    """A goal that preempts a running motion (home -> crank 230 deg, a third of the way)
    starts from its state (position, velocity, acceleration) and the new motion stays on
    the curve, whether it turns back or goes on round the return stroke."""
    cfg, mech, limits = trainer
    home = np.asarray(cfg['mechanism']['home_pose'], float)
    first = plan_motion(mech, home, coupler_point(cfg, 230 * DEG), 'minimum_jerk', limits)
    p, v, a = first.trajectory.sample(first.duration / 3)
    assert np.linalg.norm(v) > 0.05                     # premise: a moving start
    goal = coupler_point(cfg, goal_deg * DEG)
    for profile in ('minimum_jerk', 'scurve', 'logcosh'):
        plan = plan_motion(mech, p, goal, profile, limits, v0=v, a0=a)
        p0, v0, a0 = plan.trajectory.sample(0.0)
        np.testing.assert_allclose(p0, p, atol=1e-9)
        np.testing.assert_allclose(v0, v, atol=1e-9)
        np.testing.assert_allclose(a0, a, atol=1e-6)
        P = plan.trajectory.sample_many(np.linspace(0.0, plan.duration, 201))[0]
        assert distance_to_oracle_curve(cfg, P, -50 * DEG, 310 * DEG) < 1e-6, profile
        np.testing.assert_allclose(P[-1], goal, atol=1e-9)


def test_a_motion_carried_past_the_end_of_the_crank_range_is_rejected(trainer):
    """The crank turns fully: past the end of its range it would read the same poses. A
    goal that preempts a fast motion towards the range's end (-50 deg) with a goal behind
    it cannot stop in time within the limits: rejected naming the crank's range, never
    planned round the wrong way."""
    cfg, mech, limits = trainer
    start_deg = -35.0
    p = coupler_point(cfg, start_deg * DEG)
    t = (coupler_point(cfg, (start_deg - 1e-4) * DEG) - p) / 1e-4 * DEG   # dP per deg, downwards
    v = 2.0 * t / np.linalg.norm(t)                                       # 2 m/s towards -50 deg
    with pytest.raises(PlanRejected, match='outside its range'):
        plan_motion(mech, p, coupler_point(cfg, 60 * DEG), 'minimum_jerk', limits, v0=v)


def test_velocity_and_acceleration_are_the_derivatives_of_the_poses(trainer):
    cfg, mech, limits = trainer
    home = np.asarray(cfg['mechanism']['home_pose'], float)
    plan = plan_motion(mech, home, coupler_point(cfg, -30 * DEG), 'minimum_jerk', limits)
    tr = plan.trajectory
    ts = np.linspace(0.02, plan.duration - 0.02, 40)
    h = 1e-6
    P1, V1, _ = tr.sample_many(ts + h)
    P0, V0, _ = tr.sample_many(ts - h)
    _, V, A = tr.sample_many(ts)
    np.testing.assert_allclose((P1 - P0) / (2 * h), V, atol=1e-6)
    np.testing.assert_allclose((V1 - V0) / (2 * h), A, atol=1e-4 * max(1.0, np.abs(A).max()))


def test_a_point_off_the_curve_is_still_rejected_with_its_distance(trainer):
    cfg, mech, limits = trainer
    home = np.asarray(cfg['mechanism']['home_pose'], float)
    off = coupler_point(cfg, 20 * DEG) + np.array([0.0, 0.01])
    with pytest.raises(PlanRejected, match='mm from the coupler curve'):
        plan_motion(mech, home, off, 'minimum_jerk', limits)


_FIRST_PLANS = r'''
import math, sys
from pathlib import Path
import numpy as np
sys.path.insert(0, {test!r})
from brace_control.config import load_device_config
from brace_control.mechanisms import mechanism_from_config
from brace_control.trajectory import Limits, load_planning_modules, plan_motion
from test_path_planning import coupler_point
config = Path({config!r})
plans = []
for name in ('upper_limb_trainer', 'lumbar_brace', 'continuum', 'shoulder'):
    cfg = load_device_config(config / (name + '.yaml'))
    mech = mechanism_from_config(cfg)
    limits = Limits.from_config(cfg, dof=mech.dof)
    home = np.asarray(cfg['mechanism']['home_pose'], float)
    plans.append((name, mech, limits, home))
load_planning_modules()
before = set(sys.modules)
for name, mech, limits, home in plans:
    if name == 'upper_limb_trainer':
        goal = coupler_point(load_device_config(config / (name + '.yaml')), 60 * math.pi / 180)
        plan_motion(mech, home, goal, 'minimum_jerk', limits)
        continue
    step = np.full(mech.dof, 0.005)
    plan_motion(mech, home, home + step, 'minimum_jerk', limits)
    plan_motion(mech, home, home + step, 'scurve', limits)
    plan_motion(mech, home, home, 'minimum_jerk', limits, via=[home + step], duration=2.0)
print(sorted(m for m in set(sys.modules) - before if m.startswith('scipy')))
'''


def test_planning_imports_nothing_after_the_planner_loaded_its_modules():
    """The trajectory node's planner imports :data:`PLANNING_MODULES` before its first goal,
    so that no goal's planning time (held to ``trajectory.planning_budget``) includes an
    import: the first goal on the curve imported ``scipy.interpolate`` while being planned
    (0.5 s here, 5.4 s on a loaded CI host, and it was rejected for it). In a fresh
    interpreter, planning on the curve, straight, as an S-curve and through a via point at the
    optimal time imports no scipy module after ``load_planning_modules()``."""
    import subprocess
    import sys
    here = Path(__file__).resolve().parent
    code = _FIRST_PLANS.format(test=str(here), config=str(CONFIG.parent))
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                         timeout=120, check=False)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().splitlines()[-1] == '[]', out.stdout
