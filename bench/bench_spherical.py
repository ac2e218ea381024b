#!/usr/bin/env python3
"""Shoulder (spherical 3-RRR) and continuum robot benchmarks for issue 7 (not a test).

    python bench/bench_spherical.py [--fk-calls 2000] [--repeat 50] [--cont-calls 300]

Targets (issue 7): shoulder ``forward`` <= 1 ms per call; one design evaluation over the
1320 study poses <= 20 ms; continuum inverse time per call (no target).
"""
from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

import numpy as np
from _timing import machine_line, per_call_us, repeat_seconds
from _timing import summary_us as _summary_us

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from brace_control.mechanisms import load_mechanism  # noqa: E402
from brace_control.mechanisms.continuum import Continuum2  # noqa: E402,F401  (registers continuum2)
from brace_control.mechanisms.spherical import rotation_matrices  # noqa: E402
from brace_control.tools.spm_study import evaluate_design, motion_grid  # noqa: E402


def summary_us(s: list[float]) -> str:
    return _summary_us(s, width=8)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--fk-calls', type=int, default=2000)
    ap.add_argument('--repeat', type=int, default=50)
    ap.add_argument('--cont-calls', type=int, default=300)
    ap.add_argument('--seed', type=int, default=1)
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    print(machine_line())

    sh = load_mechanism(ROOT / 'config' / 'shoulder.yaml')
    poses = np.column_stack([rng.uniform(np.radians(lo), np.radians(hi), args.fk_calls)
                             for lo, hi in ((-10, 90), (-90, 20), (-40, 50))])
    qs, counts = [], []
    for p in poses:
        try:
            qs.append((sh.inverse(p),))
        except ValueError:
            pass
    print(f'shoulder inverse, one pose:            {summary_us(per_call_us(sh.inverse, [(p,) for p in poses]))}')
    print(f'shoulder forward (all modes), per call: {summary_us(per_call_us(sh.forward, qs))}')
    counts = np.bincount([len(sh.forward(q[0])) for q in qs[:500]])
    print(f'  assembly modes found over the first 500: {dict(enumerate(counts.tolist()))}')
    hints = [(q[0], p) for q, p in zip(qs, poses)]
    print(f'shoulder forward_nearest, per call:    {summary_us(per_call_us(sh.forward_nearest, hints))}')

    design = sh.design
    s_load = float(sh.load_forces @ sh.load_lever_arms)
    q_mats = rotation_matrices(motion_grid())
    ts = [1e3 * t for t in repeat_seconds(
        lambda: evaluate_design(design, working_mode=sh.working_mode, load_moment_nm=s_load, q_mats=q_mats),
        args.repeat)]
    r = evaluate_design(design, working_mode=sh.working_mode, load_moment_nm=s_load, q_mats=q_mats)
    print(f'design evaluation, 1320 poses:          median {statistics.median(ts):.2f} ms, '
          f'best {min(ts):.2f} ms (g1 {r.g1}, g2 {r.g2:.4f}, g3 {r.g3:.3f} N·m)')
    ts = [1e3 * t for t in repeat_seconds(
        lambda: evaluate_design(design, working_mode=sh.working_mode, load_moment_nm=s_load), args.repeat)]
    print(f'  same, including the 1320 rotation matrices: median {statistics.median(ts):.2f} ms')

    co = load_mechanism(ROOT / 'config' / 'continuum.yaml')
    lo, hi = co.height_range
    ys = rng.uniform(lo + 1e-4, hi - 1e-4, args.cont_calls)
    print(f'continuum inverse (height -> sliders):  {summary_us(per_call_us(co.inverse, [([0.0, y],) for y in ys]))}')
    qc = [(co.inverse([0.0, y]),) for y in ys]
    print(f'continuum forward (sliders -> pose):    {summary_us(per_call_us(co.forward, qc))}')
    print(f'continuum jacobian:                     '
          f'{summary_us(per_call_us(co.jacobian, [([0.0, y],) for y in ys[:100]]))}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
