#!/usr/bin/env python3
"""``brace-design`` timings (not a test): the optimiser, the study grid, the whole command.

    python bench/bench_design.py [--seeds 1 2 3] [--maxiter 200] [--popsize 15] [--out DIR]

Target: the optimisation (differential evolution, 200 generations x 180 layouts x 99 poses)
<= 60 s on the project's 2-core machine. Wall time and this process's CPU time are both
printed: the machine is shared, and wall time / CPU time says how much of the wall time
other processes took. One optimisation per seed (each seed's best smallest ``|Fx|`` shows
how repeatable the optimum is), then the five layouts on the study grid, then the whole
command (``brace_control.tools.design.main``, plots included) once with the first seed.
"""
from __future__ import annotations

import argparse
import contextlib
import io
import sys
import tempfile
import time
from pathlib import Path

from _timing import machine_line

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from brace_control.tools.design import (Task, alternative_layouts, evaluate_layout, main,  # noqa: E402
                                        optimise_layout)


def _timed(fn):
    w0, c0 = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - w0, time.process_time() - c0


def run(args: argparse.Namespace) -> int:
    print(machine_line())
    task = Task()
    print(f'task: {task.describe()}')
    print(f'optimiser: maxiter {args.maxiter}, population {args.popsize * 12}')
    print(' seed | wall s | cpu s | layouts | min |Fx| N | min |Fy| N | min |Mz| N·m | feasible')
    best = None
    for seed in args.seeds:
        res, wall, cpu = _timed(lambda: optimise_layout(task, seed=seed, maxiter=args.maxiter, popsize=args.popsize))
        c = res.min_capacity
        print(f' {seed:4d} | {wall:6.1f} | {cpu:5.1f} | {res.nfev:7d} | {c[0]:10.1f} | {c[1]:10.1f} | {c[2]:12.2f} | '
              f'{res.feasible}', flush=True)
        best = best or res
    layouts = alternative_layouts(task) + [best.layout]
    reports, wall, cpu = _timed(lambda: [evaluate_layout(lay, task) for lay in layouts])
    print(f'study grid ({reports[0].n_poses} poses) x {len(layouts)} layouts: wall {wall:.2f} s, cpu {cpu:.2f} s '
          f'({", ".join(f"{r.layout.name} {r.seconds * 1e3:.0f} ms" for r in reports)})')
    out = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix='bench_design_'))
    printed = io.StringIO()

    def whole() -> int:
        with contextlib.redirect_stdout(printed):
            return main(['lumbar_brace', '--out', str(out), '--seed', str(args.seeds[0]),
                         '--maxiter', str(args.maxiter), '--popsize', str(args.popsize)])
    rc, wall, cpu = _timed(whole)
    print('\n'.join(line for line in printed.getvalue().splitlines() if line.startswith(('optimiser:', 'study grid',
                                                                                        'grid check'))))
    print(f'brace-design (whole command, plots included): exit {rc}, wall {wall:.1f} s, cpu {cpu:.1f} s; '
          f'report in {out}')
    print(machine_line())
    return 0


def parse(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--seeds', type=int, nargs='+', default=[1])
    ap.add_argument('--maxiter', type=int, default=200)
    ap.add_argument('--popsize', type=int, default=15)
    ap.add_argument('--out', help='report directory of the whole-command run (default: a temporary one)')
    return ap.parse_args(argv)


if __name__ == '__main__':
    sys.exit(run(parse()))
