"""The control cycle's process alone: SYNC overruns and CPU per thread, by scheduling and load.

    python bench/bench_cycle_process.py [--seconds 15] [--burners 2] [--motion]
        [--priority 50] [--nice -10] [--switch-interval-us 200]

A :class:`~brace_control.can.process.MasterProcess` (the lumbar brace's master and simulated
brace in a child process, as ``can_driver_node`` starts it; no ROS at all), booted, homed
and enabled; ``--priority`` / ``--nice`` set ``can.cycle_priority`` / ``can.cycle_nice``
(0 0: normal scheduling). Over ``--seconds``, at rest or (``--motion``) with 1 s
minimum-jerk moves of every leg between the home lengths and +10 mm: the SYNC cycles,
overruns, period error p99 and max (the master's own statistics), and the CPU of each of the
child's threads (their OS names). ``--burners N`` runs N busy-loop processes meanwhile.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / 'bench'))
sys.path.insert(0, str(ROOT / 'test'))

from _timing import machine_line  # noqa: E402
from bench_stack import thread_cpu  # noqa: E402
from rpr_oracles import min_jerk  # noqa: E402

from brace_control.can import ActuatorTrajectory, MasterConfig  # noqa: E402
from brace_control.can.process import MasterProcess  # noqa: E402
from brace_control.config import load_device_config  # noqa: E402
from brace_control.mechanisms import mechanism_from_config  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--seconds', type=float, default=15.0)
    ap.add_argument('--burners', type=int, default=0)
    ap.add_argument('--motion', action='store_true')
    ap.add_argument('--priority', type=int, default=None, help='can.cycle_priority (YAML: 50)')
    ap.add_argument('--nice', type=int, default=None, help='can.cycle_nice (YAML: -10)')
    ap.add_argument('--switch-interval-us', type=int, default=None, help='can.gil_switch_interval_us')
    args = ap.parse_args()
    cfg = load_device_config('lumbar_brace')
    for key, value in (('cycle_priority', args.priority), ('cycle_nice', args.nice),
                       ('gil_switch_interval_us', args.switch_interval_us)):
        if value is not None:
            cfg['can'][key] = value
    config = MasterConfig.from_device_config(cfg, mechanism=mechanism_from_config(cfg),
                                             channel=f'bench_cycle{os.getpid()}')
    burners = [subprocess.Popen([sys.executable, '-c', 'while True: pass']) for _ in range(args.burners)]
    try:
        with MasterProcess(cfg, config) as mp:
            mp.boot()
            mp.home()
            mp.enable()
            time.sleep(1.0)
            home = np.asarray(mp.feedback().position, float)
            cpu0, t0 = thread_cpu(mp.pid), time.monotonic()
            s0 = mp.status().timing
            k = 0
            while time.monotonic() - t0 < args.seconds:
                if args.motion:
                    start = np.asarray(mp.feedback().position, float)
                    t, q, v, a = min_jerk(start, home + (0.01 if k % 2 == 0 else 0.0), 1.0, 101)
                    mp.execute(ActuatorTrajectory(t, q, v, a), start=time.perf_counter() + 0.02, tag=k + 1)
                    k += 1
                time.sleep(1.1)
            cpu1, dt = thread_cpu(mp.pid), time.monotonic() - t0
            s1 = mp.status().timing
    finally:
        for b in burners:
            b.kill()
            b.wait()
    cycles, overruns = s1.cycles - s0.cycles, s1.overruns - s0.overruns
    print(machine_line())
    print(f'{"motion" if args.motion else "rest"}, {args.burners} burner(s), can.cycle_priority '
          f'{cfg["can"]["cycle_priority"]}, can.cycle_nice {cfg["can"]["cycle_nice"]}, GIL switch '
          f'{cfg["can"]["gil_switch_interval_us"]} us: {cycles} SYNCs, {overruns} overruns '
          f'({100.0 * overruns / max(cycles, 1):.2f} %), period error p99 {s1.p99 * 1e6:.0f} us, '
          f'max {s1.max * 1e6:.0f} us (last 5000 SYNCs)')
    print('threads (% of one core): ' + ', '.join(
        f'{name} {100.0 * (sec - cpu0.get(name, 0.0)) / dt:.1f}' for name, sec in sorted(cpu1.items())))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
