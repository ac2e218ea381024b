"""``brace-continuum-plot``: the continuum robot's compression and tension branches (paper Fig. 1.6).

Left: the end of bar 1 in its own frame (the robot rotated 45 deg clockwise, Figs. 1.3 and
1.6) for ``k`` from ``k_min`` (straight bar) towards 1, on the compression curve
(``psi = 135 deg``) and the tension curve (``psi = 315 deg``), mode 1 only, with the
lines of the inverse problem (``y = const``, the paper's "line parallel to the rotated
x axis") and of the direct problem (``d = const``). Right: the position problem itself,
end-effector height ``y`` against slider half-distance ``d``, and the bar force.

Usage::

    brace-continuum-plot config/continuum.yaml --out continuum.png
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

from ..mechanisms.continuum import PSI_COMPRESSION, PSI_TENSION, Continuum2, bar_end

__all__ = ['branch_curves', 'plot_branches', 'main']


def branch_curves(robot: Continuum2, n: int = 400) -> dict[str, dict[str, np.ndarray]]:
    """Per branch: ``k``, bar-frame end ``(xp, yp)``, robot ``(d, y)``, force ``R`` (SI), up to the reach."""
    out = {}
    for name, psi in (('compression', PSI_COMPRESSION), ('tension', PSI_TENSION)):
        kmin = abs(math.cos(0.5 * psi))
        k_end = robot._ends[psi][0]          # the reach found at construction
        s = np.linspace(0.0, 1.0, n)
        k = kmin + (k_end - kmin) * (1.0 - np.cos(0.5 * math.pi * s))
        k[0] = kmin * (1 + 1e-12)
        xp, yp, force = bar_end(k, psi, robot.length, robot.ei)
        out[name] = {'k': k, 'xp': xp, 'yp': yp, 'd': (xp - yp) / math.sqrt(2),
                     'y': (xp + yp) / math.sqrt(2), 'force': force}
    return out


def plot_branches(robot: Continuum2, path: Path, *, y_goal: float | None = None) -> None:
    """Write the two-panel figure (PNG)."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    cur = branch_curves(robot)
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10.0, 4.4), dpi=90)
    colors = {'compression': 'tab:red', 'tension': 'tab:blue'}
    for name, c in cur.items():
        ax1.plot(c['xp'] * 1e3, c['yp'] * 1e3, color=colors[name],
                 label=f'{name} (psi = {"135" if name == "compression" else "315"} deg), mode 1')
        ax2.plot(c['d'] * 1e3, c['y'] * 1e3, color=colors[name], label=name)
    ax1.plot([robot.length * 1e3], [0.0], 'ko', label='undeformed (k = k_min)')
    y_goal = robot.y0 + 0.25 * (robot.height_range[1] - robot.y0) if y_goal is None else y_goal
    st = robot.solve_height(y_goal)
    # in the bar frame the inverse problem's line y = const is x' + y' = sqrt(2) y
    xs = np.array([0.5, 1.1]) * robot.length * 1e3
    ax1.plot(xs, math.sqrt(2) * y_goal * 1e3 - xs, 'k--', lw=0.8, label=f'inverse: y = {y_goal * 1e3:.1f} mm')
    a, b = (st.d + st.y) / math.sqrt(2), (st.y - st.d) / math.sqrt(2)
    ax1.plot([a * 1e3], [b * 1e3], 'ks', mfc='none', label=f'solution d = {st.d * 1e3:.2f} mm')
    ax1.set_xlabel("x' (mm, along the clamp)")
    ax1.set_ylabel("y' (mm)")
    ax1.set_aspect('equal', adjustable='datalim')
    ax1.legend(fontsize=7)
    ax1.set_title('bar end, robot rotated 45 deg clockwise (Fig. 1.6)', fontsize=9)
    ax2.axhline(robot.y0 * 1e3, color='0.7', lw=0.8)
    ax2.axvline(robot.d0 * 1e3, color='0.7', lw=0.8)
    ax2.set_xlabel('slider half-distance d (mm)')
    ax2.set_ylabel('end-effector height y (mm)')
    ax2.set_title(f'position problem (L = {robot.length * 1e3:.0f} mm, EI = {robot.ei:.3g} N m^2)', fontsize=9)
    ax3 = ax2.twinx()
    for name, c in cur.items():
        ax3.plot(c['d'] * 1e3, c['force'], color=colors[name], ls=':', lw=1)
    ax3.set_ylabel('bar force R (N, dotted)')
    ax3.set_ylim(0, max(float(np.percentile(np.concatenate([c['force'] for c in cur.values()]), 90)), 1e-3))
    ax2.legend(fontsize=7, loc='upper right')
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog='brace-continuum-plot', description=__doc__.splitlines()[0])
    parser.add_argument('config', help='device YAML with mechanism.type continuum2')
    parser.add_argument('--out', default='continuum_branches.png', help='PNG file')
    args = parser.parse_args(argv)
    from ..config import load_device_config
    from ..mechanisms.loader import mechanism_from_config

    robot = mechanism_from_config(load_device_config(args.config))
    if not isinstance(robot, Continuum2):
        print(f'{args.config}: not a continuum2 device', file=sys.stderr)
        return 2
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    plot_branches(robot, out)
    lo, hi = robot.height_range
    print(f'mode-1 reach: y {lo * 1e3:.2f}-{hi * 1e3:.2f} mm (undeformed {robot.y0 * 1e3:.2f} mm); plot: {out}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
