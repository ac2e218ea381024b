"""2-DOF planar continuum parallel robot (seed paper 003, Altuzarra et al.).

Two slender bars of length ``L`` (bending stiffness ``EI``) are clamped at 45 deg on two
sliders on one guide (the x axis) and welded together at 90 deg at the end effector.
Moving the sliders together raises the end effector (the bars buckle, compression),
moving them apart lowers it (tension). Mode 1 only, as the paper argues.

Frames and coordinates
----------------------
Base frame: x along the guide, y up (the side of the bars), origin anywhere on the
guide. Actuators: slider positions ``s1 < s2`` (m) along x, bar 1 clamped on slider 1
leaving at +45 deg, bar 2 on slider 2 at 135 deg. Pose ``(x, y)``: the weld point
(m). With no load the robot is mirror-symmetric about ``x = (s1 + s2) / 2``, the weld
does not rotate, and (Newton's third law + symmetry) the force between the bars is
horizontal (parallel to the guide): ``x = (s1 + s2) / 2`` and ``y = Y(d)`` with
``d = (s2 - s1) / 2`` the slider half-distance. Undeformed: ``d0 = y0 = L / sqrt 2``.

The elastica (paper eqs. 1.1-1.15)
----------------------------------
Each bar, in its own frame (x' along the clamp direction, 45 deg; the paper's "rotate
45 deg clockwise"), is clamped at both ends with zero slope: ``theta(0) = theta(L) = 0``.
Bernoulli-Euler ``EI theta' = M`` with the end force ``R`` at angle ``psi`` *acting on the
bar at the weld* gives ``theta'' = lambda^2 sin(theta - psi)``, ``lambda^2 = R / EI``
(eq. 1.4). The paper's substitution ``cos((psi - theta) / 2) = k sin(phi)`` (eq. 1.8)
turns arc length into ``lambda ds = dphi / sqrt(1 - k^2 sin^2 phi)``, so (eq. 1.11)::

    lambda L = F(k, phi2) - F(k, phi1),   phi1 = asin(cos(psi/2) / k),   phi2 = pi - phi1 (mode 1)

and the end of the bar (eq. 1.15 and the analogous ``y'``), integrating
``dx' = cos(theta) ds``, ``dy' = sin(theta) ds``::

    lambda x' = cos(psi) [F - F1 - 2 (E - E1)] - 2 sigma k sin(psi) (cos phi - cos phi1)
    lambda y' = sin(psi) [F - F1 - 2 (E - E1)] + 2 sigma k cos(psi) (cos phi - cos phi1)

``F = F(k, phi)``, ``E = E(k, phi)`` the incomplete elliptic integrals
(``scipy.special.ellipkinc/ellipeinc`` with parameter ``m = k^2``), ``sigma`` the sign of
``sin((psi - theta) / 2) = +-sqrt(1 - k^2 sin^2 phi)``, constant along the bar for
``k < 1`` (``sigma = sign(sin(psi / 2))``). Note on eq. 1.15: as printed
(``+ 2 k sin(psi) [cos phi - cos phi1]``) it is the ``sigma = -1`` case; for the
compression branch (``psi = 135 deg``, ``sigma = +1``) the sign is minus (checked against
the boundary-value solution in the tests).

Equilibrium at the weld fixes ``psi``: compression ``psi = 135 deg`` (global -x on bar
1); tension ``psi = 315 deg``, used as ``psi = -45 deg`` because the parametrisation
needs ``cos(psi / 2) > 0`` for ``k > 0`` (the paper: "negative for the range
``[-k_min, -1]``"). On each branch ``k`` runs from ``k_min = |cos(psi / 2)|`` (straight bar,
``R = 0``) to 1 (``R -> inf``). The robot: the bar end in global coordinates is
``(d, y) = ((x' - y') / sqrt 2, (x' + y') / sqrt 2)`` relative to slider 1.

The general procedure of the paper (given the end ``(a, b)`` of a clamped-clamped bar,
iterate on ``psi`` and ``k``) is :func:`solve_bar`; for the robot ``psi`` is known and
only ``k`` is iterated (a bracketed 1-D root, :func:`scipy.optimize.brentq`).

Inverse: height ``y`` -> ``d`` (branch by ``y >< y0``); forward: ``d`` -> ``y`` and the bar
force. Both are monotonic along each branch over the default reach; a height beyond
mode 1's reach (``k -> 1``, or the sliders meeting) raises :class:`~.base.UnreachablePose`
with the reason.

Slider forces and wrench
------------------------
The horizontal force of bar 2 on bar 1 at the weld is ``H = R cos(psi_global)``
(negative in compression); slider 1 holds bar 1 with ``-H``, slider 2 with ``+H`` (push
along +x positive): ``f0(q) = (-H, H)``, the no-load slider forces. The model has no
external load, so :meth:`Continuum2.wrench` is a first-order estimate: the end-effector
force ``W = J^T (f - f0(q))`` (virtual work on the rigid-body part; valid for small loads).
"""
from __future__ import annotations

import bisect
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from .base import (MechanismBase, Statics, UnreachablePose, as_actuator_names, as_poses, as_positive, as_range,
                   as_vector, check_limits, check_section, config_errors, section_kwargs, within_limits)
from .loader import register

__all__ = ['Continuum2', 'bar_end', 'solve_bar', 'BarState', 'PSI_COMPRESSION', 'PSI_TENSION']

PSI_COMPRESSION = math.radians(135.0)
#: 315 deg, written -45 deg so that cos(psi/2) > 0 (k > 0)
PSI_TENSION = math.radians(-45.0)
_SQRT2 = math.sqrt(2.0)


def _load_elliptic() -> None:
    """Bind scipy's incomplete elliptic integrals in place of the two stubs below: scipy is
    imported on first use, not with the package (every node process's start), and the
    integrals' callers (:func:`_bar_end_scalar`, inside root finds) pay nothing afterwards."""
    global ellipkinc, ellipeinc
    from scipy.special import ellipeinc as e, ellipkinc as k
    ellipkinc, ellipeinc = k, e


def ellipkinc(phi: Any, m: Any) -> Any:
    """``scipy.special.ellipkinc``: this stub replaces itself with it on the first call."""
    _load_elliptic()
    return ellipkinc(phi, m)


def ellipeinc(phi: Any, m: Any) -> Any:
    """``scipy.special.ellipeinc``: this stub replaces itself with it on the first call."""
    _load_elliptic()
    return ellipeinc(phi, m)


def bar_end(k: float | np.ndarray, psi: float, length: float, ei: float
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """End ``(x', y')`` (m) of a mode-1 clamped-clamped bar and its end force ``R`` (N).

    Bar frame: clamp at the origin along +x', both end slopes 0. ``k`` in
    ``(|cos(psi/2)|, 1)``; vectorised over ``k``. At ``k = k_min`` the bar is straight
    (``x' = L``, ``y' = 0``, ``R = 0``).
    """
    kk = np.asarray(k, dtype=float)
    m = kk * kk
    c2 = math.cos(0.5 * psi)
    with np.errstate(invalid='ignore', divide='ignore'):
        phi1 = np.arcsin(np.clip(c2 / kk, -1.0, 1.0))
        phi2 = math.pi - phi1
        f12 = ellipkinc(phi2, m) - ellipkinc(phi1, m)            # = lambda L  (eq. 1.11)
        e12 = ellipeinc(phi2, m) - ellipeinc(phi1, m)
        dcos = np.cos(phi2) - np.cos(phi1)                        # = -2 cos(phi1)
        core = f12 - 2.0 * e12
        lam = f12 / length
        sk = math.copysign(1.0, math.sin(0.5 * psi)) * kk          # sigma k
        xp = (math.cos(psi) * core - 2.0 * sk * math.sin(psi) * dcos) / lam
        yp = (math.sin(psi) * core + 2.0 * sk * math.cos(psi) * dcos) / lam
    force = ei * lam * lam
    straight = ~(f12 > 0.0)
    if np.any(straight):
        xp = np.where(straight, length, xp)
        yp = np.where(straight, 0.0, yp)
        force = np.where(straight, 0.0, force)
    return xp, yp, force


def _bar_end_scalar(k: float, psi: float, length: float, ei: float) -> tuple[float, float, float]:
    """:func:`bar_end` for one modulus, returned as robot coordinates ``(d, y, R)``.

    The same equations on Python floats (each numpy call on a scalar costs more than the
    elliptic integrals themselves); :func:`bar_end` stays the vectorised reference and the
    tests check that both agree.
    """
    m = k * k
    c2 = math.cos(0.5 * psi)
    phi1 = math.asin(min(1.0, max(-1.0, c2 / k)))
    phi2 = math.pi - phi1
    f12 = float(ellipkinc(phi2, m)) - float(ellipkinc(phi1, m))
    if not f12 > 0.0:                               # straight bar
        return length / _SQRT2, length / _SQRT2, 0.0
    e12 = float(ellipeinc(phi2, m)) - float(ellipeinc(phi1, m))
    dcos = -2.0 * math.cos(phi1)
    core = f12 - 2.0 * e12
    lam = f12 / length
    sk = math.copysign(1.0, math.sin(0.5 * psi)) * k
    xp = (math.cos(psi) * core - 2.0 * sk * math.sin(psi) * dcos) / lam
    yp = (math.sin(psi) * core + 2.0 * sk * math.cos(psi) * dcos) / lam
    return (xp - yp) / _SQRT2, (xp + yp) / _SQRT2, ei * lam * lam


def _ascending(values: np.ndarray) -> tuple[list[float], bool]:
    """``values`` (monotonic) as an ascending list, and whether it was reversed."""
    rev = bool(values[-1] < values[0])
    return (values[::-1] if rev else values).tolist(), rev


def solve_bar(a: float, b: float, length: float, ei: float, *, psi0: float = PSI_COMPRESSION,
              k0: float | None = None) -> tuple[float, float, float]:
    """The paper's general procedure: end ``(a, b)`` (bar frame, m) -> ``(psi, k, R)``, mode 1.

    Iterates on ``psi`` and ``k`` (``scipy.optimize.fsolve`` on eqs. 1.11-1.15, starting at
    ``psi0`` and ``k0``) until the end matches ``(a, b)``.

    :raises UnreachablePose: no convergence (e.g. an end outside mode 1's reach).
    """
    c2 = abs(math.cos(0.5 * psi0))
    if k0 is None:
        k0 = 0.5 * (c2 + 1.0)

    def res(z: np.ndarray) -> np.ndarray:
        psi, k = float(z[0]), float(z[1])
        if not (abs(math.cos(0.5 * psi)) < k < 1.0):
            return np.array([1e3, 1e3])
        xp, yp, _ = bar_end(k, psi, length, ei)
        return np.array([float(xp) - a, float(yp) - b]) / length

    from scipy.optimize import fsolve
    sol, info, ier, msg = fsolve(res, [psi0, k0], full_output=True, xtol=1e-13)
    if ier != 1 or np.max(np.abs(res(sol))) > 1e-10:
        raise UnreachablePose(f'bar end ({a:.5f}, {b:.5f}) m: no mode-1 elastica found ({msg.strip()})')
    psi, k = float(sol[0]), float(sol[1])
    return psi, k, float(bar_end(k, psi, length, ei)[2])


@dataclass(frozen=True)
class BarState:
    """One solved configuration of the robot (no load)."""

    d: float          #: slider half-distance (m)
    y: float          #: end-effector height above the guide (m)
    k: float          #: elliptic modulus
    psi: float        #: end-force angle in the bar frame (rad): 135 deg or -45 (= 315) deg
    force: float      #: R, the force between the bars (N), >= 0
    horizontal: float  #: H, global x-force of bar 2 on bar 1 (N): < 0 compression, > 0 tension

    @property
    def branch(self) -> str:
        return 'compression' if self.horizontal < 0 else ('tension' if self.horizontal > 0 else 'straight')


@register('continuum2')
class Continuum2(MechanismBase):
    """The 2-DOF continuum parallel robot; see the module docstring.

    :param bar_length: ``L`` (m), each bar.
    :param youngs_modulus: ``E`` (Pa); PTFE 4 GPa as the paper states.
    :param width: bar cross-section width (m, out of plane).
    :param thickness: bar thickness (m, in the bending plane): ``I = width thickness^3 / 12``.
    :param stroke: ``(lo, hi)`` slider position range (m), each a scalar or two values.
    :param actuator_names: two distinct names (slider 1, slider 2).
    :param home_pose: rest pose ``(x, y)`` (m); default the undeformed robot centred in the stroke.
    :param k_max: the largest modulus used (reach limit of each branch, ``k -> 1`` is
        ``R -> inf``); default ``1 - 1e-6``.
    :param min_half_distance: sliders closer than ``2 * this`` (m) collide; default 0.
    """

    dof: int = 2
    n_actuators: int = 2
    pose_kind: str = 'xy'
    wrench_axes = ('Fx', 'Fy')
    wrench_units = ('N', 'N')

    def __init__(self, bar_length: float, youngs_modulus: float, width: float, thickness: float,
                 stroke: tuple[Any, Any], *, actuator_names: Sequence[str] = ('s1', 's2'),
                 home_pose: Sequence[float] | None = None, k_max: float = 1.0 - 1e-6,
                 min_half_distance: float = 0.0) -> None:
        self.length = as_positive(bar_length, 'bar_length', unit='m')
        self.youngs_modulus = as_positive(youngs_modulus, 'youngs_modulus', unit='Pa')
        self.width = as_positive(width, 'width', unit='m')
        self.thickness = as_positive(thickness, 'thickness', unit='m')
        #: bending stiffness EI (N·m^2)
        self.ei = self.youngs_modulus * self.width * self.thickness ** 3 / 12.0
        self._lo, self._hi = lo, hi = as_range(stroke, 2, 'stroke', unit='m')
        self.actuator_names: tuple[str, ...] = as_actuator_names(actuator_names, 2)
        if not (0.5 < float(k_max) < 1.0):
            raise ValueError(f'k_max: expected a modulus in (0.5, 1), got {k_max!r}')
        self.k_max = float(k_max)
        self.min_half_distance = float(min_half_distance)
        if not (math.isfinite(self.min_half_distance) and self.min_half_distance >= 0.0):
            raise ValueError(f'min_half_distance: expected >= 0 m, got {min_half_distance!r}')
        #: undeformed half-distance and height (m)
        self.d0 = self.y0 = self.length / _SQRT2
        self._kmin = {PSI_COMPRESSION: abs(math.cos(0.5 * PSI_COMPRESSION)),
                      PSI_TENSION: abs(math.cos(0.5 * PSI_TENSION))}
        self._reach()
        if home_pose is None:
            mid = 0.5 * float(np.mean(lo) + np.mean(hi))
            self._home = np.array([mid, self.y0])
        else:
            self._home = as_vector(home_pose, 2, 'home_pose')
        self.inverse(self._home)

    # ------------------------------------------------------------------ the elastica, per branch
    def _branch_end(self, k: float | np.ndarray, psi: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(d, y, R)`` of the robot at modulus ``k`` on the branch ``psi``."""
        xp, yp, force = bar_end(k, psi, self.length, self.ei)
        return (xp - yp) / _SQRT2, (xp + yp) / _SQRT2, force

    def _reach(self) -> None:
        """Branch ends (k = k_max) and monotonicity check on a dense k grid."""
        self._ends: dict[float, tuple[float, float]] = {}
        self._tables: dict[float, tuple[list[float], tuple[list[float], bool], tuple[list[float], bool]]] = {}
        self._height_tables: dict[float, tuple[np.ndarray, np.ndarray, np.ndarray, bool]] = {}
        for psi in (PSI_COMPRESSION, PSI_TENSION):
            kmin = self._kmin[psi]
            # dense in k near k_min (where d, y move fastest) and near 1 (R -> inf)
            s = np.linspace(0.0, 1.0, 2001)[1:]
            k = kmin + (self.k_max - kmin) * (1.0 - np.cos(0.5 * math.pi * s)) ** 1.0
            d, y, _ = self._branch_end(k, psi)
            sd, sy = np.sign(np.diff(d)), np.sign(np.diff(y))
            if not (np.all(sd == sd[0]) and np.all(sy == sy[0])):
                # not monotonic: keep the monotonic part from k_min (the reach ends at the first turn)
                bad = np.flatnonzero((sd != sd[0]) | (sy != sy[0]))[0]
                k_end = float(k[bad])
            else:
                k_end = self.k_max
            de, ye, _ = self._branch_end(k_end, psi)
            self._ends[psi] = (float(k_end), float(de), float(ye))  # type: ignore[assignment]
            # the bracket table of _solve_branch: k from just above k_min to k_end, with
            # d and y oriented increasing (bisect needs ascending values)
            # (the grid's d and y above, plus the two ends)
            k0 = kmin * (1.0 + 1e-15)
            d0, y0, _ = _bar_end_scalar(k0, psi, self.length, self.ei)
            keep = k < k_end
            kt = np.concatenate([[k0], k[keep], [k_end]])
            dt = np.concatenate([[d0], d[keep], [de]])
            yt = np.concatenate([[y0], y[keep], [ye]])
            self._tables[psi] = (kt.tolist(), *(_ascending(v) for v in (dt, yt)))
            # the same for the vectorised solve: moduli, ascending heights, the height at
            # each modulus, whether the heights fall with k
            y_asc, y_rev = self._tables[psi][2]
            self._height_tables[psi] = (kt, np.asarray(y_asc), yt, y_rev)
        kc, dc, yc = self._ends[PSI_COMPRESSION]   # type: ignore[misc]
        kt, dt, yt = self._ends[PSI_TENSION]       # type: ignore[misc]
        #: heights reachable in mode 1 (m): (lowest in tension, highest in compression)
        self.height_range = (float(yt), float(yc))
        #: half-distances of the mode-1 reach (m): (closest in compression, widest in tension)
        self.half_distance_range = (max(float(dc), self.min_half_distance), float(dt))

    def _solve_branch(self, target: float, psi: float, which: int) -> BarState:
        """The modulus ``k`` on branch ``psi`` where ``d`` (``which = 0``) or ``y`` (1) is ``target``.

        The table built in :meth:`_reach` (d and y at 2000 moduli, monotonic along the
        branch) brackets the root between two neighbouring moduli; Brent's method then
        solves the exact elliptic solution inside that bracket (a handful of scalar
        evaluations, about 25 us instead of 0.2 ms over the whole branch).
        """
        kt, *columns = self._tables[psi]
        values, reversed_ = columns[which]
        n = len(kt)
        i = bisect.bisect_left(values, target)
        # table index j (ascending values) -> k index
        j_lo, j_hi = max(i - 1, 0), min(i, n - 1)
        a, b = (n - 1 - j_hi, n - 1 - j_lo) if reversed_ else (j_lo, j_hi)
        k_lo, k_hi = kt[min(a, b)], kt[max(a, b)]
        length, ei = self.length, self.ei

        def g(k: float) -> float:
            return _bar_end_scalar(k, psi, length, ei)[which] - target

        g_lo, g_hi = g(k_lo), g(k_hi)
        if g_lo * g_hi < 0.0:
            from scipy.optimize import brentq
            k = brentq(g, k_lo, k_hi, xtol=1e-16, rtol=1e-15, maxiter=100)
        else:                                   # target on a table node (or the branch end)
            k = k_lo if abs(g_lo) <= abs(g_hi) else k_hi
        d, y, force = _bar_end_scalar(k, psi, length, ei)
        hx = force * math.cos(psi + math.pi / 4.0)   # bar-frame angle psi -> global angle psi + 45 deg
        return BarState(d, y, float(k), psi, force, hx)

    def _solve_branch_batch(self, target: np.ndarray, psi: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`_solve_branch` for heights (``which = 1``), vectorised: ``(k, d, R)``.

        The same table bracket, then the Illinois variant of regula falsi on :func:`bar_end`
        in lock step (no Python loop over heights) until the bracket or the last step is
        ~1e-15 wide (relative) or ``y`` is met to its rounding, as tight as the scalar's
        Brent solve.
        """
        kt_a, values, y_of_k, reversed_ = self._height_tables[psi]
        n = kt_a.size
        i = np.searchsorted(values, target, side='left')
        j_lo, j_hi = np.maximum(i - 1, 0), np.minimum(i, n - 1)
        a, b = ((n - 1 - j_hi, n - 1 - j_lo) if reversed_ else (j_lo, j_hi))
        lo_i, hi_i = np.minimum(a, b), np.maximum(a, b)
        k_lo, k_hi = kt_a[lo_i], kt_a[hi_i]

        def g(k: np.ndarray, y: np.ndarray) -> np.ndarray:
            return self._branch_end(k, psi)[1] - y

        rows = np.arange(target.size)
        g_lo, g_hi = y_of_k[lo_i] - target, y_of_k[hi_i] - target     # the table holds y at its nodes
        k = np.where(np.abs(g_lo) <= np.abs(g_hi), k_lo, k_hi)      # on a node (or the branch end)
        bracket = g_lo * g_hi < 0.0
        idx = rows[bracket]
        s, t, fs, ft = k_lo[bracket], k_hi[bracket], g_lo[bracket], g_hi[bracket]
        root = np.where(np.abs(fs) <= np.abs(ft), s, t)             # best iterate so far (least |g|)
        best = np.minimum(np.abs(fs), np.abs(ft))
        side = np.zeros(idx.size)
        prev = np.full(idx.size, np.nan)
        act = np.arange(idx.size)
        for _ in range(100):
            if act.size == 0:
                break
            sa, ta, fsa, fta = s[act], t[act], fs[act], ft[act]
            r = (sa * fta - ta * fsa) / (fta - fsa)
            inside = (r > np.minimum(sa, ta)) & (r < np.maximum(sa, ta))
            # the secant lands on an end: nothing left between the floats, the best end stands
            act, r, sa, ta, fsa, fta = act[inside], r[inside], sa[inside], ta[inside], fsa[inside], fta[inside]
            ya = target[idx[act]]
            fr = g(r, ya)
            better = np.abs(fr) < best[act]
            root[act] = np.where(better, r, root[act])
            best[act] = np.where(better, np.abs(fr), best[act])
            moved = np.abs(r - prev[act])                         # NaN on the first pass
            prev[act] = r
            keep_t = fr * fta > 0.0                                # r replaces t (Illinois: halve f(s) on a repeat)
            keep_s = fr * fsa > 0.0                                # r replaces s
            sd = side[act]
            ta = np.where(keep_t, r, ta)
            fta = np.where(keep_t, fr, fta)
            fsa = np.where(keep_t & (sd == -1), 0.5 * fsa, fsa)
            sa = np.where(keep_s, r, sa)
            fsa = np.where(keep_s, fr, fsa)
            fta = np.where(keep_s & (sd == 1), 0.5 * fta, fta)
            s[act], t[act], fs[act], ft[act] = sa, ta, fsa, fta
            side[act] = np.where(keep_t, -1, np.where(keep_s, 1, sd))
            tol = 1e-16 + 1e-15 * np.abs(r)
            # converged: y met to its rounding, a bracket or a step of ~1e-15
            done = (np.abs(fr) <= 2.0 ** -52 * np.abs(ya)) | (np.abs(ta - sa) <= tol) | (moved <= tol)
            act = act[~done]
        k[idx] = root
        d, _, force = self._branch_end(k, psi)
        return k, d, force

    def _solve_heights(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`solve_height` for heights (N,): ``(k, psi, d, H)``, NaN where it raises."""
        k = np.full(y.shape, np.nan)
        psi = np.full(y.shape, PSI_COMPRESSION)
        d = np.full(y.shape, np.nan)
        hx = np.full(y.shape, np.nan)
        ylo, yhi = self.height_range
        inside = (ylo <= y) & (y <= yhi)
        straight = inside & (y == self.y0)
        k[straight], d[straight], hx[straight] = self._kmin[PSI_COMPRESSION], self.d0, 0.0
        for branch, sel in ((PSI_COMPRESSION, inside & (y > self.y0)), (PSI_TENSION, inside & (y < self.y0))):
            if sel.any():
                kb, db, fb = self._solve_branch_batch(y[sel], branch)
                k[sel], d[sel], psi[sel] = kb, db, branch
                hx[sel] = fb * math.cos(branch + math.pi / 4.0)
        near = d < self.min_half_distance
        k[near] = d[near] = hx[near] = np.nan
        return k, psi, d, hx

    def _slope_batch(self, k: np.ndarray, psi: np.ndarray) -> np.ndarray:
        """:meth:`slope` from solved moduli (the same central difference in ``k``)."""
        out = np.full(k.shape, np.nan)
        for branch, other in ((PSI_COMPRESSION, PSI_TENSION), (PSI_TENSION, PSI_COMPRESSION)):
            sel = (psi == branch) & np.isfinite(k)
            if not sel.any():
                continue
            kmin, k_end = self._kmin[branch], self._ends[branch][0]       # type: ignore[index]
            h = 1e-6 * (k_end - kmin)
            kmin_o = self._kmin[other]
            h_o = 1e-6 * (self._ends[other][0] - kmin_o)                  # type: ignore[index]
            ks = k[sel]
            inner = ks - kmin > h
            d_a, y_a, _ = self._branch_end(np.where(inner, ks - h, kmin + h), branch)
            d_bi, y_bi, _ = self._branch_end(np.minimum(ks + h, k_end), branch)
            d_bo, y_bo, _ = self._branch_end(np.array(kmin_o + h_o), other)
            d_b, y_b = np.where(inner, d_bi, d_bo), np.where(inner, y_bi, y_bo)
            out[sel] = (d_b - d_a) / (y_b - y_a)
        return out

    def _batch_state(self, p: np.ndarray, limits: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Slider positions (N, 2) (NaN rows as :meth:`inverse_batch`), moduli, branches and ``H``."""
        k, psi, d, hx = self._solve_heights(p[:, 1])
        q = np.column_stack([p[:, 0] - d, p[:, 0] + d])
        if limits:
            q[~within_limits(q, self._lo, self._hi)] = np.nan
        bad = np.isnan(q).any(axis=1)
        k[bad] = hx[bad] = np.nan
        return q, k, psi, hx

    def inverse_batch(self, poses: np.ndarray, *, limits: bool = True) -> np.ndarray:
        """Vectorised :meth:`inverse`: slider positions (N, 2) (m) for end-effector points (N, 2).

        The heights are solved together (:meth:`_solve_branch_batch`: the same table
        bracket as the scalar, then regula falsi on the elliptic solution). A NaN row beyond
        mode 1's reach, with the sliders closer than allowed, or (with ``limits``) a slider
        outside its stroke — where :meth:`inverse` raises :class:`~.base.UnreachablePose`.

        :param limits: ``False``: no stroke check.
        :raises ValueError: not an (N, 2) array, or a non-finite value.
        """
        return self._batch_state(as_poses(poses, 2), limits)[0]

    def jacobian_batch(self, poses: np.ndarray, *, limits: bool = True) -> np.ndarray:
        """Vectorised :meth:`jacobian`: ``[[1, -d'], [1, d']]`` (N, 2, 2), ``d' = dd/dy`` by the
        same central difference in the modulus as :meth:`slope`; a NaN matrix where
        :meth:`inverse_batch` has a NaN row."""
        p = as_poses(poses, 2)
        _, k, psi, _ = self._batch_state(p, limits)
        dd = self._slope_batch(k, psi)
        jac = np.empty((p.shape[0], 2, 2))
        jac[:, :, 0] = 1.0
        jac[:, 0, 1], jac[:, 1, 1] = -dd, dd
        jac[np.isnan(dd)] = np.nan
        return jac

    def _statics_batch(self, p: np.ndarray) -> Statics:
        """``W = J^T (f - f0)``: ``G = J^T``, ``b = f0 = (-H, H)``, ``H = J^-T`` in closed form
        ``[[1/2, -1/(2 d')], [1/2, 1/(2 d')]]`` (regular where ``d' != 0``)."""
        _, k, psi, hx = self._batch_state(p, True)
        dd = self._slope_batch(k, psi)
        reach = np.isfinite(dd)
        g = np.empty((p.shape[0], 2, 2))
        g[:, 0, :] = 1.0
        g[:, 1, 0], g[:, 1, 1] = -dd, dd
        with np.errstate(divide='ignore'):
            inv = 0.5 / dd
        h = np.empty((p.shape[0], 2, 2))
        h[:, :, 0] = 0.5
        h[:, 0, 1], h[:, 1, 1] = -inv, inv
        g[~reach] = h[~reach] = np.nan
        return Statics(reach, g, h, reach & (dd != 0.0), np.column_stack([-hx, hx]))

    def solve_height(self, y: float) -> BarState:
        """The no-load configuration with the end effector at height ``y`` (m), mode 1.

        :raises UnreachablePose: ``y`` beyond mode 1's reach (the reason in the message).
        """
        ylo, yhi = self.height_range
        if not (ylo <= y <= yhi):
            side = ('above the highest point of the compression branch' if y > yhi
                    else 'below the lowest point of the tension branch')
            raise UnreachablePose(
                f'height y = {y:.5f} m is beyond mode 1\'s reach: {side} (mode 1 reaches '
                f'{ylo:.5f}-{yhi:.5f} m; beyond it the bars would need an infinite force or a higher '
                'buckling mode, which the paper excludes)', value=float(y), limits=(ylo, yhi))
        if y == self.y0:
            return BarState(self.d0, self.y0, self._kmin[PSI_COMPRESSION], PSI_COMPRESSION, 0.0, 0.0)
        psi = PSI_COMPRESSION if y > self.y0 else PSI_TENSION
        st = self._solve_branch(y, psi, 1)
        if st.d < self.min_half_distance:
            raise UnreachablePose(f'height y = {y:.5f} m needs the sliders {2 * st.d:.5f} m apart, '
                                  f'closer than the {2 * self.min_half_distance:.5f} m they can come')
        return st

    def solve_half_distance(self, d: float) -> BarState:
        """The no-load configuration for slider half-distance ``d`` (m), mode 1.

        :raises UnreachablePose: ``d`` beyond mode 1's reach.
        """
        dlo, dhi = self.half_distance_range
        if not (dlo <= d <= dhi):
            raise UnreachablePose(
                f'slider half-distance d = {d:.5f} m is beyond mode 1\'s reach ({dlo:.5f}-{dhi:.5f} m)',
                value=float(d), limits=(dlo, dhi))
        if d == self.d0:
            return BarState(self.d0, self.y0, self._kmin[PSI_COMPRESSION], PSI_COMPRESSION, 0.0, 0.0)
        psi = PSI_COMPRESSION if d < self.d0 else PSI_TENSION
        return self._solve_branch(d, psi, 0)

    # ------------------------------------------------------------------ protocol
    # actuator_limits (slider positions, m) and home_pose (x, y, m): MechanismBase
    def __repr__(self) -> str:
        return (f'Continuum2(bar_length={self.length} m, E={self.youngs_modulus:.3g} Pa, '
                f'section {self.width * 1e3:.2f} x {self.thickness * 1e3:.2f} mm, EI={self.ei:.4g} N·m^2)')

    def inverse(self, pose: Sequence[float]) -> np.ndarray:
        """Slider positions ``(s1, s2)`` (m) for the end effector at ``pose = (x, y)`` (m).

        :raises ValueError: malformed pose.
        :raises UnreachablePose: beyond mode 1's reach, or a slider outside its stroke.
        """
        x, y = as_vector(pose, 2, 'pose')
        st = self.solve_height(float(y))
        q = np.array([x - st.d, x + st.d])
        check_limits(q, self._lo, self._hi, self.actuator_names)
        return q

    def forward_state(self, q: Sequence[float]) -> tuple[np.ndarray, BarState]:
        """End-effector position ``(x, y)`` (m) and the bar state for slider positions ``q``.

        :raises ValueError: malformed ``q`` or ``s1 >= s2``.
        :raises UnreachablePose: a half-distance beyond mode 1's reach.
        """
        s1, s2 = as_vector(q, 2, 'q')
        if not s2 > s1:
            raise ValueError(f'q: slider 1 must be left of slider 2 (s1 < s2), got s1={s1:.5f} m, s2={s2:.5f} m')
        st = self.solve_half_distance(0.5 * (s2 - s1))
        return np.array([0.5 * (s1 + s2), st.y]), st

    def forward(self, q: Sequence[float]) -> list[np.ndarray]:
        """Every mode-1 no-load configuration: one ``(x, y)`` (m), or ``[]`` beyond mode 1's reach."""
        try:
            return [self.forward_state(q)[0]]
        except UnreachablePose:
            return []

    def forward_nearest(self, q: Sequence[float], hint_pose: Sequence[float]) -> np.ndarray:
        """The (single) mode-1 solution; ``hint_pose`` is validated only.

        :raises UnreachablePose: beyond mode 1's reach.
        """
        as_vector(hint_pose, 2, 'hint_pose')
        return self.forward_state(q)[0]

    def bar_force(self, q: Sequence[float]) -> float:
        """``H`` (N): global x-force of bar 2 on bar 1 at the weld (< 0 compression)."""
        return self.forward_state(q)[1].horizontal

    def slope(self, y: float) -> float:
        """``dd/dy`` at height ``y``: ``(dd/dk) / (dy/dk)`` along the branch, by a central
        difference in the modulus about the solved ``k`` (step ``1e-6`` of the branch's
        modulus range; no further root solves). At the straight bar (``k = k_min`` on both
        branches, where ``d(y)`` is smooth but ``k(y)`` is not) the difference is taken across
        the two branches instead.
        """
        st = self.solve_height(y)
        length, ei = self.length, self.ei
        def step(psi: float) -> tuple[float, float]:
            """(k_min, difference step) of the branch ``psi``."""
            kmin = self._kmin[psi]
            return kmin, 1e-6 * (self._ends[psi][0] - kmin)    # type: ignore[index]

        kmin, h = step(st.psi)
        if st.k - kmin > h:
            k_end = self._ends[st.psi][0]                    # type: ignore[index]
            d_a, y_a, _ = _bar_end_scalar(st.k - h, st.psi, length, ei)
            d_b, y_b, _ = _bar_end_scalar(min(st.k + h, k_end), st.psi, length, ei)
        else:
            other = PSI_TENSION if st.psi == PSI_COMPRESSION else PSI_COMPRESSION
            kmin_o, h_o = step(other)
            d_a, y_a, _ = _bar_end_scalar(kmin + h, st.psi, length, ei)
            d_b, y_b, _ = _bar_end_scalar(kmin_o + h_o, other, length, ei)
        return (d_b - d_a) / (y_b - y_a)

    def jacobian(self, pose: Sequence[float]) -> np.ndarray:
        """``J`` (2, 2) with ``q_dot = J @ (x_dot, y_dot)``: ``s1 = x - d(y)``, ``s2 = x + d(y)``.

        ``d'(y)`` from :meth:`slope` (a central difference in the elliptic modulus).
        """
        _, y = as_vector(pose, 2, 'pose')
        dd = self.slope(float(y))
        return np.array([[1.0, -dd], [1.0, dd]])

    def slider_forces_no_load(self, q: Sequence[float]) -> np.ndarray:
        """``f0 = (-H, H)`` (N, push along +x positive): the slider forces with no load."""
        h = self.forward_state(q)[1].horizontal
        return np.array([-h, h])

    def unloaded_forces(self, q: Sequence[float]) -> np.ndarray:
        """The bent bars' push on the sliders with no load: :meth:`slider_forces_no_load`."""
        return self.slider_forces_no_load(q)

    def wrench(self, pose: Sequence[float], forces: Sequence[float]) -> np.ndarray:
        """End-effector force ``(Fx, Fy)`` (N), first order: ``J^T (f - f0)`` (module docstring).

        :param forces: slider forces (N), along +x positive.
        """
        f = as_vector(forces, 2, 'forces')
        p = as_vector(pose, 2, 'pose')
        q = self.inverse(p)
        return self.jacobian(p).T @ (f - self.slider_forces_no_load(q))

    def in_workspace(self, pose: Sequence[float]) -> bool:
        """Within mode 1's reach and the strokes. :raises ValueError: malformed pose."""
        return self._in_workspace(pose, singularity=False)

    # ------------------------------------------------------------------ configuration
    @classmethod
    def from_config(cls, section: Mapping[str, Any]) -> 'Continuum2':
        """Build from the YAML's ``mechanism`` section.

        Reads ``bar_length``, ``youngs_modulus``, ``width``, ``thickness``, ``stroke_min``,
        ``stroke_max``, ``actuator_names``, ``home_pose``, ``k_max``, ``min_half_distance``.

        :raises ConfigError: a missing or malformed value, naming the parameter.
        """
        check_section(section, 'continuum2', 'Continuum2',
                      ('bar_length', 'youngs_modulus', 'width', 'thickness', 'stroke_min', 'stroke_max'))
        kwargs = section_kwargs(section, given=('actuator_names', 'home_pose', 'k_max', 'min_half_distance'))
        with config_errors():
            return cls(section['bar_length'], section['youngs_modulus'], section['width'], section['thickness'],
                       (section['stroke_min'], section['stroke_max']), **kwargs)
