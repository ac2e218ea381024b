"""Planar 3-RPR parallel mechanism: the lumbar brace (seed paper 001, Guo et al.).

Base (pelvic ring) anchors ``A_i``, platform (thoracic ring) anchors ``B_i`` in the
platform frame, three prismatic legs of length ``l_i = |A_i B_i|`` (m). The pose is
``(x, y, theta)``: the platform origin ``P`` at ``(x, y)``, the platform frame rotated by
``theta`` (rad, counter-clockwise), so ``B_i = P + R(theta) b_i`` (paper eq. 1).

For the brace, ``A1 = (-r1, 0)``, ``A2 = O``, ``A3 = (r1, 0)``, ``b1 = (-r2, 0)``, ``b2 = 0``,
``b3 = (r2, 0)``; :meth:`Rpr3.inverse` is then the paper's eq. 3.

Forward kinematics (every real assembly mode)
---------------------------------------------
General architecture. Move the base origin to ``A1`` and the platform origin to ``B1``
(``a_i' = A_i - A1``, ``b_i' = b_i - b1``) and write ``p = B1 - A1``. Subtracting leg 1's
loop equation ``|p|^2 = l1^2`` from legs 2 and 3 leaves two equations *linear* in ``p``::

    m_i(theta) . p = r_i(theta),   m_i = R b_i' - a_i',
    r_i = (l_i^2 - l1^2 - |a_i'|^2 - |b_i'|^2 + 2 a_i' . R b_i') / 2,   i = 2, 3

(the general form of the paper's eq. 5). Cramer's rule gives
``p = (r2 perp'(m3) - r3 perp'(m2)) / D`` with ``D = m2 x m3``, and leg 1 then reads::

    g(theta) = |r2 m3 - r3 m2|^2 - l1^2 D^2 = 0.

With ``z = e^{i theta}`` the ``m_i`` are of degree 0..1 in ``z``, the ``r_i`` of degree
-1..1, so ``g`` is a trigonometric polynomial of degree 3: ``z^3 g(z)`` is the classic
*sextic* (Gosselin, Sefrioui and Richard; Husty), at most six real assembly modes. Its
coefficients are read off with an FFT of eight samples, its roots come from the
companion matrix (``numpy.roots``), the roots on ``|z| = 1`` are the real ``theta``.
Unlike the tan-half-angle substitution, ``theta = pi`` is an ordinary root here (no
degree drop to watch for). Roots within 2e-2 of the circle are candidates (a double root
splits off the circle by ~sqrt(eps)). Each is lifted to a pose (Cramer; where ``D`` is
small at that root — ``g`` then has a spurious double root and Cramer is 0/0-like — also
each row cut by the circle ``|p| = l1``), polished by Newton on the three loop equations
only if needed, kept only if it reproduces the input lengths to ``verify_tol`` (1e-9 m),
and de-duplicated.

Degenerate architectures (``D(theta) = 0`` for every ``theta``, so ``g`` collapses to a
square and the Cramer lift fails):

* *aligned*: ``a_3' = k a_2'`` and ``b_3' = k b_2'`` with the same real ``k`` — collinear
  base joints, collinear platform joints, same division ratio. **The lumbar brace**
  (``k = 2``: the middle joints at the midpoints). Closed form, the paper's eqs. 6-13
  generalised: ``a_2' . R b_2' = C(l)`` gives ``cos(theta + phi_b - phi_a)`` (eq. 6),
  two ``theta``; for each, ``p`` is a line (``m_2 . p = r_2``) cut by the circle
  ``|p| = l1`` (eqs. 7-9), two points: at most four modes. The paper pairs the sign of
  ``theta`` with the sign of ``y`` in eqs. 10-13; that pairing does not hold in general
  (``y = (a - b x) / c`` from eq. 5 fixes it; eq. 5 prints ``- 4 r2 v2 y``, the
  expansion of eq. 4 and the paper's own eq. 8 have ``+``: erratum 3), so no pairing is assumed here. The modes
  come in mirror pairs ``(x, y, t) <-> (x, -y, -t)`` (reflection in the base line), so
  two of the four have ``y > 0``, one of each pair: "the mode with y > 0" is not unique,
  use :meth:`Rpr3.forward_nearest`.
  Two more remarks on the paper: ``l1 < l2 < l3`` does not always give four modes (with
  ``l1 + l3 = 2 l2`` eq. 9 has a double root, two modes merge; some triples have none);
  and every ``theta = 0`` pose is singular (the three leg lines meet at the rings'
  homothety centre), see :meth:`Rpr3.check_singularity`.
* *mirror* (any other ``D = 0`` architecture, e.g. base and platform triangles congruent
  and mirror images): the roots of ``h(theta) = (r2 m3 - r3 m2) . (m2 + m3)`` (degree 2,
  a quartic in ``z``) with the line-circle lift.

Lengths that leave the platform a continuous self-motion (``g`` identically zero, e.g.
directly congruent triangles with equal legs) raise :class:`~.base.SingularPose`: the
assembly modes cannot be listed. Near a self-motion the roots cluster and the solution
is ill-conditioned (as at any singularity: the lengths no longer pin the pose down).

Kinetics
--------
``W = J^T f`` (virtual work, ``f . q_dot = W . x_dot``): with unit leg vectors
``u_i = (B_i - A_i) / l_i`` and ``rho_i = R b_i``, ``Fx = sum f_i u_ix``,
``Fy = sum f_i u_iy``, ``M = sum rho_i x (f_i u_i)`` about ``P``, counter-clockwise positive.
Relation to the paper's eqs. 14-20: ``(cos alpha, sin alpha)`` etc. are the ``u_i`` —
but eqs. 14-16 divide by the *squared* length; the unit vector needs its square root
(erratum 1). ``Fx``, ``Fy`` equal eq. 20's. For the brace, ``rho_1 = -rho_3 =
-r2 (cos t, sin t)`` and ``rho_2 = 0``, so ``M = r2 cos t (F3Y - F1Y) + r2 sin t (F1X -
F3X)``: the *negative* of eq. 20's ``M`` although the paper calls counter-clockwise
positive (erratum 2). :meth:`Rpr3.wrench` returns the counter-clockwise ``r x F`` moment.

Force transmission (:meth:`~.base.MechanismBase.wrench_capacity`): the legs that hold a
wrench ``W`` push with ``f = J^-T W``. The brace's legs are nearly parallel: at ``x = 0``,
``y = 390 mm``, 10 N sideways (base-frame ``Fx``) takes 1770 / -3515 / 1751 N at
``theta = 5 deg``, 800 / -1579 / 782 N at 10 deg, 127 / -232 / 108 N at 30 deg, so with
250 N actuators the lateral capacity is 0.711 N, 1.58 N and 10.8 N (the middle leg a2
binds) and 0 at ``theta = 0`` (singular). The 30 deg pose is outside the brace's stroke
(a1 would need 296 mm < 340 mm): the capacity there is the geometry's, not a reachable
pose's.
"""
from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from .base import (MechanismBase, SingularPose, UnreachablePose, as_actuator_names, as_condition_max,
                   as_points, as_poses, as_range, as_vector, check_limits, check_section, condition_number,
                   config_errors, section_kwargs, section_points, within_limits)
from .loader import register
from .planar import RprLegs, trig_poly_coefficients, trig_poly_real_roots, wrap_angle

__all__ = ['Rpr3']

_TWO_PI = 2.0 * math.pi


@register('rpr3')
class Rpr3(RprLegs, MechanismBase):
    """Planar 3-RPR mechanism (general anchors); the lumbar brace is one instance.

    :param base_anchors: ``A_1..A_3`` in the base frame, shape (3, 2) or flat (6,), m.
    :param platform_anchors: ``b_1..b_3`` in the platform frame, shape (3, 2) or (6,), m.
    :param stroke: ``(lo, hi)`` installed-length range of the actuators, m; each a scalar
        or three values (per actuator).
    :param actuator_names: three distinct names, in leg order.
    :param home_pose: a rest pose ``(x, y, theta)`` within stroke; default: the pose that
        puts every leg at mid-stroke when one exists near ``theta = 0``, else ``(0, mid, 0)``.
    :param singularity_condition_max: ``cond(J)`` above this is treated as singular.
    :raises ValueError: malformed anchors/stroke/names, two identical legs, a home pose
        outside the stroke.
    """

    dof: int = 3
    pose_kind: str = 'planar'
    n_actuators: int = 3
    #: an FK solution must reproduce the input lengths to this (m)
    verify_tol: float = 1e-9

    def __init__(self, base_anchors: Sequence[Sequence[float]] | np.ndarray,
                 platform_anchors: Sequence[Sequence[float]] | np.ndarray,
                 stroke: tuple[Any, Any] | Sequence[Any], *,
                 actuator_names: Sequence[str] = ('a1', 'a2', 'a3'),
                 home_pose: Sequence[float] | None = None,
                 singularity_condition_max: float = 1e4) -> None:
        self.base_anchors = as_points(base_anchors, 3, 'base_anchors')
        self.platform_anchors = as_points(platform_anchors, 3, 'platform_anchors')
        self._lo, self._hi = as_range(stroke, 3, 'stroke', unit='m', lo_min=0.0)
        self.actuator_names: tuple[str, ...] = as_actuator_names(actuator_names, 3)
        self.singularity_condition_max = as_condition_max(singularity_condition_max)
        # also sets _platform_size (m, weighs the angle against position in forward_nearest)
        self._check_legs(': the mechanism is not 3-DOF')
        self._prepare_forward()
        if home_pose is None:
            self._home = self._default_home()
        else:
            self._home = as_vector(home_pose, 3, 'home_pose')
            self._home[2] = wrap_angle(self._home[2])
            self.inverse(self._home)     # raises UnreachablePose (a ValueError) when outside stroke

    # ------------------------------------------------------------------ properties
    # actuator_limits (installed lengths, m) and home_pose (x, y, theta): MechanismBase
    @property
    def architecture(self) -> str:
        """``'general'`` (sextic), ``'aligned'`` (the brace's closed form) or ``'mirror'`` (other ``D = 0``)."""
        return self._kind

    def __repr__(self) -> str:
        return (f'Rpr3(base_anchors={self.base_anchors.tolist()}, '
                f'platform_anchors={self.platform_anchors.tolist()}, '
                f'stroke=({self._lo.tolist()}, {self._hi.tolist()}), actuator_names={self.actuator_names})')

    def _default_home(self) -> np.ndarray:
        """A rest pose when the YAML gives none: the best-conditioned of a few candidates.

        Candidates: the assembly modes with every leg at mid-stroke, and the base centroid
        raised by the mean mid-stroke at ``theta`` in {0, +-10, +-20} deg. Preferred: within
        stroke, ``y`` above the base, lowest ``cond(J)``.
        """
        mid = 0.5 * (self._lo + self._hi)
        try:
            cands = list(self.forward(mid))
        except SingularPose:
            cands = []
        cx, cy = self.base_anchors.mean(axis=0)
        cands += [np.array([cx, cy + float(np.mean(mid)), math.radians(d)]) for d in (0, 10, -10, 20, -20)]
        poses = np.array(cands)
        ok = self.reachable_batch(poses)
        if not ok.any():
            raise ValueError('home_pose: none given and no default rest pose within stroke was found; '
                             'set home_pose explicitly')
        cond = self._condition_batch(poses)
        key = np.where(ok, 0, 2) + (poses[:, 1] <= cy) + np.where(np.isfinite(cond), cond / (1.0 + cond), 1.0)
        return poses[int(np.argmin(key))].copy()

    # ------------------------------------------------------------------ inverse kinematics
    # _legs (leg vectors B_i - A_i and rho_i = R b_i): RprLegs
    def inverse(self, pose: Sequence[float]) -> np.ndarray:
        """Actuator lengths ``l_1..l_3`` (m) for ``pose = (x, y, theta)`` (paper eq. 3 for the brace).

        :raises ValueError: non-finite or wrong-shape ``pose``.
        :raises UnreachablePose: a length outside the stroke, naming the actuator, the
            length it would need and its stroke.
        """
        p = as_vector(pose, 3, 'pose')
        q = np.linalg.norm(self._legs(p)[0], axis=1)
        check_limits(q, self._lo, self._hi, self.actuator_names)
        return q

    def inverse_batch(self, poses: np.ndarray, *, limits: bool = True) -> np.ndarray:
        """Vectorised eq. 3: lengths (N, 3) (m) for poses (N, 3); a NaN row where a length is
        outside the stroke (where :meth:`inverse` raises), never an exception.

        Singular poses (e.g. the brace at ``theta = 0``) are reachable and get their lengths:
        conditioning is the caller's check (:meth:`in_workspace_batch`, ``condition``).

        :param limits: ``False``: every pose's lengths, no stroke check.
        :raises ValueError: not an (N, 3) array, or a non-finite value (naming the rows).
        """
        p = as_poses(poses, 3)
        c, s = np.cos(p[:, 2]), np.sin(p[:, 2])
        out = np.empty((p.shape[0], 3))
        for i in range(3):
            bx, by = self.platform_anchors[i]
            ax, ay = self.base_anchors[i]
            dx = p[:, 0] + (c * bx - s * by) - ax
            dy = p[:, 1] + (s * bx + c * by) - ay
            np.hypot(dx, dy, out=out[:, i])
        if limits:
            out[~within_limits(out, self._lo, self._hi)] = np.nan
        return out

    def jacobian_batch(self, poses: np.ndarray, *, limits: bool = True) -> np.ndarray:
        """Vectorised :meth:`jacobian`: ``J`` (N, 3, 3), rows ``(u_i, rho_i x u_i)``.

        A NaN matrix where :meth:`inverse_batch` has a NaN row (outside the stroke; with
        ``limits=False`` only where a leg has zero length, as :meth:`jacobian` raises there).

        :raises ValueError: not an (N, 3) array, or a non-finite value.
        """
        p = as_poses(poses, 3)
        jac = self._jacobian_batch(p)
        bad = ~np.isfinite(jac).all(axis=(1, 2))
        if limits:
            bad |= np.isnan(self.inverse_batch(p)).any(axis=1)
        jac[bad] = np.nan
        return jac

    def reachable_batch(self, poses: np.ndarray) -> np.ndarray:
        """Boolean mask (N,): every length of the pose within its stroke (vectorised, no singularity test)."""
        return ~np.isnan(self.inverse_batch(poses)).any(axis=1)

    def in_workspace_batch(self, poses: np.ndarray) -> np.ndarray:
        """Boolean mask (N,): within stroke and ``cond(J) <= singularity_condition_max`` (vectorised)."""
        p = np.asarray(poses, dtype=float)
        ok = self.reachable_batch(p)
        if not ok.any():
            return ok
        return ok & (self._condition_batch(p) <= self.singularity_condition_max)

    def _jacobian_batch(self, p: np.ndarray) -> np.ndarray:
        """``J`` of validated poses (N, 3), no stroke check (NaN rows for a zero-length leg)."""
        c, s = np.cos(p[:, 2]), np.sin(p[:, 2])
        bx, by = self.platform_anchors[:, 0], self.platform_anchors[:, 1]
        rx = c[:, None] * bx - s[:, None] * by
        ry = s[:, None] * bx + c[:, None] * by
        dx = p[:, 0, None] + rx - self.base_anchors[:, 0]
        dy = p[:, 1, None] + ry - self.base_anchors[:, 1]
        n = np.hypot(dx, dy)
        with np.errstate(divide='ignore', invalid='ignore'):
            ux, uy = dx / n, dy / n
        return np.stack([ux, uy, rx * uy - ry * ux], axis=-1)

    def _condition_batch(self, p: np.ndarray) -> np.ndarray:
        jac = self._jacobian_batch(p)
        bad = ~np.isfinite(jac).all(axis=(1, 2))
        jac[bad] = 0.0
        sv = np.linalg.svd(jac, compute_uv=False)
        with np.errstate(divide='ignore'):
            cond = np.where(sv[:, -1] > 0.0, sv[:, 0] / sv[:, -1], np.inf)
        cond[bad] = np.inf
        return cond

    # ------------------------------------------------------------------ differential kinematics
    def jacobian(self, pose: Sequence[float]) -> np.ndarray:
        """``J`` (3, 3) with ``q_dot = J @ (x_dot, y_dot, theta_dot)``.

        Row ``i`` is ``(u_i, rho_i x u_i)``: ``u_i`` the unit vector ``A_i -> B_i``,
        ``rho_i = R(theta) b_i`` (m). Units: columns 1-2 dimensionless, column 3 in m.

        :raises UnreachablePose: a leg of zero length (its direction is undefined).
        """
        return self._leg_jacobian(as_vector(pose, 3, 'pose'))

    def condition(self, pose: Sequence[float]) -> float:
        """``cond(J)`` (2-norm); ``inf`` at a singularity. J mixes units (column 3 in m)."""
        return condition_number(self.jacobian(pose))

    def check_singularity(self, pose: Sequence[float]) -> None:
        """Raise :class:`~.base.SingularPose` when ``cond(J) > singularity_condition_max``.

        For the lumbar brace every pose with ``theta = 0`` is singular: the three leg lines
        meet in the homothety centre of the (parallel) rings, so a small rotation about it
        is not resisted by the legs.
        """
        self._check_singularity(pose)

    def wrench(self, pose: Sequence[float], forces: Sequence[float]) -> np.ndarray:
        """Wrench on the platform ``(Fx N, Fy N, M N·m about P, counter-clockwise) = J^T f``.

        :param pose: ``(x, y, theta)`` (m, m, rad).
        :param forces: actuator thrusts ``F_1..F_3`` (N), push positive, acting on the
            platform along ``A_i -> B_i``.

        ``Fx``, ``Fy`` are the paper's eq. 20 with unit direction cosines (eqs. 14-16 lack
        the square root in the denominator); ``M = sum rho_i x F_i`` is the negative of
        eq. 20's ``M`` (whose sign contradicts its counter-clockwise convention).
        """
        f = as_vector(forces, 3, 'forces')
        return self.jacobian(pose).T @ f

    def in_workspace(self, pose: Sequence[float]) -> bool:
        """True when every length is within stroke and ``cond(J) <= singularity_condition_max``.

        :raises ValueError: non-finite or wrong-shape ``pose`` (malformed input is an
            error, never a quiet ``False``).
        """
        return self._in_workspace(pose)

    # ------------------------------------------------------------------ forward kinematics
    def _prepare_forward(self) -> None:
        a1, b1 = self.base_anchors[0], self.platform_anchors[0]
        ap = self.base_anchors - a1
        bp = self.platform_anchors - b1
        self._alpha = ap[:, 0] + 1j * ap[:, 1]          # a_i' as complex numbers
        self._beta = bp[:, 0] + 1j * bp[:, 1]           # b_i'
        self._ab2 = np.abs(self._alpha) ** 2 + np.abs(self._beta) ** 2
        scale2 = self._length_scale ** 2
        theta = _TWO_PI * np.arange(8) / 8.0
        z = np.exp(1j * theta)
        m2 = z * self._beta[1] - self._alpha[1]
        m3 = z * self._beta[2] - self._alpha[2]
        det = (np.conj(m2) * m3).imag
        self._kind = 'general'
        if np.max(np.abs(det)) <= 1e-12 * scale2:
            self._kind = 'mirror'
            ratio = None
            for num, den in ((self._alpha[2], self._alpha[1]), (self._beta[2], self._beta[1])):
                if abs(den) > 1e-12 * self._length_scale:
                    ratio = num / den
                    break
            if ratio is not None and abs(ratio.imag) <= 1e-12 * max(1.0, abs(ratio)):
                k = ratio.real
                if (abs(self._alpha[2] - k * self._alpha[1]) <= 1e-12 * self._length_scale
                        and abs(self._beta[2] - k * self._beta[1]) <= 1e-12 * self._length_scale
                        and abs(k * k - k) > 1e-9 and abs(self._alpha[1]) > 0 and abs(self._beta[1]) > 0):
                    self._kind = 'aligned'
                    self._k = k
                    a2, b2 = self._alpha[1], self._beta[1]
                    self._ab_abs = abs(a2) * abs(b2)
                    self._phi = math.atan2(a2.imag, a2.real) - math.atan2(b2.imag, b2.real)
        # directly congruent triangles (R(theta0) b_i' = a_i'): with l1 = l2 = l3 the platform
        # translates on a circle at theta0 (a self-motion, infinitely many assembly modes)
        self._congruent = False
        if abs(self._beta[1]) > 0 and abs(abs(self._beta[1]) - abs(self._alpha[1])) <= 1e-12 * self._length_scale:
            rot = self._alpha[1] / self._beta[1]
            self._congruent = abs(rot * self._beta[2] - self._alpha[2]) <= 1e-12 * self._length_scale
        # plain floats for the closed form (avoids numpy overhead per call)
        self._fa = [tuple(map(float, pt)) for pt in self.base_anchors]
        self._fb = [tuple(map(float, pt)) for pt in self.platform_anchors]

    def forward(self, q: Sequence[float]) -> list[np.ndarray]:
        """Every real assembly mode for actuator lengths ``q = (l1, l2, l3)`` (m).

        :returns: poses ``np.array([x, y, theta])`` with ``theta`` in ``(-pi, pi]``, each
            reproducing ``q`` to :attr:`verify_tol`; sorted by ``theta`` then ``x``; ``[]`` when
            the legs cannot close. At most six (general) or four (aligned, the brace).
        :raises ValueError: non-finite, negative or wrong-shape ``q``.
        :raises SingularPose: lengths that allow a continuous self-motion (infinitely many modes).
        """
        lv = as_vector(q, 3, 'q')
        if np.any(lv < 0.0):
            raise ValueError(f'q: actuator lengths must be >= 0 m, got {lv.tolist()}')
        if self._congruent and np.ptp(lv) <= 1e-12 * max(1.0, float(np.max(lv))):
            raise SingularPose(f'lengths {lv.tolist()} m leave the platform a continuous self-motion '
                               '(congruent base and platform, equal legs): infinitely many assembly modes')
        if self._kind == 'aligned':
            cands = self._forward_aligned(float(lv[0]), float(lv[1]), float(lv[2]))
        else:
            cands = self._forward_polynomial(lv)
        return self._finish(cands, lv)

    # -- lifting, polishing, verification
    def _p_to_pose(self, p: complex, theta: float) -> tuple[float, float, float]:
        """``p = B1 - A1`` (complex) and ``theta`` -> pose of the platform origin."""
        c, s = math.cos(theta), math.sin(theta)
        (a1x, a1y), (b1x, b1y) = self._fa[0], self._fb[0]
        return (a1x + p.real - (c * b1x - s * b1y), a1y + p.imag - (s * b1x + c * b1y), theta)

    def _line_circle(self, m: complex, r: float, l1: float, theta: float,
                     out: list[tuple[float, float, float]], *, only_row: bool = False) -> None:
        """Points ``p`` with ``m . p = r`` and ``|p| = l1`` (complex notation), appended as poses.

        ``only_row``: ``m . p = r`` is the only equation left besides leg 1, so a vanishing
        row means a self-motion (raised) rather than "no information" (skipped).
        """
        mm = abs(m)
        if mm <= 1e-14 * self._length_scale:
            if only_row and abs(r) <= 1e-12 * max(l1, self._length_scale) ** 2 and l1 > 0.0:
                raise SingularPose(f'theta = {theta:.6f} rad: the platform can move on a circle of radius '
                                   f'{l1:.4f} m (self-motion): infinitely many assembly modes')
            return
        h = r / mm
        disc = l1 * l1 - h * h
        tol = 1e-9 * max(l1, self._length_scale) ** 2
        if disc < -tol:
            return
        w = math.sqrt(max(disc, 0.0))
        e = m / mm
        foot = h * e
        perp = 1j * e
        out.append(self._p_to_pose(foot + w * perp, theta))
        if w > 0.0:
            out.append(self._p_to_pose(foot - w * perp, theta))

    def _forward_aligned(self, l1: float, l2: float, l3: float) -> list[tuple[float, float, float]]:
        """Closed form for the aligned class (the brace): the paper's eqs. 6-13, generalised."""
        k = self._k
        s1, s2, s3 = l1 * l1, l2 * l2, l3 * l3
        kk = k * k - k
        # a2'.R b2' = C   (eq. 6 for the brace: C = r1 r2 cos t)
        big_c = (k * (s2 - s1) - (s3 - s1) + kk * self._ab2[1]) / (2.0 * kk)
        cos_psi = big_c / self._ab_abs
        if abs(cos_psi) > 1.0 + 1e-9:
            return []
        # within a few ulps of +-1 the two angles merge (a singularity: the lengths do not
        # tell them apart); snap so that one, exact, angle is returned
        if abs(cos_psi) >= 1.0 - 4.0 * 2.220446049250313e-16:
            cos_psi = math.copysign(1.0, cos_psi)
        psi = math.acos(min(1.0, max(-1.0, cos_psi)))
        a2, b2 = complex(self._alpha[1]), complex(self._beta[1])
        r2 = 0.5 * (s2 - s1 - self._ab2[1]) + big_c
        out: list[tuple[float, float, float]] = []
        for theta in ((self._phi + psi, self._phi - psi) if psi > 0.0 else (self._phi,)):
            m2 = complex(math.cos(theta), math.sin(theta)) * b2 - a2
            self._line_circle(m2, r2, l1, theta, out, only_row=True)
        return out

    def _rm(self, z: np.ndarray, lsq: np.ndarray) -> tuple[np.ndarray, ...]:
        """``m_2, m_3`` (complex) and ``r_2, r_3`` at ``z = e^{i theta}`` (arrays)."""
        al, be = self._alpha, self._beta
        m2 = z * be[1] - al[1]
        m3 = z * be[2] - al[2]
        r2 = 0.5 * (lsq[1] - lsq[0] - self._ab2[1]) + (np.conj(al[1]) * z * be[1]).real
        r3 = 0.5 * (lsq[2] - lsq[0] - self._ab2[2]) + (np.conj(al[2]) * z * be[2]).real
        return m2, m3, r2, r3

    def _forward_polynomial(self, lv: np.ndarray) -> list[tuple[float, float, float]]:
        lsq = lv * lv
        l1 = float(lv[0])
        mirror = self._kind == 'mirror'

        terms: list[float] = []

        def residual(theta: np.ndarray) -> np.ndarray:
            m2, m3, r2, r3 = self._rm(np.exp(1j * theta), lsq)
            v = r2 * m3 - r3 * m2
            if mirror:
                terms.append(float(np.max(np.abs(v) * np.abs(m2 + m3))))
                return (np.conj(v) * (m2 + m3)).real
            det = (np.conj(m2) * m3).imag
            vv = (v * np.conj(v)).real
            dd = lsq[0] * det * det
            terms.append(float(np.max(vv + dd)))
            return vv - dd

        coeffs, _ = trig_poly_coefficients(residual, 2 if mirror else 3)
        # |coefficients| tiny next to the terms that cancel: g vanishes identically
        if float(np.max(np.abs(coeffs))) <= 1e-12 * max(terms):
            raise SingularPose(f'lengths {lv.tolist()} m leave the platform a continuous self-motion: '
                               'infinitely many assembly modes')
        thetas = trig_poly_real_roots(coeffs)
        out: list[tuple[float, float, float]] = []
        if thetas.size == 0:
            return out
        z = np.exp(1j * thetas)
        m2, m3, r2, r3 = self._rm(z, lsq)
        det = (np.conj(m2) * m3).imag
        for j, theta in enumerate(thetas):
            th = float(theta)
            mm2, mm3 = complex(m2[j]), complex(m3[j])
            rel = abs(det[j]) / max(abs(mm2) * abs(mm3), 1e-300)
            small = abs(det[j]) < 1e-3 * self._length_scale ** 2
            if not mirror and rel > 1e-9:
                # p = (r2 perp'(m3) - r3 perp'(m2)) / D, perp'(v) = -i v
                p = -1j * (r2[j] * mm3 - r3[j] * mm2) / det[j]
                out.append(self._p_to_pose(p, th))
            if mirror or rel < 1e-3 or small:
                # D (nearly) vanishes at this root (the rows parallel, or one row vanishing):
                # g has an extra double root there and the Cramer lift is 0/0-like; lift with
                # each row and the circle as well (Newton polishes, verification filters)
                self._line_circle(mm2, float(r2[j]), l1, th, out)
                self._line_circle(mm3, float(r3[j]), l1, th, out)
        return out

    def _lengths_py(self, x: float, y: float, theta: float) -> tuple[float, float, float]:
        """Eq. 3 for one pose in plain floats (the fast path of :meth:`forward`)."""
        c, s = math.cos(theta), math.sin(theta)
        (a1, a2, a3), (b1, b2, b3) = self._fa, self._fb
        return (math.hypot(x + c * b1[0] - s * b1[1] - a1[0], y + s * b1[0] + c * b1[1] - a1[1]),
                math.hypot(x + c * b2[0] - s * b2[1] - a2[0], y + s * b2[0] + c * b2[1] - a2[1]),
                math.hypot(x + c * b3[0] - s * b3[1] - a3[0], y + s * b3[0] + c * b3[1] - a3[1]))

    def _finish(self, cands: list[tuple[float, float, float]], lv: np.ndarray) -> list[np.ndarray]:
        """Newton-polish (only candidates that need it), verify against ``lv``, de-duplicate."""
        if not cands:
            return []
        l1, l2, l3 = float(lv[0]), float(lv[1]), float(lv[2])
        polish_tol = 1e-13 * max(1.0, l1, l2, l3)
        kept: list[tuple[float, float, float]] = []
        rough: list[tuple[float, float, float]] = []
        for x, y, th in cands:
            m1, m2, m3 = self._lengths_py(x, y, th)
            err = max(abs(m1 - l1), abs(m2 - l2), abs(m3 - l3))
            (kept if err <= polish_tol else rough).append((x, y, th))
        if rough:
            polished = self._newton(np.array(rough, dtype=float), lv)
            err = np.max(np.abs(self._residual(polished, lv)), axis=1)
            kept.extend(tuple(map(float, p)) for p in polished[err <= self.verify_tol])
        tol = 1e-7 * self._length_scale
        out: list[np.ndarray] = []
        for x, y, th in sorted((x, y, wrap_angle(th)) for x, y, th in kept):
            for other in out:
                if (abs(x - other[0]) <= tol and abs(y - other[1]) <= tol
                        and abs(wrap_angle(th - other[2])) <= 1e-7):
                    break
            else:
                out.append(np.array([x, y, th]))
        out = self._merge_indistinct(out, lv)
        out.sort(key=lambda p: (p[2], p[0]))
        return out

    def _merge_indistinct(self, poses: list[np.ndarray], lv: np.ndarray) -> list[np.ndarray]:
        """One pose for roots the lengths cannot tell apart: near a singularity a double root
        of the forward polynomial comes out as two poses a few 1e-8 m apart, each within
        :attr:`verify_tol`. Two poses within 1e-6 x the size of each other whose midpoint also
        reproduces ``lv`` within :attr:`verify_tol` are one root: the one closer to ``lv`` is
        kept. Distinct assembly modes have a midpoint far from ``lv``; two that are both close
        to ``lv`` but microns apart (a near-singular pair) are both kept."""
        if len(poses) < 2:
            return poses
        near = 1e-6 * self._length_scale
        target = (float(lv[0]), float(lv[1]), float(lv[2]))

        def error(x: float, y: float, th: float) -> float:
            return max(abs(a - b) for a, b in zip(self._lengths_py(x, y, th), target))
        keep = [True] * len(poses)
        for i in range(len(poses)):
            for j in range(i + 1, len(poses)):
                if not (keep[i] and keep[j]):
                    continue
                a, b = poses[i], poses[j]
                dth = wrap_angle(float(b[2] - a[2]))
                if abs(b[0] - a[0]) > near or abs(b[1] - a[1]) > near or abs(dth) > 1e-6:
                    continue
                mid = (0.5 * float(a[0] + b[0]), 0.5 * float(a[1] + b[1]), float(a[2]) + 0.5 * dth)
                if error(*mid) <= self.verify_tol:
                    worse = i if error(*map(float, a)) > error(*map(float, b)) else j
                    keep[worse] = False
        return [p for p, k in zip(poses, keep) if k]

    def _residual(self, poses: np.ndarray, lv: np.ndarray) -> np.ndarray:
        return self._lengths_unchecked(poses) - lv

    def _lengths_unchecked(self, poses: np.ndarray) -> np.ndarray:
        c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
        bx, by = self.platform_anchors[:, 0], self.platform_anchors[:, 1]
        dx = poses[:, 0, None] + c[:, None] * bx - s[:, None] * by - self.base_anchors[:, 0]
        dy = poses[:, 1, None] + s[:, None] * bx + c[:, None] * by - self.base_anchors[:, 1]
        return np.hypot(dx, dy)

    def _newton(self, poses: np.ndarray, lv: np.ndarray, iters: int = 8) -> np.ndarray:
        """Newton on the loop equations ``l_i(pose) = lv_i`` for a stack of poses (K, 3)."""
        x = poses.copy()
        for _ in range(iters):
            res = self._residual(x, lv)
            if np.max(np.abs(res)) <= 1e-15 * max(1.0, float(np.max(lv))):
                break
            jac = self._jacobian_batch(x)
            jac[~np.isfinite(jac)] = 0.0
            step = np.einsum('kij,kj->ki', np.linalg.pinv(jac, rcond=1e-12), res)
            x = x - step
        return x

    def forward_nearest(self, q: Sequence[float], hint_pose: Sequence[float]) -> np.ndarray:
        """The assembly mode nearest ``hint_pose`` (the branch continuous with the previous pose).

        Distance: ``|dx|^2 + |dy|^2 + (L dtheta)^2``, ``L`` the platform's size (m), ``dtheta``
        wrapped.

        :raises ValueError: malformed ``q`` or ``hint_pose``.
        :raises UnreachablePose: the legs cannot close (no assembly mode for ``q``).
        """
        hint = as_vector(hint_pose, 3, 'hint_pose')
        sols = self.forward(q)
        if not sols:
            lv = np.asarray(q, dtype=float)
            raise UnreachablePose(f'no assembly mode: the legs cannot close with lengths '
                                  f'{", ".join(f"{n}={v:.4f} m" for n, v in zip(self.actuator_names, lv))}')
        hx, hy, hth = float(hint[0]), float(hint[1]), float(hint[2])
        scale = self._platform_size

        def dist(s: np.ndarray) -> float:
            x, y, th = s.tolist()
            return (x - hx) ** 2 + (y - hy) ** 2 + (scale * wrap_angle(th - hth)) ** 2
        return min(sols, key=dist)

    # ------------------------------------------------------------------ configuration
    @classmethod
    def from_config(cls, section: Mapping[str, Any]) -> 'Rpr3':
        """Build from the YAML's ``mechanism`` section (flattened point lists, see config.points).

        Reads ``type`` (must be ``rpr3``), ``actuator_names``, ``base_anchors``,
        ``platform_anchors``, ``stroke_min``, ``stroke_max``, ``home_pose``,
        ``singularity_condition_max``.

        :raises ConfigError: a missing or malformed value, naming the parameter.
        """
        check_section(section, 'rpr3', 'Rpr3', ('base_anchors', 'platform_anchors', 'stroke_min', 'stroke_max'))
        base = section_points(section, 'base_anchors', 3, '3-RPR')
        plat = section_points(section, 'platform_anchors', 3, '3-RPR')
        kwargs = section_kwargs(section, present=('actuator_names', 'singularity_condition_max'),
                                given=('home_pose',))
        with config_errors():
            return cls(base, plat, (section['stroke_min'], section['stroke_max']), **kwargs)
