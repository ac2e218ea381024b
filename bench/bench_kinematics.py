#!/usr/bin/env python3
"""Kinematics benchmarks for issue 2 (not a test): IK throughput, FK time per call, workspace map.

    python bench/bench_kinematics.py [--ik-poses 1000000] [--fk-calls 5000] [--repeat 5]

Targets (issue 2): IK batch >= 1e6 poses/s; ``forward`` median <= 100 us (brace) and
<= 1 ms (general 3-RPR); the 0.1 deg, 0-30 deg, 1 mm workspace map <= 2 s.
"""
from __future__ import annotations

import argparse
import math
import statistics
import sys
from pathlib import Path

import numpy as np
from _timing import machine_line, per_call_us, repeat_seconds, summary_us

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from brace_control.mechanisms import Rpr3, load_mechanism  # noqa: E402
from brace_control.tools.workspace import workspace_map  # noqa: E402

CONFIG = Path(__file__).resolve().parent.parent / 'config' / 'lumbar_brace.yaml'


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--ik-poses', type=int, default=1_000_000)
    parser.add_argument('--fk-calls', type=int, default=5000)
    parser.add_argument('--repeat', type=int, default=5, help='repeats of the batch / map timings (best and median)')
    parser.add_argument('--seed', type=int, default=1)
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)

    print(machine_line())
    brace = load_mechanism(CONFIG)
    assert isinstance(brace, Rpr3)

    # ---- IK batch throughput
    n = args.ik_poses
    poses = np.column_stack([rng.uniform(-0.1, 0.1, n), rng.uniform(0.34, 0.44, n),
                             rng.uniform(-0.5, 0.5, n)])
    times = repeat_seconds(lambda: brace.inverse_batch(poses), args.repeat)
    print(f'IK inverse_batch, {n} poses: best {n / min(times) / 1e6:.2f} M poses/s, '
          f'median {n / statistics.median(times) / 1e6:.2f} M poses/s')
    times = repeat_seconds(lambda: brace.reachable_batch(poses), args.repeat)
    print(f'IK reachable_batch (lengths + stroke mask), {n} poses: '
          f'median {n / statistics.median(times) / 1e6:.2f} M poses/s')
    reachable = poses[:4 * args.fk_calls][brace.reachable_batch(poses[:4 * args.fk_calls])][:args.fk_calls]
    print('IK inverse (single pose, with stroke check): '
          + summary_us(per_call_us(brace.inverse, [(p,) for p in reachable])))

    # ---- FK, the brace (closed form)
    m = args.fk_calls
    cand = np.column_stack([rng.uniform(-0.3, 0.3, 20 * m), rng.uniform(0.0, 0.44, 20 * m),
                            rng.uniform(-math.radians(30), math.radians(30), 20 * m)])
    cand = cand[brace.reachable_batch(cand)][:m]
    qs = brace.inverse_batch(cand)
    fk_brace = per_call_us(brace.forward, [(q,) for q in qs])
    print(f'FK forward, lumbar brace (aligned closed form): {summary_us(fk_brace)}; '
          f'modes found: {np.bincount([len(brace.forward(q)) for q in qs[:500]]).tolist()} (count by 0..4, first 500)')
    print('FK forward_nearest, lumbar brace: '
          + summary_us(per_call_us(brace.forward_nearest, [(q, p) for q, p in zip(qs, cand)])))

    # ---- FK, general 3-RPR (sextic)
    general = Rpr3([[0.0, 0.0], [0.5, 0.0], [0.6, -0.4]], [[0.0, 0.0], [-0.4, 0.0], [-0.8, -0.7]], (0.0, 3.0),
                   home_pose=[0.0, 0.0, 0.0])
    gp = np.column_stack([rng.normal(0, 0.5, m), rng.normal(0, 0.5, m), rng.uniform(-math.pi, math.pi, m)])
    gq = general.inverse_batch(gp)
    fk_gen = per_call_us(general.forward, [(q,) for q in gq])
    counts = np.bincount([len(general.forward(q)) for q in gq[:500]], minlength=7).tolist()
    print(f'FK forward, general 3-RPR (sextic + verify): {summary_us(fk_gen)}; modes by 0..6 (first 500): {counts}')
    six = per_call_us(general.forward, [([1.06, 0.86, 1.28],)] * m)
    print(f'FK forward, general 3-RPR, six-mode case: {summary_us(six)}')

    # ---- workspace map
    theta = np.radians(0.1 * np.arange(301))
    lo, hi = brace.actuator_limits
    times = []
    for _ in range(args.repeat):
        ws = workspace_map(brace.base_anchors, brace.platform_anchors, lo, hi, theta, grid=0.001)
        times.append(ws.seconds)
    print(f'workspace map, 301 angles (0-30 deg, 0.1 deg), 1 mm grid ({ws.union.shape[1]} x {ws.union.shape[0]}): '
          f'best {min(times) * 1e3:.0f} ms, median {statistics.median(times) * 1e3:.0f} ms; '
          f'union {ws.union_area * 1e4:.1f} cm^2')
    return 0


if __name__ == '__main__':
    sys.exit(main())
