#!/usr/bin/env python3
"""Batch kinematics and wrench capacity per device (not a test): ``inverse_batch``,
``jacobian_batch`` and ``wrench_capacity_batch`` on N reachable poses, against the scalar loop.

    python bench/bench_batch.py [--sizes 300 3000] [--repeat 20] [--seed 1]

Target: IK + Jacobian of 300 poses <= 1 ms for the lumbar brace, well under 5 ms for
every device (the continuum's elastica measured and reported). The poses: seeded random
samples of each device's workspace kept where ``inverse_batch`` is finite (the four-bar's
on its coupler curve; a second four-bar row is the projection path, points 0.3 mm off
the curve). Times: best and median of ``--repeat`` runs (ms).
"""
from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from _timing import machine_line, repeat_seconds

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from brace_control.config import load_device_config  # noqa: E402
from brace_control.mechanisms import mechanism_from_config  # noqa: E402


def _planar(home: np.ndarray, dx: float, dth: float) -> Callable[[np.random.Generator, int], np.ndarray]:
    def sample(rng: np.random.Generator, n: int) -> np.ndarray:
        return home + np.column_stack([rng.uniform(-dx, dx, n), rng.uniform(-dx, dx, n), rng.uniform(-dth, dth, n)])
    return sample


def samplers(mech: Any, name: str) -> dict[str, Callable[[np.random.Generator, int], np.ndarray]]:
    """Candidate poses per device (filtered to reachable by the caller)."""
    home = mech.home_pose
    if name == 'lumbar_brace':
        return {'': _planar(home, 0.05, math.radians(25.0))}
    if name == 'neck_brace_4rpr':
        return {'': _planar(home, 0.06, 0.4)}
    if name == 'neck_brace_3rrr':
        return {'': _planar(home, 0.04, 0.5)}
    if name == 'neck_brace_2r':
        return {'': lambda rng, n: home + rng.uniform(-0.08, 0.08, (n, 2))}
    if name == 'shoulder':
        return {'': lambda rng, n: np.column_stack([rng.uniform(-0.17, 1.57, n), rng.uniform(-1.57, 0.35, n),
                                                    rng.uniform(-0.7, 0.87, n)])}
    if name == 'continuum':
        return {'': lambda rng, n: np.column_stack([rng.uniform(-0.05, 0.05, n), rng.uniform(0.03, 0.18, n)])}
    if name == 'upper_limb_trainer':
        lo, hi = mech.actuator_limits

        def on_curve(rng: np.random.Generator, n: int) -> np.ndarray:
            th = rng.uniform(lo[0], hi[0], n)
            p = mech.position_analysis(th)['P']
            return np.column_stack([p.real, p.imag])

        def near_curve(rng: np.random.Generator, n: int) -> np.ndarray:
            p = on_curve(rng, n)
            ang = rng.uniform(0.0, 2.0 * math.pi, n)
            return p + 3e-4 * np.column_stack([np.cos(ang), np.sin(ang)])
        return {' (on curve)': on_curve, ' (0.3 mm off, projected)': near_curve}
    raise ValueError(f'no pose sampler for {name}')


def reachable_poses(mech: Any, sample: Callable[[np.random.Generator, int], np.ndarray],
                    rng: np.random.Generator, n: int) -> np.ndarray:
    out = np.empty((0, mech.dof))
    while out.shape[0] < n:
        cand = sample(rng, 4 * n)
        out = np.vstack([out, cand[~np.isnan(mech.inverse_batch(cand)).any(axis=1)]])
    return out[:n]


def best_median_ms(fn: Callable[[], Any], repeat: int) -> str:
    t = repeat_seconds(fn, repeat)
    return f'{min(t) * 1e3:.3f} / {statistics.median(t) * 1e3:.3f}'


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--sizes', type=int, nargs='+', default=[300, 3000])
    ap.add_argument('--repeat', type=int, default=20)
    ap.add_argument('--seed', type=int, default=1)
    args = ap.parse_args()
    print(machine_line())
    devices = ['lumbar_brace', 'neck_brace_4rpr', 'neck_brace_3rrr', 'neck_brace_2r', 'shoulder',
               'upper_limb_trainer', 'continuum']
    print('| device | N | IK | J | IK + J | capacity | scalar loop IK + J |')
    print('|---|---|---|---|---|---|---|')
    for name in devices:
        cfg = load_device_config(ROOT / 'config' / f'{name}.yaml')
        mech = mechanism_from_config(cfg)
        limit = float(cfg.get_path('actuator.max_force'))
        for label, sample in samplers(mech, name).items():
            rng = np.random.default_rng(args.seed)
            for n in args.sizes:
                poses = reachable_poses(mech, sample, rng, n)
                ik = best_median_ms(lambda: mech.inverse_batch(poses), args.repeat)
                jac = best_median_ms(lambda: mech.jacobian_batch(poses), args.repeat)
                both = best_median_ms(lambda: (mech.inverse_batch(poses), mech.jacobian_batch(poses)), args.repeat)
                cap = best_median_ms(lambda: mech.wrench_capacity_batch(poses, limit), max(3, args.repeat // 4))
                if n <= 300:
                    t0 = time.perf_counter()
                    for p in poses:
                        mech.inverse(p)
                        mech.jacobian(p)
                    loop = f'{(time.perf_counter() - t0) * 1e3:.1f}'
                else:
                    loop = '-'
                print(f'| {name}{label} | {n} | {ik} | {jac} | {both} | {cap} | {loop} |', flush=True)
    print('(times in ms, best / median; capacity with actuator.max_force of each YAML; '
          'the scalar loop once, N = 300 only)')
    return 0


if __name__ == '__main__':
    sys.exit(main())
