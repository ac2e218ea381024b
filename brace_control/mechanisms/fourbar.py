"""Hoeken four-bar linkage: the upper-limb trainer (seed 002, Kurmashev thesis, ch. 3-4).

Geometry and conventions
------------------------
Base frame: the crank pivot ``O2`` at the origin, the rocker pivot ``O4 = (L1, 0)``; angles
counter-clockwise from +x (rad); SI units (m, rad, s, kg, N, N·m). Links (thesis Fig. 3.4):

* ``L1`` ground ``O2 O4``, ``L2`` crank ``O2 A`` (the motor's link, angle ``theta2``),
* ``L3`` coupler ``A B`` (angle ``theta3``), ``L4`` rocker ``O4 B`` (angle ``theta4``),
* the coupler point ``P`` (the hand) on ``AB`` extended beyond ``B``: ``BP`` (Hoeken: ``BP =
  L3 = L4``, so ``AP = 2 L3`` and eq. 3.4 reads ``R2 + 2 R3 - RP = 0``).

Table 3.1, ``Delta beta = 180 deg``: ``L1/L2 = 2.2``, ``L3/L2 = 2.8``, ``L2 = 0.2525 / 4.181 m``
(eq. 3.1-3.3); the straight stroke is ``theta2`` in ``[90, 270] deg``.

Assembly modes ("branches"): for a crank angle ``B`` is one of the two intersections of the
circles ``|B - A| = L3`` and ``|B - O4| = L4``. ``'open'``: ``B`` on the left of the directed
line ``A -> O4`` (the convex quadrilateral when the crank points up, Norton's open circuit);
``'crossed'``: on the right. The thesis's straight *and* curved motions both run on the
open assembly (the crossed assembly's coupler curve is the mirror image below the ground
line, > 0.5 m away); what the thesis calls "open / crossed" in §3.2 is the choice of the
root of eq. 3.12 (two crank angles put ``A`` at ``2 L3`` from ``P``; only one of them
closes the loop at the rocker) — :meth:`HoekenFourBar.inverse` tries both roots and keeps
the one that closes.

Pose, protocol
--------------
* pose = the coupler point ``P = (x, y)`` in the base frame (m): ``dof = 2`` is the length of
  the pose vector (what the nodes use, ``pose_kind = 'xy'``); the mechanism's mobility is
  one (``mobility = 1``): reachable poses lie on the coupler curve.
* ``q = [theta2]`` (rad), one actuator ``'crank'``, within ``crank_range``.
* :meth:`~HoekenFourBar.inverse`: eq. 3.12 (both roots), the loop closed at the rocker; a
  point within ``curve_tolerance`` of the curve is projected onto it (its nearest curve
  point's crank angle is returned); farther points raise :class:`~.base.UnreachablePose`
  naming the distance.
* :meth:`~HoekenFourBar.jacobian`: ``J = t^T / |t|^2`` (shape (1, 2)), ``t = dP/dtheta2``:
  ``theta2_dot = J @ (x_dot, y_dot)`` for a velocity along the curve (the normal component
  of any other velocity is dropped, least squares).
* :meth:`~HoekenFourBar.wrench`: ``F = J^T T`` (N), the force the crank torque ``T`` makes the
  massless, static linkage apply at ``P`` (virtual work ``T theta2_dot = F . P_dot``); only
  the tangential component is set by the motor — a force normal to the path is carried
  by the frame — so this is the minimum-norm force.

Kinematics (eqs. 3.8-3.14)
--------------------------
Position: circle intersection (equivalent to the tan-half-angle eqs. 3.8-3.12, without
their singular ``theta = pi``); velocity and acceleration from the time derivatives of
the loop ``A + L3 e3 = O4 + L4 e4`` (the first two rows of eqs. 3.13 and 3.14, solved
for ``omega3, omega4`` / ``alpha3, alpha4``), then ``P``, ``A`` and the centres of gravity.
The thesis prescribes only the x-motion of ``P`` in its velocity and acceleration
matrices (``VPx``, ``APx`` given, ``VPy``, ``APy`` solved): :meth:`~HoekenFourBar.follow_x`
does the same at the position level too, so the state is always on the coupler curve.

Kinetostatics (eq. 3.19 / 3.20)
-------------------------------
Newton–Euler for the three moving links with unknowns ``F12, F32, F43, F14`` (``Fij``: the
force of link ``i`` on link ``j``) and the drive torque: ``T2`` on the crank
(``drive='crank'``, eq. 3.19) or ``T4`` on the rocker with a free crank (``drive='rocker'``,
eq. 3.20); both counter-clockwise positive, the torque the drive applies to its link.
Moment arms ``Rij`` are from the link's centre of gravity to the joint. The external
force ``FP`` acts on the coupler at ``P`` (the patient's hand, eq. 3.20: an imaginary
spring ``k_PU = F_PUmax / Delta d_max``). Link 4's moment row is ``R34y F43x - R34x F43y
- R14y F14x + R14x F14y`` (eq. 3.19 prints ``+R34x``: the printed matrix's sign slip; the
thesis's code has it right). The crank carries the flywheel (its centre on the axis
``O2``); gravity (in the plane) defaults to zero — the trainer moves in a horizontal plane.

Springs (eqs. 3.21-3.26)
------------------------
:func:`spring_torque`: a spring from the ground point ``F = O4 + Ls1 e^{i beta}`` to the
contact ``C = O4 + Ls2 e^{i theta4}`` on the rocker; length (3.21), Hooke (3.23), torque on
the rocker about ``O4`` as the cross product ``(C - O4) x F_s`` (3.24 x 3.25)::

    T_s = k (L0 - Ls) Ls1 Ls2 sin(theta4 - beta) / Ls      (counter-clockwise positive)

the magnitude of eq. 3.26 (law of sines: ``sin gamma = Ls1 sin(theta4 - beta) / Ls``); the
sign follows the vector product, not eq. 3.22's ``atan``, which loses the quadrant when
``Ls1 cos(theta4 - beta) < Ls2``. Springs are contact (compression) springs by default:
they push only while shorter than their free length (the thesis's accelerating spring
"stops acting" once released); ``unilateral=False`` gives the two-sided eq. 3.23.
:func:`optimise_springs`: eq. 4.1 (10 design variables, §4.1 bounds) with scipy's
differential evolution (fixed seed) instead of MATLAB's GA.
"""
from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .base import (MechanismBase, Statics, UnreachablePose, as_actuator_names, as_poses, as_vector, check_limits,
                   check_section, config_errors, section_kwargs, within_limits)
from .loader import register

__all__ = [
    'HoekenFourBar', 'FourBarState', 'Kinetostatics', 'ExerciseProfile',
    'spring_torque', 'spring_torques', 'SpringFit', 'optimise_springs', 'SPRING_VARIABLES',
    'imaginary_spring_stiffness', 'run_exercise', 'table_3_1_lengths',
]

_TWO_PI = 2.0 * math.pi
_BRANCHES = {'open': 1.0, 'crossed': -1.0}

#: the 10 design variables of eq. 4.1, in the order of :func:`optimise_springs`' vector
SPRING_VARIABLES = ('Ls11', 'Ls12', 'beta1', 'Ls21', 'Ls22', 'beta2', 'L01', 'L02', 'k1', 'k2')


def table_3_1_lengths(stroke: float = 0.2525, ratio_stroke: float = 4.181, ratio_ground: float = 2.2,
                      ratio_coupler: float = 2.8) -> tuple[float, float, float]:
    """``(L1, L2, L3)`` (m) from Table 3.1 (``Delta beta = 180 deg``), eqs. 3.1-3.3."""
    l2 = stroke / ratio_stroke
    return ratio_ground * l2, l2, ratio_coupler * l2


def _wrap_from(lo: float, theta: Any) -> Any:
    """``theta`` (rad, a number or an array) wrapped into ``[lo, lo + 2 pi)``. An angle that
    rounding left within 1e-12 rad below ``lo + 2 pi`` is ``lo``: the crank range is exactly
    one turn, and at its seam ``inverse`` and ``inverse_batch`` gave the same curve point two
    representatives a turn apart (-50 deg and 310 deg for the trainer)."""
    r = np.mod(np.asarray(theta, dtype=float) - lo, _TWO_PI)
    return lo + np.where(_TWO_PI - r <= 1e-12, 0.0, r)


def _cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Planar cross product of complex numbers ``u x v = Im(conj(u) v)``."""
    return (np.conj(u) * v).imag


@dataclass
class FourBarState:
    """Positions, velocities, accelerations of the linkage (arrays of a common shape).

    Points, velocities and accelerations are complex numbers ``x + i y`` (m, m/s, m/s^2);
    angles in rad, rates in rad/s and rad/s^2. ``g2, g3, g4``: centres of gravity (the
    crank's including the flywheel).
    """

    theta2: np.ndarray
    theta3: np.ndarray
    theta4: np.ndarray
    omega2: np.ndarray
    omega3: np.ndarray
    omega4: np.ndarray
    alpha2: np.ndarray
    alpha3: np.ndarray
    alpha4: np.ndarray
    a: np.ndarray
    b: np.ndarray
    p: np.ndarray
    vp: np.ndarray
    ap: np.ndarray
    g: tuple[np.ndarray, np.ndarray, np.ndarray]
    vg: tuple[np.ndarray, np.ndarray, np.ndarray]
    ag: tuple[np.ndarray, np.ndarray, np.ndarray]

    @property
    def P(self) -> np.ndarray:
        """Coupler point as ``(..., 2)`` floats (m)."""
        return np.stack([self.p.real, self.p.imag], axis=-1)


@dataclass
class Kinetostatics:
    """Solution of eq. 3.19 (``drive='crank'``) or eq. 3.20 (``drive='rocker'``).

    ``torque``: the drive torque (N·m, counter-clockwise on its link); joint forces complex
    (N): ``f12`` ground on crank (at ``O2``), ``f32`` coupler on crank (at ``A``), ``f43`` rocker
    on coupler (at ``B``), ``f14`` ground on rocker (at ``O4``).
    """

    drive: str
    torque: np.ndarray
    f12: np.ndarray
    f32: np.ndarray
    f43: np.ndarray
    f14: np.ndarray


@register('hoeken_fourbar')
class HoekenFourBar(MechanismBase):
    """Hoeken's four-bar (one motor on the crank), pose = the coupler point ``P``.

    :param ground: ``L1`` (m), ``O2 O4``.
    :param crank: ``L2`` (m), the shortest link (a full-turning crank).
    :param coupler: ``L3`` (m), ``A B``.
    :param rocker: ``L4`` (m), ``O4 B``.
    :param coupler_extension: ``BP`` (m) beyond ``B`` on ``AB``; default ``L3`` (Hoeken).
    :param branch: ``'open'`` or ``'crossed'`` assembly (module docstring).
    :param crank_range: ``(lo, hi)`` (rad) the crank may take, ``hi - lo <= 2 pi``;
        :meth:`inverse` returns angles in ``[lo, lo + 2 pi)``.
    :param curve_tolerance: a pose within this distance (m) of the coupler curve is
        projected onto it; farther is unreachable.
    :param home_pose: rest pose ``(x, y)`` (m) on the curve; default: ``P`` at mid crank range.
    :param masses: ``(m2, m3, m4)`` (kg) of the crank bar, coupler, rocker.
    :param cg_fractions: centre of gravity along each link as a fraction: crank from
        ``O2`` towards ``A``, coupler from ``A`` towards ``P`` (of ``AP``), rocker from ``O4``
        towards ``B``. Thesis: ``(0, 0.5, 0.5)`` (coupler's at ``B``).
    :param inertias: ``(I2, I3, I4)`` (kg m^2) about each centre of gravity (crank bar
        without the flywheel); default: uniform bars ``m (l^2 + w^2) / 12`` of lengths
        ``L2, AP, L4`` and width ``bar_width``.
    :param flywheel_mass: kg, centred on ``O2`` (moves nothing but the bearing).
    :param flywheel_inertia: kg m^2 about ``O2``.
    :param gravity: ``(gx, gy)`` (m/s^2) in the plane of motion; zero for a horizontal table.
    :raises ValueError: non-positive lengths, a crank that cannot turn fully, bad branch,
        range or inertia values, a home pose off the curve.
    """

    dof: int = 2
    mobility: int = 1
    n_actuators: int = 1
    pose_kind: str = 'xy'
    #: capacity axis: the force along the path (arc length, the direction of increasing
    #: crank angle), the generalised force of the one degree of freedom
    wrench_axes = ('F_path',)
    wrench_units = ('N',)
    #: curve samples per crank turn used to seed the projection onto the coupler curve
    curve_samples: int = 1440

    def __init__(self, ground: float, crank: float, coupler: float, rocker: float, *,
                 coupler_extension: float | None = None, branch: str = 'open',
                 crank_range: Sequence[float] = (-math.pi, math.pi),
                 curve_tolerance: float = 5e-4, home_pose: Sequence[float] | None = None,
                 actuator_names: Sequence[str] = ('crank',),
                 masses: Sequence[float] = (0.0, 0.0, 0.0),
                 cg_fractions: Sequence[float] = (0.0, 0.5, 0.5),
                 inertias: Sequence[float] | None = None, bar_width: float = 0.0,
                 flywheel_mass: float = 0.0, flywheel_inertia: float = 0.0,
                 gravity: Sequence[float] = (0.0, 0.0)) -> None:
        lengths = as_vector([ground, crank, coupler, rocker], 4, 'link lengths (L1, L2, L3, L4)')
        bp = float(coupler) if coupler_extension is None else float(coupler_extension)
        if not math.isfinite(bp) or bp < 0.0:
            raise ValueError(f'coupler_extension: expected a finite length >= 0 m, got {coupler_extension!r}')
        if np.any(lengths <= 0.0):
            raise ValueError(f'link lengths must be > 0 m, got L1..L4 = {lengths.tolist()}')
        self.L1, self.L2, self.L3, self.L4 = (float(v) for v in lengths)
        self.BP = bp
        self.AP = self.L3 + bp
        s, l = float(np.min(lengths)), float(np.max(lengths))
        if self.L2 != s or s + l > float(np.sum(lengths)) - s - l + 1e-15:
            raise ValueError(f'L1..L4 = {lengths.tolist()} m: not a crank-rocker (the crank must be the shortest '
                             'link and s + l <= p + q, Grashof) — the motor could not turn the crank fully')
        if branch not in _BRANCHES:
            raise ValueError(f'branch: expected "open" or "crossed", got {branch!r}')
        self.branch = branch
        self._sigma = _BRANCHES[branch]
        rng = as_vector(crank_range, 2, 'crank_range')
        if not (rng[1] > rng[0] and rng[1] - rng[0] <= _TWO_PI + 1e-12):
            raise ValueError(f'crank_range: need lo < hi <= lo + 2 pi (rad), got {rng.tolist()}')
        self._lo, self._hi = float(rng[0]), float(rng[1])
        tol = float(curve_tolerance)
        if not (math.isfinite(tol) and tol > 0.0):
            raise ValueError(f'curve_tolerance: expected a length > 0 m, got {curve_tolerance!r}')
        self.curve_tolerance = tol
        self.actuator_names: tuple[str, ...] = as_actuator_names(actuator_names, 1)
        # ---- mass properties
        m = as_vector(masses, 3, 'masses (m2, m3, m4)')
        cg = as_vector(cg_fractions, 3, 'cg_fractions')
        w = float(bar_width)
        if np.any(m < 0.0) or not (math.isfinite(w) and w >= 0.0):
            raise ValueError(f'masses must be >= 0 kg and bar_width >= 0 m, got {m.tolist()}, {bar_width!r}')
        if inertias is None:
            ell = np.array([self.L2, self.AP, self.L4])
            inertia = m * (ell ** 2 + w ** 2) / 12.0
        else:
            inertia = as_vector(inertias, 3, 'inertias (I2, I3, I4)')
        mf, jf = float(flywheel_mass), float(flywheel_inertia)
        if np.any(inertia < 0.0) or not (math.isfinite(mf) and mf >= 0.0 and math.isfinite(jf) and jf >= 0.0):
            raise ValueError('inertias, flywheel_mass and flywheel_inertia must be finite and >= 0')
        self.masses, self.cg_fractions, self.inertias = m, cg, inertia
        self.flywheel_mass, self.flywheel_inertia = mf, jf
        self.gravity = complex(*as_vector(gravity, 2, 'gravity'))
        # crank + flywheel as one body: mass, CG distance from O2, inertia about that CG
        r2 = cg[0] * self.L2
        m2c = m[0] + mf
        self._r2c = m[0] * r2 / m2c if m2c > 0.0 else 0.0
        self._m = np.array([m2c, m[1], m[2]])
        self._i = np.array([inertia[0] + m[0] * (r2 - self._r2c) ** 2 + jf + mf * self._r2c ** 2,
                            inertia[1], inertia[2]])
        self._r3 = cg[1] * self.AP
        self._r4 = cg[2] * self.L4
        # dense coupler curve (projection seeds)
        th = np.linspace(0.0, _TWO_PI, self.curve_samples, endpoint=False)
        self._curve_theta = th
        self._curve_p = self._positions(th)[2]
        if home_pose is None:
            self._home = self.forward_branch(0.5 * (self._lo + self._hi))
        else:
            self._home = as_vector(home_pose, 2, 'home_pose')
            self.inverse(self._home)

    # ------------------------------------------------------------------ protocol basics
    # home_pose (x, y of P, m, on the coupler curve): MechanismBase; actuator_limits is
    # its own (``_lo``, ``_hi`` are floats here)
    @property
    def actuator_limits(self) -> tuple[np.ndarray, np.ndarray]:
        """Crank angle range ``(lo, hi)`` (rad), arrays of shape (1,)."""
        return np.array([self._lo]), np.array([self._hi])

    @property
    def crank_inertia(self) -> float:
        """Moment of inertia of the crank with its flywheel about ``O2`` (kg m^2)."""
        return float(self._i[0] + self._m[0] * self._r2c ** 2)

    def __repr__(self) -> str:
        return (f'HoekenFourBar(ground={self.L1}, crank={self.L2}, coupler={self.L3}, rocker={self.L4}, '
                f'coupler_extension={self.BP}, branch={self.branch!r})')

    # ------------------------------------------------------------------ position analysis
    def _positions(self, theta2: np.ndarray, sigma: float | None = None
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``A, B, P, theta3, theta4`` for crank angles (arrays; NaN where it cannot assemble)."""
        sg = self._sigma if sigma is None else sigma
        th = np.asarray(theta2, dtype=float)
        a = self.L2 * np.exp(1j * th)
        d = self.L1 - a
        dist = np.abs(d)
        u = d / dist
        along = (self.L3 ** 2 - self.L4 ** 2 + dist ** 2) / (2.0 * dist)
        with np.errstate(invalid='ignore'):
            h = np.sqrt(self.L3 ** 2 - along ** 2)
        b = a + along * u + sg * h * 1j * u
        e3 = (b - a) / self.L3
        p = a + self.AP * e3
        return a, b, p, np.angle(e3), np.angle(b - self.L1)

    def position_analysis(self, theta2: float | np.ndarray, branch: str | None = None) -> dict[str, np.ndarray]:
        """Eqs. 3.8-3.12 forward: ``theta3, theta4`` (rad) and ``A, B, P`` (complex, m) for crank angles."""
        sg = self._sigma if branch is None else _BRANCHES[branch]
        a, b, p, t3, t4 = self._positions(theta2, sg)
        return {'theta3': t3, 'theta4': t4, 'A': a, 'B': b, 'P': p}

    def forward_branch(self, theta2: float) -> np.ndarray:
        """``P = (x, y)`` (m) on the configured branch for a crank angle (rad)."""
        p = self._curve_scalar(float(theta2))[0]
        return np.array([p.real, p.imag])

    def forward(self, q: Sequence[float]) -> list[np.ndarray]:
        """Coupler point ``(x, y)`` for every assembly mode at crank angle ``q = [theta2]``.

        :returns: the configured branch first, then the other one (one point if the two
            coincide, ``[]`` if the loop cannot close — not for a crank-rocker).
        :raises ValueError: non-finite or wrong-shape ``q``.
        """
        th = float(as_vector(q, 1, 'q')[0])
        out: list[np.ndarray] = []
        for sg in (self._sigma, -self._sigma):
            p = complex(self._positions(np.array(th), sg)[2])
            if not (math.isfinite(p.real) and math.isfinite(p.imag)):
                continue
            pt = np.array([p.real, p.imag])
            if not any(np.allclose(pt, o, atol=1e-12) for o in out):
                out.append(pt)
        return out

    def forward_nearest(self, q: Sequence[float], hint_pose: Sequence[float]) -> np.ndarray:
        """The assembly mode's ``P`` nearest ``hint_pose`` (m).

        :raises UnreachablePose: the loop cannot close at this crank angle.
        """
        hint = as_vector(hint_pose, 2, 'hint_pose')
        sols = self.forward(q)
        if not sols:
            raise UnreachablePose(f'the loop cannot close at crank angle {float(q[0]):.4f} rad',
                                  actuator=self.actuator_names[0])
        return min(sols, key=lambda s: float(np.sum((s - hint) ** 2)))

    # ------------------------------------------------------------------ inverse
    def _wrap_q(self, theta: float) -> float:
        return float(_wrap_from(self._lo, theta))

    def _curve_derivatives(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``P, dP/dtheta2, d2P/dtheta2^2`` (complex) on the configured branch."""
        st = self.analysis(theta, 1.0, 0.0)
        return st.p, st.vp, st.ap

    def _curve_scalar(self, th: float) -> tuple[complex, complex, complex]:
        """:meth:`_curve_derivatives` for one angle in plain Python (the fast path of the projection)."""
        e2 = complex(math.cos(th), math.sin(th))
        a = self.L2 * e2
        d = self.L1 - a
        dist = abs(d)
        u = d / dist
        along = (self.L3 ** 2 - self.L4 ** 2 + dist * dist) / (2.0 * dist)
        b = a + along * u + self._sigma * math.sqrt(max(self.L3 ** 2 - along * along, 0.0)) * 1j * u
        e3 = (b - a) / self.L3
        e4 = (b - self.L1) / self.L4
        s34 = (e4.conjugate() * e3).imag
        va = 1j * self.L2 * e2
        w3 = (e4.conjugate() * va).real / (self.L3 * s34)
        w4 = (e3.conjugate() * va).real / (self.L4 * s34)
        aa = -self.L2 * e2
        rr = aa - self.L3 * w3 * w3 * e3 + self.L4 * w4 * w4 * e4
        al3 = (e4.conjugate() * rr).real / (self.L3 * s34)
        return (a + self.AP * e3, va + 1j * w3 * self.AP * e3, aa + self.AP * (1j * al3 - w3 * w3) * e3)

    def _curve_batch(self, th: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`_curve_scalar` for an array of crank angles (the same equations in numpy)."""
        e2 = np.exp(1j * th)
        a = self.L2 * e2
        d = self.L1 - a
        dist = np.abs(d)
        u = d / dist
        along = (self.L3 ** 2 - self.L4 ** 2 + dist * dist) / (2.0 * dist)
        b = a + along * u + self._sigma * np.sqrt(np.maximum(self.L3 ** 2 - along * along, 0.0)) * 1j * u
        e3 = (b - a) / self.L3
        e4 = (b - self.L1) / self.L4
        s34 = (np.conj(e4) * e3).imag
        va = 1j * self.L2 * e2
        w3 = (np.conj(e4) * va).real / (self.L3 * s34)
        w4 = (np.conj(e3) * va).real / (self.L4 * s34)
        aa = -self.L2 * e2
        rr = aa - self.L3 * w3 * w3 * e3 + self.L4 * w4 * w4 * e4
        al3 = (np.conj(e4) * rr).real / (self.L3 * s34)
        return (a + self.AP * e3, va + 1j * w3 * self.AP * e3, aa + self.AP * (1j * al3 - w3 * w3) * e3)

    def _nearest_on_curve_batch(self, target: np.ndarray, chunk: int = 256) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`nearest_on_curve` for targets (K,) complex: crank angles (wrapped) and distances (m).

        The same seeds (the two best local minima of the distance over the sampled curve)
        and the same damped Newton, run in lock step (each row stops where the scalar does);
        ``chunk`` rows at a time bound the (rows x curve samples) distance table.
        """
        theta = np.empty(target.size)
        dmin = np.empty(target.size)
        for start in range(0, target.size, chunk):
            tg = target[start:start + chunk]
            diff = self._curve_p[None, :] - tg[:, None]
            dist = diff.real * diff.real + diff.imag * diff.imag        # squared: the same order
            dist[~np.isfinite(dist)] = np.inf
            local = (dist <= np.roll(dist, 1, axis=1)) & (dist <= np.roll(dist, -1, axis=1))
            masked = np.where(local, dist, np.inf)
            two = np.argpartition(masked, 1, axis=1)[:, :2]                # the two best, in either order
            d2 = np.take_along_axis(masked, two, axis=1)
            swap = (d2[:, 1] < d2[:, 0]) | ((d2[:, 1] == d2[:, 0]) & (two[:, 1] < two[:, 0]))
            ranked = np.where(swap[:, None], two[:, ::-1], two)
            has_local = local.any(axis=1)
            ranked[~has_local, 0] = np.argmin(dist[~has_local], axis=1)
            second = local.sum(axis=1) >= 2
            best_t = np.zeros(tg.size)
            best_d = np.full(tg.size, np.inf)
            for s in range(2):
                use = np.ones(tg.size, dtype=bool) if s == 0 else second
                th = self._curve_theta[ranked[:, s]].astype(float)
                active = use.copy()
                for _ in range(40):
                    if not active.any():
                        break
                    p, dp, ddp = self._curve_batch(th[active])
                    r = p - tg[active]
                    g = (np.conj(r) * dp).real
                    hess = np.abs(dp) ** 2 + (np.conj(r) * ddp).real
                    step = np.where(hess > 0.0, -g / np.where(hess > 0.0, hess, 1.0),
                                    -g / np.maximum(np.abs(dp) ** 2, 1e-300))
                    step = np.clip(step, -0.05, 0.05)
                    th[active] += step
                    idx = np.flatnonzero(active)
                    active[idx[np.abs(step) < 1e-13]] = False
                d = np.abs(self._curve_batch(th)[0] - tg)
                better = use & (d < best_d)
                best_t = np.where(better, th, best_t)
                best_d = np.where(better, d, best_d)
            theta[start:start + chunk] = best_t
            dmin[start:start + chunk] = best_d
        return _wrap_from(self._lo, theta), dmin

    def nearest_on_curve(self, pose: Sequence[float]) -> tuple[float, float]:
        """``(theta2, distance)``: the crank angle (rad, wrapped into the crank range) of
        the coupler-curve point nearest ``pose`` (m) and its distance (m). No range check.

        Seeds: the two best local minima of the distance over the sampled curve; each is
        refined by Newton on ``(P - target) . P' = 0``.
        """
        pt = as_vector(pose, 2, 'pose')
        target = complex(pt[0], pt[1])
        dist = np.abs(self._curve_p - target)
        dist = np.where(np.isfinite(dist), dist, np.inf)
        local = np.flatnonzero((dist <= np.roll(dist, 1)) & (dist <= np.roll(dist, -1)))
        seeds = local[np.argsort(dist[local])][:2] if local.size else [int(np.argmin(dist))]
        best_t, best_d = 0.0, math.inf
        for i in seeds:
            th = float(self._curve_theta[i])
            for _ in range(40):
                p, dp, ddp = self._curve_scalar(th)
                r = p - target
                g = (r.conjugate() * dp).real
                hess = abs(dp) ** 2 + (r.conjugate() * ddp).real
                step = -g / hess if hess > 0.0 else -g / max(abs(dp) ** 2, 1e-300)
                step = max(-0.05, min(0.05, step))
                th += step
                if abs(step) < 1e-13:
                    break
            d = abs(self._curve_scalar(th)[0] - target)
            if d < best_d:
                best_t, best_d = th, d
        return self._wrap_q(best_t), float(best_d)

    def _nearest_local(self, pt: np.ndarray, reach: float = 1e-3) -> float | None:
        """The crank angle of the curve point nearest ``pt`` when ``pt`` is within ``reach``
        (m) of the curve, by Newton on ``(P - pt) . P' = 0`` from eq. 3.12's root (the crank
        angle putting ``A`` at ``AP`` from ``pt`` that best closes the loop); None when there
        is no such root, Newton does not settle, or the point is farther: then the global
        :meth:`nearest_on_curve` (a few times slower) decides."""
        target = complex(pt[0], pt[1])
        r = abs(target)
        if r == 0.0:
            return None
        c = (r * r + self.L2 ** 2 - self.AP ** 2) / (2.0 * self.L2 * r)
        if abs(c) > 1.0:
            return None
        phi, acc = math.atan2(pt[1], pt[0]), math.acos(c)
        th, best = None, math.inf
        for cand in (phi + acc, phi - acc):
            a = self.L2 * complex(math.cos(cand), math.sin(cand))
            b = a + (target - a) * (self.L3 / self.AP)
            if _cross(np.array(self.L1 - a), np.array(b - a)) * self._sigma <= 0.0:
                continue
            res = abs(abs(b - self.L1) - self.L4)
            if res < best:
                th, best = cand, res
        if th is None:
            return None
        for _ in range(8):
            p, dp, ddp = self._curve_scalar(th)
            rr = p - target
            hess = abs(dp) ** 2 + (rr.conjugate() * ddp).real
            if hess <= 0.0:
                return None
            step = -(rr.conjugate() * dp).real / hess
            th += max(-0.05, min(0.05, step))
            if abs(step) < 1e-13:
                break
        else:
            return None
        if abs(self._curve_scalar(th)[0] - target) > reach:
            return None
        return self._wrap_q(th)

    def inverse(self, pose: Sequence[float]) -> np.ndarray:
        """Crank angle ``[theta2]`` (rad, in ``[lo, lo + 2 pi)``) putting ``P`` at ``pose = (x, y)``.

        Eq. 3.12 (both roots of ``|P - A(theta2)| = AP``), kept where ``B`` (on ``AP``) is at
        ``L4`` from ``O4`` on the configured branch; a pose off the curve but within
        ``curve_tolerance`` gets its nearest curve point's crank angle.

        :raises ValueError: non-finite or wrong-shape ``pose``.
        :raises UnreachablePose: ``pose`` farther than ``curve_tolerance`` from the coupler
            curve (the message gives the distance and the nearest curve point), or a crank
            angle outside ``crank_range`` (naming the crank, the angle and the range).
        """
        pt = as_vector(pose, 2, 'pose')
        target = complex(pt[0], pt[1])
        r = abs(target)
        theta: float | None = None
        scale = self.L1 + self.L2 + self.L3 + self.L4
        if r > 0.0:
            c = (r * r + self.L2 ** 2 - self.AP ** 2) / (2.0 * self.L2 * r)
            if abs(c) <= 1.0:
                phi = math.atan2(pt[1], pt[0])
                acc = math.acos(c)
                best = math.inf
                for th in (phi + acc, phi - acc):
                    a = self.L2 * complex(math.cos(th), math.sin(th))
                    b = a + (target - a) * (self.L3 / self.AP)
                    res = abs(abs(b - self.L1) - self.L4)
                    side = _cross(np.array(self.L1 - a), np.array(b - a))
                    if res <= 1e-10 * scale and side * self._sigma > 0.0 and res < best:
                        theta, best = th, res
        if theta is None:
            theta, d = self.nearest_on_curve(pt)
            if d > self.curve_tolerance:
                near = self.forward_branch(theta)
                raise UnreachablePose(
                    f'coupler point ({pt[0]:.4f}, {pt[1]:.4f}) m is {d * 1e3:.3f} mm from the coupler curve '
                    f'({self.branch} assembly; tolerance {self.curve_tolerance * 1e3:.3f} mm); nearest curve point '
                    f'({near[0]:.4f}, {near[1]:.4f}) m at crank angle {math.degrees(theta):.2f} deg',
                    actuator=None, value=float(d), limits=(0.0, self.curve_tolerance))
        q = np.array([self._wrap_q(theta)])
        check_limits(q, np.array([self._lo]), np.array([self._hi]), self.actuator_names, unit='rad')
        return q

    def _inverse_batch(self, p: np.ndarray, limits: bool) -> np.ndarray:
        """Crank angles (N,) for validated points (N, 2); NaN where :meth:`inverse` raises."""
        target = p[:, 0] + 1j * p[:, 1]
        r = np.abs(target)
        scale = self.L1 + self.L2 + self.L3 + self.L4
        with np.errstate(divide='ignore', invalid='ignore'):
            c = (r * r + self.L2 ** 2 - self.AP ** 2) / (2.0 * self.L2 * r)
        closed = (r > 0.0) & (np.abs(c) <= 1.0)
        phi = np.arctan2(p[:, 1], p[:, 0])
        acc = np.arccos(np.where(closed, c, 0.0))
        theta = np.full(p.shape[0], np.nan)
        best = np.full(p.shape[0], np.inf)
        for sign in (1.0, -1.0):               # eq. 3.12's two roots, in the scalar's order
            th = phi + sign * acc
            a = self.L2 * np.exp(1j * th)
            b = a + (target - a) * (self.L3 / self.AP)
            res = np.abs(np.abs(b - self.L1) - self.L4)
            side = _cross(self.L1 - a, b - a)
            take = closed & (res <= 1e-10 * scale) & (side * self._sigma > 0.0) & (res < best)
            theta = np.where(take, th, theta)
            best = np.where(take, res, best)
        project = np.isnan(theta)
        if project.any():
            th_p, d = self._nearest_on_curve_batch(target[project])
            theta[project] = np.where(d <= self.curve_tolerance, th_p, np.nan)
        q = _wrap_from(self._lo, theta)
        if limits:
            q = np.where(within_limits(q[:, None], np.array([self._lo]), np.array([self._hi])), q, np.nan)
        return q

    def inverse_batch(self, poses: np.ndarray, *, limits: bool = True) -> np.ndarray:
        """Vectorised :meth:`inverse`: crank angles (N, 1) (rad) for coupler points (N, 2) (m).

        Eq. 3.12 in closed form for points on the curve, the projection of
        :meth:`nearest_on_curve` (vectorised) for the others; a NaN row farther than
        ``curve_tolerance`` from the curve or (with ``limits``) outside ``crank_range`` —
        where :meth:`inverse` raises :class:`~.base.UnreachablePose`.

        :param limits: ``False``: no crank-range check.
        :raises ValueError: not an (N, 2) array, or a non-finite value.
        """
        return self._inverse_batch(as_poses(poses, 2), limits)[:, None]

    def jacobian_batch(self, poses: np.ndarray, *, limits: bool = True) -> np.ndarray:
        """Vectorised :meth:`jacobian`: ``J = t^T / |t|^2`` (N, 1, 2); a NaN matrix where
        :meth:`inverse_batch` has a NaN row."""
        q = self._inverse_batch(as_poses(poses, 2), limits)
        dp = self._curve_batch(np.where(np.isnan(q), 0.0, q))[1]
        t = np.stack([dp.real, dp.imag], axis=-1)
        jac = (t / np.sum(t * t, axis=-1, keepdims=True))[:, None, :]
        jac[np.isnan(q)] = np.nan
        return jac

    # ------------------------------------------------------------------ capacity along the path
    def _capacity_axes(self, pose: np.ndarray, **branch: Any) -> np.ndarray:
        """The unit tangent ``t / |t|`` (1, 2): :meth:`wrench` projected on the path."""
        t = self.tangent(pose)
        return (t / math.hypot(t[0], t[1]))[None, :]

    def _statics_batch(self, p: np.ndarray) -> Statics:
        """Along the path (arc length ``s``): ``F_s = T2 / |t|`` (virtual work, ``t = dP/dtheta2``),
        so ``G = 1 / |t|`` and ``H = |t|`` (1 x 1; ``|t| = 0`` at a dead point of the path:
        no torque needed, capacity infinite)."""
        q = self._inverse_batch(p, True)
        reach = ~np.isnan(q)
        speed = np.abs(self._curve_batch(np.where(reach, q, 0.0))[1])
        with np.errstate(divide='ignore'):
            g = (1.0 / speed)[:, None, None]
        g[~reach] = np.nan
        h = speed[:, None, None].copy()
        h[~reach] = np.nan
        return Statics(reach, g, h, reach, np.zeros((p.shape[0], 1)))

    def distance_to_curve(self, pose: Sequence[float]) -> float:
        """Distance (m) from ``pose`` to the coupler curve of the configured branch."""
        return self.nearest_on_curve(pose)[1]

    # ------------------------------------------------------------------ velocity, acceleration
    def analysis(self, theta2: float | np.ndarray, omega2: float | np.ndarray = 0.0,
                 alpha2: float | np.ndarray = 0.0) -> FourBarState:
        """Position, velocity and acceleration analysis (eqs. 3.8-3.14) for crank motion.

        :param theta2: crank angle (rad); ``omega2`` (rad/s), ``alpha2`` (rad/s^2); arrays
            broadcast together.
        """
        th2, w2, al2 = np.broadcast_arrays(np.asarray(theta2, float), np.asarray(omega2, float),
                                           np.asarray(alpha2, float))
        a, b, p, th3, th4 = self._positions(th2)
        e2, e3, e4 = np.exp(1j * th2), np.exp(1j * th3), np.exp(1j * th4)
        # velocity loop (eq. 3.13, rows 1-2): vA + i w3 L3 e3 = i w4 L4 e4; project on e4 and
        # e3 (Re(conj(e) . ) removes the term along i e):  w3 = Re(e4* vA) / (L3 sin(t3 - t4)),
        # w4 = Re(e3* vA) / (L4 sin(t3 - t4))
        va = 1j * w2 * self.L2 * e2
        s34 = _cross(e4, e3)                             # sin(theta3 - theta4)
        w3 = (np.conj(e4) * va).real / (self.L3 * s34)
        w4 = (np.conj(e3) * va).real / (self.L4 * s34)
        # acceleration loop (eq. 3.14): aA + L3 (i a3 - w3^2) e3 = L4 (i a4 - w4^2) e4, the same
        # structure with vA -> R = aA - L3 w3^2 e3 + L4 w4^2 e4
        aa = self.L2 * (1j * al2 - w2 ** 2) * e2
        rr = aa - self.L3 * w3 ** 2 * e3 + self.L4 * w4 ** 2 * e4
        al3 = (np.conj(e4) * rr).real / (self.L3 * s34)
        al4 = (np.conj(e3) * rr).real / (self.L4 * s34)
        vp = va + 1j * w3 * self.AP * e3
        ap = aa + self.AP * (1j * al3 - w3 ** 2) * e3
        g2 = self._r2c * e2
        g3 = a + self._r3 * e3
        g4 = self.L1 + self._r4 * e4
        vg = (1j * w2 * g2, va + 1j * w3 * self._r3 * e3, 1j * w4 * self._r4 * e4)
        ag = (self._r2c * (1j * al2 - w2 ** 2) * e2, aa + self._r3 * (1j * al3 - w3 ** 2) * e3,
              self._r4 * (1j * al4 - w4 ** 2) * e4)
        return FourBarState(th2, th3, th4, w2, w3, w4, al2, al3, al4, a, b, p, vp, ap,
                            (g2, g3, g4), vg, ag)

    def follow_x(self, x: np.ndarray, vx: np.ndarray, ax: np.ndarray, *, theta_start: float) -> FourBarState:
        """The linkage state when ``P`` follows a prescribed x-motion along the coupler curve.

        The thesis's ``VPx``/``APx`` prescription (eqs. 3.13-3.14) carried to the position
        level: ``Px(theta2) = x`` (Newton from the previous sample, the first from
        ``theta_start``), ``omega2 = vx / Px'``, ``alpha2 = (ax - Px'' omega2^2) / Px'``.

        :raises ValueError: ``x`` not reachable along the curve from ``theta_start``, or a
            vertical tangent (``Px' = 0``: x cannot parametrise the path there).
        """
        x, vx, ax = (np.asarray(v, dtype=float).ravel() for v in (x, vx, ax))
        if not (x.shape == vx.shape == ax.shape) or not np.all(np.isfinite(np.concatenate([x, vx, ax]))):
            raise ValueError('follow_x: x, vx, ax must be finite arrays of one length')
        th = np.empty_like(x)
        cur = float(theta_start)
        for k, xk in enumerate(x):
            for _ in range(50):
                p, dp, _ = self._curve_scalar(cur)
                f = p.real - xk
                d = dp.real
                if abs(d) < 1e-12:
                    raise ValueError(f'follow_x: vertical tangent of the coupler curve at crank angle '
                                     f'{math.degrees(cur):.2f} deg: x cannot parametrise the path')
                step = max(-0.2, min(0.2, -f / d))
                cur += step
                if abs(step) < 1e-14:
                    break
            if abs(self._curve_scalar(cur)[0].real - xk) > 1e-9:
                raise ValueError(f'follow_x: x = {xk:.5f} m not reached along the coupler curve '
                                 f'(sample {k}, crank angle {math.degrees(cur):.2f} deg)')
            th[k] = cur
        _, dp, ddp = self._curve_derivatives(th)
        w2 = vx / dp.real
        al2 = (ax - ddp.real * w2 ** 2) / dp.real
        return self.analysis(th, w2, al2)

    def _third_derivative(self, theta: np.ndarray) -> np.ndarray:
        """``d3P/dtheta2^3`` (complex): 5-point central difference of the analytic ``P''`` (h = 1e-3 rad)."""
        h = 1e-3
        f = [self.analysis(theta + k * h, 1.0, 0.0).ap for k in (-2, -1, 1, 2)]
        return (f[0] - 8.0 * f[1] + 8.0 * f[2] - f[3]) / (12.0 * h)

    def follow_path(self, p: np.ndarray, v: np.ndarray, a: np.ndarray, *, theta_start: float) -> FourBarState:
        """The linkage state when ``P`` tracks the nearest curve point of a planned path.

        For a path ``Q(t)`` off the coupler curve (the thesis's via-point reach is up to 5 mm
        off it) the crank takes the angle of the nearest curve point, ``g = (P - Q) . P' = 0``,
        differentiated implicitly: with ``G = |P'|^2 + (P - Q) . P''``,
        ``omega2 = Q_dot . P' / G`` and
        ``alpha2 = (Q_ddot . P' + Q_dot . P'' omega2 - G_dot omega2) / G``,
        ``G_dot = 3 P' . P'' omega2 - Q_dot . P'' + (P - Q) . P''' omega2``. On the curve it
        is exact tracking; ``P'''`` comes from a 5-point difference of the analytic ``P''``.

        :param p, v, a: ``(N, 2)`` positions (m), velocities (m/s), accelerations (m/s^2) of ``Q``.
        :raises ValueError: malformed arrays, or a path leaving the curve's neighbourhood
            (``G <= 0``: the nearest point jumps).
        """
        p, v, a = (np.asarray(arr, dtype=float).reshape(-1, 2) for arr in (p, v, a))
        if not (p.shape == v.shape == a.shape) or not np.all(np.isfinite(np.concatenate([p, v, a]))):
            raise ValueError('follow_path: p, v, a must be finite (N, 2) arrays of one length')
        q = p[:, 0] + 1j * p[:, 1]
        qd = v[:, 0] + 1j * v[:, 1]
        qdd = a[:, 0] + 1j * a[:, 1]

        def dot(u: Any, w: Any) -> Any:
            return (np.conj(u) * w).real
        th = np.empty(q.size)
        cur = float(theta_start)
        for k in range(q.size):
            for _ in range(50):
                pp, dp, ddp = self._curve_scalar(cur)
                r = pp - q[k]
                gg = abs(dp) ** 2 + dot(r, ddp)
                if gg <= 0.0:
                    raise ValueError(f'follow_path: sample {k} is too far from the coupler curve '
                                     f'(the nearest point is not unique, crank angle {math.degrees(cur):.2f} deg)')
                step = max(-0.2, min(0.2, -dot(r, dp) / gg))
                cur += step
                if abs(step) < 1e-14:
                    break
            th[k] = cur
        pp, dp, ddp = self._curve_derivatives(th)
        d3 = self._third_derivative(th)
        r = pp - q
        gg = np.abs(dp) ** 2 + dot(r, ddp)
        w2 = dot(qd, dp) / gg
        gdot = 3.0 * dot(dp, ddp) * w2 - dot(qd, ddp) + dot(r, d3) * w2
        al2 = (dot(qdd, dp) + dot(qd, ddp) * w2 - gdot * w2) / gg
        return self.analysis(th, w2, al2)

    # ------------------------------------------------------------------ kinetostatics
    def kinetostatics(self, state: FourBarState, *, drive: str = 'crank',
                      force_p: complex | np.ndarray = 0.0, crank_torque: float | np.ndarray = 0.0,
                      rocker_torque: float | np.ndarray = 0.0) -> Kinetostatics:
        """Newton–Euler force analysis, eq. 3.19 (``drive='crank'``: ``T2``, free rocker) or
        eq. 3.20 (``drive='rocker'``: ``T4``, free crank), vectorised over the state.

        :param force_p: external force on the coupler at ``P`` (complex, N), e.g. the
            patient's (:func:`imaginary_spring_stiffness`).
        :param crank_torque: other external torque on the crank (N·m, CCW), added to the drive.
        :param rocker_torque: other external torque on the rocker (N·m, CCW), e.g. springs
            (:func:`spring_torques`): the drive then supplies only the rest.
        """
        if drive not in ('crank', 'rocker'):
            raise ValueError(f'drive: expected "crank" or "rocker", got {drive!r}')
        st = state
        shape = np.shape(st.theta2)
        fp = np.broadcast_to(np.asarray(force_p, dtype=complex), shape)
        tc = np.broadcast_to(np.asarray(crank_torque, dtype=float), shape)
        tr = np.broadcast_to(np.asarray(rocker_torque, dtype=float), shape)
        g2, g3, g4 = st.g
        r12, r32 = 0.0 - g2, st.a - g2
        r23, r43, rp = st.a - g3, st.b - g3, st.p - g3
        r34, r14 = st.b - g4, self.L1 - g4
        n = int(np.prod(shape)) if shape else 1
        M = np.zeros((n, 9, 9))
        rhs = np.zeros((n, 9))

        def flat(v: Any) -> np.ndarray:
            return np.broadcast_to(np.asarray(v), shape).reshape(n)
        m2, m3, m4 = self._m
        i2, i3, i4 = self._i
        gr = self.gravity
        a2, a3, a4 = (flat(v) for v in st.ag)
        # link 2: F12 + F32 + m2 g = m2 aG2 ; T2 + R12 x F12 + R32 x F32 + Tc = I2 alpha2
        M[:, 0, 0] = M[:, 0, 2] = 1.0
        M[:, 1, 1] = M[:, 1, 3] = 1.0
        rhs[:, 0], rhs[:, 1] = m2 * (a2 - gr).real, m2 * (a2 - gr).imag
        M[:, 2, 0], M[:, 2, 1] = -flat(r12).imag, flat(r12).real
        M[:, 2, 2], M[:, 2, 3] = -flat(r32).imag, flat(r32).real
        rhs[:, 2] = i2 * flat(st.alpha2) - flat(tc)
        # link 3: -F32 + F43 + FP + m3 g = m3 aG3 ; R23 x (-F32) + R43 x F43 + RP x FP = I3 alpha3
        fpf = flat(fp)
        M[:, 3, 2], M[:, 3, 4] = -1.0, 1.0
        M[:, 4, 3], M[:, 4, 5] = -1.0, 1.0
        rhs[:, 3], rhs[:, 4] = m3 * (a3 - gr).real - fpf.real, m3 * (a3 - gr).imag - fpf.imag
        M[:, 5, 2], M[:, 5, 3] = flat(r23).imag, -flat(r23).real
        M[:, 5, 4], M[:, 5, 5] = -flat(r43).imag, flat(r43).real
        rhs[:, 5] = i3 * flat(st.alpha3) - _cross(flat(rp), fpf)
        # link 4: -F43 + F14 + m4 g = m4 aG4 ; R34 x (-F43) + R14 x F14 + T4 + Tr = I4 alpha4
        M[:, 6, 4], M[:, 6, 6] = -1.0, 1.0
        M[:, 7, 5], M[:, 7, 7] = -1.0, 1.0
        rhs[:, 6], rhs[:, 7] = m4 * (a4 - gr).real, m4 * (a4 - gr).imag
        M[:, 8, 4], M[:, 8, 5] = flat(r34).imag, -flat(r34).real
        M[:, 8, 6], M[:, 8, 7] = -flat(r14).imag, flat(r14).real
        rhs[:, 8] = i4 * flat(st.alpha4) - flat(tr)
        M[:, 2 if drive == 'crank' else 8, 8] = 1.0
        with np.errstate(all='ignore'):
            try:
                sol = np.linalg.solve(M, rhs[..., None])[..., 0]
            except np.linalg.LinAlgError:
                sol = np.full((n, 9), np.nan)
                for k in range(n):
                    try:
                        sol[k] = np.linalg.solve(M[k], rhs[k])
                    except np.linalg.LinAlgError:
                        pass                       # a dead point for this drive: NaN
        sol = sol.reshape(shape + (9,))
        f = sol[..., 0:8:2] + 1j * sol[..., 1:8:2]
        return Kinetostatics(drive, sol[..., 8], f[..., 0], f[..., 1], f[..., 2], f[..., 3])

    def kinetic_energy(self, state: FourBarState) -> np.ndarray:
        """``sum (m |vG|^2 + I omega^2) / 2`` (J), the crank with its flywheel."""
        w = (state.omega2, state.omega3, state.omega4)
        return sum(0.5 * self._m[k] * np.abs(state.vg[k]) ** 2 + 0.5 * self._i[k] * w[k] ** 2
                   for k in range(3))

    # ------------------------------------------------------------------ differential protocol
    def path_point(self, theta: float | np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The coupler curve by crank angle: ``P``, ``dP/dtheta2`` and ``d2P/dtheta2^2``, each
        of shape (N, 2) (m, m/rad, m/rad^2), on the configured assembly (the path a planner
        moves along: :class:`~brace_control.trajectory.path.CurvePath`)."""
        th = np.atleast_1d(np.asarray(theta, dtype=float))
        p, dp, ddp = self._curve_batch(th)
        return (np.column_stack([p.real, p.imag]), np.column_stack([dp.real, dp.imag]),
                np.column_stack([ddp.real, ddp.imag]))

    def tangent(self, pose: Sequence[float]) -> np.ndarray:
        """``dP/dtheta2`` (m/rad) at ``pose`` (on the curve, or projected within tolerance)."""
        th = float(self.inverse(pose)[0])
        dp = self._curve_scalar(th)[1]
        return np.array([dp.real, dp.imag])

    def jacobian(self, pose: Sequence[float]) -> np.ndarray:
        """``J`` (1, 2) with ``theta2_dot = J @ (x_dot, y_dot)``: ``J = t^T / |t|^2``, ``t = dP/dtheta2``.

        Exact for velocities along the coupler curve; a velocity component normal to it is
        dropped (least squares). Units rad/m.

        :raises UnreachablePose: ``pose`` not on the curve (see :meth:`inverse`).
        """
        t = self.tangent(pose)
        return (t / float(t @ t)).reshape(1, 2)

    def path_direction(self, pose: Sequence[float]) -> np.ndarray:
        """The unit tangent ``t / |t|`` of the coupler curve at ``pose`` (the direction of
        increasing crank angle; ``(0, 0)`` at a dead point of the path)."""
        t = self.tangent(pose)
        norm = math.hypot(t[0], t[1])
        return t / norm if norm > 0.0 else np.zeros(2)

    def constrain_motion(self, pose: Sequence[float], velocity: Sequence[float]
                         ) -> tuple[np.ndarray, np.ndarray]:
        """A motion of ``P`` kept on the coupler curve (mobility 1): the curve point nearest
        ``pose`` and the component of ``velocity`` along the curve there.

        For a model that moves the pose coordinates freely (the admittance, braking): a step
        along the tangent leaves the curve by its curvature; this puts it back.
        """
        pt = as_vector(pose, 2, 'pose')
        vel = as_vector(velocity, 2, 'velocity')
        theta = self._nearest_local(pt)
        if theta is None:
            theta, _ = self.nearest_on_curve(pt)
        p, dp, _ = self._curve_scalar(theta)
        t = np.array([dp.real, dp.imag])
        tt = float(t @ t)
        v = t * (float(t @ vel) / tt) if tt > 0.0 else np.zeros(2)
        return np.array([p.real, p.imag]), v

    def wrench(self, pose: Sequence[float], forces: Sequence[float]) -> np.ndarray:
        """Force ``(Fx, Fy)`` (N) the crank torque makes the (static, massless) linkage apply at ``P``.

        :param forces: ``[T2]`` (N·m), the motor's torque on the crank, counter-clockwise.
        :returns: ``J^T T2`` — the tangential, minimum-norm force: ``F . P_dot = T2 theta2_dot``.
        """
        torque = as_vector(forces, 1, 'forces')
        return self.jacobian(pose).T @ torque

    def in_workspace(self, pose: Sequence[float]) -> bool:
        """True when ``pose`` is within ``curve_tolerance`` of the curve at an allowed crank angle.

        :raises ValueError: malformed ``pose``.
        """
        return self._in_workspace(pose, singularity=False)

    # ------------------------------------------------------------------ configuration
    @classmethod
    def from_config(cls, section: Mapping[str, Any]) -> 'HoekenFourBar':
        """Build from the YAML's ``mechanism`` section (``type: hoeken_fourbar``).

        Reads ``ground, crank, coupler, rocker`` (m), optional ``coupler_extension``,
        ``branch``, ``crank_range`` (rad), ``curve_tolerance`` (m), ``home_pose`` (m),
        ``actuator_names``, ``masses``, ``cg_fractions``, ``inertias``, ``bar_width``,
        ``flywheel_mass``, ``flywheel_inertia``, ``gravity``.

        :raises ConfigError: a missing or malformed value, naming the parameter.
        """
        check_section(section, 'hoeken_fourbar', 'HoekenFourBar', ('ground', 'crank', 'coupler', 'rocker'))
        kwargs = section_kwargs(section, given=('coupler_extension', 'branch', 'crank_range', 'curve_tolerance',
                                                'home_pose', 'actuator_names', 'masses', 'cg_fractions', 'inertias',
                                                'bar_width', 'flywheel_mass', 'flywheel_inertia', 'gravity'))
        with config_errors():
            return cls(float(section['ground']), float(section['crank']), float(section['coupler']),
                       float(section['rocker']), **kwargs)


# ====================================================================== patient, springs, exercise
def imaginary_spring_stiffness(max_force: float, max_deviation: float) -> float:
    """Eq. 3.20: ``k_PU = F_PUmax / Delta d_max`` (N/m)."""
    if not (max_deviation > 0.0 and math.isfinite(max_deviation) and math.isfinite(max_force)):
        raise ValueError(f'imaginary spring: need a finite force and a deviation > 0 m, got '
                         f'{max_force!r} N, {max_deviation!r} m')
    return float(max_force) / float(max_deviation)


def spring_torque(theta4: np.ndarray, ls1: float, ls2: float, beta: float, l0: float, k: float, *,
                  unilateral: bool = True) -> np.ndarray:
    """Torque (N·m, CCW on the rocker about ``O4``) of one spring, eqs. 3.21-3.26.

    ``Ls = sqrt(Ls1^2 + Ls2^2 - 2 Ls1 Ls2 cos(theta4 - beta))`` (3.21); force ``k (L0 - Ls)``
    pushing the contact away from the ground point (3.23, compression positive); torque
    ``k (L0 - Ls) Ls1 Ls2 sin(theta4 - beta) / Ls`` (3.24 x 3.25 = 3.26 with the law of sines).
    ``unilateral``: a contact spring, no force once longer than ``L0``.
    """
    th = np.asarray(theta4, dtype=float)
    ls = np.sqrt(ls1 ** 2 + ls2 ** 2 - 2.0 * ls1 * ls2 * np.cos(th - beta))
    comp = l0 - ls
    if unilateral:
        comp = np.maximum(comp, 0.0)
    with np.errstate(divide='ignore', invalid='ignore'):
        out = k * comp * ls1 * ls2 * np.sin(th - beta) / ls
    return np.where(ls > 0.0, out, 0.0)


def spring_torques(theta4: np.ndarray, x: Sequence[float], *, unilateral: bool = True) -> np.ndarray:
    """Sum of the two springs' torques for the 10 variables ``x`` (order :data:`SPRING_VARIABLES`)."""
    ls11, ls12, b1, ls21, ls22, b2, l01, l02, k1, k2 = (float(v) for v in x)
    return (spring_torque(theta4, ls11, ls12, b1, l01, k1, unilateral=unilateral)
            + spring_torque(theta4, ls21, ls22, b2, l02, k2, unilateral=unilateral))


@dataclass
class SpringFit:
    """Result of :func:`optimise_springs`: the variables, the residual and the fitted torque."""

    x: np.ndarray                 #: the 10 variables (m, m, rad, m, m, rad, m, m, N/m, N/m)
    cost: float                   #: sum (T4 - T_s)^2 (N^2 m^2), eq. 4.1
    rms: float                    #: sqrt(cost / n) (N·m)
    torque: np.ndarray            #: T_s at the samples (N·m)
    nfev: int
    seed: int

    def as_dict(self) -> dict[str, float]:
        return dict(zip(SPRING_VARIABLES, (float(v) for v in self.x)))


def optimise_springs(theta4: np.ndarray, t4: np.ndarray, bounds: Sequence[tuple[float, float]], *,
                     seed: int = 1, maxiter: int = 200, popsize: int = 15, tol: float = 1e-8,
                     unilateral: bool = True, polish: bool = True) -> SpringFit:
    """Eq. 4.1: ``min sum (T4 - T_s)^2`` over the 10 spring variables by differential evolution.

    :param theta4: rocker angles along the motion (rad); ``t4`` the required rocker torque (N·m).
    :param bounds: 10 ``(lo, hi)`` pairs in the order of :data:`SPRING_VARIABLES`.
    :param seed: fixed for reproducible runs. ``maxiter``/``popsize``: the budget.
    """
    from scipy.optimize import differential_evolution
    th = np.asarray(theta4, dtype=float).ravel()
    target = np.asarray(t4, dtype=float).ravel()
    ok = np.isfinite(th) & np.isfinite(target)
    th, target = th[ok], target[ok]
    bnds = [tuple(map(float, b)) for b in bounds]
    if len(bnds) != 10 or any(not (lo <= hi) for lo, hi in bnds):
        raise ValueError(f'bounds: expected 10 (lo, hi) pairs for {SPRING_VARIABLES}, got {bounds!r}')

    def cost(x: np.ndarray) -> np.ndarray | float:
        x = np.asarray(x, dtype=float)
        if x.ndim == 1:
            return float(np.sum((target - spring_torques(th, x, unilateral=unilateral)) ** 2))
        # vectorised: x (10, S)
        tau = np.zeros((x.shape[1], th.size))
        for j in range(2):
            ls1, ls2, beta, l0, k = (x[i][:, None] for i in (3 * j, 3 * j + 1, 3 * j + 2, 6 + j, 8 + j))
            ls = np.sqrt(ls1 ** 2 + ls2 ** 2 - 2.0 * ls1 * ls2 * np.cos(th - beta))
            comp = l0 - ls
            if unilateral:
                comp = np.maximum(comp, 0.0)
            with np.errstate(divide='ignore', invalid='ignore'):
                tau += np.where(ls > 0.0, k * comp * ls1 * ls2 * np.sin(th - beta) / ls, 0.0)
        return np.sum((target - tau) ** 2, axis=1)

    res = differential_evolution(cost, bnds, seed=seed, maxiter=maxiter, popsize=popsize, tol=tol,
                                 polish=polish, vectorized=True, updating='deferred')
    x = np.asarray(res.x, dtype=float)
    fitted = spring_torques(th, x, unilateral=unilateral)
    c = float(np.sum((target - fitted) ** 2))
    return SpringFit(x, c, math.sqrt(c / max(th.size, 1)), fitted, int(res.nfev), int(seed))


@dataclass
class ExerciseProfile:
    """One exercise through :func:`run_exercise` (arrays over the sample times ``t``)."""

    t: np.ndarray
    state: FourBarState
    hand_x: np.ndarray            #: the patient's hand x (m)
    stiffness: float              #: imaginary spring k_PU (N/m), eq. 3.20
    force_p: np.ndarray           #: force on P (complex, N)
    t2: np.ndarray                #: crank torque, free rocker (N·m), eq. 3.19
    t4: np.ndarray                #: rocker torque, free crank (N·m), eq. 3.20
    path_offset: np.ndarray       #: |P - MJM (x, y)| (m): how far the MJM path is off the curve
    extras: dict[str, Any] = field(default_factory=dict)

    def peak(self, which: str = 't2') -> tuple[float, int]:
        """``(value, index)`` of the largest positive torque (``'t2'``/``'t4'``)."""
        arr = getattr(self, which)
        i = int(np.nanargmax(arr))
        return float(arr[i]), i

    def peak_abs(self, which: str = 't2') -> tuple[float, int]:
        """``(signed value, index)`` of the largest |torque|."""
        arr = getattr(self, which)
        i = int(np.nanargmax(np.abs(arr)))
        return float(arr[i]), i


def run_exercise(mech: HoekenFourBar, sample: Callable[[float], tuple[Any, Any, Any]],
                 times: np.ndarray, *, hand: Callable[[np.ndarray], np.ndarray] | None = None,
                 max_patient_force: float = 0.0, follow: str = 'nearest') -> ExerciseProfile:
    """Crank and rocker torques for a minimum-jerk reach of the hand (thesis ch. 4).

    :param sample: ``t -> (p, v, a)`` of the planned hand path (``p = (x, y)``; e.g.
        :class:`~brace_control.trajectory.MinimumJerk`'s ``sample``).
    :param follow: ``'nearest'``: the crank tracks the nearest curve point of the path
        (:meth:`HoekenFourBar.follow_path`); ``'x'``: ``P`` follows the path's x exactly and its
        y is the curve's (:meth:`HoekenFourBar.follow_x`, the thesis's ``VPx``/``APx`` scheme).
    :param times: sample times (s).
    :param hand: ``t -> x`` of the patient's hand (m); with ``max_patient_force`` (N) the
        imaginary spring (eq. 3.20) ``k = F_max / max |x_MJM - x_hand|`` pulls ``P`` towards the
        hand along x: ``FP = k (x_hand - x_P)`` (the deviation is horizontal, thesis §4.2).
    """
    t = np.asarray(times, dtype=float)
    pva = [sample(float(tk)) for tk in t]
    p = np.array([np.asarray(s[0], float) for s in pva])
    v = np.array([np.asarray(s[1], float) for s in pva])
    acc = np.array([np.asarray(s[2], float) for s in pva])
    th0, _ = mech.nearest_on_curve(p[0])
    if follow == 'x':
        state = mech.follow_x(p[:, 0], v[:, 0], acc[:, 0], theta_start=th0)
    elif follow == 'nearest':
        state = mech.follow_path(p, v, acc, theta_start=th0)
    else:
        raise ValueError(f'follow: expected "nearest" or "x", got {follow!r}')
    hx = np.asarray(hand(t), dtype=float) if hand is not None else p[:, 0].copy()
    dev = p[:, 0] - hx
    dmax = float(np.max(np.abs(dev)))
    k = imaginary_spring_stiffness(max_patient_force, dmax) if (hand is not None and dmax > 0.0) else 0.0
    fp = (k * (hx - state.p.real)).astype(complex)
    t2 = mech.kinetostatics(state, drive='crank', force_p=fp).torque
    t4 = mech.kinetostatics(state, drive='rocker', force_p=fp).torque
    offset = np.abs(state.p - (p[:, 0] + 1j * p[:, 1]))
    return ExerciseProfile(t, state, hx, k, fp, t2, t4, offset)
