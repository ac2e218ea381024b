"""``brace-spm-study``: the shoulder's design study (seed paper 004) and its optimiser.

The slides' three objectives over the motion range discretised at 10 deg (abduction
[-10, 90], flexion-extension [-90, 20], rotation [-40, 50] deg: 12 x 11 x 10 = 1320 poses):

* ``g1`` — poses where every leg's quadratic ``A T^2 + B T + C = 0`` has a real root
  (maximise);
* ``g2`` — share of the 1320 poses with ``k(J) = ||Kq^-1 Jx|| ||Jx^-1 Kq||`` in [1, 10]
  (2-norm; unreachable poses count as outside; maximise);
* ``g3`` — the largest motor torque ``|tau_i|`` (N·m) holding the arm's weight,
  ``tau = -(Jx^-1 Kq)^T M``, over the poses counted in ``g2`` (``k(J) <= 10``; minimise).
  Over *all* reachable poses (``g3_all``) the maximum is set by the few poses next to a
  serial singularity, where the torque grows without bound; the slides' finite 4.5 N·m
  suggests they did not include those. ``M`` is the moment of the arm (15 N), hand
  (5 N) and payload (5 N) at the YAML's lever arms (the slides give none), gravity along
  the hanging arm.

One design is evaluated for all 1320 poses at once (numpy, no Python loop over poses):
:func:`evaluate_design`. The optimiser (``--optimise``) runs
``scipy.optimize.differential_evolution`` on the weighted sum
``-w1 g1/1320 - w2 g2 + w3 g3/g3_ref`` over the 11 parameters within ``--bounds``,
keeps every evaluated design, and plots the non-dominated ones (Pareto front) with the
paper's and the optimiser's designs (PNG).

Usage::

    brace-spm-study config/shoulder.yaml --out study/            # the YAML's design
    brace-spm-study config/shoulder.yaml --out study/ --optimise --maxiter 15 --popsize 6
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..config import load_device_config
from ..mechanisms.spherical import (PAPER_DESIGN_DEG, WORKING_MODES, inverse_batch, leg_geometry,
                                    rotation_matrices, velocity_batch)

__all__ = ['motion_grid', 'evaluate_design', 'StudyResult', 'mode_table', 'optimise', 'main',
           'PAPER_G', 'DESIGN_KEYS', 'design_vector', 'design_from_vector']

#: the slides' reported objectives for their chosen design
PAPER_G = {'g1': 1320, 'g2': 0.99, 'g3': 4.5}
#: order of the 11 parameters in a design vector (rad)
DESIGN_KEYS = ('gamma', 'beta', 'alpha1_1', 'alpha1_2', 'alpha1_3', 'alpha2_1', 'alpha2_2', 'alpha2_3',
               'delta_1', 'delta_2', 'delta_3')
#: the paper's motion ranges (deg): abduction, flexion-extension, rotation
MOTION_RANGES_DEG = ((-10.0, 90.0), (-90.0, 20.0), (-40.0, 50.0))


def motion_grid(step_deg: float = 10.0) -> np.ndarray:
    """Poses (N, 3) rad over the motion ranges, ``step_deg`` apart, ends included (10 deg: 1320)."""
    axes = [np.radians(np.arange(lo, hi + 1e-9, step_deg)) for lo, hi in MOTION_RANGES_DEG]
    grid = np.meshgrid(*axes, indexing='ij')
    return np.column_stack([g.ravel() for g in grid])


def design_vector(design: dict[str, Any]) -> np.ndarray:
    """Design dict (rad; ``alpha1``/``alpha2``/``delta`` as triples) -> the 11-vector (rad)."""
    return np.concatenate([[design['gamma'], design['beta']], design['alpha1'], design['alpha2'],
                           design['delta']]).astype(float)


def design_from_vector(x: np.ndarray) -> dict[str, Any]:
    """The 11-vector (rad) -> design dict."""
    return {'gamma': float(x[0]), 'beta': float(x[1]), 'alpha1': np.asarray(x[2:5], float),
            'alpha2': np.asarray(x[5:8], float), 'delta': np.asarray(x[8:11], float)}


@dataclass
class StudyResult:
    """Objectives of one design (and the per-pose data behind them)."""

    g1: int                       #: poses with a real inverse solution (of N)
    g2: float                     #: share of the N poses with k(J) in [1, 10]
    g3: float                     #: max |motor torque| (N·m) over the poses with k(J) <= k_max
    n_poses: int
    g3_all: float                 #: max |motor torque| (N·m) over every reachable pose
    reach: np.ndarray = field(repr=False)      #: (N,) bool
    k: np.ndarray = field(repr=False)          #: (N,) dexterity (inf where unreachable/singular)
    tau: np.ndarray = field(repr=False)        #: (N, 3) N·m (NaN where unreachable)
    theta: np.ndarray = field(repr=False)      #: (N, 3) rad motor angles (NaN where unreachable)
    kq_min: float = math.nan                   #: min |Kq_ii| over reachable poses (serial margin)
    elbow_gap_deg: float = math.nan            #: min angle between two elbow axes w_i, w_j (deg)


def evaluate_design(design: dict[str, Any], poses: np.ndarray | None = None, *,
                    working_mode: str = '+++', load_moment_nm: float = 0.0,
                    q_mats: np.ndarray | None = None, k_max: float = 10.0) -> StudyResult:
    """g1, g2, g3 of one design over ``poses`` (default: the 1320-pose grid), vectorised.

    :param design: ``gamma``, ``beta``, ``alpha1``, ``alpha2``, ``delta`` in rad.
    :param working_mode: ``'+-+'``-style signs of ``Kq_ii`` (see :mod:`..mechanisms.spherical`).
    :param load_moment_nm: ``sum F_k l_k`` (N·m): the arm's moment when horizontal.
    :param q_mats: precomputed rotation matrices of ``poses`` (saves ~10 % per call).
    """
    if q_mats is None:
        q_mats = rotation_matrices(motion_grid() if poses is None else poses)
    signs = np.array([1.0 if ch == '+' else -1.0 for ch in working_mode])
    a1, a2 = np.asarray(design['alpha1'], float), np.asarray(design['alpha2'], float)
    reach, theta, w, v = inverse_batch(design['gamma'], design['beta'], a1, a2,
                                       np.asarray(design['delta'], float), q_mats, signs)
    u = leg_geometry(design['gamma'], design['beta'], design['delta'])[0]
    n = q_mats.shape[0]
    jx, kq = velocity_batch(u, w, v)
    ok = reach & np.all(np.abs(kq) > 1e-12, axis=1)
    eye = np.eye(3)
    jac = np.where(ok[:, None, None], jx / np.where(ok[:, None], kq, 1.0)[:, :, None], eye)
    # k = sigma_max / sigma_min from the eigenvalues of J^T J (cheaper than a batched SVD)
    ev = np.linalg.eigvalsh(np.swapaxes(jac, 1, 2) @ jac)
    with np.errstate(divide='ignore', invalid='ignore'):
        k = np.where(ok & (ev[:, 0] > 0.0), np.sqrt(ev[:, 2] / ev[:, 0]), np.inf)
    g2 = float(np.count_nonzero(k <= k_max)) / n
    # tau = -(J^-1)^T M = -J^-T M with M = S (Q z) x z
    arm = q_mats[:, :, 2]
    mom = load_moment_nm * np.stack([arm[:, 1], -arm[:, 0], np.zeros(n)], axis=1)    # arm x z
    good = ok & np.isfinite(k)
    tau = np.full((n, 3), np.nan)
    if good.any():
        tau[good] = -np.linalg.solve(np.swapaxes(jac[good], 1, 2), mom[good][:, :, None])[:, :, 0]
    well = good & (k <= k_max)
    g3 = float(np.max(np.abs(tau[well]))) if well.any() else math.inf
    g3_all = float(np.nanmax(np.abs(tau))) if good.any() else math.inf
    kq_min = float(np.min(np.abs(kq[reach]))) if reach.any() else math.nan
    if reach.any():
        wr = w[reach]
        cos = np.stack([np.einsum('nj,nj->n', wr[:, i], wr[:, j]) for i, j in ((0, 1), (0, 2), (1, 2))], 1)
        gap = float(np.degrees(np.arccos(np.clip(cos.max(), -1.0, 1.0))))
    else:
        gap = math.nan
    return StudyResult(int(reach.sum()), g2, g3, n, g3_all, reach, k, tau, theta, kq_min, gap)


def mode_table(design: dict[str, Any], load_moment_nm: float, poses: np.ndarray | None = None
               ) -> list[dict[str, Any]]:
    """Every working mode's g2, g3, serial margin, elbow gap and motor angle ranges."""
    q_mats = rotation_matrices(motion_grid() if poses is None else poses)
    rows = []
    for mode in WORKING_MODES:
        r = evaluate_design(design, working_mode=mode, load_moment_nm=load_moment_nm, q_mats=q_mats)
        th = np.degrees(_unwrap_grid(r.theta, poses is None)[r.reach])
        rows.append({'mode': mode, 'g1': r.g1, 'g2': r.g2, 'g3': r.g3, 'kq_min': r.kq_min,
                     'elbow_gap_deg': r.elbow_gap_deg,
                     'theta_min_deg': th.min(axis=0).round(2).tolist() if th.size else None,
                     'theta_max_deg': th.max(axis=0).round(2).tolist() if th.size else None})
    return rows


def _unwrap_grid(theta: np.ndarray, is_grid: bool) -> np.ndarray:
    """Motor angles made continuous over the 12 x 11 x 10 grid (they are circular).

    Unwrapped along abduction at (flexion, rotation) = first, then along flexion, then along
    rotation, so that each motor's range is its continuous sweep over the motion range
    (not a value wrapped into a 2 pi window). Other pose sets are returned unchanged.
    """
    if not is_grid or theta.shape[0] != 1320 or not np.all(np.isfinite(theta)):
        return theta
    g = theta.reshape(12, 11, 10, 3).copy()
    g[:, 0, 0] = np.unwrap(g[:, 0, 0], axis=0)
    g[:, :, 0] = np.unwrap(g[:, :, 0], axis=1)
    g = np.unwrap(g, axis=2)
    return g.reshape(1320, 3)


def _objective_weights(text: str) -> tuple[float, float, float]:
    vals = [float(v) for v in text.split(',')]
    if len(vals) != 3 or min(vals) < 0:
        raise argparse.ArgumentTypeError('weights: three non-negative numbers "w1,w2,w3"')
    return vals[0], vals[1], vals[2]


def optimise(*, load_moment_nm: float, working_mode: str, weights=(1.0, 1.0, 0.2), g3_ref: float = 4.5,
             maxiter: int = 15, popsize: int = 6, seed: int = 1,
             bounds_deg: tuple[tuple[float, float], ...] | None = None) -> dict[str, Any]:
    """Weighted-sum differential evolution over the 11 parameters; every evaluated design is kept.

    :returns: ``{'best': design vector (rad), 'best_g': (g1, g2, g3), 'history': (M, 3) array of
        (g1, g2, g3), 'designs': (M, 11), 'seconds': float, 'evaluations': int}``.
    """
    from scipy.optimize import differential_evolution

    if bounds_deg is None:
        bounds_deg = ((50.0, 90.0), (50.0, 90.0)) + ((40.0, 110.0),) * 6 + (
            (30.0, 110.0), (150.0, 230.0), (260.0, 340.0))
    q_mats = rotation_matrices(motion_grid())
    n = q_mats.shape[0]
    hist: list[tuple[float, float, float]] = []
    xs: list[np.ndarray] = []
    w1, w2, w3 = weights

    def f(x: np.ndarray) -> float:
        r = evaluate_design(design_from_vector(x), working_mode=working_mode,
                            load_moment_nm=load_moment_nm, q_mats=q_mats)
        g3 = r.g3 if math.isfinite(r.g3) else 10.0 * g3_ref
        hist.append((r.g1, r.g2, g3))
        xs.append(np.array(x, dtype=float))
        return -w1 * r.g1 / n - w2 * r.g2 + w3 * min(g3, 10.0 * g3_ref) / g3_ref

    t0 = time.perf_counter()
    res = differential_evolution(f, [tuple(np.radians(b)) for b in bounds_deg], maxiter=maxiter,
                                 popsize=popsize, seed=seed, tol=1e-6, polish=False, updating='deferred')
    best = evaluate_design(design_from_vector(res.x), working_mode=working_mode,
                           load_moment_nm=load_moment_nm, q_mats=q_mats)
    return {'best': res.x, 'best_g': (best.g1, best.g2, best.g3), 'history': np.array(hist),
            'designs': np.array(xs), 'seconds': time.perf_counter() - t0, 'evaluations': len(hist)}


def pareto_mask(g: np.ndarray) -> np.ndarray:
    """Non-dominated rows of ``(g1, g2, g3)`` (maximise g1, g2; minimise g3)."""
    obj = np.column_stack([-g[:, 0], -g[:, 1], g[:, 2]])
    keep = np.ones(len(obj), dtype=bool)
    order = np.argsort(obj[:, 2])
    for i in order:
        if not keep[i]:
            continue
        dominated = np.all(obj[i] <= obj, axis=1) & np.any(obj[i] < obj, axis=1)
        keep &= ~dominated
    return keep


def plot_pareto(path: Path, hist: np.ndarray, paper: tuple[float, float, float],
                best: tuple[float, float, float]) -> None:
    """Scatter of every evaluated design (g2 vs g3, colour g1), the Pareto front, paper and best."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.0, 4.2), dpi=90)
    ok = np.isfinite(hist[:, 2])
    sc = ax.scatter(hist[ok, 2], hist[ok, 1], c=hist[ok, 0], s=6, cmap='viridis', alpha=0.5, vmin=0, vmax=1320)
    front = pareto_mask(hist[ok])
    fr = hist[ok][front]
    fr = fr[np.argsort(fr[:, 2])]
    ax.plot(fr[:, 2], fr[:, 1], 'r.-', lw=1, ms=5, label=f'non-dominated ({len(fr)})')
    ax.plot(paper[2], paper[1], 'k*', ms=12, label=f'paper design (this model): g1={paper[0]}')
    ax.plot(best[2], best[1], 'bs', ms=7, mfc='none', label=f'optimiser best: g1={best[0]}')
    ax.set_xlabel('g3: max motor torque (N·m)')
    ax.set_ylabel('g2: share of poses with k(J) in [1, 10]')
    ax.set_xlim(0, min(float(np.nanpercentile(hist[ok, 2], 95)) * 1.2, 40.0) if ok.any() else 10)
    ax.set_ylim(0, 1.02)
    fig.colorbar(sc, ax=ax, label='g1: reachable poses (of 1320)')
    ax.legend(fontsize=7, loc='lower right')
    ax.set_title('Spherical 3-RRR shoulder: evaluated designs', fontsize=9)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _design_from_config(section: dict[str, Any]) -> dict[str, Any]:
    return {'gamma': float(section['gamma']), 'beta': float(section['beta']),
            'alpha1': np.asarray(section['alpha1'], float), 'alpha2': np.asarray(section['alpha2'], float),
            'delta': np.asarray(section['delta'], float)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog='brace-spm-study', description=__doc__.splitlines()[0])
    parser.add_argument('config', help='device YAML (mechanism.type spherical_3rrr), e.g. config/shoulder.yaml')
    parser.add_argument('--out', default='spm_study', help='output directory (JSON summary, PNG)')
    parser.add_argument('--paper-design', action='store_true',
                        help="evaluate the slides' published design instead of the YAML's")
    parser.add_argument('--optimise', action='store_true', help='run differential evolution (Pareto PNG)')
    parser.add_argument('--maxiter', type=int, default=15, help='DE generations (budget)')
    parser.add_argument('--popsize', type=int, default=6, help='DE population per parameter (budget)')
    parser.add_argument('--weights', type=_objective_weights, default=(1.0, 1.0, 0.2),
                        help='w1,w2,w3 of -w1 g1/1320 - w2 g2 + w3 g3/4.5 (default 1,1,0.2)')
    parser.add_argument('--seed', type=int, default=1)
    args = parser.parse_args(argv)

    cfg = load_device_config(args.config)
    mech = cfg.section('mechanism')
    if mech.get('type') != 'spherical_3rrr':
        print(f'{args.config}: mechanism.type is {mech.get("type")!r}, expected spherical_3rrr', file=sys.stderr)
        return 2
    if args.paper_design:
        design = {k: (math.radians(v) if np.ndim(v) == 0 else np.radians(v)) for k, v in PAPER_DESIGN_DEG.items()}
    else:
        design = _design_from_config(mech)
    mode = str(mech.get('working_mode', '+++'))
    forces = np.asarray(mech.get('load_forces', [15.0, 5.0, 5.0]), float)
    levers = np.asarray(mech.get('load_lever_arms', [0.15, 0.30, 0.30]), float)
    s_load = float(forces @ levers)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    q_mats = rotation_matrices(motion_grid())
    res = evaluate_design(design, working_mode=mode, load_moment_nm=s_load, q_mats=q_mats)
    reps = 50
    t0 = time.perf_counter()
    for _ in range(reps):
        evaluate_design(design, working_mode=mode, load_moment_nm=s_load, q_mats=q_mats)
    ms = (time.perf_counter() - t0) / reps * 1e3
    gain = res.g3 / s_load if s_load > 0 else math.nan
    print(f'design: {"paper" if args.paper_design else args.config}, working mode {mode!r}, '
          f'load sum F*l = {s_load:.3f} N·m')
    print(f'{"":12s}{"this model":>14s}{"paper":>10s}')
    print(f'{"g1":12s}{res.g1:>14d}{PAPER_G["g1"]:>10d}   (poses with a real inverse, of {res.n_poses})')
    print(f'{"g2":12s}{res.g2:>14.4f}{PAPER_G["g2"]:>10.2f}   (share with k(J) in [1, 10], 2-norm)')
    print(f'{"g3 (N·m)":12s}{res.g3:>14.3f}{PAPER_G["g3"]:>10.1f}   (max |tau| where k(J) <= 10; '
          f'= {gain:.3f} x sum F*l)')
    print(f'{"g3_all":12s}{res.g3_all:>14.3f}{"":>10s}   (max |tau| over every reachable pose)')
    if math.isfinite(gain) and gain > 0:
        print(f'the paper\'s g3 = 4.5 N·m would need sum F*l = {4.5 / gain:.3f} N·m with this model')
    print(f'one design evaluation over {res.n_poses} poses: {ms:.2f} ms (mean of {reps})')
    rows = mode_table(design, s_load)
    print('\nworking modes (sign of Kq_ii per leg):')
    print(f'{"mode":6s}{"g2":>8s}{"g3":>8s}{"min|Kq|":>9s}{"elbow gap":>10s}  motor range (deg)')
    for r in rows:
        rng = (' '.join(f'[{a:.0f},{b:.0f}]' for a, b in zip(r['theta_min_deg'], r['theta_max_deg']))
               if r['theta_min_deg'] else '-')
        print(f'{r["mode"]:6s}{r["g2"]:8.3f}{r["g3"]:8.2f}{r["kq_min"]:9.3f}{r["elbow_gap_deg"]:9.1f}°  {rng}')
    summary: dict[str, Any] = {
        'config': str(args.config), 'design_deg': {k: np.degrees(v).tolist() for k, v in design.items()},
        'working_mode': mode, 'load_moment_nm': s_load,
        'g1': res.g1, 'g2': res.g2, 'g3': res.g3, 'g3_all': res.g3_all, 'paper': PAPER_G,
        'evaluation_ms': ms, 'modes': rows}
    if args.optimise:
        opt = optimise(load_moment_nm=s_load, working_mode=mode, weights=args.weights,
                       maxiter=args.maxiter, popsize=args.popsize, seed=args.seed)
        best = opt['best_g']
        print(f'\noptimiser: {opt["evaluations"]} designs in {opt["seconds"]:.1f} s; best g1 = {best[0]}, '
              f'g2 = {best[1]:.4f}, g3 = {best[2]:.3f} N·m')
        print('best design (deg): ' + ', '.join(f'{k} {v:.4f}' for k, v in zip(DESIGN_KEYS, np.degrees(opt['best']))))
        png = out / 'spm_pareto.png'
        plot_pareto(png, opt['history'], (res.g1, res.g2, res.g3), best)
        print(f'Pareto plot: {png}')
        summary['optimiser'] = {'best_deg': dict(zip(DESIGN_KEYS, np.degrees(opt['best']).tolist())),
                                'best_g': list(best), 'evaluations': opt['evaluations'],
                                'seconds': opt['seconds'], 'weights': list(args.weights),
                                'maxiter': args.maxiter, 'popsize': args.popsize}
    (out / 'spm_study.json').write_text(json.dumps(summary, indent=2))
    print(f'summary: {out / "spm_study.json"}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
