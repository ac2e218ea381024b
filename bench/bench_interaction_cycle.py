"""The per-cycle cost of the in-loop admittance (brace_control/interaction/inloop.py), per device.

    PYTHONPATH=$PWD .venv/bin/python bench/bench_interaction_cycle.py [--updates 2000] [--seed 1]

For every bundled device with an ``interaction`` section: the driver's source
(:class:`~brace_control.interaction.inloop.InLoopAdmittance`, built as can_driver_node
builds it) starts at the home pose and runs ``--updates`` admittance updates fed with
load-cell forces of the device's simulated trunk (``sim.stiffness`` about a rest pose
swaying 2 mm / 1 deg at 0.5 Hz about home, plus 1 % noise, seeded), so every update does
the full work: the wrench ``J^T f``, equation (2), the look-ahead limit checks (stroke, singularity, capacity at the braking pose),
the acceleration scale, ``IK`` and ``J v``. An update that starts a limit stop restarts
the mode at home (the stop's periods are cheaper and are not what the budget is for).

Printed per device: the kinematics used (plain-float planar or the numpy model), the
update's median / 95th percentile / max (us), the SYNC period and the admittance period.
One update runs every ``n = round(sync_rate_hz / interaction.rate_hz)`` SYNCs, within one
SYNC period (with the rest of the cycle): the SYNC period is its budget; the SYNCs in
between carry only the cubic Hermite (microseconds).
"""
from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _timing import machine_line  # noqa: E402

from brace_control.config import load_device_config  # noqa: E402
from brace_control.interaction import AdmittanceParams  # noqa: E402
from brace_control.interaction.inloop import InLoopAdmittance  # noqa: E402
from brace_control.mechanisms import mechanism_from_config  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent


def forces_for(mech, pose: np.ndarray, wrench: np.ndarray) -> np.ndarray:
    """Actuator forces whose wrench (the mechanism's ``wrench(pose, f)``, linear in ``f``)
    is ``wrench`` (least squares)."""
    n = int(mech.n_actuators)
    G = np.column_stack([np.asarray(mech.wrench(pose, np.eye(n)[j]), dtype=float) for j in range(n)])
    return np.linalg.lstsq(G, wrench, rcond=None)[0]


def bench_device(path: Path, updates: int, rng: np.random.Generator) -> dict[str, object] | None:
    cfg = load_device_config(path)
    if 'interaction' not in cfg:
        return None
    mech = mechanism_from_config(cfg)
    params = AdmittanceParams.from_config(cfg, mech)
    period = 1.0 / float(cfg['can']['sync_rate_hz'])
    a_max = float(np.max(np.atleast_1d(cfg['actuator']['max_acceleration'])))
    src = InLoopAdmittance(mech, params, sync_period=period, a_max=a_max)
    home = np.asarray(mech.home_pose, dtype=float)
    q0 = np.asarray(mech.inverse(home), dtype=float)
    src.begin(q0, np.zeros_like(q0))
    dof = int(mech.dof)
    K = np.diag(np.reshape(np.asarray(cfg['sim']['stiffness'], dtype=float), (dof, dof)))
    # the trunk sways about home (2 mm or 1 deg per force axis, 0.5 Hz at the update rate)
    amp = np.where(np.asarray(mech.wrench_axes if hasattr(mech, 'wrench_axes') else ['F'] * dof)
                   .astype(str).astype('U1') == 'M', math.radians(1.0), 0.002)[:dof] * params.force_axes
    times: list[float] = []
    restarts = 0
    clock = time.perf_counter
    for k in range(updates):
        rest = home + amp * math.sin(2.0 * math.pi * 0.5 * k * src.dt)
        w = K * (src.controller.x - rest) + 0.01 * K * amp * rng.standard_normal(dof)
        try:
            f = forces_for(mech, src.controller.x, w)
        except ValueError:
            f = np.zeros(int(mech.n_actuators))
        t0 = clock()
        src.update(f)
        times.append((clock() - t0) * 1e6)
        if src.mode.value != 'active':
            restarts += 1
            src.controller.mode = src.controller.mode.IDLE
            src.begin(q0, np.zeros_like(q0))
    times.sort()
    return {'device': path.stem, 'kinematics': type(src.kin).__name__,
            'median': statistics.median(times), 'p95': times[int(0.95 * len(times))],
            'max': times[-1], 'sync_ms': period * 1e3, 'n_syncs': src.n_syncs,
            'period_ms': src.dt * 1e3, 'restarts': restarts}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--updates', type=int, default=2000)
    ap.add_argument('--seed', type=int, default=1)
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    print(machine_line())
    print('| device | kinematics | update median us | p95 | max | SYNC ms | syncs per update | '
          'admittance period ms | median / SYNC period | p95 / SYNC period | limit restarts |')
    print('|---|---|---|---|---|---|---|---|---|---|---|')
    for path in sorted((ROOT / 'config').glob('*.yaml')):
        row = bench_device(path, args.updates, rng)
        if row is None:
            continue
        print(f"| {row['device']} | {row['kinematics']} | {row['median']:.0f} | {row['p95']:.0f} | "
              f"{row['max']:.0f} | {row['sync_ms']:.1f} | {row['n_syncs']} | {row['period_ms']:.1f} | "
              f"{row['median'] / (row['sync_ms'] * 1e3):.0%} | {row['p95'] / (row['sync_ms'] * 1e3):.0%} | "
              f"{row['restarts']} |")
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
