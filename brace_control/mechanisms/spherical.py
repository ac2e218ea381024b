"""Spherical 3-RRR parallel mechanism: the prosthetic shoulder joint (seed paper 004).

Gosselin's formulation, 11 design parameters ``gamma, beta, alpha1_1..3, alpha2_1..3,
delta_1..3`` (the slides' "11 structural parameters"; all angles in rad here, the YAML
gives them in rad with the paper's degrees in comments).

Frames (right shoulder; the left one is its mirror image)
--------------------------------------------------------
Base frame ``{B}`` (fixed to the torso), origin ``O`` at the centre of rotation (every
joint axis passes through ``O``): ``x_B`` lateral, ``y_B`` posterior, ``z_B`` inferior,
i.e. along the hanging arm. The platform frame ``{P}`` (fixed to the arm) coincides with
``{B}`` at the reference orientation (pose ``(0, 0, 0)``: arm hanging, the neutral posture);
the platform orientation is ``Q`` (``{P}`` -> ``{B}``), the arm's long axis is ``z_P``.

* base (motor) axes on a cone of half-angle ``gamma`` about ``-z_B`` (pointing to the torso):
  ``u_i = (cos d_i sin gamma, sin d_i sin gamma, -cos gamma)``, ``d_i = delta_i`` the leg
  azimuths, counter-clockwise about ``z_B`` from ``x_B``;
* platform axes on a cone of half-angle ``beta`` about ``+z_P`` (pointing to the arm):
  ``v_i = Q v_i^P``, ``v_i^P = (cos d_i sin beta, sin d_i sin beta, cos beta)`` (same azimuths);
* intermediate (elbow) axes ``w_i = cos a1_i u_i + sin a1_i (cos th_i e1_i + sin th_i e2_i)``:
  ``th_i`` the motor angle, right-handed about ``u_i``; ``e1_i`` the unit vector normal to
  ``u_i`` in the plane of ``u_i`` and ``z_B`` with ``e1_i . z_B > 0`` (at ``th_i = 0`` the
  proximal link leans to the arm side), ``e2_i = u_i x e1_i``;
* leg closure: ``w_i . v_i = cos a2_i`` (the distal link angle).

This is Gosselin and Angeles' layout (base axes ``-cos gamma``, platform axes ``+cos beta``);
with it and the motion angles below, the paper's design reaches all 1320 poses (g1).

Pose: the three motion angles (rad)
-----------------------------------
``pose = (abduction, flexion_extension, rotation)``, signs as the paper's ranges read:
abduction positive (adduction negative, range [-10, 90] deg), extension positive
(flexion negative, [-90, 20] deg), internal rotation positive (external negative,
[-40, 50] deg). Intrinsic Y-X-Z sequence::

    Q = R_y(abduction) R_x(-flexion_extension) R_z(-rotation)

abduction about the posterior axis ``y_B`` (the arm swings out to ``+x_B``), then
flexion-extension about the (moved) medial axis, then axial rotation about the arm's
long axis ``z_P``. Gimbal lock at ``flexion_extension = +-90 deg`` (the edge of the
paper's range): there the pose-rate Jacobian :meth:`Spherical3Rrr.jacobian` loses rank
(the mechanism's angular Jacobian does not). ROS messages carry the quaternion
``(x, y, z, w)`` of ``Q``: :meth:`~Spherical3Rrr.pose_from_quaternion`,
:meth:`~Spherical3Rrr.quaternion_from_pose`.

Inverse kinematics (the slides' quadratic)
------------------------------------------
With ``a = sin a1 (e1 . v)``, ``b = sin a1 (e2 . v)``, ``c = cos a2 - cos a1 (u . v)`` the
closure is ``a cos th + b sin th = c``; with ``T = tan(th / 2)`` it is the slides'
``A T^2 + B T + C = 0``, ``A = -(a + c)``, ``B = 2 b``, ``C = a - c`` (the slides write
``tan(th)``; it is the half angle). Real iff ``a^2 + b^2 >= c^2``. Two roots per leg,
``2^3 = 8`` working modes. A mode is labelled by the sign of ``Kq_ii = (u_i x w_i) . v_i``
(the two roots are mirror images of the elbow across the plane of ``u_i`` and ``v_i``,
so the sign tells them apart and changes only through a serial singularity ``Kq_ii =
0``): ``working_mode = '+-+'`` etc.; ``th_i = atan2(b, a) - s_i acos(c / sqrt(a^2 + b^2))``.

Forward kinematics (every real assembly mode)
---------------------------------------------
Given the motors, the ``w_i`` are known. Put ``v_1`` on its cone about ``w_1`` and ``v_2``
on its cone about ``w_2`` (angles ``t1``, ``t2``); two orientation-independent equations
remain: ``v_1 . v_2 = v_1^P . v_2^P`` and leg 3, ``v_3 . w_3 = cos a2_3`` with
``v_3 = a v_1 + b v_2 + c v_1 x v_2`` (``a, b, c`` constants of the platform). Both are
bilinear in ``(cos t1, sin t1, 1)`` and ``(cos t2, sin t2, 1)``, i.e. biquadratic in the
half-angle tangents ``x1, x2``; the Sylvester resultant in ``x2`` is a polynomial of
degree 8 in ``x1`` (the slides' 8th-degree polynomial; 8 = the Bezout number of two
bidegree-(2, 2) curves, so at most 8 assembly modes and no spurious input-independent
roots: every root of the system is an orientation, ``Q`` being fixed by ``v_1``, ``v_2``).
Its roots come from the companion matrix; the real ones are lifted (``x2`` from the
linear combination of the two quadratics), polished by Newton on ``(t1, t2)`` and kept
only when all three legs close to :attr:`Spherical3Rrr.verify_tol`. ``t1 = pi`` (a root
at infinity: the degree drops) is checked separately. An identically vanishing
resultant (a self-motion) raises :class:`~.base.SingularPose`.

Differential kinematics and statics
-----------------------------------
Differentiating ``w_i . v_i = cos a2_i`` with ``w_i' = th_i' u_i x w_i``, ``v_i' = omega x v_i``:
``Kq th' = Jx omega``, rows ``Jx_i = (w_i x v_i)^T``, ``Kq = diag((u_i x w_i) . v_i)``
(``omega`` the platform's angular velocity in ``{B}``). Dexterity (slides)
``k(J) = ||Kq^-1 Jx|| ||Jx^-1 Kq||``, 2-norm. Singularities: serial (``Kq_ii = 0``, a
leg stretched or folded), parallel (``det Jx = 0``). Statics by virtual work
(``tau . th' + M . omega = 0``): the motor torques that hold an external moment ``M``
on the platform are ``tau = -(Jx^-1 Kq)^T M``, the slides' ``tau = J^T F`` with
``J = Jx^-1 Kq`` (``omega = J th'``).
"""
from __future__ import annotations

import itertools
import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from .base import (MechanismBase, SingularPose, Statics, UnreachablePose, as_actuator_names, as_condition_max,
                   as_per_actuator, as_poses, as_range, as_vector, check_limits, check_section, config_errors,
                   section_kwargs, within_limits)
from .capacity import regular_inverse
from .loader import register

__all__ = [
    'Spherical3Rrr', 'WORKING_MODES', 'PAPER_DESIGN_DEG',
    'rotation_matrices', 'pose_from_matrix', 'euler_rate_matrix', 'leg_geometry',
    'inverse_batch', 'velocity_batch', 'design_from_degrees',
]

_TWO_PI = 2.0 * math.pi
#: the 8 working modes, in the order of ``inverse_all``: sign of ``Kq_ii`` per leg
WORKING_MODES: tuple[str, ...] = tuple(''.join(m) for m in itertools.product('+-', repeat=3))

#: the slides' chosen design (deg): gamma, beta, alpha1_1..3, alpha2_1..3, delta_1..3
PAPER_DESIGN_DEG: dict[str, Any] = {
    'gamma': 73.97034, 'beta': 74.02084,
    'alpha1': (65.55052, 89.83113, 81.71658),
    'alpha2': (66.60625, 83.08663, 81.55116),
    'delta': (68.03214, 186.1973, 295.7946),
}

# the motion angles -> Q = R_y(a) R_x(-f) R_z(-r): axis index and sign per angle
_SEQ_AXES = (1, 0, 2)
_SEQ_SIGNS = (1.0, -1.0, -1.0)


def design_from_degrees(design_deg: Mapping[str, Any]) -> dict[str, Any]:
    """``{'gamma': deg, ...}`` -> the same keys in rad (alpha/delta as arrays)."""
    return {k: (math.radians(v) if k in ('gamma', 'beta') else np.radians(np.asarray(v, float)))
            for k, v in design_deg.items()}


# ---------------------------------------------------------------------- orientation helpers
def _axis_rotations(axis: int, angle: np.ndarray) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    out = np.zeros(np.shape(angle) + (3, 3))
    j, k = ((1, 2), (2, 0), (0, 1))[axis]
    out[..., axis, axis] = 1.0
    out[..., j, j] = c
    out[..., k, k] = c
    out[..., j, k] = -s
    out[..., k, j] = s
    return out


def rotation_matrices(poses: np.ndarray) -> np.ndarray:
    """``Q`` for poses ``(abduction, flexion_extension, rotation)`` (rad), shape (N, 3) -> (N, 3, 3)."""
    p = np.asarray(poses, dtype=float)
    q = _axis_rotations(_SEQ_AXES[0], _SEQ_SIGNS[0] * p[..., 0])
    q = q @ _axis_rotations(_SEQ_AXES[1], _SEQ_SIGNS[1] * p[..., 1])
    return q @ _axis_rotations(_SEQ_AXES[2], _SEQ_SIGNS[2] * p[..., 2])


def pose_from_matrix(q: np.ndarray) -> np.ndarray:
    """The motion angles of a rotation matrix (inverse of :func:`rotation_matrices` for one pose).

    ``Q = R_y(a) R_x(b) R_z(c)``: ``sin b = -Q[1, 2]``, ``a = atan2(Q[0, 2], Q[2, 2])``,
    ``c = atan2(Q[1, 0], Q[1, 1])``; pose ``= (a, -b, -c)``. At the gimbal lock
    (``cos b = 0``) the axial rotation is set to 0.
    """
    m = np.asarray(q, dtype=float)
    cb = math.hypot(m[1, 0], m[1, 1])
    b = math.atan2(-m[1, 2], cb)
    if cb > 1e-12:
        a = math.atan2(m[0, 2], m[2, 2])
        c = math.atan2(m[1, 0], m[1, 1])
    else:
        a = math.atan2(-m[2, 0], m[0, 0])
        c = 0.0
    return np.array([a, -b, -c])


def euler_rate_matrix(pose: np.ndarray) -> np.ndarray:
    """``E`` (3, 3) with ``omega = E @ pose_dot`` (``omega`` in ``{B}``, rad/s); poses (..., 3)
    give (..., 3, 3).

    Columns: ``s_1 e_y``, ``s_2 R_y(a) e_x``, ``s_3 R_y(a) R_x(b) e_z`` (``s`` the angle signs).
    Singular at the gimbal lock ``flexion_extension = +-90 deg``.
    """
    p = np.asarray(pose, dtype=float)
    a = _SEQ_SIGNS[0] * p[..., 0]
    b = _SEQ_SIGNS[1] * p[..., 1]
    r1 = _axis_rotations(_SEQ_AXES[0], a)
    r2 = r1 @ _axis_rotations(_SEQ_AXES[1], b)
    first = np.broadcast_to(_SEQ_SIGNS[0] * np.eye(3)[_SEQ_AXES[0]], r1.shape[:-1])
    return np.stack([first, _SEQ_SIGNS[1] * r1[..., :, _SEQ_AXES[1]],
                     _SEQ_SIGNS[2] * r2[..., :, _SEQ_AXES[2]]], axis=-1)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a x b`` over the last axis (broadcasting); faster than ``np.cross`` for small arrays."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[..., 0] = a1 * b2 - a2 * b1
    out[..., 1] = a2 * b0 - a0 * b2
    out[..., 2] = a0 * b1 - a1 * b0
    return out


# ---------------------------------------------------------------------- vectorised core
def leg_geometry(gamma: float, beta: float, delta: np.ndarray) -> tuple[np.ndarray, ...]:
    """``u_i``, ``e1_i``, ``e2_i`` (base, (3, 3) each, one row per leg) and ``v_i^P`` (3, 3)."""
    d = np.asarray(delta, dtype=float)
    sg, cg = math.sin(gamma), math.cos(gamma)
    u = np.column_stack([np.cos(d) * sg, np.sin(d) * sg, np.full(3, -cg)])
    # e1: the unit vector normal to u in the plane of u and z_B, e1 . z_B = sin(gamma) > 0
    e1 = np.column_stack([np.cos(d) * cg, np.sin(d) * cg, np.full(3, sg)])
    e2 = _cross(u, e1)
    sb, cb = math.sin(beta), math.cos(beta)
    vp = np.column_stack([np.cos(d) * sb, np.sin(d) * sb, np.full(3, cb)])
    return u, e1, e2, vp


def _closure_terms(u, e1, e2, alpha1, alpha2, v):
    """``a, b, c`` of ``a cos th + b sin th = c`` for platform axes ``v`` (..., 3, 3)."""
    s1 = np.sin(alpha1)
    a = s1 * np.einsum('kj,...kj->...k', e1, v)
    b = s1 * np.einsum('kj,...kj->...k', e2, v)
    c = np.cos(alpha2) - np.cos(alpha1) * np.einsum('kj,...kj->...k', u, v)
    return a, b, c


def inverse_batch(gamma: float, beta: float, alpha1: np.ndarray, alpha2: np.ndarray,
                  delta: np.ndarray, q_mats: np.ndarray, signs: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Vectorised inverse kinematics for orientations ``q_mats`` (N, 3, 3).

    :param signs: working mode, ``+-1`` per leg (3,), or (M, 3) for several modes at once
        (then the outputs get a leading mode axis).
    :returns: ``(reach, theta, w, v)``: ``reach`` (N,) bool, every leg closes; ``theta``
        (..., N, 3) rad (NaN where a leg cannot close); ``w`` (..., N, 3, 3) elbow axes;
        ``v`` (N, 3, 3) platform axes (rows = legs).
    """
    u, e1, e2, vp = leg_geometry(gamma, beta, delta)
    v = np.einsum('nij,kj->nki', q_mats, vp)
    a, b, c = _closure_terms(u, e1, e2, alpha1, alpha2, v)
    rho = np.hypot(a, b)
    with np.errstate(invalid='ignore', divide='ignore'):
        ratio = c / rho
    leg_ok = np.abs(ratio) <= 1.0
    reach = leg_ok.all(axis=-1)
    s = np.asarray(signs, dtype=float)
    phi = np.arctan2(b, a)
    half = np.arccos(np.where(leg_ok, ratio, np.nan))
    if s.ndim == 2:
        theta = phi[None] - s[:, None, :] * half[None]
    else:
        theta = phi - s * half
    ct, st = np.cos(theta), np.sin(theta)
    ca1, sa1 = np.cos(alpha1)[:, None], np.sin(alpha1)[:, None]
    w = ca1 * u + sa1 * (ct[..., None] * e1 + st[..., None] * e2)
    return reach, theta, w, v


def velocity_batch(u: np.ndarray, w: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``Jx`` (..., 3, 3) rows ``w_i x v_i`` and the diagonal of ``Kq`` (..., 3): ``(u_i x w_i) . v_i``."""
    jx = _cross(w, v)
    kq = np.einsum('...kj,...kj->...k', _cross(u, w), v)
    return jx, kq


def _parse_mode(mode: Any) -> tuple[str, np.ndarray]:
    if isinstance(mode, (int, np.integer)) and not isinstance(mode, bool) and 0 <= int(mode) < 8:
        mode = WORKING_MODES[int(mode)]
    if not isinstance(mode, str) or len(mode) != 3 or set(mode) - {'+', '-'}:
        raise ValueError(f"working_mode: expected three signs such as '+-+' (sign of Kq_ii per leg) "
                         f'or an index 0..7, got {mode!r}')
    return mode, np.array([1.0 if ch == '+' else -1.0 for ch in mode])


# ---------------------------------------------------------------------- the mechanism
@register('spherical_3rrr')
class Spherical3Rrr(MechanismBase):
    """Spherical 3-RRR parallel mechanism (the shoulder joint); see the module docstring.

    :param gamma: half-angle of the base-axis cone (rad).
    :param beta: half-angle of the platform-axis cone (rad).
    :param alpha1: proximal link angles ``alpha1_1..3`` (rad), angle ``u_i`` -> ``w_i``.
    :param alpha2: distal link angles ``alpha2_1..3`` (rad), angle ``w_i`` -> ``v_i``.
    :param delta: leg azimuths ``delta_1..3`` (rad).
    :param working_mode: ``'+-+'``-style sign of ``Kq_ii`` per leg (or an index into
        :data:`WORKING_MODES`): which of the 8 inverse solutions the built joint uses.
    :param joint_limits: ``(lo, hi)`` motor angle range (rad), scalars or three values
        each, ``hi - lo <= 2 pi``; angles are reported in ``[lo, lo + 2 pi)`` so that they
        are continuous over the range.
    :param actuator_names: three distinct names (motor order = leg order).
    :param home_pose: rest pose (rad), default ``(0, 0, 0)`` (arm hanging); must be
        reachable, within limits and not singular.
    :param singularity_condition_max: ``k(J)`` above this is treated as singular.
    :param load_forces: weights (N) of the arm, the hand and the payload (slides: 15, 5, 5).
    :param load_lever_arms: their distances (m) from ``O`` along the arm axis ``z_P``.
    """

    dof: int = 3
    n_actuators: int = 3
    pose_kind: str = 'spherical'
    #: capacity axes: the moment of :meth:`wrench`, in the platform frame {P}
    wrench_axes = ('Mx', 'My', 'Mz')
    wrench_units = ('N·m', 'N·m', 'N·m')
    #: a forward solution must close every leg to this (|w_i . v_i - cos alpha2_i|)
    verify_tol: float = 1e-9
    _measure_name = 'k(J)'

    def __init__(self, gamma: float, beta: float, alpha1: Sequence[float], alpha2: Sequence[float],
                 delta: Sequence[float], *, working_mode: str | int = '+++',
                 joint_limits: tuple[Any, Any] = (-math.pi, math.pi),
                 actuator_names: Sequence[str] = ('m1', 'm2', 'm3'),
                 home_pose: Sequence[float] | None = None,
                 singularity_condition_max: float = 100.0,
                 load_forces: Sequence[float] = (15.0, 5.0, 5.0),
                 load_lever_arms: Sequence[float] = (0.15, 0.30, 0.30)) -> None:
        try:
            self.gamma, self.beta = float(gamma), float(beta)
        except (TypeError, ValueError) as exc:
            raise ValueError(f'gamma, beta: expected angles in rad, got {gamma!r}, {beta!r}') from exc
        for name, val in (('gamma', self.gamma), ('beta', self.beta)):
            if not (0.0 < val < math.pi):
                raise ValueError(f'{name}: expected a cone half-angle in (0, pi) rad, got {val!r}')
        self.alpha1 = as_per_actuator(alpha1, 3, 'alpha1', unit='rad')
        self.alpha2 = as_per_actuator(alpha2, 3, 'alpha2', unit='rad')
        self.delta = as_per_actuator(delta, 3, 'delta', unit='rad')
        for name, arr in (('alpha1', self.alpha1), ('alpha2', self.alpha2)):
            if np.any(arr <= 0.0) or np.any(arr >= math.pi):
                raise ValueError(f'{name}: link angles must lie in (0, pi) rad, got {arr.tolist()}')
        self.working_mode, self._signs = _parse_mode(working_mode)
        self._lo, self._hi = as_range(joint_limits, 3, 'joint_limits', unit='rad', max_turn_tol=1e-9)
        self.actuator_names: tuple[str, ...] = as_actuator_names(actuator_names, 3)
        self.singularity_condition_max = as_condition_max(singularity_condition_max)
        n_loads = len(load_forces) if isinstance(load_forces, (list, tuple, np.ndarray)) else -1
        self.load_forces = as_vector(load_forces, n_loads, 'load_forces')
        self.load_lever_arms = as_vector(load_lever_arms, n_loads, 'load_lever_arms')
        self._u, self._e1, self._e2, self._vp = leg_geometry(self.gamma, self.beta, self.delta)
        if abs(np.linalg.det(self._vp)) < 1e-9:
            raise ValueError('beta = 90 deg with these azimuths puts the platform axes in one plane: '
                             'the platform orientation is not determined by them')
        self._prepare_forward()
        self._home = np.zeros(3) if home_pose is None else as_vector(home_pose, 3, 'home_pose')
        self.inverse(self._home)          # UnreachablePose (a ValueError) when out of reach / limits
        self.check_singularity(self._home)

    # ------------------------------------------------------------------ properties
    # actuator_limits (motor angles, rad) and home_pose (abduction, flexion_extension,
    # rotation; rad): MechanismBase
    @property
    def design(self) -> dict[str, Any]:
        """The 11 design parameters (rad)."""
        return {'gamma': self.gamma, 'beta': self.beta, 'alpha1': self.alpha1.copy(),
                'alpha2': self.alpha2.copy(), 'delta': self.delta.copy()}

    def __repr__(self) -> str:
        deg = np.degrees
        return (f'Spherical3Rrr(gamma={math.degrees(self.gamma):.5f} deg, beta={math.degrees(self.beta):.5f} deg, '
                f'alpha1={deg(self.alpha1).round(5).tolist()} deg, alpha2={deg(self.alpha2).round(5).tolist()} deg, '
                f'delta={deg(self.delta).round(4).tolist()} deg, working_mode={self.working_mode!r})')

    # ------------------------------------------------------------------ orientation conversions
    @staticmethod
    def rotation_matrix(pose: Sequence[float]) -> np.ndarray:
        """``Q`` ({P} -> {B}) of a pose (module docstring: intrinsic Y-X-Z with signs)."""
        return rotation_matrices(as_vector(pose, 3, 'pose')[None])[0]

    @staticmethod
    def pose_from_matrix(q: np.ndarray) -> np.ndarray:
        """Motion angles (rad) of a rotation matrix."""
        m = np.asarray(q, dtype=float)
        if m.shape != (3, 3) or not np.all(np.isfinite(m)):
            raise ValueError(f'expected a finite 3x3 rotation matrix, got shape {m.shape}')
        if np.max(np.abs(m.T @ m - np.eye(3))) > 1e-6 or np.linalg.det(m) < 0.0:
            raise ValueError('not a rotation matrix (Q^T Q != I or det Q < 0)')
        return pose_from_matrix(m)

    @staticmethod
    def quaternion_from_pose(pose: Sequence[float]) -> np.ndarray:
        """Unit quaternion ``(x, y, z, w)`` of ``Q`` (``w >= 0``), as in geometry_msgs."""
        m = Spherical3Rrr.rotation_matrix(pose)
        tr = m[0, 0] + m[1, 1] + m[2, 2]
        # Shepperd: pick the largest of 4w^2, 4x^2, 4y^2, 4z^2
        cand = np.array([tr, m[0, 0], m[1, 1], m[2, 2]])
        i = int(np.argmax(cand))
        if i == 0:
            s = 2.0 * math.sqrt(max(1.0 + tr, 0.0))
            q = np.array([(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, s / 4])
        elif i == 1:
            s = 2.0 * math.sqrt(max(1.0 + m[0, 0] - m[1, 1] - m[2, 2], 0.0))
            q = np.array([s / 4, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s])
        elif i == 2:
            s = 2.0 * math.sqrt(max(1.0 + m[1, 1] - m[0, 0] - m[2, 2], 0.0))
            q = np.array([(m[0, 1] + m[1, 0]) / s, s / 4, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s])
        else:
            s = 2.0 * math.sqrt(max(1.0 + m[2, 2] - m[0, 0] - m[1, 1], 0.0))
            q = np.array([(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, s / 4, (m[1, 0] - m[0, 1]) / s])
        q /= np.linalg.norm(q)
        return -q if q[3] < 0.0 else q

    @staticmethod
    def pose_from_quaternion(quat: Sequence[float]) -> np.ndarray:
        """Motion angles (rad) of a unit quaternion ``(x, y, z, w)``.

        :raises ValueError: not 4 finite numbers, or a norm off 1 by more than 1e-6.
        """
        x, y, z, w = as_vector(quat, 4, 'quaternion')
        n = math.sqrt(x * x + y * y + z * z + w * w)
        if abs(n - 1.0) > 1e-6:
            raise ValueError(f'quaternion: norm {n:.9f}, expected a unit quaternion (x, y, z, w)')
        x, y, z, w = x / n, y / n, z / n, w / n
        m = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                      [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                      [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
        return pose_from_matrix(m)

    # ------------------------------------------------------------------ inverse kinematics
    def platform_axes(self, pose: Sequence[float]) -> np.ndarray:
        """``v_i = Q v_i^P`` in {B}, rows = legs (3, 3)."""
        return self._vp @ self.rotation_matrix(pose).T

    def ik_quadratic(self, pose: Sequence[float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The slides' ``A T^2 + B T + C = 0`` (``T = tan(th_i / 2)``) per leg: arrays ``A, B, C`` (3,)."""
        v = self.platform_axes(pose)
        a, b, c = _closure_terms(self._u, self._e1, self._e2, self.alpha1, self.alpha2, v)
        return -(a + c), 2.0 * b, a - c

    def _wrap(self, theta: np.ndarray) -> np.ndarray:
        """Angles into ``[lo, lo + 2 pi)`` per motor (continuous over the joint range)."""
        return self._lo + np.mod(theta - self._lo, _TWO_PI)

    def _leg_reach_error(self, pose: np.ndarray, v: np.ndarray, bad: np.ndarray) -> UnreachablePose:
        i = int(np.flatnonzero(bad)[0])
        ang = math.degrees(math.acos(max(-1.0, min(1.0, float(self._u[i] @ v[i])))))
        a1, a2 = math.degrees(self.alpha1[i]), math.degrees(self.alpha2[i])
        lo, hi = abs(a1 - a2), min(a1 + a2, 360.0 - a1 - a2)
        name = self.actuator_names[i]
        return UnreachablePose(
            f'leg {name} cannot close at pose (abduction {math.degrees(pose[0]):.2f}, flexion-extension '
            f'{math.degrees(pose[1]):.2f}, rotation {math.degrees(pose[2]):.2f}) deg: its base and platform '
            f'axes would be {ang:.2f} deg apart, links alpha1 = {a1:.2f} and alpha2 = {a2:.2f} deg span '
            f'{lo:.2f}-{hi:.2f} deg', actuator=name, value=math.radians(ang),
            limits=(math.radians(lo), math.radians(hi)))

    def inverse_all(self, pose: Sequence[float]) -> np.ndarray:
        """Motor angles of all 8 working modes, (8, 3) rad, rows in :data:`WORKING_MODES` order.

        No joint-limit check. :raises UnreachablePose: a leg cannot close (naming it).
        """
        p = as_vector(pose, 3, 'pose')
        signs = np.array([[1.0 if ch == '+' else -1.0 for ch in m] for m in WORKING_MODES])
        reach, theta, _, v = inverse_batch(self.gamma, self.beta, self.alpha1, self.alpha2, self.delta,
                                           rotation_matrices(p[None]), signs)
        if not reach[0]:
            raise self._leg_reach_error(p, v[0], ~np.isfinite(theta[0, 0]))
        return self._wrap(theta[:, 0, :])

    def inverse(self, pose: Sequence[float]) -> np.ndarray:
        """Motor angles ``th_1..3`` (rad) of the configured working mode.

        :raises ValueError: non-finite or wrong-shape pose.
        :raises UnreachablePose: a leg cannot close (naming the motor and the angles), or a
            motor angle outside its joint range.
        """
        p = as_vector(pose, 3, 'pose')
        reach, theta, _, v = inverse_batch(self.gamma, self.beta, self.alpha1, self.alpha2, self.delta,
                                           rotation_matrices(p[None]), self._signs)
        if not reach[0]:
            raise self._leg_reach_error(p, v[0], ~np.isfinite(theta[0]))
        q = self._wrap(theta[0])
        check_limits(q, self._lo, self._hi, self.actuator_names, unit='rad')
        return q

    def inverse_poses(self, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Vectorised inverse: ``(reach (N,), theta (N, 3))`` for poses (N, 3) (NaN where out of reach).

        No joint-limit check (compare with :attr:`actuator_limits`).
        """
        p = np.asarray(poses, dtype=float)
        if p.ndim != 2 or p.shape[1] != 3 or not np.all(np.isfinite(p)):
            raise ValueError(f'poses: expected a finite (N, 3) array, got shape {p.shape}')
        reach, theta, _, _ = inverse_batch(self.gamma, self.beta, self.alpha1, self.alpha2, self.delta,
                                           rotation_matrices(p), self._signs)
        return reach, self._wrap(theta)

    def inverse_batch(self, poses: np.ndarray, *, limits: bool = True) -> np.ndarray:
        """Vectorised :meth:`inverse`: motor angles (N, 3) (rad, in ``[lo, lo + 2 pi)``) for
        poses (N, 3) (rad), in the configured working mode.

        A NaN row where a leg cannot close or (with ``limits``) a motor angle is outside its
        range — where :meth:`inverse` raises :class:`~.base.UnreachablePose`.

        :param limits: ``False``: no joint-limit check (as :meth:`inverse_poses`).
        :raises ValueError: not an (N, 3) array, or a non-finite value.
        """
        p = as_poses(poses, 3)
        reach, theta, _, _ = inverse_batch(self.gamma, self.beta, self.alpha1, self.alpha2, self.delta,
                                           rotation_matrices(p), self._signs)
        q = self._wrap(theta)
        bad = ~reach
        if limits:
            bad |= ~within_limits(q, self._lo, self._hi)
        q[bad] = np.nan
        return q

    def _velocity_batch(self, p: np.ndarray, limits: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``Jx`` (N, 3, 3), ``diag(Kq)`` (N, 3) at validated poses and the reachable mask."""
        reach, theta, w, v = inverse_batch(self.gamma, self.beta, self.alpha1, self.alpha2, self.delta,
                                           rotation_matrices(p), self._signs)
        if limits:
            reach = reach & within_limits(self._wrap(theta), self._lo, self._hi)
        jx, kq = velocity_batch(self._u, w, v)
        return jx, kq, reach

    def jacobian_batch(self, poses: np.ndarray, *, limits: bool = True) -> np.ndarray:
        """Vectorised :meth:`jacobian`: ``Kq^-1 Jx E(pose)`` (N, 3, 3).

        A NaN matrix where :meth:`inverse_batch` has a NaN row; non-finite rows at a serial
        singularity (``Kq_ii = 0``, where :meth:`angular_jacobian` raises ``SingularPose``).
        """
        p = as_poses(poses, 3)
        jx, kq, reach = self._velocity_batch(p, limits)
        with np.errstate(divide='ignore', invalid='ignore'):
            jac = (jx / np.where(np.abs(kq) < 1e-12, 0.0, kq)[..., None]) @ euler_rate_matrix(p)
        jac[~reach] = np.nan
        return jac

    def _statics_batch(self, p: np.ndarray) -> Statics:
        """:meth:`wrench` in {P}: ``W_P = Q^T Jx^T Kq^-1 tau``, so ``G = Q^T (Kq^-1 Jx)^T`` and
        ``H = Kq Jx^-T Q`` (finite at a serial singularity; regular where ``Jx`` is)."""
        jx, kq, reach = self._velocity_batch(p, True)
        qm = rotation_matrices(p)
        with np.errstate(divide='ignore', invalid='ignore'):
            g = np.swapaxes(qm, -1, -2) @ np.swapaxes(jx / np.where(np.abs(kq) < 1e-12, 0.0, kq)[..., None], -1, -2)
        g[~reach] = np.nan
        jx_inv_t, regular = regular_inverse(np.swapaxes(jx, -1, -2))
        return Statics(reach, g, kq[..., None] * (jx_inv_t @ qm), regular & reach, np.zeros((p.shape[0], 3)))

    # ------------------------------------------------------------------ differential kinematics
    def elbow_axes(self, q: Sequence[float]) -> np.ndarray:
        """``w_i`` (rows) for motor angles ``q`` (rad)."""
        th = as_vector(q, 3, 'q')
        ca, sa = np.cos(self.alpha1)[:, None], np.sin(self.alpha1)[:, None]
        return ca * self._u + sa * (np.cos(th)[:, None] * self._e1 + np.sin(th)[:, None] * self._e2)

    def velocity_matrices(self, pose: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
        """``(Jx, Kq)`` (3, 3) each at ``pose`` in the working mode: ``Kq q_dot = Jx omega``.

        :raises UnreachablePose: out of reach (no Jacobian there).
        """
        p = as_vector(pose, 3, 'pose')
        reach, theta, w, v = inverse_batch(self.gamma, self.beta, self.alpha1, self.alpha2, self.delta,
                                           rotation_matrices(p[None]), self._signs)
        if not reach[0]:
            raise self._leg_reach_error(p, v[0], ~np.isfinite(theta[0]))
        jx, kq = velocity_batch(self._u, w[0], v[0])
        return jx, np.diag(kq)

    def angular_jacobian(self, pose: Sequence[float]) -> np.ndarray:
        """``Kq^-1 Jx`` (3, 3): ``q_dot = J omega`` (``omega`` rad/s in {B}).

        :raises SingularPose: a serial singularity (``Kq_ii = 0``).
        """
        jx, kq = self.velocity_matrices(pose)
        d = np.diag(kq)
        if np.any(np.abs(d) < 1e-12):
            i = int(np.argmin(np.abs(d)))
            raise SingularPose(f'serial singularity: leg {self.actuator_names[i]} is stretched or folded '
                               f'(u, w, v coplanar, Kq = {d[i]:.2e})', actuator=self.actuator_names[i])
        return jx / d[:, None]

    def jacobian(self, pose: Sequence[float]) -> np.ndarray:
        """``J`` (3, 3) with ``q_dot = J @ pose_dot``: ``Kq^-1 Jx E(pose)`` (``omega = E pose_dot``).

        Rank-deficient at the gimbal lock (flexion-extension = +-90 deg) of the motion
        angles; :meth:`angular_jacobian` is the mechanism's own.
        """
        p = as_vector(pose, 3, 'pose')
        return self.angular_jacobian(p) @ euler_rate_matrix(p)

    def dexterity(self, pose: Sequence[float]) -> float:
        """``k(J) = ||Kq^-1 Jx||_2 ||Jx^-1 Kq||_2`` (>= 1; ``inf`` at a singularity)."""
        jx, kq = self.velocity_matrices(pose)
        d = np.diag(kq)
        if np.any(np.abs(d) < 1e-300):
            return math.inf
        sv = np.linalg.svd(jx / d[:, None], compute_uv=False)
        return float(sv[0] / sv[-1]) if sv[-1] > 0.0 else math.inf

    def singularity(self, pose: Sequence[float], *, tol: float = 1e-6) -> list[str]:
        """Which singularities ``pose`` is at (within ``tol``): ``'serial:<motor>'``, ``'parallel'``."""
        jx, kq = self.velocity_matrices(pose)
        out = [f'serial:{n}' for n, k in zip(self.actuator_names, np.diag(kq)) if abs(k) < tol]
        if abs(np.linalg.det(jx)) < tol:
            out.append('parallel')
        return out

    def _singularity_measure(self, pose: Sequence[float], **branch: Any) -> float:
        return self.dexterity(pose)

    def _pose_text(self, pose: Sequence[float]) -> str:
        p = np.degrees(as_vector(pose, 3, 'pose'))
        return f'pose ({p[0]:.2f}, {p[1]:.2f}, {p[2]:.2f}) deg'

    def check_singularity(self, pose: Sequence[float]) -> None:
        """Raise :class:`~.base.SingularPose` when ``k(J) > singularity_condition_max``."""
        self._check_singularity(pose)

    def in_workspace(self, pose: Sequence[float]) -> bool:
        """Reachable in the working mode, within the joint limits, ``k(J) <= singularity_condition_max``.

        :raises ValueError: malformed pose (never a quiet ``False``).
        """
        return self._in_workspace(pose)

    # ------------------------------------------------------------------ statics
    def load_moment(self, pose: Sequence[float]) -> np.ndarray:
        """Moment (N·m, in {B}) of the arm's weights about ``O``: ``sum F_k l_k (Q z) x z``.

        Gravity is ``+z_B`` (the arm hangs along it at the neutral pose), weight ``k`` sits
        at ``l_k`` along the arm axis ``z_P``.
        """
        m = self.rotation_matrix(pose)
        arm = m[:, 2]
        return float(self.load_forces @ self.load_lever_arms) * _cross(arm, np.array([0.0, 0.0, 1.0]))

    def joint_torques(self, pose: Sequence[float], moment: Sequence[float] | None = None) -> np.ndarray:
        """Motor torques (N·m) that hold the external moment ``moment`` (N·m, {B}; default: :meth:`load_moment`).

        ``tau = -(Jx^-1 Kq)^T M`` (the slides' ``tau = J^T F``).
        """
        p = as_vector(pose, 3, 'pose')
        mom = self.load_moment(p) if moment is None else as_vector(moment, 3, 'moment')
        jac = self.angular_jacobian(p)
        return -np.linalg.solve(jac.T, mom)

    def wrench(self, pose: Sequence[float], forces: Sequence[float]) -> np.ndarray:
        """Moment (N·m) the motors apply to the platform, in the platform frame {P}.

        ``M_B = (Kq^-1 Jx)^T tau`` (virtual work), returned as ``Q^T M_B`` because the
        kinetics node publishes it in ``platform_frame`` without converting.

        :param forces: motor torques ``tau_1..3`` (N·m), positive right-handed about ``u_i``.
        """
        tau = as_vector(forces, 3, 'forces')
        p = as_vector(pose, 3, 'pose')
        return self.rotation_matrix(p).T @ (self.angular_jacobian(p).T @ tau)

    # ------------------------------------------------------------------ forward kinematics
    def _prepare_forward(self) -> None:
        vp = self._vp
        self._c12 = float(vp[0] @ vp[1])
        basis = np.column_stack([vp[0], vp[1], _cross(vp[0], vp[1])])
        self._abc = np.linalg.solve(basis, vp[2])        # v3^P = a v1^P + b v2^P + c v1^P x v2^P
        self._ca2 = np.cos(self.alpha2)
        self._sa2 = np.sin(self.alpha2)
        # T[i] = coefficients of x^i in (1 - x^2, 2x, 1 + x^2)
        self._T = np.array([[1.0, 0.0, 1.0], [0.0, 2.0, 0.0], [-1.0, 0.0, 1.0]])
        self._fp_t = self._frame(vp[None, 0], vp[None, 1])[0].T

    @staticmethod
    def _cone_basis(w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """An orthonormal pair normal to ``w`` (fixed, generic reference direction)."""
        ref = np.array([0.5773502691896258, -0.2672612419124244, 0.7715167498104596])
        a = _cross(w, ref)
        n = np.linalg.norm(a)
        if n < 0.2:
            a = _cross(w, np.array([0.8, 0.6, 0.0]))
            n = np.linalg.norm(a)
        a /= n
        return a, _cross(w, a)

    def forward_matrices(self, q: Sequence[float]) -> list[np.ndarray]:
        """Every real assembly mode for motor angles ``q`` (rad), as rotation matrices ``Q``."""
        th = as_vector(q, 3, 'q')
        w = self.elbow_axes(th)
        a1, b1 = self._cone_basis(w[0])
        a2, b2 = self._cone_basis(w[1])
        s0, s1 = self._sa2[0], self._sa2[1]
        v1m = np.column_stack([s0 * a1, s0 * b1, self._ca2[0] * w[0]])    # v1 = V1 (c1, s1, 1)
        v2m = np.column_stack([s1 * a2, s1 * b2, self._ca2[1] * w[1]])
        ka, kb, kc = self._abc
        w3 = w[2]
        m1 = v1m.T @ v2m
        m1[2, 2] -= self._c12
        cross_w3 = _cross(v2m.T, w3)                      # rows: V2[:, k] x w3
        m2 = kc * (v1m.T @ cross_w3.T)                      # (V1[:, j] x V2[:, k]) . w3 = V1[:, j] . (V2[:, k] x w3)
        m2[:, 2] += ka * (v1m.T @ w3)
        m2[2, :] += kb * (v2m.T @ w3)
        m2[2, 2] -= self._ca2[2]
        T = self._T
        cp = T @ m1 @ T.T            # cp[i, j]: coefficient of x1^i x2^j
        cq = T @ m2 @ T.T
        p0, p1, p2 = cp[:, 0], cp[:, 1], cp[:, 2]           # ascending in x1
        q0, q1, q2 = cq[:, 0], cq[:, 1], cq[:, 2]
        cv = np.convolve
        e20 = cv(p2, q0) - cv(p0, q2)
        e21 = cv(p2, q1) - cv(p1, q2)
        e10 = cv(p1, q0) - cv(p0, q1)
        res = cv(e20, e20) - cv(e21, e10)                   # degree 8, ascending
        scale = float(np.max(np.abs(res)))
        ref = float(np.max(np.abs(cp))) * float(np.max(np.abs(cq)))
        if scale <= 1e-13 * ref * ref:
            raise SingularPose(f'motor angles {th.tolist()} rad leave the platform a self-motion '
                               '(the resultant vanishes identically)')
        t1_list: list[float] = []
        coeffs = res[::-1]
        if abs(coeffs[0]) <= 1e-10 * scale:
            t1_list.append(math.pi)                          # root at x1 = infinity
        nz = np.flatnonzero(np.abs(coeffs) > 1e-14 * scale)
        roots = np.roots(coeffs[nz[0]:]) if nz.size else np.zeros(0)
        real = roots[np.abs(roots.imag) <= 1e-5 * (1.0 + np.abs(roots))].real
        t1_list.extend((2.0 * np.arctan(real)).tolist())
        if not t1_list:
            return []
        t1 = np.array(t1_list)
        # x2 from eliminating x2^2: (p2 q1 - p1 q2) x2 = (p0 q2 - p2 q0)
        x1 = np.tan(0.5 * t1)
        big = np.abs(x1) > 1e8
        pw = np.vander(np.where(big, 0.0, x1), 3, increasing=True)         # 1, x1, x1^2
        pv = pw @ cp
        qv = pw @ cq
        if np.any(big):          # at x1 = inf the leading (x1^2) coefficients are what is left
            pv[big] = cp[2]
            qv[big] = cq[2]
        num = pv[:, 0] * qv[:, 2] - pv[:, 2] * qv[:, 0]
        den = pv[:, 2] * qv[:, 1] - pv[:, 1] * qv[:, 2]
        cand_t1: list[float] = []
        cand_t2: list[float] = []
        for j in range(t1.size):
            if abs(den[j]) > 1e-9 * (abs(num[j]) + 1e-300) and abs(den[j]) > 1e-12 * ref:
                cand_t1.append(float(t1[j]))
                cand_t2.append(2.0 * math.atan(num[j] / den[j]))
            else:
                # degenerate elimination: both roots of p (and x2 = inf) are candidates
                for poly in (pv[j], qv[j]):
                    for r in np.roots(poly[::-1]) if np.any(poly[1:] != 0) else []:
                        if abs(r.imag) <= 1e-5 * (1.0 + abs(r)):
                            cand_t1.append(float(t1[j]))
                            cand_t2.append(2.0 * math.atan(r.real))
                cand_t1.append(float(t1[j]))
                cand_t2.append(math.pi)
        t = np.column_stack([cand_t1, cand_t2])
        t = self._polish(t, v1m, v2m, w3)
        return self._finish(t, v1m, v2m, w)

    def _residual_t(self, t, v1m, v2m, w3):
        c1, s1 = np.cos(t[:, 0:1]), np.sin(t[:, 0:1])
        c2, s2 = np.cos(t[:, 1:2]), np.sin(t[:, 1:2])
        a1, b1, w1 = v1m[:, 0], v1m[:, 1], v1m[:, 2]
        a2, b2, w2 = v2m[:, 0], v2m[:, 1], v2m[:, 2]
        v1 = c1 * a1 + s1 * b1 + w1
        v2 = c2 * a2 + s2 * b2 + w2
        dv1 = c1 * b1 - s1 * a1
        dv2 = c2 * b2 - s2 * a2
        ka, kb, kc = self._abc
        f1 = np.einsum('ij,ij->i', v1, v2) - self._c12
        v3 = ka * v1 + kb * v2 + kc * _cross(v1, v2)
        f2 = v3 @ w3 - self._ca2[2]
        j11 = np.einsum('ij,ij->i', dv1, v2)
        j12 = np.einsum('ij,ij->i', v1, dv2)
        j21 = (ka * dv1 + kc * _cross(dv1, v2)) @ w3
        j22 = (kb * dv2 + kc * _cross(v1, dv2)) @ w3
        return f1, f2, j11, j12, j21, j22

    def _polish(self, t: np.ndarray, v1m, v2m, w3, iters: int = 6) -> np.ndarray:
        t = t.copy()
        for _ in range(iters):
            f1, f2, j11, j12, j21, j22 = self._residual_t(t, v1m, v2m, w3)
            if np.max(np.abs(f1) + np.abs(f2)) < 1e-15:
                break
            det = j11 * j22 - j12 * j21
            ok = np.abs(det) > 1e-14
            safe = np.where(ok, det, 1.0)
            d1 = np.where(ok, (j22 * f1 - j12 * f2) / safe, 0.0)
            d2 = np.where(ok, (-j21 * f1 + j11 * f2) / safe, 0.0)
            t[:, 0] -= np.clip(d1, -0.5, 0.5)
            t[:, 1] -= np.clip(d2, -0.5, 0.5)
        return t

    def _finish(self, t: np.ndarray, v1m, v2m, w: np.ndarray) -> list[np.ndarray]:
        c1, s1 = np.cos(t[:, 0:1]), np.sin(t[:, 0:1])
        c2, s2 = np.cos(t[:, 1:2]), np.sin(t[:, 1:2])
        v1 = c1 * v1m[:, 0] + s1 * v1m[:, 1] + v1m[:, 2]
        v2 = c2 * v2m[:, 0] + s2 * v2m[:, 1] + v2m[:, 2]
        # Q from two vectors: orthonormal frames (f1 = v1, f2 = v2's part normal to v1)
        fb = self._frame(v1, v2)
        vp = self._vp
        qs = fb @ self._fp_t
        resid = np.abs(np.einsum('nij,kj,ki->nk', qs, vp, w) - self._ca2)
        good = np.max(resid, axis=1) <= self.verify_tol
        out: list[np.ndarray] = []
        for m in qs[good]:
            for o in out:
                if float(np.abs(m - o).max()) < 1e-7:
                    break
            else:
                out.append(m)
        return out

    @staticmethod
    def _frame(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        f1 = a / np.linalg.norm(a, axis=1)[:, None]
        f2 = b - np.einsum('ij,ij->i', b, f1)[:, None] * f1
        f2 /= np.linalg.norm(f2, axis=1)[:, None]
        return np.stack([f1, f2, _cross(f1, f2)], axis=-1)    # columns f1, f2, f3

    def forward(self, q: Sequence[float]) -> list[np.ndarray]:
        """Every real assembly mode for motor angles ``q`` (rad), as motion angles (rad).

        :returns: poses sorted by abduction (then the other angles); ``[]`` when the legs
            cannot close; at most 8. Each closes all three legs to :attr:`verify_tol`.
        :raises ValueError: malformed ``q``.
        :raises SingularPose: a self-motion (infinitely many modes).
        """
        out = [pose_from_matrix(m) for m in self.forward_matrices(q)]
        out.sort(key=lambda p: (p[0], p[1], p[2]))
        return out

    def forward_nearest(self, q: Sequence[float], hint_pose: Sequence[float]) -> np.ndarray:
        """The assembly mode with the smallest rotation angle from ``hint_pose`` (tracking).

        :raises UnreachablePose: no assembly mode for ``q``.
        """
        hint = self.rotation_matrix(as_vector(hint_pose, 3, 'hint_pose'))
        mats = self.forward_matrices(q)
        if not mats:
            raise UnreachablePose('no assembly mode: the legs cannot close with motor angles '
                                  + ', '.join(f'{n}={math.degrees(v):.3f} deg'
                                              for n, v in zip(self.actuator_names, np.asarray(q, float))))
        best = max(mats, key=lambda m: float(np.trace(hint.T @ m)))    # largest trace = smallest angle
        return pose_from_matrix(best)

    # ------------------------------------------------------------------ configuration
    @classmethod
    def from_config(cls, section: Mapping[str, Any]) -> 'Spherical3Rrr':
        """Build from the YAML's ``mechanism`` section (angles in rad).

        Reads ``gamma``, ``beta``, ``alpha1``, ``alpha2``, ``delta``, ``working_mode``,
        ``joint_min``, ``joint_max``, ``actuator_names``, ``home_pose``,
        ``singularity_condition_max``, ``load_forces``, ``load_lever_arms``.

        :raises ConfigError: a missing or malformed value, naming the parameter.
        """
        check_section(section, 'spherical_3rrr', 'Spherical3Rrr', ('gamma', 'beta', 'alpha1', 'alpha2', 'delta'))
        kwargs = section_kwargs(section, given=('working_mode', 'actuator_names', 'home_pose',
                                                'singularity_condition_max', 'load_forces', 'load_lever_arms'))
        if 'joint_min' in section or 'joint_max' in section:
            kwargs['joint_limits'] = (section.get('joint_min', -math.pi), section.get('joint_max', math.pi))
        with config_errors():
            return cls(section['gamma'], section['beta'], section['alpha1'], section['alpha2'],
                       section['delta'], **kwargs)
