"""Trajectory benchmarks (issue 3): sampling cost, planning time.

    python bench/bench_trajectory.py

Runs on the lumbar brace's geometry (config/lumbar_brace.yaml) with the home pose
tilted to theta = 0.1 rad (the configured home, theta = 0, is singular for the
collinear 3-RPR: every goal from it is rejected). Prints a Markdown section for
bench/RESULTS.md.
"""
from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from brace_control.config import load_device_config  # noqa: E402
from brace_control.mechanisms import mechanism_from_config  # noqa: E402
from brace_control.trajectory import (FittsLaw, Limits, LogCosh, MinimumJerk, Profile,  # noqa: E402
                                      SCurve, ViaPointMinimumJerk, plan_motion)
from brace_control.trajectory.limits import executed_actuator_motion  # noqa: E402

HOME = np.array([0.0, 0.39, 0.1])
GOAL = HOME + [0.03, 0.0, 0.08]
VIA = HOME + [0.015, 0.01, 0.03]


def per_call_us(fn, n: int) -> tuple[float, float]:
    """Best and median of 7 runs of ``n`` calls, in µs per call (best: least disturbed
    by the other jobs on the machine)."""
    runs = []
    for _ in range(7):
        t0 = time.perf_counter()
        for i in range(n):
            fn(i)
        runs.append((time.perf_counter() - t0) / n * 1e6)
    return min(runs), statistics.median(runs)


def sample_costs(limits: Limits) -> list[tuple[str, tuple[float, float]]]:
    trajs = {
        'minimum_jerk': MinimumJerk(HOME, GOAL, 2.0),
        'minimum_jerk via point': ViaPointMinimumJerk(HOME, VIA, GOAL, 2.0),
        'scurve (Ruckig)': SCurve(HOME, GOAL, limits.max_velocity, limits.max_acceleration, limits.max_jerk),
        'logcosh': LogCosh(HOME, GOAL, 2.0),
    }
    rows = []
    for name, tr in trajs.items():
        T = tr.duration
        rows.append((name, per_call_us(lambda i: tr.sample(T * (i % 1000) / 1000.0), 2000)))
    return rows


def planning_times(limits: Limits, mech) -> list[tuple[str, float, float, float, float]]:
    cases = {
        'minimum_jerk, Fitts duration (stretched)': dict(profile=Profile.MINIMUM_JERK),
        'minimum_jerk, 3 s': dict(profile=Profile.MINIMUM_JERK, duration=3.0),
        'scurve (Ruckig), time-optimal': dict(profile=Profile.SCURVE),
        'logcosh, 3 s': dict(profile=Profile.LOGCOSH, duration=3.0),
        'via point, t1 optimised, 3 s': dict(profile=Profile.MINIMUM_JERK, duration=3.0, via=[VIA]),
        'via point, t1 given, 3 s': dict(profile=Profile.MINIMUM_JERK, duration=3.0, via=[VIA], t_via=[1.2]),
    }
    rows = []
    for name, kw in cases.items():
        profile = kw.pop('profile')
        times, motion = [], []
        for _ in range(15):
            t0 = time.perf_counter()
            plan = plan_motion(mech, HOME, GOAL, profile, limits, fitts=FittsLaw(), fitts_axes=(0, 1), **kw)
            t1 = time.perf_counter()
            executed_actuator_motion(mech, plan.trajectory)
            times.append((t1 - t0) * 1e3)
            motion.append((time.perf_counter() - t1) * 1e3)
        rows.append((name, statistics.median(times), max(times), statistics.median(motion), plan.duration))
    return rows


def main() -> None:
    argparse.ArgumentParser(description=__doc__.split('\n\n')[0]).parse_args()
    cfg = load_device_config(REPO / 'config' / 'lumbar_brace.yaml')
    cfg['mechanism']['home_pose'] = HOME.tolist()
    mech = mechanism_from_config(cfg)
    limits = Limits.from_config(cfg)

    print('## Trajectories (issue 3)\n')
    print(f'{platform.python_implementation()} {platform.python_version()}, numpy {np.__version__}, '
          f'{os.cpu_count()} cores shared with other work (load average {os.getloadavg()[0]:.2f} at '
          f'start), {time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}. Lumbar brace geometry, '
          'home tilted to theta = 0.1 rad (the configured home is singular).\n')
    print('### Cost of one sample (best / median of 7 x 2000 calls)\n')
    print('| profile | `trajectory.sample(t)` (µs) |')
    print('|---|---:|')
    for name, s in sample_costs(limits):
        print(f'| {name} | {s[0]:.1f} / {s[1]:.1f} |')
    print('\n### Planning a goal, limit check included (200 path samples: IK, cond(J), det(J) sign; '
          'the actuator speed and acceleration of the knots ik_node makes, as the driver checks them)\n')
    print('| goal | median (ms) | max of 15 (ms) | of which one actuator-motion check (median ms) '
          '| planned duration (s) |')
    print('|---|---:|---:|---:|---:|')
    for name, med, mx, motion, dur in planning_times(limits, mech):
        print(f'| {name} | {med:.1f} | {mx:.1f} | {motion:.1f} | {dur:.3f} |')


if __name__ == '__main__':
    main()
