"""The load tiers in the SYNC cycle (brace_control/safety, issue 25): reaction and cost.

    PYTHONPATH=$PWD .venv/bin/python bench/bench_safety_tiers.py [--trials 8]

* a wrench step to the latch: three load cells of the simulated lumbar brace to 120 N at
  once (together above ``safety.max_wrench``), counted in SYNCs sent between the step and
  the latch, ``--trials`` times;
* the trainer's crank against the arm: a 0.6 s reach from crank 90° to 10° (the arm a
  300 N/m spring), where it was braked, the TRUE crank torque's peak, whether anything
  latched, then a reach to 60°; three times;
* the cost of one ``WrenchTiers.check`` per device, at rest (the pose cached) and with a
  forward solution; and of the whole per-cycle load check in the lumbar rig at rest.

Uses the rigs of test/test_safety_tiers.py (the same master and simulator the tests drive).
"""
from __future__ import annotations

import argparse
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path[:0] = [str(ROOT), str(ROOT / 'test')]
os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')

from brace_control.can import FaultKind  # noqa: E402
from brace_control.config import load_device_config, resolve_device_file  # noqa: E402
from brace_control.mechanisms import mechanism_from_config  # noqa: E402
from brace_control.mechanisms.planar_floats import PlanarRprFloats  # noqa: E402
from brace_control.safety import PlatformWrench, WrenchTiers  # noqa: E402
import test_safety_tiers as rigs  # noqa: E402


def wrench_step(trials: int) -> list[int]:
    out = []
    for _ in range(trials):
        sim, master = rigs._rig('lumbar_brace')
        try:
            seen: list[int] = []
            react = master.supervisor._on_fault

            def on_fault(fault, seen=seen, master=master, react=react):
                seen.append(master.clock.index)
                react(fault)
            master.supervisor._on_fault = on_fault
            k0 = master.clock.index
            for node_id in (1, 2, 3):
                sim.faults.set_load_cell(node_id, 120.0)
            rigs.wait_for(lambda: master.supervisor.has(FaultKind.WRENCH_LIMIT), 2.0, 'the wrench stop')
            out.append(seen[0] - k0)
        finally:
            master.shutdown()
            sim.shutdown()
    return out


def trainer(trials: int) -> None:
    for _ in range(trials):
        sim, master = rigs._rig('upper_limb_trainer')
        try:
            events, peak = rigs._crank_goal(master, sim, math.radians(10.0), 0.6)
            at = math.degrees(float(sim.truth().lengths[0]))
            latched = master.supervisor.latched
            events2, peak2 = rigs._crank_goal(master, sim, math.radians(60.0), 0.6)
            print(f'  crank 10 deg: {events[-1].kind} at {at:.1f} deg, TRUE peak {peak:.2f} N·m, '
                  f'latched {latched}; then 60 deg: {events2[-1].kind} (peak {peak2:.2f} N·m)')
            print(f'    {events[-1].reason}')
        finally:
            master.shutdown()
            sim.shutdown()


def cost() -> None:
    for device in ('lumbar_brace', 'upper_limb_trainer', 'neck_brace_3rrr', 'shoulder', 'continuum'):
        mech = mechanism_from_config(load_device_config(resolve_device_file(device)))
        tiers = WrenchTiers(PlatformWrench(mech, legs=PlanarRprFloats.of(mech)), [1e9] * 3)
        q = np.asarray(mech.inverse(mech.home_pose), float)
        f = np.ones(mech.n_actuators)
        best_rest = best_fk = math.inf
        for rep in range(5):
            t0 = time.perf_counter()
            for k in range(400):
                tiers.check(rep * 10.0 + k * 0.002, q, f, lambda: None)
            best_rest = min(best_rest, (time.perf_counter() - t0) / 400)
            t0 = time.perf_counter()
            for k in range(20):       # a new q, far enough apart in time: solved every call
                tiers.check(1000.0 + rep * 100.0 + k, q + 1e-7 * ((k % 2) + 1), f, lambda: None)
            best_fk = min(best_fk, (time.perf_counter() - t0) / 20)
        print(f'  {device:20s} at rest {best_rest * 1e6:7.1f} us   with a forward solution '
              f'{best_fk * 1e6:7.0f} us')


def in_cycle(seconds: float = 3.0) -> None:
    """The whole per-cycle load check (``Monitors.monitor_loads``) in the lumbar rig, enabled, at rest."""
    sim, master = rigs._rig('lumbar_brace')
    took: list[float] = []
    inner = master.monitors.monitor_loads

    def timed(now, tracking):
        t0 = time.perf_counter()
        inner(now, tracking)
        took.append(time.perf_counter() - t0)
    master.monitors.monitor_loads = timed
    try:
        time.sleep(seconds)                 # the SYNC thread runs the cycles meanwhile
    finally:
        master.shutdown()
        sim.shutdown()
    us = np.array(took) * 1e6
    print(f'  {us.size} cycles: median {np.median(us):.0f} us, p99 {np.percentile(us, 99):.0f} us, '
          f'max {us.max():.0f} us')


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--trials', type=int, default=8)
    args = ap.parse_args()
    print('wrench step -> latch, SYNCs:', wrench_step(args.trials))
    print('trainer crank against the arm:')
    trainer(3)
    print('WrenchTiers.check per sample (best of 5 x 400 / 5 x 20):')
    cost()
    print('the load checks of one SYNC cycle, lumbar brace at rest, 3 s:')
    in_cycle()


if __name__ == '__main__':
    main()
