#!/usr/bin/env python3
"""Cost of one load-aware pose estimate (issue 12): what kinetics_node spends per joint state.

    python bench/bench_pose_estimate.py [--samples 2000] [--devices lumbar_brace continuum ...]

Per device: a slow sway about the home pose (a few mm and a few degrees, one cycle in 4 s,
the speed of the bundled exercises) sampled at 100 Hz like /brace/joint_states; encoder
lengths quantised to the encoder count, efforts = a constant load plus the YAML's load-cell
noise, lengths q = l(p) + F / k. Timed: ``PoseEstimator.update`` per joint state while
moving, and at rest (the same pose, new noise), next to the old encoder-only
``forward_nearest`` and to one ``inverse`` + one ``jacobian`` of the model.
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np
from _timing import machine_line, per_call_us, summary_us

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from brace_control.can.units import actuator_kind, scaling_from_config  # noqa: E402
from brace_control.config import load_device_config  # noqa: E402
from brace_control.mechanisms import mechanism_from_config  # noqa: E402
from brace_control.mechanisms.pose_estimate import MeasurementModel, PoseEstimator  # noqa: E402

CONFIG = Path(__file__).resolve().parent.parent / 'config'
DEVICES = ['lumbar_brace', 'continuum', 'neck_brace_2r', 'neck_brace_3rrr', 'neck_brace_4rpr',
           'shoulder', 'upper_limb_trainer']


def readings(mech, cfg, n: int, moving: bool, rng: np.random.Generator) -> list[tuple[np.ndarray, np.ndarray]]:
    """(q, f) at 100 Hz along the sway (or at its start, at rest)."""
    home = np.asarray(mech.home_pose, float)
    dof, na = mech.dof, mech.n_actuators
    amp = np.full(dof, 0.05) if pose_is_angles(cfg) else np.where(np.arange(dof) < 2, 0.004, 0.03)
    scaling = scaling_from_config(cfg)
    k = float(cfg['actuator']['stiffness'])
    noise = float(cfg['kinetics']['load_cell_noise'])
    load = 0.2 * float(cfg['actuator']['max_force'])
    f0 = -np.full(na, load) if getattr(mech, 'actuation', None) == 'cable' else np.full(na, load)
    out = []
    for i in range(n):
        t = 0.01 * i if moving else 0.0
        if na < dof:                                            # the four-bar: along its curve
            q0 = float(mech.inverse(home)[0]) + 0.5 * math.sin(2 * math.pi * t / 4.0)
            pose = mech.forward_nearest([q0], home)
        else:
            pose = home + amp * np.sin(2 * math.pi * t / 4.0 + np.arange(dof))
        f = f0 + rng.normal(0.0, noise, na)
        q = np.asarray(mech.inverse(pose), float) + f0 / k
        q = np.floor(q * scaling.counts_per_unit) / scaling.counts_per_unit
        out.append((q, f))
    return out


def pose_is_angles(cfg) -> bool:
    return cfg['mechanism']['type'] == 'spherical_3rrr'


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--samples', type=int, default=2000, help='joint states per device and case')
    parser.add_argument('--devices', nargs='*', default=DEVICES)
    parser.add_argument('--seed', type=int, default=1)
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    print(machine_line())
    for name in args.devices:
        cfg = load_device_config(CONFIG / f'{name}.yaml')
        mech = mechanism_from_config(cfg)
        scaling = scaling_from_config(cfg)
        act, kin = cfg['actuator'], cfg['kinetics']
        model = MeasurementModel(stiffness=float(act['stiffness']), resolution=1.0 / scaling.counts_per_unit,
                                 force_noise=float(kin['load_cell_noise']),
                                 stiffness_rel_std=float(kin['stiffness_rel_std']),
                                 force_resolution=scaling.newton_per_count, force_limit=float(act['max_force']))
        rotary = actuator_kind(cfg) == 'rotary'
        home = np.asarray(mech.home_pose, float)
        print(f'\n{name} ({type(mech).__name__}, {mech.n_actuators} actuators, dof {mech.dof})')
        for case, moving in (('moving', True), ('at rest', False)):
            data = readings(mech, cfg, args.samples, moving, rng)
            est = PoseEstimator(mech, model, rotary=rotary)
            est.update(*data[0])                                # the first one: forward_nearest + solve
            its: list[int] = []

            def update(q, f):
                its.append(est.update(q, f).iterations)
            times = per_call_us(update, data[1:])
            hist = np.bincount(its)
            print(f'  update, {case:8s}: {summary_us(times)}; steps per update '
                  + ', '.join(f'{i}: {c}' for i, c in enumerate(hist) if c))
        old = per_call_us(lambda q: mech.forward_nearest(q, home), [(q,) for q, _ in data[:500]])
        print(f'  old forward_nearest(q, hint):   {summary_us(old)}')
        ij = per_call_us(lambda p: (mech.inverse(p), mech.jacobian(p)), [(home,)] * 500)
        print(f'  inverse + jacobian (one pose):  {summary_us(ij)}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
