"""Planar 3-RRR parallel mechanism: the neck-brace report's "Planar 3RRR" (seed 000).

Leg ``i``: an actuated revolute joint at the base pivot ``B_i`` (motor angle ``theta_i``,
rad, from the base x axis), a proximal link of length ``r_i`` to the elbow
``M_i = B_i + r_i (cos theta_i, sin theta_i)`` (report's ``M_n``), a passive elbow joint,
a distal link of length ``l_i`` to the platform joint ``A_i = P + R(phi) a_i`` (``a_i`` in
the platform frame; pose ``(x, y, phi)`` as in every planar mechanism here). The
report's equilateral platform of side ``d`` with the end effector at its centroid is one
configuration: ``a_i`` on a circle of radius ``d / sqrt(3)`` (see ``config/neck_brace_3rrr.yaml``).

Inverse kinematics (2^3 working modes)
--------------------------------------
Each leg is a 2R arm from ``B_i`` to ``A_i`` (report's ``alpha_n``, ``theta_n``)::

    cos(alpha_i) = (|A_i - B_i|^2 - r_i^2 - l_i^2) / (2 r_i l_i)
    alpha_i = sigma_i acos(...),
    theta_i = atan2(A_i - B_i) - atan2(l_i sin alpha_i, r_i + l_i cos alpha_i)

``alpha_i`` is the elbow angle (distal link relative to proximal, counter-clockwise).
The working mode is ``sigma = (sigma_1, sigma_2, sigma_3)``, each ``+1`` or ``-1``:
``sigma_i = sign(u_i x w_i)`` with ``u_i`` the proximal direction and ``w_i = A_i - M_i``
(``+1``: the distal link turns counter-clockwise from the proximal one). Default from the
YAML (``working_mode``); a device cannot change it without passing a leg through a
stretched/folded (serial) singularity.

Forward kinematics (every assembly mode): with the motor angles fixed the elbows
``M_i`` are known points and the distal links fixed lengths ``l_i``: a 3-RPR with base
anchors ``M_i`` and leg lengths ``l_i``. :meth:`Rrr3.forward` builds that :class:`~.rpr3.Rpr3`
and calls its forward solution (the sextic: at most six assembly modes). No second solver.

Jacobian
--------
Differentiating ``|A_i - M_i|^2 = l_i^2``::

    w_i . p_dot + (rho_i x w_i) phi_dot = r_i (u_i x w_i) theta_i_dot,   rho_i = R(phi) a_i

i.e. ``A x_dot = D theta_dot`` with rows ``A_i = (w_i, rho_i x w_i)`` (m, m, m^2) and
``D = diag(r_i (u_i x w_i))`` (m^2). The protocol's ``J`` (``theta_dot = J x_dot``) is
``J = D^-1 A``; the report's ``J = A^-1 D`` is its inverse (``x_dot = J_report theta_dot``),
with the report's own (garbled) ``a_n..d_n`` entries. ``D_ii = 0`` (leg ``i`` stretched or
folded: serial singularity) -> ``J`` infinite, :class:`~.base.SingularPose`; ``A`` singular
(the three distal lines concurrent or parallel: parallel singularity) -> ``cond(J)`` large.

Statics: ``wrench(pose, torques) = J^T tau = A^T D^-1 tau`` (virtual work): the wrench
``(Fx N, Fy N, M N·m about P, counter-clockwise)`` the motors' torques ``tau_i`` (N·m,
counter-clockwise on the proximal link) apply to the platform with massless links. The
distal links are two-force members: leg ``i`` pushes the platform with
``f_i w_i / |w_i|``, ``f_i |w_i| r_i (u_i x w_i) / |w_i| = tau_i`` — the test's independent
``sum r x F``.

Report errata (noted here, not followed): ``G_6`` should use ``M_3``, not ``M_2``; the
height of the equilateral triangle is ``sqrt(d^2 - (d/2)^2)``, not ``sqrt(d^2 + (d/2)^2)``;
the printed ``alpha_n = +-cos(...)`` needs ``acos``; in the printed ``theta_n`` the
proximal and distal lengths are swapped relative to ``M_n = B_n + r_n (cos, sin)`` and
``(x_n, y_n)`` must be taken relative to ``B_n``; the tan-half-angle "eighth-degree"
polynomial has at most six real roots that are assembly modes (the degree-8 form carries
the extraneous ``(1 + T^2)`` factor).
"""
from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from .base import (MechanismBase, SingularPose, Statics, UnreachablePose, as_actuator_names, as_condition_max,
                   as_per_actuator, as_points, as_poses, as_range, as_vector, check_limits, check_section,
                   condition_number, config_errors, rot2, section_kwargs, section_points, within_limits)
from .capacity import regular_inverse
from .loader import register
from .planar import cross2, wrap_angle
from .rpr3 import Rpr3
from .rr2 import angle_into_range, angles_into_range

__all__ = ['Rrr3']

_WORKING_MODES = tuple((a, b, c) for a in (1, -1) for b in (1, -1) for c in (1, -1))


def _mode(value: Any) -> tuple[int, int, int]:
    try:
        mode = tuple(int(v) for v in value)
        ok = len(mode) == 3 and all(v in (1, -1) for v in mode) and all(float(v) == int(v) for v in value)
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise ValueError(f'working_mode: expected three signs (+1 or -1), got {value!r}')
    return mode  # type: ignore[return-value]


@register('rrr3')
class Rrr3(MechanismBase):
    """Planar 3-RRR parallel mechanism (general geometry).

    :param base_pivots: ``B_1..B_3`` (actuated joints), shape (3, 2) or flat (6,), m.
    :param proximal_lengths: ``r_i`` (m), a scalar or three values, > 0.
    :param distal_lengths: ``l_i`` (m), a scalar or three values, > 0.
    :param platform_anchors: ``a_1..a_3`` in the platform frame, shape (3, 2) or (6,), m.
    :param joint_range: ``(lo, hi)`` motor-angle range (rad), each a scalar or three values.
    :param working_mode: ``(sigma_1, sigma_2, sigma_3)``, each ``+1``/``-1`` (module docstring).
    :param actuator_names: three distinct names, in leg order.
    :param home_pose: rest pose ``(x, y, phi)``; default the centroid of the base pivots at
        ``phi = 0``.
    :param singularity_condition_max: ``cond(J)`` above this is treated as singular.
    :raises ValueError: malformed geometry, an unreachable home pose.
    """

    dof: int = 3
    pose_kind: str = 'planar'
    n_actuators: int = 3
    _angle_name = 'phi'

    def __init__(self, base_pivots: Sequence[Sequence[float]] | np.ndarray,
                 proximal_lengths: Any, distal_lengths: Any,
                 platform_anchors: Sequence[Sequence[float]] | np.ndarray,
                 joint_range: tuple[Any, Any] | Sequence[Any], *,
                 working_mode: Sequence[int] = (1, 1, 1),
                 actuator_names: Sequence[str] = ('m1', 'm2', 'm3'),
                 home_pose: Sequence[float] | None = None,
                 singularity_condition_max: float = 1e4) -> None:
        self.base_pivots = as_points(base_pivots, 3, 'base_pivots')
        self.platform_anchors = as_points(platform_anchors, 3, 'platform_anchors')
        self.proximal_lengths = as_per_actuator(proximal_lengths, 3, 'proximal_lengths', unit='m')
        self.distal_lengths = as_per_actuator(distal_lengths, 3, 'distal_lengths', unit='m')
        for name, arr in (('proximal_lengths', self.proximal_lengths), ('distal_lengths', self.distal_lengths)):
            if np.any(arr <= 0.0):
                raise ValueError(f'{name}: every link length must be > 0 m, got {arr.tolist()}')
        self._lo, self._hi = as_range(joint_range, 3, 'joint_range', unit='rad', max_turn_tol=1e-12)
        self.working_mode = _mode(working_mode)
        self.actuator_names: tuple[str, ...] = as_actuator_names(actuator_names, 3)
        self.singularity_condition_max = as_condition_max(singularity_condition_max)
        b = self.platform_anchors
        self._platform_size = max(float(np.max(np.linalg.norm(b - b.mean(axis=0), axis=1))), 1e-3)
        self._scale = float(max(np.max(self.proximal_lengths), np.max(self.distal_lengths), 1e-3))
        if home_pose is None:
            cx, cy = self.base_pivots.mean(axis=0)
            home_pose = (float(cx), float(cy), 0.0)
        self._home = as_vector(home_pose, 3, 'home_pose')
        self._home[2] = wrap_angle(float(self._home[2]))
        self.inverse(self._home)     # raises UnreachablePose (a ValueError) when unreachable

    # ------------------------------------------------------------------ properties
    # actuator_limits (motor angles, rad) and home_pose (x, y, phi): MechanismBase
    @staticmethod
    def working_modes() -> tuple[tuple[int, int, int], ...]:
        """The eight working modes ``(sigma_1, sigma_2, sigma_3)``."""
        return _WORKING_MODES

    def __repr__(self) -> str:
        return (f'Rrr3(base_pivots={self.base_pivots.tolist()}, proximal_lengths={self.proximal_lengths.tolist()}, '
                f'distal_lengths={self.distal_lengths.tolist()}, platform_anchors={self.platform_anchors.tolist()}, '
                f'working_mode={self.working_mode})')

    # ------------------------------------------------------------------ helpers
    def _mode_of(self, working_mode: Sequence[int] | None) -> tuple[int, int, int]:
        return self.working_mode if working_mode is None else _mode(working_mode)

    def platform_joints(self, pose: Sequence[float]) -> np.ndarray:
        """``A_i = P + R(phi) a_i`` (3, 2), m."""
        p = as_vector(pose, 3, 'pose')
        return p[:2] + self.platform_anchors @ rot2(p[2]).T

    def elbows(self, q: Sequence[float]) -> np.ndarray:
        """``M_i = B_i + r_i (cos theta_i, sin theta_i)`` (3, 2), m, for motor angles ``q`` (rad)."""
        t = as_vector(q, 3, 'q')
        return self.base_pivots + self.proximal_lengths[:, None] * np.column_stack([np.cos(t), np.sin(t)])

    def _angles(self, p: np.ndarray, mode: tuple[int, int, int]) -> np.ndarray:
        """Motor angles (wrapped, no range check); raises when a leg cannot close."""
        a_pts = p[:2] + self.platform_anchors @ rot2(p[2]).T
        out = np.empty(3)
        for i in range(3):
            dx, dy = a_pts[i] - self.base_pivots[i]
            dist = math.hypot(dx, dy)
            r, l = float(self.proximal_lengths[i]), float(self.distal_lengths[i])
            lo, hi = abs(r - l), r + l
            tol = 1e-12 * hi
            if not (lo - tol <= dist <= hi + tol):
                name = self.actuator_names[i]
                raise UnreachablePose(
                    f'leg of {name} cannot close: its platform joint is {dist:.4f} m from the base pivot, '
                    f'the leg (r = {r:.4f} m, l = {l:.4f} m) reaches {lo:.4f}–{hi:.4f} m',
                    actuator=name, value=dist, limits=(lo, hi))
            if dist <= tol:
                raise SingularPose(f'leg of {self.actuator_names[i]}: the platform joint is on the base pivot '
                                   '(r = l): the motor angle is undefined')
            c = min(1.0, max(-1.0, (dist * dist - r * r - l * l) / (2.0 * r * l)))
            alpha = mode[i] * math.acos(c)
            out[i] = wrap_angle(math.atan2(dy, dx) - math.atan2(l * math.sin(alpha), r + l * math.cos(alpha)))
        return out

    # ------------------------------------------------------------------ inverse kinematics
    def inverse(self, pose: Sequence[float], *, working_mode: Sequence[int] | None = None) -> np.ndarray:
        """Motor angles ``theta_1..3`` (rad) for ``pose = (x, y, phi)`` in a working mode.

        :param working_mode: three signs; default the configured one.
        :returns: angles moved by whole turns into the joint ranges where possible.
        :raises ValueError: malformed ``pose`` / ``working_mode``.
        :raises UnreachablePose: a leg that cannot close (``actuator`` = that leg's motor,
            ``value`` the pivot-to-platform-joint distance in m, ``limits`` the leg's reach in
            m) or a motor angle outside its range (naming it, in rad).
        """
        p = as_vector(pose, 3, 'pose')
        t = self._angles(p, self._mode_of(working_mode))
        q = np.array([angle_into_range(float(t[i]), self._lo[i], self._hi[i]) for i in range(3)])
        check_limits(q, self._lo, self._hi, self.actuator_names, unit='rad')
        return q

    def _legs_batch(self, p: np.ndarray, mode: tuple[int, int, int]
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """For validated poses (N, 3): motor angles (wrapped, no range check), the mask of
        legs that close, ``rho_i = R(phi) a_i`` and ``A_i - B_i`` (N, 3, 2)."""
        rho = self.platform_anchors @ np.swapaxes(rot2(p[:, 2]), -1, -2)          # (N, 3, 2)
        d = p[:, None, :2] + rho - self.base_pivots
        dist = np.hypot(d[..., 0], d[..., 1])
        r, l = self.proximal_lengths, self.distal_lengths
        hi = r + l
        tol = 1e-12 * hi
        close = (np.abs(r - l) - tol <= dist) & (dist <= hi + tol)
        c = np.clip((dist * dist - r * r - l * l) / (2.0 * r * l), -1.0, 1.0)
        alpha = np.asarray(mode, dtype=float) * np.arccos(c)
        theta = wrap_angle(np.arctan2(d[..., 1], d[..., 0]) - np.arctan2(l * np.sin(alpha), r + l * np.cos(alpha)))
        return np.asarray(theta, dtype=float).reshape(dist.shape), close, rho, d

    def inverse_batch(self, poses: np.ndarray, *, limits: bool = True,
                      working_mode: Sequence[int] | None = None) -> np.ndarray:
        """Vectorised :meth:`inverse`: motor angles (N, 3) (rad) for poses (N, 3).

        A NaN row where a leg cannot close or (with ``limits``) a motor angle is outside its
        range — where :meth:`inverse` raises :class:`~.base.UnreachablePose`. A platform joint
        on its base pivot (``r = l``, :meth:`inverse` raises ``SingularPose``: the angle is
        undefined) gets the formula's angle.

        :param limits: ``False``: no joint-range check (angles still moved by whole turns
            towards the ranges).
        :param working_mode: three signs; default the configured one.
        :raises ValueError: not an (N, 3) array, a non-finite value, a bad working mode.
        """
        p = as_poses(poses, 3)
        theta, close, _, _ = self._legs_batch(p, self._mode_of(working_mode))
        q = angles_into_range(theta, self._lo, self._hi)
        bad = ~close.all(axis=1)
        if limits:
            bad |= ~within_limits(q, self._lo, self._hi)
        q[bad] = np.nan
        return q

    def _constraints_batch(self, p: np.ndarray, working_mode: Sequence[int] | None, limits: bool
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``A`` (N, 3, 3), ``d`` (N, 3) of :meth:`constraint_matrices` for validated poses,
        and the reachable mask (as :meth:`inverse_batch`)."""
        mode = self._mode_of(working_mode)
        theta, close, rho, dvec = self._legs_batch(p, mode)
        u = np.stack([np.cos(theta), np.sin(theta)], axis=-1)
        w = dvec - self.proximal_lengths[:, None] * u
        a_mat = np.concatenate([w, cross2(rho, w)[..., None]], axis=-1)
        reach = ~np.isnan(self.inverse_batch(p, limits=limits, working_mode=mode)).any(axis=1)
        return a_mat, self.proximal_lengths * cross2(u, w), reach

    def jacobian_batch(self, poses: np.ndarray, *, limits: bool = True,
                       working_mode: Sequence[int] | None = None) -> np.ndarray:
        """Vectorised :meth:`jacobian`: ``J = D^-1 A`` (N, 3, 3).

        A NaN matrix where :meth:`inverse_batch` has a NaN row; non-finite rows where a leg
        is stretched or folded (``D_ii = 0``: :meth:`jacobian` raises ``SingularPose``).
        """
        p = as_poses(poses, 3)
        a_mat, d, reach = self._constraints_batch(p, working_mode, limits)
        small = np.abs(d) <= 1e-12 * self._scale ** 2
        with np.errstate(divide='ignore', invalid='ignore'):
            jac = a_mat / np.where(small, 0.0, d)[..., None]
        jac[~reach] = np.nan
        return jac

    def _statics_batch(self, p: np.ndarray, *, working_mode: Sequence[int] | None = None) -> Statics:
        """``W = J^T tau = A^T D^-1 tau``: ``G = J^T``, ``H = D A^-T`` (finite when a leg is
        stretched or folded; regular where ``A`` is, i.e. away from parallel singularities)."""
        a_mat, d, reach = self._constraints_batch(p, working_mode, True)
        small = np.abs(d) <= 1e-12 * self._scale ** 2
        with np.errstate(divide='ignore', invalid='ignore'):
            g = np.swapaxes(a_mat / np.where(small, 0.0, d)[..., None], -1, -2)
        g[~reach] = np.nan
        a_inv_t, regular = regular_inverse(np.swapaxes(a_mat, -1, -2))
        return Statics(reach, g, d[..., None] * a_inv_t, regular & reach, np.zeros((p.shape[0], 3)))

    # ------------------------------------------------------------------ forward kinematics
    def equivalent_rpr3(self, q: Sequence[float]) -> Rpr3:
        """The 3-RPR the mechanism is with motor angles ``q`` fixed: base anchors = elbows ``M_i``."""
        m = self.elbows(q)
        return Rpr3(m, self.platform_anchors, (0.0, 1e9), home_pose=(0.0, 0.0, 0.0),
                    actuator_names=tuple(f'{n}_distal' for n in self.actuator_names))

    def forward(self, q: Sequence[float]) -> list[np.ndarray]:
        """Every real assembly mode for motor angles ``q`` (rad), via :meth:`Rpr3.forward`.

        :returns: poses ``(x, y, phi)``, ``phi`` in ``(-pi, pi]``, at most six, sorted by
            ``phi``; ``[]`` when the distal links cannot close. No range check on ``q``.
        :raises ValueError: malformed ``q``.
        :raises SingularPose: a continuous self-motion at these motor angles.
        """
        return self.equivalent_rpr3(q).forward(self.distal_lengths)

    def forward_nearest(self, q: Sequence[float], hint_pose: Sequence[float]) -> np.ndarray:
        """The assembly mode nearest ``hint_pose`` (distance as :meth:`Rpr3.forward_nearest`).

        :raises UnreachablePose: no assembly mode for ``q``.
        """
        hint = as_vector(hint_pose, 3, 'hint_pose')
        sols = self.forward(q)
        if not sols:
            qv = np.asarray(q, dtype=float)
            raise UnreachablePose('no assembly mode: the distal links cannot close with motor angles '
                                  + ', '.join(f'{n}={v:.4f} rad' for n, v in zip(self.actuator_names, qv)))
        scale = self._platform_size
        return min(sols, key=lambda s: float((s[0] - hint[0]) ** 2 + (s[1] - hint[1]) ** 2
                                             + (scale * wrap_angle(float(s[2] - hint[2]))) ** 2))

    # ------------------------------------------------------------------ differential kinematics
    def constraint_matrices(self, pose: Sequence[float], *,
                            working_mode: Sequence[int] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``(A, d)``: ``A x_dot = diag(d) theta_dot`` (module docstring); ``A`` (3, 3), ``d`` (3,).

        :raises UnreachablePose: a leg cannot close at ``pose``.
        """
        p = as_vector(pose, 3, 'pose')
        t = self._angles(p, self._mode_of(working_mode))
        u = np.column_stack([np.cos(t), np.sin(t)])
        rho = self.platform_anchors @ rot2(p[2]).T
        w = p[:2] + rho - (self.base_pivots + self.proximal_lengths[:, None] * u)
        a_mat = np.column_stack([w, cross2(rho, w)])
        return a_mat, self.proximal_lengths * cross2(u, w)

    def jacobian(self, pose: Sequence[float], *, working_mode: Sequence[int] | None = None) -> np.ndarray:
        """``J = D^-1 A`` (3, 3): ``theta_dot = J @ (x_dot, y_dot, phi_dot)`` (rad/m, rad/m, rad/rad).

        No joint-range check. :raises SingularPose: a leg stretched or folded (``D_ii = 0``).
        """
        a_mat, d = self.constraint_matrices(pose, working_mode=working_mode)
        small = np.abs(d) <= 1e-12 * self._scale ** 2
        if small.any():
            i = int(np.flatnonzero(small)[0])
            raise SingularPose(f'leg of {self.actuator_names[i]} is stretched or folded at pose '
                               f'{np.asarray(pose, dtype=float).tolist()} (serial singularity): '
                               'its motor rate is unbounded')
        return a_mat / d[:, None]

    def report_jacobian(self, pose: Sequence[float], *, working_mode: Sequence[int] | None = None) -> np.ndarray:
        """The report's ``J = A^-1 D`` (3, 3): ``x_dot = J_report @ theta_dot`` (the inverse of :meth:`jacobian`).

        :raises SingularPose: ``A`` singular (parallel singularity: the pose is not determined
            by the motor rates there).
        """
        a_mat, d = self.constraint_matrices(pose, working_mode=working_mode)
        sv = np.linalg.svd(a_mat, compute_uv=False)
        if not sv[-1] > 1e-12 * sv[0]:
            raise SingularPose(f'pose {np.asarray(pose, dtype=float).tolist()} is a parallel singularity '
                               '(distal lines concurrent or parallel): A is singular')
        return np.linalg.solve(a_mat, np.diag(d))

    def condition(self, pose: Sequence[float], *, working_mode: Sequence[int] | None = None) -> float:
        """``cond(J)`` (2-norm; J mixes units, column 3 per m); ``inf`` at a singularity."""
        try:
            jac = self.jacobian(pose, working_mode=working_mode)
        except SingularPose:
            return math.inf
        return condition_number(jac)

    def check_singularity(self, pose: Sequence[float], *, working_mode: Sequence[int] | None = None) -> None:
        """Raise :class:`~.base.SingularPose` when ``cond(J) > singularity_condition_max``."""
        self._check_singularity(pose, working_mode=working_mode)

    def wrench(self, pose: Sequence[float], forces: Sequence[float], *,
               working_mode: Sequence[int] | None = None) -> np.ndarray:
        """Wrench on the platform ``(Fx N, Fy N, M N·m about P, ccw) = J^T tau`` from motor
        torques ``forces = tau_1..3`` (N·m, counter-clockwise on the proximal links).

        :raises SingularPose: a leg stretched or folded (the torque is not transmitted).
        """
        tau = as_vector(forces, 3, 'forces')
        return self.jacobian(pose, working_mode=working_mode).T @ tau

    def in_workspace(self, pose: Sequence[float], *, working_mode: Sequence[int] | None = None) -> bool:
        """Legs close, motor angles in range, ``cond(J) <= singularity_condition_max``.

        :raises ValueError: malformed ``pose``.
        """
        return self._in_workspace(pose, working_mode=working_mode)

    # ------------------------------------------------------------------ configuration
    @classmethod
    def from_config(cls, section: Mapping[str, Any]) -> 'Rrr3':
        """Build from the YAML's ``mechanism`` section.

        Reads ``type`` (``rrr3``), ``base_pivots`` and ``platform_anchors`` (flattened point
        lists, m), ``proximal_lengths``, ``distal_lengths`` (m, scalar or three),
        ``joint_min``, ``joint_max`` (rad), ``working_mode``, ``actuator_names``,
        ``home_pose``, ``singularity_condition_max``.

        :raises ConfigError: a missing or malformed value, naming the parameter.
        """
        check_section(section, 'rrr3', 'Rrr3', ('base_pivots', 'platform_anchors', 'proximal_lengths',
                                                'distal_lengths', 'joint_min', 'joint_max'))
        base = section_points(section, 'base_pivots', 3, '3-RRR')
        plat = section_points(section, 'platform_anchors', 3, '3-RRR')
        kwargs = section_kwargs(section, present=('working_mode', 'actuator_names', 'singularity_condition_max'),
                                given=('home_pose',))
        with config_errors():
            return cls(base, section['proximal_lengths'], section['distal_lengths'], plat,
                       (section['joint_min'], section['joint_max']), **kwargs)
