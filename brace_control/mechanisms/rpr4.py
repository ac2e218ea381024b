"""Planar 4-RPR parallel mechanism: the neck brace (report seed 000, §"FOUR RPR", eqs. 1-6).

Four base anchors ``A_n = (x_n, y_n)`` (the report's ``(x_n, y_n)``), a platform of radius
``r`` with its joints at angles ``delta_n`` in the platform frame, four prismatic legs
(rods) or cables of length ``d_n``. Pose ``(x, y, psi)``; platform joint
``B_n = (x, y) + r (cos(psi + delta_n), sin(psi + delta_n))`` (eqs. 1-2). General platform
anchors ``b_n`` (any four points of the platform frame) are accepted as well; the
report's layout is ``b_n = r (cos delta_n, sin delta_n)``.

Inverse kinematics: ``d_n = |B_n - A_n|`` (eq. 6, the ``+`` root: a length is not
negative) and the leg direction ``theta_n = atan2(B_n - A_n)`` (eq. 5, with ``atan2``: the
printed ``tan^-1`` of the quotient loses the quadrant) — :meth:`Rpr4.leg_angles`.

Forward kinematics from four lengths (redundant sensing)
--------------------------------------------------------
Three lengths fix the pose up to the 3-RPR's assembly modes; the fourth is redundant.
Each 3-leg subset is solved exactly by :meth:`Rpr3.forward` (the sextic), every such
pose seeds a damped Gauss-Newton (Levenberg-Marquardt) on the four loop residuals
``d_n(pose) - q_n``, the converged minima are de-duplicated, and the *residual*
``||d(pose) - q||_2`` (m) of each is reported (:meth:`Rpr4.forward_with_residual`).
Consistent lengths give residual ~ 0; a slack (or broken) cable whose motor has paid out
more cable than the geometric distance, a slipped encoder, a bent rod give a residual
``~ |n_k| / |n| * error_k`` (``n`` the null vector of ``J^T``, below): above
``residual_max`` (YAML) it is a fault. One redundant length *detects* such a fault but
cannot, in general, isolate which leg it is.
:meth:`Rpr4.forward` returns the minima with residual <= ``residual_max``, best first;
:meth:`Rpr4.forward_nearest` raises :class:`InconsistentLengths` when there is none.

Statics, sign convention, redundancy
------------------------------------
``W = J^T f`` with ``J`` (4, 3), row ``n`` = ``(u_n, rho_n x u_n)``, ``u_n`` the unit vector
``A_n -> B_n``, ``rho_n = R(psi) b_n``: ``f_n`` is the actuator *thrust*, push positive
(as in :class:`~.rpr3.Rpr3`). A **cable** pulls the platform towards its base anchor: its
tension ``t_n >= 0`` is the thrust ``f_n = -t_n``. With four actuators and three DOF,
``J^T f = W`` has a one-parameter family ``f = f_p + lambda n``: ``f_p = pinv(J^T) W``
(minimum norm), ``n`` the unit null vector of ``J^T`` (its components are the signed 3x3
minors of ``J^T``). Bounds ``lo_n <= f_n <= hi_n`` (rods ``[-force_max, force_max]``,
cables ``[-t_max, -t_min]``) cut ``lambda`` to an interval; empty means the wrench is
infeasible at that pose. :meth:`Rpr4.distribute` picks the interval's centre (``'centre'``,
the farthest from the two binding limits) or its point of least norm (``'min_norm'``);
with an unbounded side the centre is undefined and the least-norm point is used.
A pose where ``n`` has components of both signs is not wrench-closure for cables: no
positive pretension balances itself there.

Report errata: eq. 6's ``+-`` (take ``+``); eq. 5's quadrant (``atan2``); the ``sigma`` in
``B_4`` (row 3, column 4) is a stray entry (``B`` is diagonal blocks); the report's
``J = A_p^-1 B`` maps all eight joint rates (four passive angles, four lengths) to the
pose rate, it is not the ``q_dot = J x_dot`` of this protocol (here ``J`` is (4, 3)).
"""
from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..config import ConfigError
from .base import (MechanismBase, SingularPose, UnreachablePose, as_actuator_names, as_condition_max,
                   as_points, as_poses, as_positive, as_range, as_vector, check_limits, check_section,
                   condition_number, config_errors, section_kwargs, section_points, within_limits)
from .loader import register
from .planar import RprLegs, cross2, wrap_angle
from .rpr3 import Rpr3

__all__ = ['Rpr4', 'InconsistentLengths', 'InfeasibleWrench', 'Distribution', 'ACTUATION_MODES']

ACTUATION_MODES = ('rod', 'cable')
_SUBSETS = ((0, 1, 2), (0, 1, 3), (0, 2, 3), (1, 2, 3))


class InconsistentLengths(UnreachablePose):
    """Four measured lengths that no pose reproduces within ``residual_max``: a fault
    (slack or broken cable, encoder slip). ``residual`` (m) and ``pose`` (best fit) attached."""

    def __init__(self, message: str, *, residual: float, pose: np.ndarray) -> None:
        super().__init__(message)
        self.residual = residual
        self.pose = pose


class InfeasibleWrench(ValueError):
    """No actuator forces within their bounds produce the wanted wrench; ``reason`` says why."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


@dataclass
class Distribution:
    """Result of :meth:`Rpr4.distribute`.

    ``forces``: actuator thrusts (N, push positive) with ``J^T f = W`` (``None`` if
    infeasible); ``tensions``: ``-forces`` for cables (``None`` for rods or infeasible);
    ``feasible``; ``reason`` (empty when feasible); ``interval``: the feasible ``lambda``
    range along ``null``, the unit null vector of ``J^T``.
    """

    feasible: bool
    forces: np.ndarray | None
    tensions: np.ndarray | None
    reason: str
    interval: tuple[float, float]
    null: np.ndarray = field(repr=False)


def report_anchors(radius: float, delta: Sequence[float]) -> np.ndarray:
    """The report's platform joints ``b_n = r (cos delta_n, sin delta_n)`` (4, 2), m."""
    d = as_vector(delta, 4, 'anchor_angles')
    r = as_positive(radius, 'platform_radius', unit='m')
    return r * np.column_stack([np.cos(d), np.sin(d)])


def _null_vectors(jt: np.ndarray) -> np.ndarray:
    """Null vectors of a stack of (3, 4) matrices: ``n_k = (-1)^k det(J^T without column k)``."""
    cols = [[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]]
    return np.stack([(-1) ** k * np.linalg.det(jt[..., cols[k]]) for k in range(4)], axis=-1)


@register('rpr4')
class Rpr4(RprLegs, MechanismBase):
    """Planar 4-RPR (neck brace, cable or rod driven, one degree of redundancy).

    :param base_anchors: ``A_1..A_4`` (4, 2) or flat (8,), m.
    :param platform_anchors: ``b_1..b_4`` in the platform frame (4, 2) or (8,), m (see
        :func:`report_anchors` for the report's ``r``, ``delta_n``).
    :param stroke: ``(lo, hi)`` length range (m), each a scalar or four values.
    :param actuation: ``'cable'`` (pull only) or ``'rod'`` (push/pull).
    :param tension_min, tension_max: cable tension bounds (N), ``0 <= t_min < t_max``
        (``t_max`` may be ``inf``).
    :param force_max: rod force bound (N), ``|f| <= force_max`` (default ``inf``).
    :param distribution: ``'centre'`` or ``'min_norm'`` (module docstring).
    :param residual_max: forward residual (m) above which the lengths are inconsistent.
    :param actuator_names: four distinct names.
    :param home_pose: rest pose ``(x, y, psi)``; default the base anchors' centroid, ``psi = 0``.
    :param singularity_condition_max: ``cond(J)`` above this is treated as singular.
    :raises ValueError: malformed arguments, an unreachable home pose.
    """

    dof: int = 3
    pose_kind: str = 'planar'
    n_actuators: int = 4
    _angle_name = 'psi'

    def __init__(self, base_anchors: Sequence[Sequence[float]] | np.ndarray,
                 platform_anchors: Sequence[Sequence[float]] | np.ndarray,
                 stroke: tuple[Any, Any] | Sequence[Any], *,
                 actuation: str = 'cable', tension_min: float = 0.0, tension_max: float = math.inf,
                 force_max: float = math.inf, distribution: str = 'centre',
                 residual_max: float = 1e-3,
                 actuator_names: Sequence[str] = ('c1', 'c2', 'c3', 'c4'),
                 home_pose: Sequence[float] | None = None,
                 singularity_condition_max: float = 1e4) -> None:
        self.base_anchors = as_points(base_anchors, 4, 'base_anchors')
        self.platform_anchors = as_points(platform_anchors, 4, 'platform_anchors')
        self._lo, self._hi = as_range(stroke, 4, 'stroke', unit='m', lo_min=0.0)
        if actuation not in ACTUATION_MODES:
            raise ValueError(f'actuation: expected "cable" or "rod", got {actuation!r}')
        self.actuation = actuation
        self.tension_min = as_positive(tension_min, 'tension_min', unit='N', allow_zero=True)
        self.tension_max = as_positive(tension_max, 'tension_max', unit='N', allow_inf=True)
        if not self.tension_min < self.tension_max:
            raise ValueError(f'tension_min {self.tension_min} N must be < tension_max {self.tension_max} N')
        self.force_max = as_positive(force_max, 'force_max', unit='N', allow_inf=True)
        if distribution not in ('centre', 'min_norm'):
            raise ValueError(f'distribution: expected "centre" or "min_norm", got {distribution!r}')
        self.distribution = distribution
        self.residual_max = as_positive(residual_max, 'residual_max', unit='m')
        self.actuator_names: tuple[str, ...] = as_actuator_names(actuator_names, 4)
        self.singularity_condition_max = as_condition_max(singularity_condition_max)
        self._check_legs()
        a, b = self.base_anchors, self.platform_anchors
        # the four 3-leg sub-mechanisms whose exact forward solutions seed the least squares
        self._subs: list[Rpr3 | None] = []
        for sub in _SUBSETS:
            try:
                self._subs.append(Rpr3(a[list(sub)], b[list(sub)], (0.0, 1e9), home_pose=(0.0, 0.0, 0.0)))
            except ValueError:        # e.g. two of the three legs identical: no exact seed from it
                self._subs.append(None)
        if home_pose is None:
            cx, cy = a.mean(axis=0)
            home_pose = (float(cx), float(cy), 0.0)
        self._home = as_vector(home_pose, 3, 'home_pose')
        self._home[2] = wrap_angle(float(self._home[2]))
        self.inverse(self._home)

    # ------------------------------------------------------------------ properties
    # actuator_limits (leg/cable lengths, m) and home_pose (x, y, psi): MechanismBase
    def __repr__(self) -> str:
        return (f'Rpr4(base_anchors={self.base_anchors.tolist()}, platform_anchors={self.platform_anchors.tolist()}, '
                f'stroke=({self._lo.tolist()}, {self._hi.tolist()}), actuation={self.actuation!r})')

    # ------------------------------------------------------------------ inverse kinematics
    # _legs (leg vectors B_n - A_n and rho_n = R b_n): RprLegs
    def inverse(self, pose: Sequence[float]) -> np.ndarray:
        """Leg lengths ``d_1..d_4`` (m) for ``pose = (x, y, psi)`` (eq. 6).

        :raises UnreachablePose: a length outside the stroke, naming the actuator.
        """
        p = as_vector(pose, 3, 'pose')
        q = np.linalg.norm(self._legs(p)[0], axis=1)
        check_limits(q, self._lo, self._hi, self.actuator_names)
        return q

    def leg_angles(self, pose: Sequence[float]) -> np.ndarray:
        """Direction ``theta_n`` (rad) of each leg ``A_n -> B_n`` (eq. 5, with ``atan2``)."""
        d = self._legs(as_vector(pose, 3, 'pose'))[0]
        return np.arctan2(d[:, 1], d[:, 0])

    def inverse_batch(self, poses: np.ndarray, *, limits: bool = True) -> np.ndarray:
        """Vectorised eq. 6: lengths (N, 4) (m) for poses (N, 3); a NaN row where a length is
        outside the stroke (where :meth:`inverse` raises), never an exception.

        :param limits: ``False``: every pose's lengths, no stroke check.
        :raises ValueError: not an (N, 3) array, or a non-finite value (naming the rows).
        """
        p = as_poses(poses, 3)
        out = np.linalg.norm(self._legs_batch(p)[0], axis=-1)
        if limits:
            out[~within_limits(out, self._lo, self._hi)] = np.nan
        return out

    def jacobian_batch(self, poses: np.ndarray, *, limits: bool = True) -> np.ndarray:
        """Vectorised :meth:`jacobian`: ``J`` (N, 4, 3), rows ``(u_n, rho_n x u_n)``; a NaN
        matrix where :meth:`inverse_batch` has a NaN row (or a leg has zero length).

        :raises ValueError: not an (N, 3) array, or a non-finite value.
        """
        p = as_poses(poses, 3)
        jac = self._jacobian_batch(p)
        bad = ~np.isfinite(jac).all(axis=(1, 2))
        if limits:
            bad |= np.isnan(self.inverse_batch(p)).any(axis=1)
        jac[bad] = np.nan
        return jac

    def _effort_bounds(self, limits: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Thrust range for :meth:`wrench_capacity`: rods ``[-limit, limit]``; cables pull
        only, ``[-limit, 0]`` (thrust = minus tension; ``tension_min`` is not imposed)."""
        if self.actuation == 'cable':
            return -limits, np.zeros_like(limits)
        return -limits, limits.copy()

    def _legs_batch(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        c, s = np.cos(p[:, 2])[:, None], np.sin(p[:, 2])[:, None]
        bx, by = self.platform_anchors[:, 0], self.platform_anchors[:, 1]
        rho = np.stack([c * bx - s * by, s * bx + c * by], axis=-1)          # (N, 4, 2)
        return p[:, None, :2] + rho - self.base_anchors, rho

    def _jacobian_batch(self, p: np.ndarray) -> np.ndarray:
        d, rho = self._legs_batch(p)
        n = np.linalg.norm(d, axis=-1, keepdims=True)
        with np.errstate(divide='ignore', invalid='ignore'):
            u = d / n
        return np.concatenate([u, cross2(rho, u)[..., None]], axis=-1)       # (N, 4, 3)

    # ------------------------------------------------------------------ differential kinematics
    def jacobian(self, pose: Sequence[float]) -> np.ndarray:
        """``J`` (4, 3): ``q_dot = J @ (x_dot, y_dot, psi_dot)``; row ``(u_n, rho_n x u_n)``.

        :raises UnreachablePose: a leg of zero length (direction undefined).
        """
        return self._leg_jacobian(as_vector(pose, 3, 'pose'))

    def condition(self, pose: Sequence[float]) -> float:
        """``cond(J)`` (ratio of the largest to the third singular value); ``inf`` when rank < 3."""
        return condition_number(self.jacobian(pose))

    def check_singularity(self, pose: Sequence[float]) -> None:
        """Raise :class:`~.base.SingularPose` when ``cond(J) > singularity_condition_max``."""
        self._check_singularity(pose)

    def wrench(self, pose: Sequence[float], forces: Sequence[float]) -> np.ndarray:
        """Wrench on the platform ``(Fx N, Fy N, M N·m about P, ccw) = J^T f``.

        :param forces: thrusts ``f_1..f_4`` (N), push positive along ``A_n -> B_n``; a cable
            with tension ``t`` is ``f = -t``.
        """
        f = as_vector(forces, 4, 'forces')
        return self.jacobian(pose).T @ f

    def in_workspace(self, pose: Sequence[float]) -> bool:
        """Within stroke, ``cond(J) <= singularity_condition_max`` and, for cables, the
        platform can be held unloaded with tensions in ``[t_min, t_max]`` (zero wrench feasible).

        :raises ValueError: malformed ``pose``.
        """
        return self._in_workspace(pose) and (self.actuation != 'cable'
                                             or self.distribute(pose, (0.0, 0.0, 0.0)).feasible)

    def workspace_reason(self, pose: Sequence[float]) -> str:
        """Why ``pose`` is outside the workspace (:meth:`in_workspace`; '' when it is not):
        the stroke or the singularity (the message of :meth:`inverse` /
        :meth:`check_singularity`), or cables that cannot hold it unloaded."""
        try:
            self.inverse(pose)
            self.check_singularity(pose)
        except UnreachablePose as exc:
            return str(exc)
        if self.actuation == 'cable':
            d = self.distribute(pose, (0.0, 0.0, 0.0))
            if not d.feasible:
                return f'the cables cannot hold it unloaded: {d.reason}'
        return ''

    # ------------------------------------------------------------------ redundancy resolution
    def _bounds(self, mode: str) -> tuple[float, float]:
        if mode == 'cable':
            return -self.tension_max, -self.tension_min
        if mode == 'rod':
            return -self.force_max, self.force_max
        raise ValueError(f'mode: expected "cable" or "rod", got {mode!r}')

    def _intervals(self, jac: np.ndarray, w: np.ndarray, lo: float, hi: float
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Vectorised core: ``jac`` (N, 4, 3), ``w`` (N, K, 3) -> ``f_p`` (N, K, 4), unit null
        vectors (N, 4), ``lambda`` interval ends (N, K) and a mask of components pinned by a
        zero null component that violate their bounds (N, K)."""
        jt = np.swapaxes(jac, -1, -2)                                  # (N, 3, 4)
        # minimum-norm particular solution pinv(J^T) W = J (J^T J)^-1 W (J has rank 3 here;
        # callers exclude singular poses first)
        jtj = np.einsum('nji,njk->nik', jac, jac)
        with np.errstate(all='ignore'):
            try:
                sol = np.linalg.solve(jtj, np.swapaxes(w, -1, -2))      # (N, 3, K)
            except np.linalg.LinAlgError:
                sol = np.linalg.pinv(jtj) @ np.swapaxes(w, -1, -2)
        fp = np.swapaxes(jac @ sol, -1, -2)                            # (N, K, 4)
        null = _null_vectors(jt)
        norm = np.linalg.norm(null, axis=-1, keepdims=True)
        with np.errstate(divide='ignore', invalid='ignore'):
            null = np.where(norm > 0.0, null / norm, 0.0)
        nn = null[:, None, :]
        tiny = np.abs(nn) <= 1e-12
        with np.errstate(divide='ignore', invalid='ignore'):
            a = (lo - fp) / nn
            b = (hi - fp) / nn
        low = np.where(tiny, -np.inf, np.minimum(a, b))
        high = np.where(tiny, np.inf, np.maximum(a, b))
        tol = 1e-9 * max(1.0, abs(lo) if math.isfinite(lo) else 1.0, abs(hi) if math.isfinite(hi) else 1.0)
        pinned_bad = np.any(tiny & ((fp < lo - tol) | (fp > hi + tol)), axis=-1)
        return fp, null, np.max(low, axis=-1), np.min(high, axis=-1), pinned_bad

    def distribute(self, pose: Sequence[float], wrench: Sequence[float], *, mode: str | None = None,
                   method: str | None = None) -> Distribution:
        """Actuator forces for the wanted platform wrench ``W = (Fx, Fy, M)`` (N, N, N·m).

        :param mode: ``'cable'`` (tensions in ``[t_min, t_max]``) or ``'rod'`` (``|f| <=
            force_max``; with no bound this is the minimum-norm ``pinv(J^T) W``); default the
            configured actuation.
        :param method: ``'centre'`` or ``'min_norm'``; default: the configured one for cables,
            ``'min_norm'`` for rods (the minimum-norm forces, clipped into ``force_max`` along
            the null space when needed).
        :returns: a :class:`Distribution` (``feasible``, ``forces``, ``tensions``, ``reason``).
        """
        p = as_vector(pose, 3, 'pose')
        w = as_vector(wrench, 3, 'wrench')
        mode = self.actuation if mode is None else mode
        if method is None:
            method = self.distribution if mode == 'cable' else 'min_norm'
        if method not in ('centre', 'min_norm'):
            raise ValueError(f'method: expected "centre" or "min_norm", got {method!r}')
        lo, hi = self._bounds(mode)
        unit = 'tension' if mode == 'cable' else 'force'
        jac = self.jacobian(p)
        cond = self.condition(p)
        if not cond <= self.singularity_condition_max:
            return Distribution(False, None, None, f'pose {p.tolist()} is singular (cond(J) = {cond:.3g}): '
                                'the legs cannot resist every wrench', (math.nan, math.nan), np.zeros(4))
        fp, null, lam_lo, lam_hi, pinned = self._intervals(jac[None], w[None, None], lo, hi)
        fp, null = fp[0, 0], null[0]
        lam_lo, lam_hi, pinned = float(lam_lo[0, 0]), float(lam_hi[0, 0]), bool(pinned[0, 0])
        tol = 1e-9 * max(1.0, float(np.max(np.abs(fp))))
        if pinned or lam_lo > lam_hi + tol:
            # the best compromise: lambda halfway between the conflicting limits
            lam = 0.5 * (lam_lo + lam_hi) if math.isfinite(lam_lo + lam_hi) else 0.0
            f = fp + lam * null
            vals = -f if mode == 'cable' else f
            vlo, vhi = (-hi, -lo) if mode == 'cable' else (lo, hi)
            bad = [f'{self.actuator_names[i]} = {vals[i]:.2f} N ({"< min" if vals[i] < vlo else "> max"})'
                   for i in range(4) if not (vlo - tol <= vals[i] <= vhi + tol)]
            reason = (f'wrench {w.tolist()} infeasible at pose {[round(float(v), 5) for v in p]}: no {unit} '
                      f'distribution within [{vlo:g}, {vhi:g}] N; the best compromise needs '
                      + (', '.join(bad) if bad else 'a limit violated'))
            return Distribution(False, None, None, reason, (lam_lo, lam_hi), null)
        if method == 'centre' and math.isfinite(lam_lo) and math.isfinite(lam_hi):
            lam = 0.5 * (lam_lo + lam_hi)
        else:        # least norm: f_p is orthogonal to the null vector, so the lambda nearest 0
            lam = min(max(0.0, lam_lo), lam_hi)
        f = fp + lam * null
        f = np.clip(f, lo, hi)       # only rounding-level moves (the interval guarantees the bounds)
        return Distribution(True, f, -f if mode == 'cable' else None, '', (lam_lo, lam_hi), null)

    def actuator_forces(self, pose: Sequence[float], wrench: Sequence[float], mode: str | None = None, *,
                        method: str | None = None) -> np.ndarray:
        """Thrusts ``f`` (N, push positive; cables ``f = -t <= 0``) with ``J^T f = W``.

        ``mode='rod'``: minimum-norm (``pinv``) forces, within ``force_max`` if configured;
        ``mode='cable'``: a tension distribution within ``[t_min, t_max]``.

        :raises InfeasibleWrench: no such forces (the reason names the actuators and values).
        """
        d = self.distribute(pose, wrench, mode=mode, method=method)
        if not d.feasible:
            raise InfeasibleWrench(d.reason)
        assert d.forces is not None
        return d.forces

    def cable_tensions(self, pose: Sequence[float], wrench: Sequence[float], *,
                       method: str | None = None) -> np.ndarray:
        """Cable tensions ``t`` (N, all in ``[t_min, t_max]``) producing ``W``; see :meth:`actuator_forces`."""
        return -self.actuator_forces(pose, wrench, 'cable', method=method)

    def wrench_feasible_batch(self, poses: np.ndarray, wrenches: np.ndarray, *,
                              mode: str | None = None) -> np.ndarray:
        """Mask (N,): pose within stroke, ``cond(J)`` below the limit, and *every* wrench of
        ``wrenches`` (K, 3) feasible with the bounds of ``mode`` (vectorised)."""
        p = np.asarray(poses, dtype=float)
        if p.ndim != 2 or p.shape[1] != 3 or not np.isfinite(p).all():
            raise ValueError(f'poses: expected a finite (N, 3) array, got shape {p.shape}')
        w = np.asarray(wrenches, dtype=float)
        if w.ndim == 1:
            w = w[None]
        if w.ndim != 2 or w.shape[1] != 3 or not np.isfinite(w).all():
            raise ValueError(f'wrenches: expected a finite (K, 3) array, got shape {w.shape}')
        lo, hi = self._bounds(self.actuation if mode is None else mode)
        q = self.inverse_batch(p, limits=False)
        ok = np.all((q >= self._lo) & (q <= self._hi), axis=1) & np.all(q > 1e-12, axis=1)
        out = np.zeros(p.shape[0], dtype=bool)
        if not ok.any():
            return out
        jac = self._jacobian_batch(p[ok])
        sv = np.linalg.svd(jac, compute_uv=False)
        with np.errstate(divide='ignore', invalid='ignore'):
            regular = sv[:, 0] <= self.singularity_condition_max * sv[:, -1]
        fp, _, lam_lo, lam_hi, pinned = self._intervals(jac, np.broadcast_to(w, (jac.shape[0],) + w.shape), lo, hi)
        tol = 1e-9 * np.maximum(1.0, np.max(np.abs(fp), axis=-1))
        feas = (lam_lo <= lam_hi + tol) & ~pinned
        out[ok] = regular & np.all(feas, axis=1)
        return out

    def wrench_feasible_workspace(self, xs: Sequence[float], ys: Sequence[float], psi: float,
                                  wrenches: np.ndarray, *, mode: str | None = None) -> np.ndarray:
        """The wrench-feasible workspace at orientation ``psi`` on the grid ``xs`` x ``ys`` (m).

        :returns: bool array (len(ys), len(xs)): ``[j, i]`` true when the pose
            ``(xs[i], ys[j], psi)`` can apply every wrench in ``wrenches`` (K, 3) within the
            force bounds (and is within stroke, not singular).
        """
        x = np.asarray(xs, dtype=float).ravel()
        y = np.asarray(ys, dtype=float).ravel()
        gx, gy = np.meshgrid(x, y)
        poses = np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, float(psi))])
        return self.wrench_feasible_batch(poses, wrenches, mode=mode).reshape(gy.shape)

    # ------------------------------------------------------------------ forward kinematics
    def _lengths(self, poses: np.ndarray) -> np.ndarray:
        return np.linalg.norm(self._legs_batch(poses)[0], axis=-1)

    def _least_squares(self, seeds: np.ndarray, lv: np.ndarray, iters: int = 40) -> np.ndarray:
        """Levenberg-Marquardt on ``d(pose) - lv`` for a stack of seeds (K, 3)."""
        x = seeds.copy()
        mu = np.full(x.shape[0], 1e-6)
        res = self._lengths(x) - lv
        cost = np.sum(res * res, axis=1)
        eye = np.eye(3)
        for _ in range(iters):
            jac = self._jacobian_batch(x)
            jac[~np.isfinite(jac)] = 0.0
            jtj = np.einsum('kni,knj->kij', jac, jac)
            g = np.einsum('kni,kn->ki', jac, res)
            scale = np.einsum('kii->ki', jtj).mean(axis=1) + 1e-300
            step = np.linalg.solve(jtj + (mu * scale)[:, None, None] * eye, g[..., None])[..., 0]
            x_new = x - step
            res_new = self._lengths(x_new) - lv
            cost_new = np.sum(res_new * res_new, axis=1)
            better = cost_new <= cost
            x = np.where(better[:, None], x_new, x)
            res = np.where(better[:, None], res_new, res)
            cost = np.where(better, cost_new, cost)
            mu = np.where(better, np.maximum(mu * 0.1, 1e-12), mu * 10.0)
            if np.all(np.max(np.abs(step), axis=1) <= 1e-15 * max(1.0, float(np.max(lv)))):
                break
        return x

    def forward_with_residual(self, q: Sequence[float], hint_pose: Sequence[float] | None = None
                              ) -> tuple[np.ndarray, float]:
        """The least-squares pose for four lengths and its residual ``||d(pose) - q||_2`` (m).

        Without ``hint_pose``: the minimum with the smallest residual. With it: among the
        minima within ``residual_max`` the one nearest the hint (else the smallest residual).
        A residual above :attr:`residual_max` is fault-worthy (slack/broken cable).

        :raises ValueError: malformed or negative ``q``.
        """
        sols = self._solutions(q)
        if hint_pose is not None:
            hint = as_vector(hint_pose, 3, 'hint_pose')
            good = [s for s in sols if s[1] <= self.residual_max]
            if good:
                return min(good, key=lambda s: self._distance(s[0], hint))
        return sols[0]

    def _track(self, q: Sequence[float], hint: np.ndarray) -> np.ndarray | None:
        """Tracking shortcut of :meth:`forward_nearest` (called at the joint-state rate):
        Gauss-Newton on ``d(pose) - q`` from the hint. Accepted only when it converges
        close to the hint (1 cm, 0.05 rad: the least-squares minimum continuous with it)
        with a residual within :attr:`residual_max`; ``None`` sends the caller to the
        global solution (every minimum, then the nearest)."""
        lv = np.asarray(q, dtype=float)
        if lv.shape != (4,) or not np.all(np.isfinite(lv)) or np.any(lv < 0.0):
            return None
        x = hint.copy()
        try:
            for _ in range(6):
                r = self._lengths(x[None])[0] - lv
                step = np.linalg.lstsq(self._leg_jacobian(x), -r, rcond=None)[0]
                x = x + step
                if float(np.max(np.abs(step))) < 1e-13:
                    break
            else:
                return None
        except (ValueError, np.linalg.LinAlgError):
            return None
        res = float(np.linalg.norm(self._lengths(x[None])[0] - lv))
        if res > self.residual_max or np.hypot(x[0] - hint[0], x[1] - hint[1]) > 0.01 \
                or abs(wrap_angle(float(x[2] - hint[2]))) > 0.05:
            return None
        return x

    def _distance(self, pose: np.ndarray, hint: np.ndarray) -> float:
        return float((pose[0] - hint[0]) ** 2 + (pose[1] - hint[1]) ** 2
                     + (self._platform_size * wrap_angle(float(pose[2] - hint[2]))) ** 2)

    def _solutions(self, q: Sequence[float]) -> list[tuple[np.ndarray, float]]:
        """Distinct least-squares minima ``(pose, residual)``, smallest residual first."""
        lv = as_vector(q, 4, 'q')
        if np.any(lv < 0.0):
            raise ValueError(f'q: actuator lengths must be >= 0 m, got {lv.tolist()}')
        seeds: list[np.ndarray] = []
        for sub, mech in zip(_SUBSETS, self._subs):
            if mech is None:
                continue
            try:
                seeds.extend(mech.forward(lv[list(sub)]))
            except SingularPose:
                continue
        seeds.append(self._home)
        polished = self._least_squares(np.array(seeds), lv)
        res = np.linalg.norm(self._lengths(polished) - lv, axis=1)
        order = np.argsort(res, kind='stable')
        out: list[tuple[np.ndarray, float]] = []
        tol = 1e-7 * self._length_scale
        for k in order:
            pose = polished[k].copy()
            pose[2] = wrap_angle(float(pose[2]))
            if any(abs(pose[0] - o[0]) <= tol and abs(pose[1] - o[1]) <= tol
                   and abs(wrap_angle(float(pose[2] - o[2]))) <= 1e-7 for o, _ in out):
                continue
            out.append((pose, float(res[k])))
        return out

    def forward(self, q: Sequence[float]) -> list[np.ndarray]:
        """Every pose reproducing the four lengths within :attr:`residual_max` (least squares),
        smallest residual first; ``[]`` when none does (inconsistent lengths: a fault).

        :raises ValueError: malformed or negative ``q``.
        """
        return [p for p, r in self._solutions(q) if r <= self.residual_max]

    def forward_nearest(self, q: Sequence[float], hint_pose: Sequence[float]) -> np.ndarray:
        """The consistent pose nearest ``hint_pose``.

        :raises InconsistentLengths: no pose within :attr:`residual_max` (slack or broken
            cable, encoder fault); carries the best fit and its residual.
        """
        hint = as_vector(hint_pose, 3, 'hint_pose')
        local = self._track(q, hint)
        if local is not None:
            return local
        pose, res = self.forward_with_residual(q, hint)
        if res > self.residual_max:
            lv = np.asarray(q, dtype=float)
            raise InconsistentLengths(
                f'the four lengths ({", ".join(f"{n}={v:.4f} m" for n, v in zip(self.actuator_names, lv))}) '
                f'are inconsistent: least-squares residual {res * 1000:.2f} mm > {self.residual_max * 1000:.2f} mm '
                '(a slack or broken cable, or a length sensor fault)', residual=res, pose=pose)
        return pose

    # ------------------------------------------------------------------ configuration
    @classmethod
    def from_config(cls, section: Mapping[str, Any]) -> 'Rpr4':
        """Build from the YAML's ``mechanism`` section.

        Reads ``type`` (``rpr4``), ``base_anchors`` (flattened, m), either
        ``platform_radius`` (m) + ``anchor_angles`` (rad, the report's ``delta_n``) or
        ``platform_anchors`` (flattened, m), ``stroke_min``, ``stroke_max``, ``actuation``,
        ``tension_min``, ``tension_max``, ``force_max``, ``distribution``, ``residual_max``,
        ``actuator_names``, ``home_pose``, ``singularity_condition_max``.

        :raises ConfigError: a missing or malformed value, naming the parameter.
        """
        check_section(section, 'rpr4', 'Rpr4', ('base_anchors', 'stroke_min', 'stroke_max'))
        base = section_points(section, 'base_anchors', 4, '4-RPR')
        with config_errors():
            if 'platform_anchors' in section:
                plat = section_points(section, 'platform_anchors', 4, '4-RPR')
            elif 'platform_radius' in section and 'anchor_angles' in section:
                plat = report_anchors(section['platform_radius'], section['anchor_angles'])
            else:
                raise ConfigError('mechanism: give platform_radius and anchor_angles, or platform_anchors')
            kwargs = section_kwargs(section, present=('actuation', 'tension_min', 'tension_max', 'force_max',
                                                      'distribution', 'residual_max', 'actuator_names',
                                                      'singularity_condition_max'),
                                    given=('home_pose',))
            return cls(base, plat, (section['stroke_min'], section['stroke_max']), **kwargs)
