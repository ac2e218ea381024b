"""Trajectory benchmarks (issue 3): setpoint cost, planning time, setpoint period jitter.

    ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST python bench/bench_trajectory.py [--seconds 5]

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
from brace_control.trajectory import (FittsLaw, GoalRequest, Limits, LogCosh, MinimumJerk,  # noqa: E402
                                      Profile, SCurve, TrajectoryRunner, ViaPointMinimumJerk,
                                      plan_motion)

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


def setpoint_costs(limits: Limits, mech) -> list[tuple[str, tuple[float, float], tuple[float, float]]]:
    trajs = {
        'minimum_jerk': MinimumJerk(HOME, GOAL, 2.0),
        'minimum_jerk via point': ViaPointMinimumJerk(HOME, VIA, GOAL, 2.0),
        'scurve (Ruckig)': SCurve(HOME, GOAL, limits.max_velocity, limits.max_acceleration, limits.max_jerk),
        'logcosh': LogCosh(HOME, GOAL, 2.0),
    }
    rows = []
    for name, tr in trajs.items():
        T = tr.duration
        sample = per_call_us(lambda i: tr.sample(T * (i % 1000) / 1000.0), 2000)
        profile = {'minimum_jerk': Profile.MINIMUM_JERK, 'scurve (Ruckig)': Profile.SCURVE,
                   'logcosh': Profile.LOGCOSH}.get(name, Profile.MINIMUM_JERK)
        run = TrajectoryRunner(mech, limits, profile=profile, fitts=FittsLaw())
        via = np.array([VIA]) if 'via' in name else None
        run.submit(GoalRequest('b', GOAL, via=via, t_via=[1.0] if via is not None else None,
                               duration=None if profile is Profile.SCURVE and via is None else 2.5), now=0.0)
        step = per_call_us(lambda i: run.step(2.0 * (i % 1000) / 1000.0), 2000)
        rows.append((name, sample, step))
    return rows


def planning_times(limits: Limits, mech) -> list[tuple[str, float, float, float]]:
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
        times = []
        for _ in range(15):
            t0 = time.perf_counter()
            plan = plan_motion(mech, HOME, GOAL, profile, limits, fitts=FittsLaw(), fitts_axes=(0, 1), **kw)
            times.append((time.perf_counter() - t0) * 1e3)
        rows.append((name, statistics.median(times), max(times), plan.duration))
    return rows


def jitter(rate_hz: float, seconds: float, goal_every: float) -> dict[str, float]:
    """Run trajectory_node in-process; a goal every ``goal_every`` s (planning in the
    worker thread meanwhile); periods from the setpoints' header stamps (taken at
    publication)."""
    import rclpy
    from geometry_msgs.msg import PoseStamped
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node

    from brace_control.nodes.ik_node import SETPOINT_QOS
    from brace_control.nodes.msgs import pose_msg, stamp_to_ns
    from brace_control.nodes.trajectory_node import GOAL_TOPIC, TrajectoryNode

    from brace_control.nodes.trajectory_node import GIL_SWITCH_INTERVAL_S
    sys.setswitchinterval(GIL_SWITCH_INTERVAL_S)        # as trajectory_node's main() does
    ctx = Context()
    rclpy.init(context=ctx)
    try:
        node = TrajectoryNode(context=ctx, cli_args=[
            '--ros-args', '--params-file', str(REPO / 'config' / 'lumbar_brace.yaml'),
            '-p', 'mechanism.home_pose:=[0.0, 0.39, 0.1]', '-p', f'trajectory.rate_hz:={rate_hz}'])
        client = Node('bench_client', context=ctx)
        stamps: list[int] = []
        client.create_subscription(PoseStamped, '/brace/pose_setpoint',
                                   lambda m: stamps.append(stamp_to_ns(m.header.stamp)), SETPOINT_QOS)
        pub = client.create_publisher(PoseStamped, GOAL_TOPIC, 10)
        ex = SingleThreadedExecutor(context=ctx)
        ex.add_node(node)
        ex.add_node(client)
        goals = [HOME + [0.03, 0.0, 0.08], HOME + [0.0, -0.005, 0.12], HOME + [0.02, 0.01, 0.05]]
        if goal_every > seconds:                  # one long motion: no planning while measured
            goals = [HOME + [0.03, 0.0, 0.08]]
        t_end = time.monotonic() + seconds
        next_goal, k = time.monotonic() + 0.5, 0
        while time.monotonic() < t_end:
            if time.monotonic() >= next_goal:
                pub.publish(pose_msg(goals[k % len(goals)], frame_id='brace_base'))
                k, next_goal = k + 1, next_goal + goal_every
            ex.spin_once(timeout_sec=0.001)
        node.shutdown()
        ex.shutdown()
        node.destroy_node()
        client.destroy_node()
    finally:
        rclpy.try_shutdown(context=ctx)
    p = np.diff(np.asarray(stamps, dtype=np.int64)) * 1e-6          # ms
    nominal = 1e3 / rate_hz
    return {'n': len(p), 'mean': p.mean(), 'std': p.std(), 'p99': np.percentile(p, 99),
            'max': p.max(), 'late': float(np.mean(p > 1.5 * nominal) * 100), 'nominal': nominal}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--seconds', type=float, default=5.0, help='jitter run per rate (s)')
    args = ap.parse_args()
    cfg = load_device_config(REPO / 'config' / 'lumbar_brace.yaml')
    cfg['mechanism']['home_pose'] = HOME.tolist()
    mech = mechanism_from_config(cfg)
    limits = Limits.from_config(cfg)

    print('## Trajectories (issue 3)\n')
    print(f'Run `--seconds {args.seconds:g}`: {platform.python_implementation()} '
          f'{platform.python_version()}, numpy {np.__version__}, {os.cpu_count()} cores shared '
          f'with other work (load average {os.getloadavg()[0]:.2f} at start), '
          f'{time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}. '
          'Lumbar brace geometry, home tilted to theta = 0.1 rad (the configured home is singular).\n')
    print('### Cost of one setpoint (best / median of 7 x 2000 calls)\n')
    print('| profile | `trajectory.sample(t)` (µs) | `TrajectoryRunner.step(now)` (µs) |')
    print('|---|---:|---:|')
    for name, s, st in setpoint_costs(limits, mech):
        print(f'| {name} | {s[0]:.1f} / {s[1]:.1f} | {st[0]:.1f} / {st[1]:.1f} |')
    print('\n### Planning a goal, limit check included (200 samples: IK, cond(J), '
          'det(J) sign, actuator speed and acceleration)\n')
    print('| goal | median (ms) | max of 15 (ms) | planned duration (s) |')
    print('|---|---:|---:|---:|')
    for name, med, mx, dur in planning_times(limits, mech):
        print(f'| {name} | {med:.1f} | {mx:.1f} | {dur:.3f} |')
    print('\n### Setpoint period (trajectory_node in-process with a subscriber, '
          'periods from the setpoint header stamps)\n')
    print('| rate | goals | setpoints | mean (ms) | std (ms) | p99 (ms) | max (ms) '
          '| periods > 1.5x nominal |')
    print('|---|---|---:|---:|---:|---:|---:|---:|')
    for rate in (200.0, 500.0):
        for every, label in ((1e9, 'one goal, no planning during the run'),
                             (1.5, 'a new goal every 1.5 s (preempting)')):
            j = jitter(rate, args.seconds, every)
            print(f'| {rate:g} Hz ({j["nominal"]:.1f} ms) | {label} | {j["n"]} | {j["mean"]:.3f} | '
                  f'{j["std"]:.3f} | {j["p99"]:.3f} | {j["max"]:.3f} | {j["late"]:.2f} % |')


if __name__ == '__main__':
    main()
