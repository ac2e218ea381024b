"""``brace-workspace``: the constant-orientation workspaces of a 3-RPR and their union.

The paper's "global workspace" (seed 001, section IV-B, eq. 21, Figs. 8-10): for a fixed
``theta`` the platform origin ``P`` must lie, for every leg ``i``, in the annulus centred at
``c_i(theta) = A_i - R(theta) b_i`` with radii the stroke limits ``[lo_i, hi_i]`` (for the
brace: centres ``(r2 cos t - r1, r2 sin t)``, ``(0, 0)``, ``(r1 - r2 cos t, -r2 sin t)``). The
workspace at ``theta`` is the intersection of the three annuli with ``y > 0``; the brace's
workspace is the union over ``theta`` in ``[0, 30] deg`` in 0.1 deg steps.

Vectorised without a loop over grid points or angles: on every grid row ``y_j`` each
annulus is two ``x``-intervals ``w_in <= |x - c_x| <= w_out`` (``w = sqrt(r^2 - (y_j -
c_y)^2)``); the intersection of three annuli is the union of the 2 x 2 x 2 pairwise
disjoint interval intersections. The area per angle is the exact length of those
intervals summed over rows (times the row spacing), and the union raster is painted from
the intervals with a difference array (``np.add.at`` + ``cumsum``).

The map ignores singularities, as the paper does; note that for the brace every pose with
``theta = 0`` is singular (``Rpr3.check_singularity``).

Next to it, the force-transmission map (:func:`capacity_map`): at a chosen ``theta`` (the
home pose's by default), the largest lateral force ``|Fx|`` (N, base frame) the three
actuators can hold at each grid point of the workspace, both directions, with the
actuator limit ``actuator.max_force`` of the YAML (``Mechanism.wrench_capacity_batch``:
closed form ``min_i limit / |(J^-T)_i,x|``, vectorised over the grid). Near ``theta = 0``
the legs are nearly parallel and the capacity collapses (0.71 N at the brace's 5 deg
home with 250 N actuators; exactly 0 at ``theta = 0``).
"""
from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..mechanisms.base import Mechanism

__all__ = ['WorkspaceMap', 'workspace_map', 'annulus_centres', 'CapacityMap', 'capacity_map', 'main']


@dataclass
class WorkspaceMap:
    """Result of :func:`workspace_map` (SI units)."""

    theta: np.ndarray        #: angles (rad), shape (n_theta,)
    area: np.ndarray         #: workspace area at each angle (m^2), shape (n_theta,)
    x: np.ndarray            #: grid columns (m), shape (nx,)
    y: np.ndarray            #: grid rows (m), shape (ny,)
    union: np.ndarray        #: bool (ny, nx): grid point in the workspace for some angle
    grid: float              #: grid spacing (m)
    seconds: float           #: wall time of the computation (s)

    @property
    def union_area(self) -> float:
        """Area of the union (m^2), from the raster (grid points x grid^2)."""
        return float(self.union.sum()) * self.grid ** 2


def annulus_centres(base_anchors: np.ndarray, platform_anchors: np.ndarray,
                    theta: np.ndarray) -> np.ndarray:
    """Centres ``c_i(theta) = A_i - R(theta) b_i`` (m), shape (n_theta, 3, 2) (paper Fig. 9)."""
    c, s = np.cos(theta)[:, None], np.sin(theta)[:, None]
    bx, by = platform_anchors[:, 0], platform_anchors[:, 1]
    return np.stack([base_anchors[:, 0] - (c * bx - s * by),
                     base_anchors[:, 1] - (s * bx + c * by)], axis=-1)


def _intervals(centres: np.ndarray, lo: np.ndarray, hi: np.ndarray,
               y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per (theta, row) the 8 candidate pieces ``[start, end]`` of the three-annulus intersection.

    :returns: ``start, end`` of shape (n_theta, ny, 8); empty pieces have ``end < start``.
    """
    dy2 = (y[None, :, None] - centres[:, None, :, 1]) ** 2          # (nt, ny, 3)
    with np.errstate(invalid='ignore'):
        w_out = np.sqrt(hi ** 2 - dy2)                               # NaN: row misses the disc
        w_in = np.sqrt(np.maximum(lo ** 2 - dy2, 0.0))
    cx = np.broadcast_to(centres[:, None, :, 0], dy2.shape)
    # each annulus on a row: left [cx - w_out, cx - w_in], right [cx + w_in, cx + w_out]
    left_s, left_e = cx - w_out, cx - w_in
    right_s, right_e = cx + w_in, cx + w_out
    miss = np.isnan(w_out)
    for arr in (left_s, right_s):
        arr[miss] = np.inf
    for arr in (left_e, right_e):
        arr[miss] = -np.inf
    starts = np.stack([left_s, right_s], axis=-1)                    # (nt, ny, 3, 2)
    ends = np.stack([left_e, right_e], axis=-1)
    combos = np.array(np.meshgrid([0, 1], [0, 1], [0, 1], indexing='ij')).reshape(3, -1)  # (3, 8)
    s_all = np.max(np.stack([starts[..., i, combos[i]] for i in range(3)]), axis=0)      # (nt, ny, 8)
    e_all = np.min(np.stack([ends[..., i, combos[i]] for i in range(3)]), axis=0)
    return s_all, e_all


def workspace_map(base_anchors: np.ndarray, platform_anchors: np.ndarray,
                  stroke_lo: np.ndarray, stroke_hi: np.ndarray, theta: np.ndarray, *,
                  grid: float = 0.001, y_min: float = 0.0) -> WorkspaceMap:
    """Constant-orientation workspaces at each ``theta`` and their union (paper Figs. 8, 10).

    :param base_anchors: ``A_i`` (3, 2), m.
    :param platform_anchors: ``b_i`` (3, 2), m (platform frame).
    :param stroke_lo: lower stroke limits (3,), m (inner radii of the annuli, eq. 21).
    :param stroke_hi: upper stroke limits (3,), m (outer radii).
    :param theta: orientations (rad), shape (n_theta,).
    :param grid: grid spacing (m) of the rows and of the union raster.
    :param y_min: keep ``y > y_min`` (the paper: ``y > 0``).
    """
    t0 = time.perf_counter()
    a = np.asarray(base_anchors, dtype=float).reshape(3, 2)
    b = np.asarray(platform_anchors, dtype=float).reshape(3, 2)
    lo = np.broadcast_to(np.asarray(stroke_lo, dtype=float), (3,))
    hi = np.broadcast_to(np.asarray(stroke_hi, dtype=float), (3,))
    theta = np.atleast_1d(np.asarray(theta, dtype=float))
    if not (grid > 0 and np.isfinite(grid)):
        raise ValueError(f'grid: expected a positive spacing in m, got {grid!r}')
    centres = annulus_centres(a, b, theta)                           # (nt, 3, 2)
    # bounding box: every leg's outer disc, over all angles, intersected
    x_lo = np.max(np.min(centres[..., 0], axis=0) - hi)
    x_hi = np.min(np.max(centres[..., 0], axis=0) + hi)
    y_hi = np.min(np.max(centres[..., 1], axis=0) + hi)
    y_lo = max(np.max(np.min(centres[..., 1], axis=0) - hi), y_min)
    x = grid * np.arange(np.floor(x_lo / grid), np.ceil(x_hi / grid) + 1)
    y = grid * np.arange(np.floor(y_lo / grid), np.ceil(y_hi / grid) + 1)
    y = y[y > y_min]
    if x.size == 0 or y.size == 0:
        return WorkspaceMap(theta, np.zeros(theta.size), x, y, np.zeros((y.size, x.size), bool), grid,
                            time.perf_counter() - t0)
    s_all, e_all = _intervals(centres, lo, hi, y)
    length = np.clip(e_all - s_all, 0.0, None)
    length[~np.isfinite(length)] = 0.0
    area = length.sum(axis=(1, 2)) * grid
    # union raster: paint [i0, i1] of every non-empty piece into a difference array
    nx = x.size
    ok = e_all >= s_all
    t_idx, row, _ = np.nonzero(ok)
    i0 = np.ceil((s_all[ok] - x[0]) / grid - 1e-9).astype(np.int64)
    i1 = np.floor((e_all[ok] - x[0]) / grid + 1e-9).astype(np.int64)
    i0 = np.clip(i0, 0, nx)
    i1 = np.clip(i1, -1, nx - 1)
    keep = i1 >= i0
    row, i0, i1 = row[keep], i0[keep], i1[keep]
    diff = np.zeros(y.size * (nx + 1), dtype=np.int32)
    np.add.at(diff, row * (nx + 1) + i0, 1)
    np.add.at(diff, row * (nx + 1) + i1 + 1, -1)
    union = np.cumsum(diff.reshape(y.size, nx + 1), axis=1)[:, :nx] > 0
    return WorkspaceMap(theta, area, x, y, union, float(grid), time.perf_counter() - t0)


@dataclass
class CapacityMap:
    """Result of :func:`capacity_map` (SI units)."""

    theta: float             #: orientation of every pose (rad)
    x: np.ndarray            #: grid columns (m), shape (nx,)
    y: np.ndarray            #: grid rows (m), shape (ny,)
    capacity: np.ndarray     #: (ny, nx) capacity along ``axis`` (N or N·m); NaN where unreachable
    limiting: np.ndarray     #: (ny, nx) index of the limiting actuator; -1 where none or unreachable
    axis: str                #: the capacity axis (``'Fx'``: lateral force, base frame)
    force_limits: np.ndarray  #: actuator limits used (N), shape (n_actuators,)
    seconds: float           #: wall time of the computation (s)


def capacity_map(mech: Mechanism, x: np.ndarray, y: np.ndarray, theta: float, force_limits: float | np.ndarray,
                 *, axis: str = 'Fx', chunk: int = 65536) -> CapacityMap:
    """Force-transmission capacity along ``axis`` over the grid ``x`` x ``y`` at orientation ``theta``.

    Each grid point ``(x_i, y_j, theta)`` within stroke gets
    ``mech.wrench_capacity_batch(...)[:, axis]``: the largest force along the axis, both
    directions, that the actuators hold within ``force_limits`` (closed form, vectorised;
    singular poses exact by LP, 0 along the unsupported direction).

    :param mech: a planar mechanism (pose ``(x, y, theta)``).
    :param x, y: grid columns and rows (m).
    :param theta: orientation (rad).
    :param force_limits: actuator limit(s) (N), a scalar or one per actuator.
    :param axis: one of ``mech.wrench_axes`` (``'Fx'``, ``'Fy'``, ``'Mz'``).
    :param chunk: poses per call (bounds the memory of the batch).
    :raises ValueError: an unknown axis, bad limits.
    """
    t0 = time.perf_counter()
    if axis not in mech.wrench_axes:
        raise ValueError(f'axis: expected one of {mech.wrench_axes}, got {axis!r}')
    a = mech.wrench_axes.index(axis)
    xs = np.asarray(x, dtype=float).ravel()
    ys = np.asarray(y, dtype=float).ravel()
    gx, gy = np.meshgrid(xs, ys)
    poses = np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, float(theta))])
    cap = np.full(gx.size, np.nan)
    which = np.full(gx.size, -1, dtype=int)
    reach = np.flatnonzero(~np.isnan(mech.inverse_batch(poses)).any(axis=1))
    limits = np.broadcast_to(np.asarray(force_limits, dtype=float), (mech.n_actuators,)).copy()
    for start in range(0, reach.size, chunk):
        rows = reach[start:start + chunk]
        c, w = mech.wrench_capacity_batch(poses[rows], limits, return_limiting=True)
        cap[rows], which[rows] = c[:, a], w[:, a]
    return CapacityMap(float(theta), xs, ys, cap.reshape(gx.shape), which.reshape(gx.shape), axis, limits,
                       time.perf_counter() - t0)


def _plot(ws: WorkspaceMap, out: Path, title: str, caps: Sequence[CapacityMap] = ()) -> None:
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm

    n = 1 + len(caps)
    fig, axes = plt.subplots(1, n, figsize=(7 * n, 4.5), dpi=120, squeeze=False)
    ax = axes[0, 0]
    extent = (ws.x[0] * 1e3, ws.x[-1] * 1e3, ws.y[0] * 1e3, ws.y[-1] * 1e3)
    ax.imshow(ws.union, origin='lower', extent=extent, cmap='Blues', vmin=0, vmax=1.6,
              interpolation='nearest', aspect='equal')
    ax.set_xlabel('x (mm)')
    ax.set_ylabel('y (mm)')
    deg = np.degrees(ws.theta)
    ax.set_title(f'{title}\nunion over theta = {deg[0]:.1f}..{deg[-1]:.1f} deg: '
                 f'{ws.union_area * 1e4:.1f} cm^2')
    ax.grid(True, alpha=0.3)
    for k, cm in enumerate(caps, start=1):
        ax = axes[0, k]
        positive = cm.capacity[np.isfinite(cm.capacity) & (cm.capacity > 0.0)]
        img = np.where(cm.capacity > 0.0, cm.capacity, np.nan)         # 0 (singular) left blank on a log scale
        norm = LogNorm(vmin=float(positive.min()), vmax=float(positive.max())) if positive.size else None
        im = ax.imshow(img, origin='lower', extent=extent, cmap='viridis', norm=norm,
                       interpolation='nearest', aspect='equal')
        fig.colorbar(im, ax=ax, label=f'|{cm.axis}| capacity (N)')
        ax.set_xlabel('x (mm)')
        ax.set_ylabel('y (mm)')
        lim = f'{cm.force_limits[0]:g} N' if np.all(cm.force_limits == cm.force_limits[0]) else \
            f'{cm.force_limits.tolist()} N'
        ax.set_title(f'largest |{cm.axis}| held (base frame), both directions\n'
                     f'theta = {np.degrees(cm.theta):.1f} deg, actuators <= {lim}')
        ax.grid(True, alpha=0.3)
    fig.tight_layout()
    fig.savefig(out)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    """``brace-workspace config/lumbar_brace.yaml --out workspace.png [--step-deg 0.1 --grid 0.001]
    [--capacity-theta-deg 5 20] [--force-limit 250]``."""
    parser = argparse.ArgumentParser(
        prog='brace-workspace',
        description="Workspace of a 3-RPR device (paper section IV-B): area per angle, a plot of the union, "
                    "and next to it the map of the largest lateral force |Fx| the actuators hold.")
    parser.add_argument('device', help='device YAML (e.g. config/lumbar_brace.yaml) or device name')
    parser.add_argument('--out', default='workspace.png', help='PNG to write (default: %(default)s)')
    parser.add_argument('--theta-min-deg', type=float, default=0.0)
    parser.add_argument('--theta-max-deg', type=float, default=30.0)
    parser.add_argument('--step-deg', type=float, default=0.1, help='angle step (deg)')
    parser.add_argument('--grid', type=float, default=0.001, help='grid spacing (m)')
    parser.add_argument('--table-every-deg', type=float, default=5.0,
                        help='print the area every this many degrees (default: %(default)s)')
    parser.add_argument('--capacity-theta-deg', type=float, nargs='*', default=None,
                        help='orientation(s) (deg) of the |Fx| capacity map, one panel each '
                             '(default: the home pose\'s; none given: no map)')
    parser.add_argument('--force-limit', type=float, default=None,
                        help='actuator force limit (N) of the capacity map (default: actuator.max_force of the YAML)')
    args = parser.parse_args(argv)

    from ..config import ConfigError, load_device_config
    from ..mechanisms import Rpr3, mechanism_from_config
    try:
        cfg = load_device_config(args.device)
        mech = mechanism_from_config(cfg)
        force_limit = float(cfg.get_path('actuator.max_force')) if args.force_limit is None else args.force_limit
    except (ConfigError, TypeError, ValueError) as exc:
        print(f'brace-workspace: {exc}', file=sys.stderr)
        return 2
    if not isinstance(mech, Rpr3):
        print(f'brace-workspace: {args.device} is not a 3-RPR device', file=sys.stderr)
        return 2
    if not (args.step_deg > 0 and args.grid > 0 and args.theta_max_deg >= args.theta_min_deg):
        print('brace-workspace: need --step-deg > 0, --grid > 0 and theta-max >= theta-min', file=sys.stderr)
        return 2
    if not (force_limit > 0 and np.isfinite(force_limit)):
        print(f'brace-workspace: the actuator force limit must be a positive number of N, got {force_limit!r}',
              file=sys.stderr)
        return 2
    cap_deg = [float(np.degrees(mech.home_pose[2]))] if args.capacity_theta_deg is None else args.capacity_theta_deg
    n = int(round((args.theta_max_deg - args.theta_min_deg) / args.step_deg)) + 1
    theta_deg = args.theta_min_deg + args.step_deg * np.arange(n)
    lo, hi = mech.actuator_limits
    ws = workspace_map(mech.base_anchors, mech.platform_anchors, lo, hi, np.radians(theta_deg),
                       grid=args.grid)
    print(f'{args.device}: {n} angles {theta_deg[0]:.1f}..{theta_deg[-1]:.1f} deg (step {args.step_deg} deg), '
          f'stroke {lo.min() * 1e3:.0f}-{hi.max() * 1e3:.0f} mm, grid {args.grid * 1e3:g} mm, y > 0')
    print(' theta (deg) | area (cm^2)')
    every = max(1, int(round(args.table_every_deg / args.step_deg)))
    for i in list(range(0, n, every)) + ([n - 1] if (n - 1) % every else []):
        print(f' {theta_deg[i]:11.1f} | {ws.area[i] * 1e4:10.2f}')
    print(f'union: {ws.union_area * 1e4:.2f} cm^2 ({int(ws.union.sum())} grid points); '
          f'x {ws.x[0] * 1e3:.0f}..{ws.x[-1] * 1e3:.0f} mm, y {ws.y[0] * 1e3:.0f}..{ws.y[-1] * 1e3:.0f} mm; '
          f'computed in {ws.seconds * 1e3:.0f} ms')
    caps = [capacity_map(mech, ws.x, ws.y, np.radians(d), force_limit) for d in cap_deg]
    home = mech.home_pose
    for d, cm in zip(cap_deg, caps):
        vals = cm.capacity[np.isfinite(cm.capacity)]
        if vals.size == 0:
            print(f'capacity |Fx| at theta = {d:.1f} deg: no grid point within stroke')
            continue
        print(f'capacity |Fx| at theta = {d:.1f} deg ({force_limit:g} N per actuator, {vals.size} grid points): '
              f'min {vals.min():.3g} N, median {np.median(vals):.3g} N, max {vals.max():.3g} N; '
              f'computed in {cm.seconds * 1e3:.0f} ms')
        if abs(np.radians(d) - home[2]) < 1e-12:
            cap, lim = mech.wrench_capacity(home, force_limit, return_limiting=True)
            who = f'limited by actuator {mech.actuator_names[lim[0]]}' if lim[0] >= 0 else 'no actuator limit binds'
            print(f'  at the home pose (x = {home[0] * 1e3:.1f} mm, y = {home[1] * 1e3:.1f} mm): '
                  f'{cap[0]:.3g} N, {who}')
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    _plot(ws, out, f'{Path(str(args.device)).stem}: 3-RPR workspace (y > 0)', caps)
    print(f'wrote {out}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
