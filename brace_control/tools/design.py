"""``brace-design``: the lumbar brace's force-capacity design study, and a layout that pushes sideways.

Why (issue 15). The paper's 3-RPR (seed 001: collinear joints on both rings, ``A = (-r1, 0),
O, (r1, 0)``, ``b = (-r2, 0), 0, (r2, 0)``, eq. 3) has nearly parallel legs over its whole
published workspace: with 250 N actuators it holds 0.71 N sideways at its 5 deg home, and
every ``theta = 0`` pose is singular (the leg lines meet at the rings' homothety centre).
A 15 mm lateral correction against a 2000 N/m trunk needs 30 N.

What is computed, for one layout (anchors ``A_i``, ``b_i`` and each leg's stroke window)
over a *task workspace* (default: ``|x| <= 20 mm``, ``y`` 365-425 mm, ``theta`` 0-30 deg,
100 mm windows, 250 N actuators), on a grid (default 2 mm x 2 mm x 0.5 deg, 39 711 poses):

* reachability: the share of grid poses within every stroke (``Rpr3.inverse_batch``), and
  a *certificate* for the whole box (:func:`length_range`): for each leg and each
  ``theta`` slice the exact shortest and longest length over the ``(x, y)`` rectangle
  (the distance from the annulus centre ``c_i(theta) = A_i - R(theta) b_i`` of the
  paper's eq. 21 / Fig. 9 to the rectangle, and to its farthest corner), widened by
  ``|b_i| dtheta / 2`` between slices (``c_i`` moves on a circle of radius ``|b_i|``, and
  a distance is 1-Lipschitz in it). The whole box is reachable if these bounds fit in
  the windows — not a sampled claim — and the task keeps ``stroke_margin`` (2 mm) from
  the end stops if they fit with that margin;
* force transmission: the smallest capacity per axis (``|Fx|``, ``|Fy|`` N, ``|Mz|`` N·m,
  base frame, each axis alone, both directions) over the reachable grid
  (``Rpr3.wrench_capacity_batch``: ``w_a = min_i limit / |(J^-T)_ia|``), with the pose and
  the actuator that limit it;
* conditioning: the largest ``cond(J)`` (2-norm, ``J`` rows ``(u_i, rho_i x u_i)``: columns
  1-2 dimensionless, column 3 in m);
* singularity loci: grid poses with ``cond(J)`` above the device's
  ``singularity_condition_max`` and whether ``det J`` changes sign across the reachable
  grid (a ``det J = 0`` surface runs through the task workspace);
* what it costs: stroke use and end-stop margins, installed lengths, how far the anchors
  sit off the rings' planes, the device's size, and which legs cross somewhere in the task
  (:func:`leg_clearance`: their pins then need separate layers).

Layouts compared (:func:`alternative_layouts`): the paper's; crossed outer legs; an
inclined middle leg; the outer anchors moved off the rings' diameter (30 deg round the
circles); the device's own layout when it is not the paper's (e.g. ``lumbar_brace_v2``);
and the optimised layout. A hand-made layout's windows are centred on its legs' length
range over the task (:func:`stroke_windows`); the paper keeps 340-440 mm.

The optimiser (:func:`optimise_layout`): ``scipy.optimize.differential_evolution`` (fixed
seed, vectorised over the population) over the six anchors in polar coordinates, base
anchors on or inside the pelvic ring's circle ``|A_i| <= r1``, platform anchors on or inside
the thoracic ring's ``|b_i| <= r2`` (the paper's rings, section IV: ``r1 = 217 mm``,
``r2 = 195 mm``; an anchor off the ring's diameter sits on a bracket of the ring, in the
coronal plane). Each leg's 100 mm window may start anywhere in ``stroke_min_range`` (default
340-540 mm: the drive unit's shortest installed length, plus extension bars of up to
200 mm). The window changes reachability only — not ``J``, not the capacity — so it is not
searched: it is centred on the leg's certified length range (equal margins to both end
stops; exact inner optimisation). Maximised: the smallest ``|Fx|`` capacity over the
optimiser grid (``x``, ``y`` at the box's corners, edges and centre; ``theta`` every 3 deg:
99 poses), subject to

* the *whole* task box reachable, 2 mm from the end stops (the certificate above);
* no singularity inside: ``det J`` of one sign and ``cond(J) <= singularity_condition_max``
  at every optimiser pose;
* ``|Fy| >= 60 N`` and ``|Mz| >= 6 N·m`` everywhere: the same 15 mm correction that needs
  30 N sideways against 2000 N/m needs 60 N vertically against the simulated trunk's
  4000 N/m, and 6 N·m turns it 8.6 deg against 40 N·m/rad (``sim.stiffness``);
* anchors on one ring at least 30 mm apart (two 24 mm actuators' clevises).

Constraints are handled by feasibility rules: a feasible layout scores ``-min |Fx|``, an
infeasible one ``1e4`` plus its summed, normalised violations (so any feasible layout beats
every infeasible one and infeasible ones are ranked by how far off they are). The
optimum is then re-evaluated on the study grid with the mechanism's own batch methods and
on a finer grid (:func:`grid_check`) — the table reports those numbers.

Usage::

    brace-design [config/lumbar_brace.yaml] --out design/ [--task task.yaml]
                 [--x-range -0.02 0.02] [--y-range 0.365 0.425] [--theta-range-deg 0 30]
                 [--seed 1 --maxiter 200 --popsize 15] [--no-optimise]

A task file (``--task``) holds any of :data:`TASK_KEYS` (SI units, ``theta_deg`` in deg);
command-line options override it. Output in ``--out``: ``design.md`` (the table),
``design.json``, ``layouts.png``, ``capacity.png``, ``maps.png`` and, drawn by
``brace-workspace``'s own functions, ``workspace_paper.png`` and ``workspace_optimised.png``.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..mechanisms.capacity import capacity_closed_form
from ..mechanisms.rpr3 import Rpr3
from .workspace import annulus_centres

__all__ = ['Task', 'Layout', 'LayoutReport', 'OptimisationResult', 'TASK_KEYS', 'task_grid', 'length_range',
           'stroke_windows', 'leg_clearance', 'evaluate_layout', 'alternative_layouts', 'paper_layout',
           'optimise_layout', 'decode_layout', 'design_bounds', 'grid_check', 'report_table', 'yaml_snippet', 'main']

#: keys a ``--task`` file may hold (SI units; ``theta_deg`` in degrees)
TASK_KEYS = ('x', 'y', 'theta_deg', 'stroke', 'stroke_margin', 'stroke_min_range', 'force_limit', 'min_fy',
             'min_mz', 'min_anchor_gap', 'max_anchor_offset', 'r1', 'r2', 'reference_pose')
#: a feasible layout scores ``-min |Fx|``; an infeasible one this plus its violations
_INFEASIBLE = 1.0e4
#: certificate slices (rad): the length bounds are widened by ``|b_i| * step / 2``
_CERT_STEP_RAD = math.radians(0.5)
#: upper stroke of the "kinematics only" model that gives lengths and J of any pose (m)
_NO_STROKE = (0.0, 10.0)
_AXES = ('Fx', 'Fy', 'Mz')
_PAIRS = ((0, 1), (0, 2), (1, 2))
_UNITS = ('N', 'N', 'N·m')


# ---------------------------------------------------------------------------- the task
@dataclass(frozen=True)
class Task:
    """The task workspace and the requirements of the study (SI units).

    :param x: ``(lo, hi)`` of the thoracic ring's lateral position (m).
    :param y: ``(lo, hi)`` of its height above the pelvic ring (m).
    :param theta: ``(lo, hi)`` coronal rotation (rad).
    :param stroke: length of each actuator's stroke window (m).
    :param stroke_margin: the task keeps this far from either end stop (m): load-cell and
        pin compliance (250 N at 1e6 N/m: 0.25 mm), homing and following error.
    :param stroke_min_range: ``(lo, hi)``: where a window may start (m), the drive unit's
        shortest installed length up to that plus the longest extension bar.
    :param force_limit: actuator force limit (N), push and pull.
    :param min_fy: required ``|Fy|`` capacity everywhere (N).
    :param min_mz: required ``|Mz|`` capacity everywhere (N·m).
    :param min_anchor_gap: smallest distance between two anchors on one ring (m).
    :param max_anchor_offset: if given, anchors at most this far above or below their ring's
        plane (m; brackets on the rings); default: anywhere in the rings' circles.
    :param r1: pelvic ring radius (m): base anchors on or inside ``|A| <= r1``.
    :param r2: thoracic ring radius (m): platform anchors ``|b| <= r2``.
    :param condition_max: ``cond(J)`` above this is singular (the device's limit).
    :param reference_pose: a pose every layout's capacity is also reported at (the
        paper's home, ``(0, 390 mm, 5 deg)``).
    """

    x: tuple[float, float] = (-0.020, 0.020)
    y: tuple[float, float] = (0.365, 0.425)
    theta: tuple[float, float] = (0.0, math.radians(30.0))
    stroke: float = 0.100
    stroke_margin: float = 0.002
    stroke_min_range: tuple[float, float] = (0.340, 0.540)
    force_limit: float = 250.0
    min_fy: float = 60.0
    min_mz: float = 6.0
    min_anchor_gap: float = 0.030
    max_anchor_offset: float | None = None
    r1: float = 0.217
    r2: float = 0.195
    condition_max: float = 1.0e4
    reference_pose: tuple[float, float, float] = (0.0, 0.390, math.radians(5.0))

    def __post_init__(self) -> None:
        for name in ('x', 'y', 'theta', 'stroke_min_range'):
            lo, hi = getattr(self, name)
            if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
                raise ValueError(f'task {name}: expected (lo, hi) with lo <= hi, got ({lo!r}, {hi!r})')
        for name in ('stroke', 'force_limit', 'r1', 'r2', 'condition_max'):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0.0):
                raise ValueError(f'task {name}: expected a positive number, got {v!r}')
        for name in ('min_fy', 'min_mz', 'min_anchor_gap', 'stroke_margin'):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0.0):
                raise ValueError(f'task {name}: expected a number >= 0, got {v!r}')
        if 2.0 * self.stroke_margin >= self.stroke:
            raise ValueError(f'task stroke_margin: {self.stroke_margin} m at both ends leaves nothing of the '
                             f'{self.stroke} m stroke')
        if self.max_anchor_offset is not None and not (math.isfinite(self.max_anchor_offset)
                                                       and self.max_anchor_offset >= 0.0):
            raise ValueError(f'task max_anchor_offset: expected a number >= 0 (m) or none, got '
                             f'{self.max_anchor_offset!r}')
        if self.stroke_min_range[0] <= 0.0:
            raise ValueError(f'task stroke_min_range: a window must start above 0 m, got {self.stroke_min_range}')
        if len(self.reference_pose) != 3 or not all(math.isfinite(v) for v in self.reference_pose):
            raise ValueError(f'task reference_pose: expected (x m, y m, theta rad), got {self.reference_pose!r}')

    @property
    def centre(self) -> np.ndarray:
        """The task box's centre pose ``(x, y, theta)``."""
        return np.array([sum(self.x) / 2, sum(self.y) / 2, sum(self.theta) / 2])

    def describe(self) -> str:
        return (f'x {self.x[0] * 1e3:g}..{self.x[1] * 1e3:g} mm, y {self.y[0] * 1e3:g}..{self.y[1] * 1e3:g} mm, '
                f'theta {math.degrees(self.theta[0]):g}..{math.degrees(self.theta[1]):g} deg; '
                f'{self.stroke * 1e3:g} mm windows starting at {self.stroke_min_range[0] * 1e3:g}-'
                f'{self.stroke_min_range[1] * 1e3:g} mm, {self.stroke_margin * 1e3:g} mm from the end stops; '
                f'{self.force_limit:g} N actuators')


def task_grid(task: Task, step_m: float = 0.002, step_deg: float = 0.5
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Grid of the task box, both ends of every axis included.

    :param step_m: largest spacing of ``x`` and ``y`` (m).
    :param step_deg: largest spacing of ``theta`` (deg).
    :returns: ``(x, y, theta, poses)``: axes (m, m, rad) and poses (nx * ny * nt, 3), ordered
        as ``np.meshgrid(x, y, theta, indexing='ij')``.
    :raises ValueError: a non-positive step.
    """
    if not (step_m > 0.0 and step_deg > 0.0):
        raise ValueError(f'grid steps must be positive, got {step_m!r} m and {step_deg!r} deg')

    def axis(lo: float, hi: float, step: float) -> np.ndarray:
        return np.linspace(lo, hi, max(2, int(math.ceil((hi - lo) / step - 1e-9)) + 1)) if hi > lo else np.array([lo])
    x = axis(*task.x, step_m)
    y = axis(*task.y, step_m)
    t = axis(*task.theta, math.radians(step_deg))
    gx, gy, gt = np.meshgrid(x, y, t, indexing='ij')
    return x, y, t, np.column_stack([gx.ravel(), gy.ravel(), gt.ravel()])


# ---------------------------------------------------------------------------- layouts
@dataclass(frozen=True)
class Layout:
    """A 3-RPR layout: anchors (m) and each actuator's installed-length window (m)."""

    name: str
    base_anchors: np.ndarray          #: ``A_i`` (3, 2) in the base frame (pelvic ring centre)
    platform_anchors: np.ndarray      #: ``b_i`` (3, 2) in the platform frame (thoracic ring centre)
    stroke_min: np.ndarray            #: (3,) shortest installed lengths
    stroke_max: np.ndarray            #: (3,) longest installed lengths

    def mechanism(self, home_pose: Sequence[float] | None = None, *, condition_max: float = 1.0e4) -> Rpr3:
        """The layout as the library's :class:`~brace_control.mechanisms.Rpr3`."""
        return Rpr3(self.base_anchors, self.platform_anchors, (self.stroke_min, self.stroke_max),
                    home_pose=home_pose, singularity_condition_max=condition_max)

    def kinematics(self, task: Task) -> Rpr3:
        """The same anchors without stroke limits: lengths and ``J`` of any pose."""
        return Rpr3(self.base_anchors, self.platform_anchors, _NO_STROKE, home_pose=task.centre,
                    singularity_condition_max=task.condition_max)

    def as_dict(self) -> dict[str, Any]:
        return {'name': self.name, 'base_anchors': self.base_anchors.tolist(),
                'platform_anchors': self.platform_anchors.tolist(),
                'stroke_min': self.stroke_min.tolist(), 'stroke_max': self.stroke_max.tolist()}


def length_range(base_anchors: np.ndarray, platform_anchors: np.ndarray, task: Task,
                 step_rad: float = _CERT_STEP_RAD) -> tuple[np.ndarray, np.ndarray]:
    """Certified bounds of each leg's length over the whole task box (m).

    Leg ``i`` at pose ``(x, y, theta)`` is ``|P - c_i(theta)|``, ``c_i = A_i - R(theta) b_i`` (the
    centre of the paper's eq. 21 annulus). Per ``theta`` slice the exact shortest length over
    the ``(x, y)`` rectangle is the distance from ``c_i`` to the rectangle, the longest the
    distance to its farthest corner. Between slices ``dtheta`` apart, ``c_i`` moves by at most
    ``|b_i| dtheta / 2`` from the nearest slice, so the bounds are widened by that.

    :returns: ``(lmin, lmax)``, each (3,): every pose of the box has
        ``lmin_i <= l_i <= lmax_i``.
    """
    t0, t1 = task.theta
    n = max(2, int(math.ceil((t1 - t0) / step_rad - 1e-9)) + 1) if t1 > t0 else 1
    theta = np.linspace(t0, t1, n)
    dth = (t1 - t0) / (n - 1) if n > 1 else 0.0
    c = annulus_centres(np.asarray(base_anchors, float), np.asarray(platform_anchors, float), theta)
    cx, cy = c[..., 0], c[..., 1]                                        # (n, 3)
    (x0, x1), (y0, y1) = task.x, task.y
    far = np.hypot(np.maximum(np.abs(x0 - cx), np.abs(x1 - cx)), np.maximum(np.abs(y0 - cy), np.abs(y1 - cy)))
    near = np.hypot(np.clip(cx, x0, x1) - cx, np.clip(cy, y0, y1) - cy)
    slack = np.linalg.norm(np.asarray(platform_anchors, float), axis=1) * dth / 2.0
    return near.min(axis=0) - slack, far.max(axis=0) + slack


def stroke_windows(base_anchors: np.ndarray, platform_anchors: np.ndarray, task: Task
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Each leg's window centred on its certified length range, its start within
    ``task.stroke_min_range``.

    :returns: ``(stroke_min, lmin, lmax, excess)``, each (3,): ``excess_i >= 0`` is how far (m)
        the leg's range sticks out of its window less ``task.stroke_margin`` at both ends (0:
        every pose of the box is reachable with that margin).
    """
    lmin, lmax = length_range(base_anchors, platform_anchors, task)
    lo = np.clip(0.5 * (lmin + lmax) - 0.5 * task.stroke, *task.stroke_min_range)
    m = task.stroke_margin
    excess = np.maximum(np.maximum(lo + m - lmin, lmax - (lo + task.stroke - m)), 0.0)
    return lo, lmin, lmax, excess


def _centred(name: str, base: np.ndarray, plat: np.ndarray, task: Task) -> Layout:
    lo = stroke_windows(base, plat, task)[0]
    return Layout(name, base, plat, lo, lo + task.stroke)


def paper_layout(r1: float = 0.217, r2: float = 0.195, stroke: tuple[float, float] = (0.340, 0.440)) -> Layout:
    """The paper's brace (seed 001, eq. 3): ``A = (-r1, 0), O, (r1, 0)``, ``b = (-r2, 0), 0, (r2, 0)``."""
    return Layout('paper', np.array([[-r1, 0.0], [0.0, 0.0], [r1, 0.0]]),
                  np.array([[-r2, 0.0], [0.0, 0.0], [r2, 0.0]]),
                  np.full(3, float(stroke[0])), np.full(3, float(stroke[1])))


def alternative_layouts(task: Task, paper: Layout | None = None) -> list[Layout]:
    """The paper's layout and three hand-made alternatives (windows centred on the task).

    * ``crossed``: the outer legs swap sides (``A1 -> b3``, ``A3 -> b1``): steep legs, but
      the joints stay collinear with one division ratio, so ``theta = 0`` stays singular (the
      lines now meet between the rings);
    * ``inclined middle``: the middle leg from ``(-r1/2, 0)`` to ``(r2/2, 0)`` (28 deg): the
      division ratios differ, the ``theta = 0`` singularity is gone;
    * ``off diameter``: the outer base anchors 30 deg below the pelvic ring's diameter,
      the outer platform anchors 30 deg above the thoracic ring's (``A = r1 (cos 210, sin 210)``
      ...): a mirror-symmetric layout with the middle leg on the axis, so the legs still
      meet on the axis at ``x = 0, theta = 0``.
    """
    r1, r2 = task.r1, task.r2
    paper = paper if paper is not None else paper_layout(r1, r2)
    c30, s30 = math.cos(math.radians(30.0)), math.sin(math.radians(30.0))
    out = [paper]
    out.append(_centred('crossed', paper.base_anchors, paper.platform_anchors[::-1].copy(), task))
    out.append(_centred('inclined middle', np.array([[-r1, 0.0], [-r1 / 2, 0.0], [r1, 0.0]]),
                        np.array([[-r2, 0.0], [r2 / 2, 0.0], [r2, 0.0]]), task))
    out.append(_centred('off diameter', np.array([[-r1 * c30, -r1 * s30], [0.0, 0.0], [r1 * c30, -r1 * s30]]),
                        np.array([[-r2 * c30, r2 * s30], [0.0, 0.0], [r2 * c30, r2 * s30]]), task))
    return out


# ---------------------------------------------------------------------------- evaluation
@dataclass
class LayoutReport:
    """What :func:`evaluate_layout` found for one layout (SI units)."""

    layout: Layout
    n_poses: int                          #: grid poses
    reach_fraction: float                 #: share of grid poses within every stroke
    reach_certified: bool                 #: the whole box is within every stroke (:func:`length_range`)
    length_bounds: np.ndarray             #: (3, 2) certified length range over the box (m)
    min_capacity: np.ndarray              #: (3,) smallest capacity per axis over the reachable grid
    min_pose: np.ndarray                  #: (3, 3) pose of each minimum
    min_limiting: list[str]               #: actuator limiting each minimum ('' if none binds)
    reference_capacity: np.ndarray        #: (3,) at ``task.reference_pose`` (NaN: unreachable there)
    worst_condition: float                #: largest cond(J) over the reachable grid
    n_singular: int                       #: reachable grid poses with cond(J) > task.condition_max
    singular_theta_deg: tuple[float, float] | None   #: theta range of those poses
    det_sign_change: bool                 #: det J takes both signs on the regular reachable grid
    leg_clearance: np.ndarray             #: (3,) closest approach of legs (a1, a2), (a1, a3), (a2, a3) (m)
    grid_lengths: np.ndarray = field(repr=False)     #: (N, 3) lengths (NaN unreachable)
    capacity: np.ndarray = field(repr=False)         #: (N, 3) capacities (NaN unreachable)
    condition: np.ndarray = field(repr=False)        #: (N,) cond(J) (NaN unreachable)
    det: np.ndarray = field(repr=False)              #: (N,) det J (NaN unreachable)
    axes: tuple[np.ndarray, np.ndarray, np.ndarray] = field(repr=False)  #: grid x, y, theta
    seconds: float = 0.0

    #: actuator names, in leg order
    layout_names: tuple[str, ...] = ('a1', 'a2', 'a3')

    @property
    def singular_free(self) -> bool:
        return self.n_singular == 0 and not self.det_sign_change

    @property
    def end_margin(self) -> np.ndarray:
        """(3,) how far (m) each leg's certified task range stays from its end stops (< 0: out of stroke)."""
        return np.minimum(self.length_bounds[:, 0] - self.layout.stroke_min,
                          self.layout.stroke_max - self.length_bounds[:, 1])

    def failures(self, task: Task) -> list[str]:
        """The requirements of ``task`` this layout misses (empty: it meets them all)."""
        out = []
        if not self.reach_certified:
            out.append('task not within stroke')
        elif np.min(self.end_margin) < task.stroke_margin - 1e-9:
            out.append(f'end-stop margin < {task.stroke_margin * 1e3:g} mm')
        if not self.singular_free:
            out.append('singular in the task')
        if not self.min_capacity[1] >= task.min_fy:
            out.append(f'|Fy| < {task.min_fy:g} N')
        if not self.min_capacity[2] >= task.min_mz:
            out.append(f'|Mz| < {task.min_mz:g} N·m')
        lay = self.layout
        if min(_min_gap(lay.base_anchors[None])[0], _min_gap(lay.platform_anchors[None])[0]) < \
                task.min_anchor_gap - 1e-9:
            out.append(f'anchors < {task.min_anchor_gap * 1e3:g} mm apart')
        if task.max_anchor_offset is not None and _anchor_offset(lay) > task.max_anchor_offset + 1e-9:
            out.append(f'anchor > {task.max_anchor_offset * 1e3:g} mm off its ring')
        return out

    def meets(self, task: Task) -> bool:
        """Every requirement of ``task`` met (:meth:`failures` is empty)."""
        return not self.failures(task)

    def stroke_use(self) -> np.ndarray:
        """(3,) certified length range over the box / window length (> 1: does not fit)."""
        span = self.length_bounds[:, 1] - self.length_bounds[:, 0]
        return span / (self.layout.stroke_max - self.layout.stroke_min)


def _anchor_offset(lay: Layout) -> float:
    """The farthest an anchor sits above or below its ring's plane (m)."""
    return float(max(np.max(np.abs(lay.base_anchors[:, 1])), np.max(np.abs(lay.platform_anchors[:, 1]))))


def leg_clearance(base_anchors: np.ndarray, platform_anchors: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """Closest approach (m) of two leg axes ``A_i B_i``, ``A_j B_j`` per pose and pair (N, 3), pairs
    (a1, a2), (a1, a3), (a2, a3): 0 where the two legs cross (their pins need separate layers),
    else the smallest endpoint-to-segment distance."""
    p = np.asarray(poses, float)
    c, s = np.cos(p[:, 2])[:, None], np.sin(p[:, 2])[:, None]
    b = np.stack([p[:, 0, None] + c * platform_anchors[:, 0] - s * platform_anchors[:, 1],
                  p[:, 1, None] + s * platform_anchors[:, 0] + c * platform_anchors[:, 1]], axis=-1)   # (N, 3, 2)
    a = np.broadcast_to(np.asarray(base_anchors, float), b.shape)

    def cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]

    def point_segment(q: np.ndarray, s0: np.ndarray, s1: np.ndarray) -> np.ndarray:
        d = s1 - s0
        t = np.clip(np.sum((q - s0) * d, axis=-1) / np.maximum(np.sum(d * d, axis=-1), 1e-300), 0.0, 1.0)
        return np.linalg.norm(q - (s0 + t[:, None] * d), axis=-1)

    out = np.empty((p.shape[0], 3))
    for k, (i, j) in enumerate(_PAIRS):
        p0, p1, q0, q1 = a[:, i], b[:, i], a[:, j], b[:, j]
        d1, d2 = cross(p1 - p0, q0 - p0), cross(p1 - p0, q1 - p0)
        d3, d4 = cross(q1 - q0, p0 - q0), cross(q1 - q0, p1 - q0)
        hit = (d1 * d2 < 0.0) & (d3 * d4 < 0.0)
        dist = np.minimum.reduce([point_segment(p0, q0, q1), point_segment(p1, q0, q1),
                                  point_segment(q0, p0, p1), point_segment(q1, p0, p1)])
        out[:, k] = np.where(hit, 0.0, dist)
    return out


def _reachable_home(layout: Layout, task: Task, poses: np.ndarray) -> np.ndarray | None:
    """A pose for the model's ``home_pose``: the reference pose, the centre or a grid pose within stroke."""
    kin = layout.kinematics(task)
    lo, hi = layout.stroke_min, layout.stroke_max
    cands = np.vstack([np.asarray(task.reference_pose, float), task.centre, poses])
    q = kin.inverse_batch(cands, limits=False)
    ok = np.all((q >= lo) & (q <= hi), axis=1)
    return cands[int(np.argmax(ok))] if ok.any() else None


def evaluate_layout(layout: Layout, task: Task, *, step_m: float = 0.002, step_deg: float = 0.5) -> LayoutReport:
    """Reachability, capacity per axis, conditioning and singular loci of ``layout`` over the
    task grid, with the library's batch methods (``inverse_batch``, ``jacobian_batch``,
    ``wrench_capacity_batch``; see the module docstring)."""
    t0 = time.perf_counter()
    x, y, t, poses = task_grid(task, step_m, step_deg)
    n = poses.shape[0]
    lmin, lmax = length_range(layout.base_anchors, layout.platform_anchors, task)
    certified = bool(np.all(lmin >= layout.stroke_min) and np.all(lmax <= layout.stroke_max))
    lengths = np.full((n, 3), np.nan)
    cap = np.full((n, 3), np.nan)
    cond = np.full(n, np.nan)
    det = np.full(n, np.nan)
    min_cap, min_pose, min_lim = np.full(3, np.nan), np.full((3, 3), np.nan), ['', '', '']
    ref_cap = np.full(3, np.nan)
    worst, n_sing, sing_th, sign_change, clearance = math.nan, 0, None, False, np.full(3, np.nan)
    home = _reachable_home(layout, task, poses)
    if home is not None:
        mech = layout.mechanism(home, condition_max=task.condition_max)
        lengths = mech.inverse_batch(poses)
        reach = ~np.isnan(lengths).any(axis=1)
        jac = mech.jacobian_batch(poses[reach])
        sv = np.linalg.svd(jac, compute_uv=False)
        with np.errstate(divide='ignore'):
            cond[reach] = np.where(sv[:, -1] > 0.0, sv[:, 0] / sv[:, -1], np.inf)
        det[reach] = np.linalg.det(jac)
        c, lim = mech.wrench_capacity_batch(poses[reach], task.force_limit, return_limiting=True)
        cap[reach] = c
        idx = np.flatnonzero(reach)
        for a in range(3):
            k = int(np.argmin(c[:, a]))
            min_cap[a], min_pose[a] = c[k, a], poses[idx[k]]
            min_lim[a] = mech.actuator_names[lim[k, a]] if lim[k, a] >= 0 else ''
        worst = float(np.max(cond[reach]))
        singular = reach & (cond > task.condition_max)
        n_sing = int(singular.sum())
        if n_sing:
            th = np.degrees(poses[singular, 2])
            sing_th = (float(th.min()), float(th.max()))
        regular = reach & ~singular
        sign_change = bool(np.any(det[regular] > 0.0) and np.any(det[regular] < 0.0))
        clearance = np.min(leg_clearance(layout.base_anchors, layout.platform_anchors, poses[reach]), axis=0)
        ref = np.asarray(task.reference_pose, float)
        if mech.reachable_batch(ref[None])[0]:
            ref_cap = mech.wrench_capacity(ref, task.force_limit)
    return LayoutReport(layout, n, float(np.mean(~np.isnan(lengths).any(axis=1))), certified,
                        np.column_stack([lmin, lmax]), min_cap, min_pose, min_lim, ref_cap, worst, n_sing, sing_th,
                        sign_change, clearance, lengths, cap, cond, det, (x, y, t), time.perf_counter() - t0)


def grid_check(layout: Layout, task: Task, grids: Sequence[tuple[float, float]] = ((0.004, 2.0), (0.002, 0.5),
                                                                                    (0.001, 0.25))
               ) -> list[tuple[float, float, int, np.ndarray, float]]:
    """The smallest capacities on grids of increasing density (is the grid fine enough?).

    :returns: per grid ``(step_m, step_deg, n_poses, min_capacity (3,), worst cond)``.
    """
    out = []
    for step_m, step_deg in grids:
        r = evaluate_layout(layout, task, step_m=step_m, step_deg=step_deg)
        out.append((step_m, step_deg, r.n_poses, r.min_capacity, r.worst_condition))
    return out


# ---------------------------------------------------------------------------- optimiser
@dataclass
class OptimisationResult:
    """The optimiser's best layout and its run (SI units)."""

    layout: Layout
    vector: np.ndarray            #: the design vector (see :func:`decode_layout`)
    feasible: bool                #: every constraint met on the optimiser grid and the certificate
    min_capacity: np.ndarray      #: (3,) on the optimiser grid
    energy: float                 #: ``-min |Fx|`` if feasible, else ``1e4 +`` violations
    nfev: int                     #: layouts evaluated
    nit: int                      #: generations
    seconds: float
    seed: int
    n_poses: int                  #: optimiser grid poses


def design_bounds() -> list[tuple[float, float]]:
    """Bounds of the design vector: per anchor (``A_1..A_3``, then ``b_1..b_3``) the squared
    radius fraction ``s`` in [0, 1] and the polar angle ``phi`` (rad) in [-pi, pi]."""
    return [(0.0, 1.0), (-math.pi, math.pi)] * 6


def _anchors(vectors: np.ndarray, task: Task) -> tuple[np.ndarray, np.ndarray]:
    """Design vectors (S, 12) -> base anchors (S, 3, 2) and platform anchors (S, 3, 2) (m):
    anchor ``k`` at ``r sqrt(s_k) (cos phi_k, sin phi_k)`` (``r = r1`` for the base, ``r2`` for
    the platform; ``sqrt``: uniform over the disc)."""
    v = np.asarray(vectors, dtype=float).reshape(-1, 6, 2)
    rad = np.sqrt(np.clip(v[..., 0], 0.0, 1.0))[..., None]
    pts = rad * np.stack([np.cos(v[..., 1]), np.sin(v[..., 1])], axis=-1)
    return task.r1 * pts[:, :3], task.r2 * pts[:, 3:]


def decode_layout(vector: np.ndarray, task: Task, name: str = 'optimised') -> Layout:
    """Design vector (12,) -> :class:`Layout` (anchors: :func:`_anchors`; windows:
    :func:`stroke_windows`)."""
    base, plat = _anchors(vector, task)
    return _centred(name, base[0], plat[0], task)


def _optimiser_poses(task: Task, theta_step_deg: float) -> np.ndarray:
    xs = np.linspace(*task.x, 3)
    ys = np.linspace(*task.y, 3)
    n = max(2, int(math.ceil(math.degrees(task.theta[1] - task.theta[0]) / theta_step_deg - 1e-9)) + 1)
    ts = np.linspace(*task.theta, n)
    g = np.meshgrid(xs, ys, ts, indexing='ij')
    return np.column_stack([a.ravel() for a in g])


def _min_gap(points: np.ndarray) -> np.ndarray:
    """Smallest distance between two of three points, points (S, 3, 2) -> (S,) (m)."""
    return np.min(np.stack([np.hypot(*(points[:, i] - points[:, j]).T) for i, j in ((0, 1), (0, 2), (1, 2))]), axis=0)


def _score(vectors: np.ndarray, task: Task, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Energies (S,), feasibility (S,) and grid minima (S, 3) of design vectors (S, 12).

    Per layout: the certificate and windows (:func:`stroke_windows`), ``J`` from the library
    (``Rpr3.jacobian_batch``); then for all layouts' poses at once ``cond(J)``, ``det J``
    and the closed-form capacity (``capacity_closed_form`` of :mod:`~brace_control.mechanisms.capacity`,
    on the regular poses; a pose beyond ``condition_max`` counts 0).
    """
    s_count, g_count = vectors.shape[0], poses.shape[0]
    base, plat = _anchors(vectors, task)
    gap = np.minimum(_min_gap(base), _min_gap(plat))
    excess = np.zeros(s_count)
    jac = np.zeros((s_count, g_count, 3, 3))
    broken = np.zeros(s_count, dtype=bool)
    for k in range(s_count):
        excess[k] = float(np.max(stroke_windows(base[k], plat[k], task)[3]))
        try:
            kin = Rpr3(base[k], plat[k], _NO_STROKE, home_pose=task.centre)
            jac[k] = kin.jacobian_batch(poses, limits=False)
        except ValueError:                       # two identical legs, a zero-length leg: not a mechanism
            broken[k] = True
    broken |= ~np.isfinite(jac).all(axis=(1, 2, 3))
    jac[broken] = np.eye(3)
    flat = jac.reshape(-1, 3, 3)
    sv = np.linalg.svd(flat, compute_uv=False)
    with np.errstate(divide='ignore'):
        cond = np.where(sv[:, -1] > 0.0, sv[:, 0] / sv[:, -1], np.inf)
    regular = cond <= task.condition_max
    cap = np.zeros((flat.shape[0], 3))
    if regular.any():
        g = np.swapaxes(flat[regular], -1, -2)                           # W = J^T f
        m = int(regular.sum())
        lim = np.full((m, 3), task.force_limit)
        cap[regular] = capacity_closed_form(np.linalg.inv(g), -lim, lim)[0]
    cap = cap.reshape(s_count, g_count, 3)
    mins = cap.min(axis=1)
    det = np.linalg.det(jac)
    minority = np.minimum(np.mean(det > 0.0, axis=1), np.mean(det < 0.0, axis=1))
    beyond = np.mean(~regular.reshape(s_count, g_count), axis=1)
    violation = (excess / 0.010 + 10.0 * minority + beyond
                 + np.maximum(0.0, task.min_fy - mins[:, 1]) / max(task.min_fy, 1.0)
                 + np.maximum(0.0, task.min_mz - mins[:, 2]) / max(task.min_mz, 1.0)
                 + np.maximum(0.0, task.min_anchor_gap - gap) / max(task.min_anchor_gap, 1e-3))
    if task.max_anchor_offset is not None:
        offset = np.maximum(np.max(np.abs(base[..., 1]), axis=1), np.max(np.abs(plat[..., 1]), axis=1))
        violation = violation + np.maximum(0.0, offset - task.max_anchor_offset) / 0.010
    violation = np.where(broken, 1.0e3, violation)
    feasible = violation <= 0.0
    energy = np.where(feasible, -mins[:, 0], _INFEASIBLE + violation)
    return energy, feasible, mins


def optimise_layout(task: Task, *, seed: int = 1, maxiter: int = 200, popsize: int = 15,
                    theta_step_deg: float = 3.0) -> OptimisationResult:
    """Maximise the smallest ``|Fx|`` capacity over the task (see the module docstring).

    ``scipy.optimize.differential_evolution`` (``best1bin``, recombination 0.9 — the polar
    coordinates of one anchor are coupled, so trial vectors take most coordinates of the
    mutant together; seeds 1-3 then agree within 2 %, at the default 0.7 within 10 % —
    Latin hypercube start, no polishing: the objective is a minimum, not smooth),
    ``rng=seed``, vectorised over the population (``updating='deferred'``); deterministic
    for a given seed and budget.

    :param maxiter: generations; ``popsize``: population = ``popsize * 12``.
    :param theta_step_deg: ``theta`` spacing of the optimiser grid (deg).
    """
    from scipy.optimize import differential_evolution
    if maxiter < 1 or popsize < 1:
        raise ValueError(f'maxiter and popsize must be >= 1, got {maxiter} and {popsize}')
    t0 = time.perf_counter()
    poses = _optimiser_poses(task, theta_step_deg)

    evaluated = 0

    def energies(x: np.ndarray) -> np.ndarray:             # x (12, S)
        nonlocal evaluated
        vectors = np.atleast_2d(x.T)
        evaluated += vectors.shape[0]
        return _score(vectors, task, poses)[0]

    res = differential_evolution(energies, design_bounds(), rng=seed, maxiter=maxiter, popsize=popsize,
                                 tol=1e-9, recombination=0.9, polish=False, init='latinhypercube', vectorized=True,
                                 updating='deferred')
    energy, feasible, mins = _score(res.x[None, :], task, poses)
    return OptimisationResult(decode_layout(res.x, task), np.asarray(res.x, float), bool(feasible[0]), mins[0],
                              float(energy[0]), evaluated, int(res.nit), time.perf_counter() - t0, seed,
                              poses.shape[0])


# ---------------------------------------------------------------------------- report
def _mm(v: float) -> str:
    return f'{v * 1e3:.1f}'


def _points_mm(p: np.ndarray) -> str:
    return ', '.join(f'({a * 1e3:.1f}, {b * 1e3:.1f})' for a, b in p)


def _pose_text(p: np.ndarray) -> str:
    return f'({p[0] * 1e3:.0f}, {p[1] * 1e3:.0f} mm, {math.degrees(p[2]):.1f}°)'


def _layout_size(lay: Layout, pose: Sequence[float], task: Task) -> tuple[float, float, float]:
    """Anchors' farthest offset from the ring planes (m), and width and height (m) of the device
    at ``pose``: the rings (``2 r1``, ``2 r2`` across, seen edge-on in the coronal plane) and the
    anchors."""
    p = np.asarray(pose, float)
    c, s = math.cos(p[2]), math.sin(p[2])
    rot_t = np.array([[c, s], [-s, c]])                                  # row vectors: v @ R^T
    ring2 = np.array([[-task.r2, 0.0], [task.r2, 0.0]])
    pts = np.vstack([lay.base_anchors, [[-task.r1, 0.0], [task.r1, 0.0]],
                     p[:2] + lay.platform_anchors @ rot_t, p[:2] + ring2 @ rot_t])
    return _anchor_offset(lay), float(np.ptp(pts[:, 0])), float(np.ptp(pts[:, 1]))


def report_table(reports: Sequence[LayoutReport], task: Task) -> str:
    """The comparison as a Markdown table (one column per layout)."""
    names = [r.layout.name for r in reports]
    rows: list[tuple[str, list[str]]] = []

    def cap_cell(r: LayoutReport, a: int) -> str:
        if not np.isfinite(r.min_capacity[a]):
            return '—'
        who = f', {r.min_limiting[a]}' if r.min_limiting[a] else ''
        return f'**{r.min_capacity[a]:.3g}** at {_pose_text(r.min_pose[a])}{who}'

    rows.append(('task grid reachable', [f'{100 * r.reach_fraction:.1f} %' for r in reports]))
    rows.append(('whole task box within stroke (certified)', ['yes' if r.reach_certified else 'no' for r in reports]))
    for a in range(3):
        rows.append((f'min \\|{_AXES[a]}\\| ({_UNITS[a]}), reachable grid', [cap_cell(r, a) for r in reports]))
    ref = task.reference_pose
    rows.append((f'\\|Fx\\| / \\|Fy\\| / \\|Mz\\| at {_pose_text(np.asarray(ref))}',
                 ['unreachable' if not np.isfinite(r.reference_capacity[0]) else
                  f'{r.reference_capacity[0]:.3g} / {r.reference_capacity[1]:.3g} / {r.reference_capacity[2]:.3g}'
                  for r in reports]))
    rows.append(('worst cond(J)', [f'{r.worst_condition:.3g}' for r in reports]))
    rows.append((f'singular poses (cond > {task.condition_max:.0e})',
                 [f'{r.n_singular}' + (f' (θ {r.singular_theta_deg[0]:.1f}–{r.singular_theta_deg[1]:.1f}°)'
                                       if r.singular_theta_deg else '') for r in reports]))
    rows.append(('det J changes sign', ['yes' if r.det_sign_change else 'no' for r in reports]))
    rows.append(('stroke windows (mm)', [' / '.join(f'{_mm(lo)}–{_mm(hi)}' for lo, hi in
                                                     zip(r.layout.stroke_min, r.layout.stroke_max)) for r in reports]))
    rows.append(('task length range per leg (mm)', [' / '.join(f'{_mm(lo)}–{_mm(hi)}' for lo, hi in r.length_bounds)
                                                    for r in reports]))
    rows.append(('stroke use (task range / window)', [' / '.join(f'{100 * u:.0f} %' for u in r.stroke_use())
                                                      for r in reports]))
    rows.append(('end-stop margin per leg (mm)', [' / '.join(f'{_mm(m)}' for m in r.end_margin) for r in reports]))
    def crossing(r: LayoutReport) -> str:
        if not np.isfinite(r.leg_clearance).all():
            return '—'
        names = r.layout_names
        pairs = [f'{names[i]}×{names[j]}' for k, (i, j) in enumerate(_PAIRS) if r.leg_clearance[k] == 0.0]
        return ', '.join(pairs) if pairs else f'none (closest {np.min(r.leg_clearance) * 1e3:.0f} mm apart)'
    rows.append(('legs crossing somewhere in the task (pins in separate layers)', [crossing(r) for r in reports]))
    sizes = [_layout_size(r.layout, ref, task) for r in reports]
    rows.append(('longest installed length (mm)', [f'{np.max(r.layout.stroke_max) * 1e3:.0f}' for r in reports]))
    rows.append(('anchor offset from ring plane (mm)', [f'{s[0] * 1e3:.0f}' for s in sizes]))
    rows.append(('rings and anchors: width × height at the reference pose (mm)',
                 [f'{s[1] * 1e3:.0f} × {s[2] * 1e3:.0f}' for s in sizes]))
    rows.append(('base anchors A (mm)', [_points_mm(r.layout.base_anchors) for r in reports]))
    rows.append(('platform anchors b (mm)', [_points_mm(r.layout.platform_anchors) for r in reports]))
    rows.append(('meets every requirement', ['**yes**' if r.meets(task) else 'no: ' + ', '.join(r.failures(task))
                                             for r in reports]))
    lines = ['| | ' + ' | '.join(names) + ' |', '|---|' + '---|' * len(names)]
    lines += [f'| {label} | ' + ' | '.join(c.replace('|', '\\|') for c in cells) + ' |' for label, cells in rows]
    return '\n'.join(lines)


def _print_summary(reports: Sequence[LayoutReport]) -> None:
    print(f' {"layout":<16} | reach  | cert | min |Fx| N | min |Fy| N | min |Mz| N·m | worst cond | singular | det±')
    for r in reports:
        print(f' {r.layout.name:<16} | {100 * r.reach_fraction:5.1f}% | {"yes" if r.reach_certified else "no ":>4} | '
              f'{r.min_capacity[0]:10.4g} | {r.min_capacity[1]:10.4g} | {r.min_capacity[2]:12.4g} | '
              f'{r.worst_condition:10.3g} | {r.n_singular:8d} | {"yes" if r.det_sign_change else "no"}')


def yaml_snippet(lay: Layout, home_pose: Sequence[float]) -> str:
    """The ``mechanism`` keys of a device YAML for ``lay`` (0.1 mm, flattened point lists)."""
    def flat(p: np.ndarray) -> str:
        return '[' + ', '.join(f'{v:.4f}' for v in np.round(p.ravel(), 4)) + ']'
    return (f'base_anchors: {flat(lay.base_anchors)}\nplatform_anchors: {flat(lay.platform_anchors)}\n'
            f'stroke_min: {flat(lay.stroke_min)}\nstroke_max: {flat(lay.stroke_max)}\n'
            f'home_pose: [{home_pose[0]:.4f}, {home_pose[1]:.4f}, {home_pose[2]:.10f}]')


# ---------------------------------------------------------------------------- plots
_COLOURS = ('tab:red', 'tab:orange', 'tab:green', 'tab:purple', 'tab:blue', 'tab:brown')


def _plot_layouts(reports: Sequence[LayoutReport], task: Task, out: Path) -> None:
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    from matplotlib.patches import Circle, Rectangle

    n = len(reports)
    fig, axes = plt.subplots(1, n, figsize=(3.6 * n, 5.8), dpi=110, squeeze=False)
    for ax, r in zip(axes[0], reports):
        lay = r.layout
        for ax_, ay_ in lay.base_anchors:                            # brackets from the ring to the anchors
            ax.plot([ax_ * 1e3, np.clip(ax_, -task.r1, task.r1) * 1e3], [ay_ * 1e3, 0.0], color='0.45', lw=2)
        ax.add_patch(Circle((0, 0), task.r1 * 1e3, fill=False, ls=':', color='0.6'))
        ax.plot([-task.r1 * 1e3, task.r1 * 1e3], [0, 0], color='0.3', lw=3, solid_capstyle='butt')
        ax.add_patch(Rectangle((task.x[0] * 1e3, task.y[0] * 1e3), (task.x[1] - task.x[0]) * 1e3,
                               (task.y[1] - task.y[0]) * 1e3, fill=False, color='k', lw=0.8))
        for theta, alpha in ((task.theta[0], 0.25), (task.theta[1], 0.25), (sum(task.theta) / 2, 1.0)):
            p = np.array([sum(task.x) / 2, sum(task.y) / 2, theta])
            c, s = math.cos(theta), math.sin(theta)
            b = p[:2] + lay.platform_anchors @ np.array([[c, s], [-s, c]])
            ring = p[:2] + np.array([[-task.r2, 0.0], [task.r2, 0.0]]) @ np.array([[c, s], [-s, c]])
            ax.plot(ring[:, 0] * 1e3, ring[:, 1] * 1e3, color='0.3', lw=3, alpha=alpha, solid_capstyle='butt')
            foot = p[:2] + np.column_stack([np.clip(lay.platform_anchors[:, 0], -task.r2, task.r2),
                                            np.zeros(3)]) @ np.array([[c, s], [-s, c]])
            for i in range(3):
                ax.plot([foot[i, 0] * 1e3, b[i, 0] * 1e3], [foot[i, 1] * 1e3, b[i, 1] * 1e3], color='0.45', lw=2,
                        alpha=alpha)
            if alpha == 1.0:
                ax.add_patch(Circle(tuple(p[:2] * 1e3), task.r2 * 1e3, fill=False, ls=':', color='0.6'))
            for i in range(3):
                ax.plot([lay.base_anchors[i, 0] * 1e3, b[i, 0] * 1e3], [lay.base_anchors[i, 1] * 1e3, b[i, 1] * 1e3],
                        color=_COLOURS[i], lw=4 if alpha == 1.0 else 1.5, alpha=alpha)
            ax.plot(b[:, 0] * 1e3, b[:, 1] * 1e3, 'ko', ms=4, alpha=alpha)
        ax.plot(lay.base_anchors[:, 0] * 1e3, lay.base_anchors[:, 1] * 1e3, 'ks', ms=5)
        ax.set_aspect('equal')
        ax.set_xlim(-330, 330)
        ax.set_ylim(-240, 720)
        ax.set_xlabel('x (mm)')
        ax.grid(True, alpha=0.3)
        ax.set_title(f'{lay.name}\nreach {100 * r.reach_fraction:.0f} %, min |Fx| {r.min_capacity[0]:.3g} N\n'
                     f'|Fy| {r.min_capacity[1]:.3g} N, |Mz| {r.min_capacity[2]:.3g} N·m', fontsize=9)
    axes[0, 0].set_ylabel('y (mm)')
    fig.suptitle(f'3-RPR layouts: legs a1 (red), a2 (orange), a3 (green) at theta = '
                 f'{math.degrees(sum(task.theta) / 2):.0f} deg (bold) and at the task\'s theta limits (faint); rings '
                 'seen edge-on (dark), brackets (grey)\nbox: the task range of the thoracic ring\'s centre; dotted: '
                 'the rings\' circles, where anchors may go', fontsize=9)
    fig.tight_layout(rect=(0.0, 0.03, 1.0, 0.92))
    fig.savefig(out)
    plt.close(fig)


def _plot_capacity(reports: Sequence[LayoutReport], task: Task, out: Path) -> None:
    import warnings

    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 4, figsize=(19, 4.6), dpi=110)
    for k, r in enumerate(reports):
        x, y, t = r.axes
        cap = r.capacity.reshape(x.size, y.size, t.size, 3)
        cond = r.condition.reshape(x.size, y.size, t.size)
        deg = np.degrees(t)
        with warnings.catch_warnings():
            warnings.simplefilter('ignore', RuntimeWarning)               # all-NaN slices: no reachable pose
            per_t = np.nanmin(cap, axis=(0, 1))                              # (nt, 3)
            worst = np.nanmax(cond, axis=(0, 1))
        for a in range(3):
            vals = np.where(per_t[:, a] > 0.0, per_t[:, a], np.nan)
            axes[a].semilogy(deg, vals, color=_COLOURS[k], lw=2, label=r.layout.name)
        axes[3].semilogy(deg, worst, color=_COLOURS[k], lw=2, label=r.layout.name)
    need = {0: (30.0, '30 N: 15 mm against 2000 N/m'), 1: (task.min_fy, f'required {task.min_fy:g} N'),
            2: (task.min_mz, f'required {task.min_mz:g} N·m')}
    for a in range(3):
        axes[a].axhline(need[a][0], color='k', ls='--', lw=1, label=need[a][1])
        axes[a].set_title(f'smallest |{_AXES[a]}| held over x, y (reachable)')
        axes[a].set_ylabel(f'|{_AXES[a]}| ({_UNITS[a]})')
    axes[0].axhline(task.force_limit, color='0.5', ls=':', lw=1, label=f'one actuator: {task.force_limit:g} N')
    axes[3].axhline(task.condition_max, color='k', ls='--', lw=1, label='singularity limit')
    axes[3].set_title('largest cond(J) over x, y (reachable)')
    axes[3].set_ylabel('cond(J)')
    for ax in axes:
        ax.set_xlabel('theta (deg)')
        ax.grid(True, which='both', alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(f'Force capacity over the task ({task.describe()}); a gap: no reachable pose or a singular one',
                 fontsize=9)
    fig.tight_layout()
    fig.savefig(out)
    plt.close(fig)


def _plot_maps(reports: Sequence[LayoutReport], task: Task, out: Path) -> None:
    import warnings

    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm

    n = len(reports)
    fig, axes = plt.subplots(1, n, figsize=(3.9 * n, 4.4), dpi=110, squeeze=False)
    vmax = max(float(np.nanmax(r.capacity[:, 0])) if np.isfinite(r.capacity[:, 0]).any() else 1.0 for r in reports)
    for ax, r in zip(axes[0], reports):
        x, y, t = r.axes
        cap = r.capacity[:, 0].reshape(x.size, y.size, t.size)
        det = r.det.reshape(x.size, y.size, t.size)
        cond = r.condition.reshape(x.size, y.size, t.size)
        with warnings.catch_warnings():
            warnings.simplefilter('ignore', RuntimeWarning)
            img = np.nanmin(cap, axis=0)                                     # (ny, nt): worst over x
        img = np.where(img > 0.0, img, np.nan)
        extent = (math.degrees(t[0]), math.degrees(t[-1]), y[0] * 1e3, y[-1] * 1e3)
        ax.set_facecolor('0.85')
        im = ax.imshow(img, origin='lower', extent=extent, aspect='auto', cmap='viridis',
                       norm=LogNorm(vmin=0.1, vmax=max(vmax, 1.0)), interpolation='nearest')
        mid = x.size // 2
        d = det[mid]
        if np.isfinite(d).any() and np.nanmin(d) < 0.0 < np.nanmax(d):
            ax.contour(np.degrees(t), y * 1e3, np.nan_to_num(d), levels=[0.0], colors='r', linewidths=1.5)
        sing = np.any(cond > task.condition_max, axis=0)
        if sing.any():
            jj, kk = np.nonzero(sing)
            ax.plot(np.degrees(t[kk]), y[jj] * 1e3, 'r.', ms=2)
        ax.set_title(f'{r.layout.name}: worst |Fx| over x\nred: det J = 0 (x = {x[mid] * 1e3:.0f} mm) or '
                     f'cond > {task.condition_max:.0e}', fontsize=8)
        ax.set_xlabel('theta (deg)')
        fig.colorbar(im, ax=ax, label='|Fx| (N)')
    axes[0, 0].set_ylabel('y (mm)')
    fig.suptitle('Lateral capacity over the task, the worst x at each (theta, y); grey: no x within stroke',
                 fontsize=9)
    fig.tight_layout()
    fig.savefig(out)
    plt.close(fig)


def _plot_workspace(lay: Layout, task: Task, out: Path, theta_deg: Sequence[float]) -> None:
    """``brace-workspace``'s workspace union and |Fx| panels for one layout (its functions, reused)."""
    from .workspace import _plot, capacity_map, workspace_map
    theta = np.radians(np.arange(math.degrees(task.theta[0]), math.degrees(task.theta[1]) + 1e-9, 0.5))
    ws = workspace_map(lay.base_anchors, lay.platform_anchors, lay.stroke_min, lay.stroke_max, theta, grid=0.002)
    home = _reachable_home(lay, task, np.empty((0, 3)))
    mech = lay.mechanism(home if home is not None else None, condition_max=task.condition_max)
    caps = [capacity_map(mech, ws.x, ws.y, math.radians(d), task.force_limit) for d in theta_deg]
    _plot(ws, out, f'{lay.name}: 3-RPR workspace (y > 0)', caps)


# ---------------------------------------------------------------------------- command line
def _task_from(args: argparse.Namespace, device_task: Task) -> Task:
    """Defaults <- the device (ring radii, force limit, condition limit, home) <- ``--task`` file <- options."""
    values: dict[str, Any] = {}
    if args.task:
        import yaml
        path = Path(args.task)
        if not path.is_file():
            raise ValueError(f'--task {path}: file not found')
        raw = yaml.safe_load(path.read_text()) or {}
        if not isinstance(raw, Mapping):
            raise ValueError(f'--task {path}: expected a mapping of {", ".join(TASK_KEYS)}')
        unknown = sorted(set(raw) - set(TASK_KEYS))
        if unknown:
            raise ValueError(f'--task {path}: unknown key(s) {", ".join(unknown)}; expected some of '
                             f'{", ".join(TASK_KEYS)}')
        values.update(raw)
    for key in TASK_KEYS:
        v = getattr(args, key, None)
        if v is not None:
            values[key] = v
    kwargs: dict[str, Any] = {}
    for key, v in values.items():
        try:
            if isinstance(v, bool):
                raise ValueError
            if key == 'max_anchor_offset' and v is None:
                kwargs[key] = None
            elif key in ('x', 'y', 'stroke_min_range', 'theta_deg'):
                pair = [float(e) for e in v]
                if len(pair) != 2:
                    raise ValueError
                if key == 'theta_deg':
                    kwargs['theta'] = (math.radians(pair[0]), math.radians(pair[1]))
                else:
                    kwargs[key] = (pair[0], pair[1])
            elif key == 'reference_pose':
                p = [float(e) for e in v]
                if len(p) != 3:
                    raise ValueError
                kwargs[key] = (p[0], p[1], p[2])
            else:
                kwargs[key] = float(v)
        except (TypeError, ValueError):
            shape = '(x m, y m, theta rad)' if key == 'reference_pose' else \
                '[lo, hi]' if key in ('x', 'y', 'stroke_min_range', 'theta_deg') else 'a number'
            raise ValueError(f'task {key}: expected {shape}, got {v!r}') from None
    return replace(device_task, **kwargs)


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='brace-design',
        description='Force-capacity design study of a 3-RPR brace over a task workspace: reachability, '
                    'smallest |Fx| |Fy| |Mz| capacity, conditioning and singularities of the paper\'s layout, '
                    'three alternatives and an optimised layout (differential evolution, fixed seed).')
    parser.add_argument('device', nargs='?', default='config/lumbar_brace.yaml',
                        help='device YAML: force limit, singularity limit, home pose; its layout is a column '
                             'when it is not the paper\'s (default: %(default)s)')
    parser.add_argument('--out', required=True, help='directory for design.md, design.json and the PNGs')
    parser.add_argument('--task', help=f'YAML with any of: {", ".join(TASK_KEYS)} (SI units, theta_deg in deg)')
    pair = {'type': float, 'nargs': 2, 'metavar': ('LO', 'HI')}
    parser.add_argument('--x-range', dest='x', help='m (default -0.02 0.02)', **pair)
    parser.add_argument('--y-range', dest='y', help='m (default 0.365 0.425)', **pair)
    parser.add_argument('--theta-range-deg', dest='theta_deg', help='deg (default 0 30)', **pair)
    parser.add_argument('--stroke', type=float, help='stroke window of every actuator, m (default 0.1)')
    parser.add_argument('--stroke-margin', dest='stroke_margin', type=float,
                        help='the task keeps this far from both end stops, m (default 0.002)')
    parser.add_argument('--stroke-min-range', dest='stroke_min_range',
                        help='where a window may start, m (default 0.34 0.54)', **pair)
    parser.add_argument('--force-limit', dest='force_limit', type=float,
                        help='actuator limit, N (default: actuator.max_force of the device)')
    parser.add_argument('--min-fy', dest='min_fy', type=float, help='required |Fy| everywhere, N (default 60)')
    parser.add_argument('--min-mz', dest='min_mz', type=float, help='required |Mz| everywhere, N·m (default 6)')
    parser.add_argument('--min-anchor-gap', dest='min_anchor_gap', type=float,
                        help='anchors on one ring at least this far apart, m (default 0.03)')
    parser.add_argument('--max-anchor-offset', dest='max_anchor_offset', type=float,
                        help='anchors at most this far above or below their ring, m (default: anywhere in the '
                             'rings\' circles)')
    parser.add_argument('--grid', type=float, default=0.002, help='study grid spacing of x and y, m (%(default)s)')
    parser.add_argument('--grid-deg', type=float, default=0.5, help='study grid spacing of theta, deg (%(default)s)')
    parser.add_argument('--seed', type=int, default=1, help='optimiser seed (%(default)s)')
    parser.add_argument('--maxiter', type=int, default=200, help='optimiser generations (%(default)s)')
    parser.add_argument('--popsize', type=int, default=15, help='population = popsize x 12 (%(default)s)')
    parser.add_argument('--no-optimise', action='store_true', help='evaluate the paper and the alternatives only')
    return parser


def _json_safe(value: Any) -> Any:
    """``value`` with every non-finite float as ``None`` (strict JSON)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    return value


def _write_report(out: Path, title: str, task: Task, args: argparse.Namespace, reports: Sequence[LayoutReport],
                  opt: OptimisationResult | None,
                  checks: Sequence[tuple[float, float, int, np.ndarray, float]]) -> str:
    """``design.md`` and ``design.json`` in ``out``; returns the comparison table."""
    nx, ny, nt = (a.size for a in reports[0].axes)
    table = report_table(reports, task)
    md = [f'# brace-design: {title}', '',
          f'Task: {task.describe()}. Capacities: each axis alone, both directions, base frame, '
          f'{task.force_limit:g} N per actuator; on the study grid {nx} × {ny} × {nt} = {reports[0].n_poses} poses '
          f'({args.grid * 1e3:g} mm, {args.grid_deg:g}°).', '', table, '']
    data: dict[str, Any] = {'task': asdict(task), 'grid': {'step_m': args.grid, 'step_deg': args.grid_deg,
                                                           'n_poses': reports[0].n_poses}, 'layouts': []}
    for r in reports:
        data['layouts'].append({**r.layout.as_dict(), 'reach_fraction': r.reach_fraction,
                                'reach_certified': r.reach_certified, 'length_bounds': r.length_bounds.tolist(),
                                'end_margin': r.end_margin.tolist(), 'min_capacity': r.min_capacity.tolist(),
                                'min_limiting': r.min_limiting, 'reference_capacity': r.reference_capacity.tolist(),
                                'worst_condition': r.worst_condition, 'n_singular': r.n_singular,
                                'det_sign_change': r.det_sign_change, 'failures': r.failures(task),
                                'meets_requirements': r.meets(task)})
    if opt is not None:
        c = opt.min_capacity
        md += ['## The optimised layout', '',
               f'Differential evolution (scipy, `best1bin`, recombination 0.9, seed {opt.seed}, {opt.nit} '
               f'generations, {opt.nfev} layouts of {opt.n_poses} poses) in {opt.seconds:.1f} s. On its own grid: '
               f'min |Fx| {c[0]:.4g} N, |Fy| {c[1]:.4g} N, |Mz| {c[2]:.4g} N·m.', '',
               'Is the grid fine enough? The same layout on denser grids (the library\'s batch methods):', '',
               '| grid | poses | min \\|Fx\\| N | min \\|Fy\\| N | min \\|Mz\\| N·m | worst cond(J) |',
               '|---|---|---|---|---|---|']
        md += [f'| {s_m * 1e3:g} mm, {s_d:g}° | {n} | {m[0]:.4g} | {m[1]:.4g} | {m[2]:.4g} | {w:.4g} |'
               for s_m, s_d, n, m, w in checks]
        md += ['', 'As a device file (`mechanism` keys; sim.rest_pose = home_pose):', '', '```yaml',
               yaml_snippet(opt.layout, task.reference_pose), '```', '']
        data['optimiser'] = {'seed': opt.seed, 'nit': opt.nit, 'nfev': opt.nfev, 'seconds': opt.seconds,
                             'feasible': opt.feasible, 'vector': opt.vector.tolist(), 'grid_min_capacity': c.tolist(),
                             'grid_check': [{'step_m': s_m, 'step_deg': s_d, 'n_poses': n, 'min_capacity': m.tolist(),
                                             'worst_condition': w} for s_m, s_d, n, m, w in checks]}
    (out / 'design.md').write_text('\n'.join(md))
    (out / 'design.json').write_text(json.dumps(_json_safe(data), indent=1, allow_nan=False))
    return table


def main(argv: list[str] | None = None) -> int:
    """``brace-design [device] --out DIR [--task task.yaml] [options]``; see the module docstring.

    :returns: 0; 1 when the optimised layout misses a requirement; 2 on bad input.
    """
    args = _parser().parse_args(argv)
    from ..config import ConfigError, load_device_config
    from ..mechanisms import mechanism_from_config
    try:
        cfg = load_device_config(args.device)
        mech = mechanism_from_config(cfg)
        if not isinstance(mech, Rpr3):
            raise ValueError(f'{args.device} is not a 3-RPR device (mechanism.type rpr3)')
        task = _task_from(args, Task(force_limit=float(cfg.get_path('actuator.max_force')),
                                     condition_max=float(mech.singularity_condition_max),
                                     reference_pose=tuple(float(v) for v in mech.home_pose)))
        if not (args.grid > 0 and args.grid_deg > 0):
            raise ValueError(f'--grid and --grid-deg must be positive, got {args.grid} m and {args.grid_deg} deg')
        if args.maxiter < 1 or args.popsize < 1:
            raise ValueError(f'--maxiter and --popsize must be >= 1, got {args.maxiter} and {args.popsize}')
    except (ConfigError, TypeError, ValueError) as exc:
        print(f'brace-design: {exc}', file=sys.stderr)
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    paper = paper_layout(task.r1, task.r2)
    layouts = alternative_layouts(task, paper)
    lo, hi = mech.actuator_limits
    title = Path(str(args.device)).stem
    device = Layout(title, mech.base_anchors.copy(), mech.platform_anchors.copy(), lo, hi)
    if not all(np.allclose(getattr(device, k), getattr(paper, k), rtol=0.0, atol=1e-9)
               for k in ('base_anchors', 'platform_anchors', 'stroke_min', 'stroke_max')):
        layouts.append(device)                  # the device's own layout, when it is not the paper's
    offset = '' if task.max_anchor_offset is None else f', at most {task.max_anchor_offset * 1e3:g} mm off the rings'
    print(f'brace-design {args.device}: task {task.describe()}')
    print(f'requirements: whole box within stroke, no singularity (cond(J) <= {task.condition_max:g}, one sign of '
          f'det J), |Fy| >= {task.min_fy:g} N, |Mz| >= {task.min_mz:g} N·m, anchors >= '
          f'{task.min_anchor_gap * 1e3:g} mm apart{offset}; maximise the smallest |Fx|')
    opt = None
    if not args.no_optimise:
        opt = optimise_layout(task, seed=args.seed, maxiter=args.maxiter, popsize=args.popsize)
        print(f'optimiser: differential evolution, seed {opt.seed}, {opt.nit} generations, {opt.nfev} layouts x '
              f'{opt.n_poses} poses in {opt.seconds:.1f} s; {"feasible" if opt.feasible else "NO FEASIBLE LAYOUT"}, '
              f'min |Fx| {opt.min_capacity[0]:.4g} N on its grid')
        layouts.append(opt.layout)
    t0 = time.perf_counter()
    reports = [evaluate_layout(lay, task, step_m=args.grid, step_deg=args.grid_deg) for lay in layouts]
    nx, ny, nt = (a.size for a in reports[0].axes)
    print(f'study grid: {nx} x {ny} x {nt} = {reports[0].n_poses} poses ({args.grid * 1e3:g} mm, '
          f'{args.grid_deg:g} deg), {len(reports)} layouts in {time.perf_counter() - t0:.2f} s')
    _print_summary(reports)
    checks: list[tuple[float, float, int, np.ndarray, float]] = []
    status = 0
    if opt is not None:
        checks = grid_check(opt.layout, task, ((2 * args.grid, 4 * args.grid_deg), (args.grid, args.grid_deg),
                                               (args.grid / 2, args.grid_deg / 2)))
        print('grid check of the optimised layout: ' + '; '.join(
            f'{s_m * 1e3:g} mm/{s_d:g} deg ({n} poses): |Fx| {c[0]:.4g} N, |Fy| {c[1]:.4g} N, |Mz| {c[2]:.4g} N·m'
            for s_m, s_d, n, c, w in checks))
        if not reports[-1].meets(task):
            print('brace-design: the optimised layout misses: ' + ', '.join(reports[-1].failures(task)),
                  file=sys.stderr)
            status = 1
    table = _write_report(out, title, task, args, reports, opt, checks)
    print()
    print(table)
    _plot_layouts(reports, task, out / 'layouts.png')
    _plot_capacity(reports, task, out / 'capacity.png')
    _plot_maps(reports, task, out / 'maps.png')
    ref_deg = [math.degrees(task.reference_pose[2]), math.degrees(sum(task.theta) / 2)]
    _plot_workspace(paper, task, out / 'workspace_paper.png', ref_deg)
    if opt is not None:
        _plot_workspace(opt.layout, task, out / 'workspace_optimised.png', ref_deg)
    print(f'wrote {out}/design.md, design.json, layouts.png, capacity.png, maps.png, workspace_*.png')
    return status


if __name__ == '__main__':
    sys.exit(main())
