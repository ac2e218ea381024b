"""How often the pose estimate is off right after a jump in the readings, per device.

The kinetics node skips joint states when it falls behind a fast move, so two consecutive
readings may be far apart. For each device: 200 pairs of poses near home (the second up to
30 % of the spread away), the estimator set on the first, then one update with the exact,
unloaded lengths of the second; counted: estimates more than 2 mm (or 2 mrad) off.

    PYTHONPATH=. python bench/bench_estimate_jumps.py lumbar_brace neck_brace_3rrr ...

Results: bench/RESULTS.md, "the pose estimate's excursion fixed".
"""
from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np

from brace_control.can.units import actuator_kind, scaling_from_config
from brace_control.config import load_device_config
from brace_control.demo import prepare_config
from brace_control.mechanisms import mechanism_from_config
from brace_control.mechanisms.pose_estimate import MeasurementModel, PoseEstimator


def count(name: str, pairs: int = 200, seed: int = 1) -> tuple[int, float]:
    cfg = load_device_config(prepare_config(f'config/{name}.yaml', Path(tempfile.mkdtemp()))[0])
    mech = mechanism_from_config(cfg)
    kin, act, sc = cfg['kinetics'], cfg['actuator'], scaling_from_config(cfg)
    model = MeasurementModel(
        stiffness=float(act['stiffness']), resolution=1 / sc.counts_per_unit,
        force_noise=float(kin['load_cell_noise']), stiffness_rel_std=float(kin['stiffness_rel_std']),
        force_resolution=sc.newton_per_count, force_limit=float(act['max_force']))
    home = np.asarray(mech.home_pose, float)
    scale = np.abs(home) * 0.1 + 0.05
    rng = np.random.default_rng(seed)
    bad = tried = 0
    worst = 0.0
    while tried < pairs:
        p1 = home + rng.uniform(-1, 1, home.size) * scale
        p2 = p1 + rng.uniform(-1, 1, home.size) * scale * 0.3
        try:
            q1, q2 = mech.inverse(p1), mech.inverse(p2)
        except ValueError:
            continue
        tried += 1
        est = PoseEstimator(mech, model, rotary=actuator_kind(cfg) == 'rotary',
                            max_step=float(kin['max_step']), max_iterations=int(kin['max_iterations']),
                            residual_sigmas=float(kin['residual_sigmas']))
        est.reset(p1)
        est.update(q1, np.zeros(len(q1)))
        err = float(np.max(np.abs(est.update(q2, np.zeros(len(q2))).pose - p2)))
        worst = max(worst, err)
        bad += err > 2e-3
    return bad, worst


if __name__ == '__main__':
    for device in sys.argv[1:] or ['lumbar_brace']:
        n_bad, worst = count(device)
        print(f'{device}: {n_bad} of 200 more than 2 mm (2 mrad) off, worst {worst:.4g}')
