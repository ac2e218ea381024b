#!/usr/bin/env python3
"""Random goals across a device's workspace, through the whole stack, judged on the truth.

    python scripts/random_goals.py DEVICE [--goals N] [--seed S]

DEVICE is a name in config/ (lumbar_brace, neck_brace_4rpr, upper_limb_trainer, ...). All
nodes and the simulated brace run in this process (brace_control.bringup.BringUp, as
``brace-bringup`` without ``--processes``), homed and enabled. The goals are seeded:
* for a device with as many actuators as pose coordinates (or one crank), actuator values
  3-97 % of each stroke, mapped to a pose by the forward kinematics nearest home;
* for a redundant one (the 4-RPR), poses within +-80 mm, +-0.6 rad of home whose lengths
  stay 3-97 % of the stroke;
each kept when the mechanism calls it in its workspace and its inverse kinematics gives the
values back. Goals go one after the other on /brace/pose_goal. For each it prints how it
ended (/brace/goal_status), the reason, and the error of the simulator's TRUE pose
(/brace/sim/pose) against the goal, and flags a success whose truth is outside
safety.pose_tolerance, and a goal that never ended. A protective stop is relieved,
recovered and enabled again, as an operator would.

This is the check that found, in November 2026: goals on the trainer's return stroke
refused, a relief that crawled on rigid joints, a cable brace stuck after a relief, and
hard wrench stops where a soft tier belonged. Exit status 1 when a success was untrue or
a goal never ended.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')


def sample_goals(mech, n: int, seed: int) -> list[np.ndarray]:
    home = np.asarray(mech.home_pose, float)
    lo, hi = (np.asarray(v, float) for v in mech.actuator_limits)
    inner = lo + 0.03 * (hi - lo), hi - 0.03 * (hi - lo)
    rng = np.random.default_rng(seed)
    goals: list[np.ndarray] = []
    for _ in range(200 * n):
        if len(goals) == n:
            break
        try:
            if lo.size == home.size or lo.size == 1:
                q = rng.uniform(*inner)
                pose = np.asarray(mech.forward_nearest(q, home), float)
            else:
                pose = home + np.array([0.08, 0.08, 0.6][:home.size]) * rng.uniform(-1, 1, home.size)
                q = np.asarray(mech.inverse(pose), float)
                if np.any(q < inner[0]) or np.any(q > inner[1]):
                    continue
            if mech.in_workspace(pose) and np.max(np.abs(np.asarray(mech.inverse(pose), float) - q)) < 1e-6:
                goals.append(pose)
        except ValueError:
            continue
    return goals


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('device', help='a device file name in config/, without .yaml')
    ap.add_argument('--goals', type=int, default=10)
    ap.add_argument('--seed', type=int, default=1)
    ap.add_argument('--timeout', type=float, default=60.0, help='s a goal may take to end')
    args = ap.parse_args(argv)

    import rclpy
    from diagnostic_msgs.msg import DiagnosticStatus
    from geometry_msgs.msg import PoseStamped
    from rclpy.context import Context

    from brace_control.bringup import BringUp
    from brace_control.config import load_device_config
    from brace_control.demo import prepare_config
    from brace_control.mechanisms import mechanism_from_config
    from brace_control.nodes import topics
    from brace_control.nodes.msgs import pose_from_msg, pose_msg, status_values

    out = Path(tempfile.mkdtemp(prefix=f'random_goals_{args.device}_'))
    path, _ = prepare_config(str(ROOT / 'config' / f'{args.device}.yaml'), out)
    cfg = load_device_config(path)
    mech = mechanism_from_config(cfg)
    tol = np.asarray(cfg['safety']['pose_tolerance'], float)
    frame = str(cfg.get('base_frame'))
    goals = sample_goals(mech, args.goals, args.seed)
    print(f'{args.device}: {len(goals)} goals (seed {args.seed})', flush=True)

    ctx = Context()
    rclpy.init(context=ctx)
    lock = threading.Lock()
    ends: dict[str, dict] = {}
    truth: list[np.ndarray] = []
    driver: list[str] = []
    bad = 0
    b = BringUp(path, context=ctx, extra_args=['-p', f'can.channel:=random{os.getpid()}']).start()
    try:
        node = b.helper

        def on_status(msg: DiagnosticStatus) -> None:
            e = status_values(msg)
            if e.get('state') not in (None, 'accepted'):
                with lock:
                    ends.setdefault(e['goal_id'], e)

        def on_truth(msg: PoseStamped) -> None:
            with lock:
                truth.append(pose_from_msg(msg, mechanism=mech))

        node.create_subscription(DiagnosticStatus, topics.GOAL_STATUS, on_status, topics.STATUS_QOS)
        node.create_subscription(PoseStamped, topics.SIM_POSE, on_truth, 10)
        node.create_subscription(DiagnosticStatus, topics.DRIVER_STATE,
                                 lambda m: driver.append(m.message), topics.LATCHED_QOS)
        pub = node.create_publisher(PoseStamped, topics.POSE_GOAL, topics.GOAL_QOS)
        for what in ('home', 'enable'):
            ok, msg = b.call(f'/can_driver_node/{what}', timeout=15)
            if not ok:
                print(f'{what}: {msg}')
                return 2
        for i, goal in enumerate(goals, start=1):
            t0 = time.monotonic()
            pub.publish(pose_msg(goal, frame_id=frame, mechanism=mech, stamp=node.get_clock().now().to_msg()))
            while str(i) not in ends and time.monotonic() - t0 < args.timeout:
                time.sleep(0.05)
            time.sleep(0.3)
            with lock:
                end = ends.get(str(i))
                err = np.abs(truth[-1] - goal) if truth else None
            state = end['state'] if end else f'NO END within {args.timeout:g} s'
            flag = ''
            if end is None or (state == 'succeeded' and err is not None and np.any(err > tol)):
                flag = '  <<< UNTRUE SUCCESS' if end else '  <<< LOST'
                bad += 1
            print(f'{i:3d} {np.round(goal, 4).tolist()} {state} after {time.monotonic() - t0:.1f} s, '
                  f'true error {None if err is None else np.round(err, 4).tolist()}'
                  f'{": " + end["reason"][:200] if end and end.get("reason") else ""}{flag}', flush=True)
            if driver and driver[-1].startswith('protective stop'):
                for what in ('relieve', 'recover', 'enable'):
                    ok, msg = b.call(f'/can_driver_node/{what}', timeout=60)
                    print(f'    {what}: {ok} {msg[:200]}', flush=True)
    finally:
        b.shutdown()
        rclpy.shutdown(context=ctx)
    return 1 if bad else 0


if __name__ == '__main__':
    raise SystemExit(main())
