"""Drives nobody here wrote: the lumbar brace's boot planned against each dictionary given.

    python bench/bench_dictionaries.py [EDS_OR_DCF ...] [--move]

For each file (default: every EDS/DCF in ``test/data/eds/``), the lumbar brace
(``config/lumbar_brace.yaml``) with ``can.eds`` set to it, two ways: the load cells on the
drives (``can.load_cell_object`` left as the YAML has it, 2401h) and on a CiA 401 module
(``can.load_cell_node``, ``config/analog_input_module.eds``). Prints a Markdown table: planned
(with the count of SDO writes and of warnings) or refused (the reason, shortened), and the
time the plan took. With ``--move``, each planned case boots, homes, enables and lifts the ring
6 mm on drives simulated from the same file; the oracle is the simulator's true leg lengths
(within 2 um of the goal's inverse kinematics) and no protective stop.
"""
from __future__ import annotations

import argparse
import copy
import itertools
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from brace_control.can import ActuatorTrajectory, BraceMaster, MasterConfig  # noqa: E402
from brace_control.can.errors import DriverError  # noqa: E402
from brace_control.config import DeviceConfig, load_device_config  # noqa: E402
from brace_control.mechanisms import mechanism_from_config  # noqa: E402
from brace_control.sim import SimulatedBrace  # noqa: E402

BASE = load_device_config(ROOT / 'config' / 'lumbar_brace.yaml')
MECH = mechanism_from_config(BASE)
MODULE = {'node_id': 10, 'eds': str(ROOT / 'config' / 'analog_input_module.eds')}
_ids = itertools.count()


def config(**can_params) -> DeviceConfig:
    params = copy.deepcopy(dict(BASE))
    params['can'].update(can_params)
    return DeviceConfig(params, BASE.path)


def move(cfg: DeviceConfig) -> str:
    """Boot, home, enable and a 6 mm lift on drives simulated from the file: 'moved' or why not."""
    channel = f'dictbench-{os.getpid()}-{next(_ids)}'
    sim = SimulatedBrace(cfg, channel=channel)
    master = BraceMaster(MasterConfig.from_device_config(cfg, channel=channel))
    try:
        master.boot()
        master.home()
        master.enable()
        q0 = MECH.inverse(MECH.home_pose)
        q1 = MECH.inverse(MECH.home_pose + np.array([0.0, 0.006, 0.0]))
        t = np.linspace(0.0, 0.8, 33)
        s = t / 0.8
        p = 10 * s ** 3 - 15 * s ** 4 + 6 * s ** 5
        v = (30 * s ** 2 - 60 * s ** 3 + 30 * s ** 4) / 0.8
        a = (60 * s - 180 * s ** 2 + 120 * s ** 3) / 0.64
        reason = master.execute(ActuatorTrajectory(t, q0 + np.outer(p, q1 - q0), np.outer(v, q1 - q0),
                                                   np.outer(a, q1 - q0)), start=time.perf_counter() + 0.05, tag=1)
        if reason:
            return f'refused the motion: {reason}'
        end = time.monotonic() + 5.0
        while (master.moving or np.abs(sim.truth().lengths - q1).max() > 2e-6) and time.monotonic() < end:
            if master.supervisor.latched:
                return f'protective stop: {master.supervisor.summary()}'
            time.sleep(0.01)
        err = np.abs(sim.truth().lengths - q1).max()
        return 'moved' if err <= 2e-6 else f'ended {err * 1e6:.1f} um from the goal'
    except DriverError as exc:
        return f'{type(exc).__name__}: {exc}'
    finally:
        master.shutdown()
        sim.shutdown()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('files', nargs='*', type=Path)
    ap.add_argument('--move', action='store_true', help='boot and move on drives simulated from each file')
    args = ap.parse_args()
    files = args.files or sorted(p for p in (ROOT / 'test' / 'data' / 'eds').iterdir()
                                 if p.suffix.lower() in ('.eds', '.dcf'))
    print('| file | load cells | plan | ms | ' + ('motion |' if args.move else ''))
    print('|---|---|---|---:|' + ('---|' if args.move else ''))
    for path in files:
        for where, extra in (('on the drives', {}), ('CiA 401 module', {'load_cell_node': MODULE})):
            cfg = config(eds=str(path.resolve()), **extra)
            master = BraceMaster(MasterConfig.from_device_config(cfg, channel='unused'))
            t0 = time.perf_counter()
            try:
                plans = master.plan()
            except DriverError as exc:
                ms = (time.perf_counter() - t0) * 1e3
                text = str(exc).split('cannot drive the brace: ', 1)[-1].split('cannot carry the load cells: ', 1)[-1]
                text = text.split('. Nothing was sent')[0].replace('|', '/')
                print(f'| {path.name} | {where} | refused: {text[:220]}{"..." if len(text) > 220 else ""} '
                      f'| {ms:.0f} |' + (' - |' if args.move else ''))
                continue
            ms = (time.perf_counter() - t0) * 1e3
            writes = sum(len(p.writes) + len(p.mapping) for p in plans)
            warnings = sum(len(p.warnings) for p in plans)
            row = f'| {path.name} | {where} | planned: {writes} SDO writes, {warnings} warnings | {ms:.0f} |'
            if args.move:
                row += f' {move(cfg)[:200]} |'
            print(row)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
