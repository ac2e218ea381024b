"""Planar serial 2R arm: the neck-brace report's "Planar RR" (seed 000, Ramdham 2018).

Shoulder joint at ``base`` (the origin by default), proximal link ``l1``, elbow joint,
distal link ``l2``; the actuators are the two joints, ``q = (theta1, theta2)`` (rad),
``theta1`` measured from the base x axis, ``theta2`` the elbow angle relative to link 1
(counter-clockwise positive). The *pose* is the end point ``(x, y)`` (m): dof 2, no
orientation (the report's end effector is a point).

Forward kinematics (report, "Forward Kinematics")::

    x = x0 + l1 cos(theta1) + l2 cos(theta1 + theta2)
    y = y0 + l1 sin(theta1) + l2 sin(theta1 + theta2)

Inverse kinematics (report, cosine rule)::

    cos(theta2) = (x'^2 + y'^2 - l1^2 - l2^2) / (2 l1 l2),   (x', y') = (x, y) - base
    theta2 = sigma acos(...),  sigma = +1 or -1   (the report's "+-")
    theta1 = atan2(y', x') - atan2(l2 sin theta2, l1 + l2 cos theta2)

(``atan2`` where the report writes ``tan^-1(y/x)``: the quotient loses the quadrant for
``x' < 0``.) The two elbow branches (parameter ``elbow``):

* ``'down'``: ``theta2`` in ``[0, pi]`` (``sigma = +1``): the elbow lies to the *right* of
  (clockwise from) the directed line base -> end point; for an end point along +x the
  elbow is below the line.
* ``'up'``: ``theta2`` in ``[-pi, 0]`` (``sigma = -1``): the elbow lies to the left of
  (counter-clockwise from) that line; above it for an end point along +x.

Workspace: the annulus ``|l1 - l2| <= |p - base| <= l1 + l2``, intersected with the joint
ranges. The arm is singular where ``sin(theta2) = 0`` (fully stretched on the outer
circle, folded on the inner one).

Jacobian: the protocol's meaning
--------------------------------
The protocol's ``J`` maps *pose* rates to *actuator* rates, ``q_dot = J x_dot`` (for a
parallel mechanism that is the easy direction). For a serial arm the easy one is the
other way round: the report's Jacobian ``J_s = d(x, y) / d(theta1, theta2)``
(:meth:`Rr2.serial_jacobian`). So here :meth:`Rr2.jacobian` returns ``J = J_s^-1``
(closed form, ``det J_s = l1 l2 sin(theta2)``), evaluated on the configured elbow
branch; it raises :class:`~.base.SingularPose` where ``J_s`` is singular (``J`` would be
infinite). :meth:`Rr2.condition` is ``cond(J_s) = cond(J)`` and is finite-or-inf, never raises.

Statics: ``wrench(pose, torques)`` is the force ``F = (Fx, Fy)`` (N) the end point exerts
on the body when the joint motors apply ``tau = (tau1, tau2)`` (N·m, counter-clockwise
positive, motor ``i`` acting on link ``i``): by virtual work ``tau . q_dot = F . x_dot``,
so ``F = J^T tau = J_s^-T tau`` (the classic ``tau = J_s^T F`` solved for ``F``).
"""
from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from .base import (MechanismBase, SingularPose, Statics, UnreachablePose, as_actuator_names, as_condition_max,
                   as_poses, as_range, as_vector, check_limits, check_section, condition_number, config_errors,
                   section_kwargs, within_limits)
from .loader import register
from .planar import wrap_angle

__all__ = ['Rr2', 'ELBOW_SIGN', 'angle_into_range', 'angles_into_range']

#: elbow branch name -> sign of theta2 (the report's "+-")
ELBOW_SIGN: dict[str, int] = {'down': 1, 'up': -1}

_TWO_PI = 2.0 * math.pi


def angle_into_range(theta: float, lo: float, hi: float, *, tol: float = 1e-12) -> float:
    """``theta + 2 pi k`` inside ``[lo, hi]`` if one is (the one nearest ``theta``), else the
    representative nearest the range (so the caller's limit check names a useful number).

    Joint ranges may extend beyond ``(-pi, pi]`` (e.g. ``[-200, 20]`` deg); an angle that
    comes out of ``atan2`` is moved by whole turns into them.
    """
    best, best_gap = theta, math.inf
    k0 = math.floor((lo - theta) / _TWO_PI)
    for k in range(k0 - 1, k0 + 3):
        t = theta + k * _TWO_PI
        gap = max(lo - tol - t, t - hi - tol, 0.0)
        if gap < best_gap or (gap == best_gap == 0.0 and abs(t - theta) < abs(best - theta)):
            best, best_gap = t, gap
    return best


def angles_into_range(theta: np.ndarray, lo: np.ndarray, hi: np.ndarray, *, tol: float = 1e-12) -> np.ndarray:
    """:func:`angle_into_range` element by element, vectorised (the same choice: in range
    and nearest ``theta``, else nearest the range, first of equals).

    :param theta: angles (rad), shape (..., n); ``lo``, ``hi`` broadcast against it.
    """
    th = np.asarray(theta, dtype=float)
    lo_b = np.broadcast_to(np.asarray(lo, dtype=float), th.shape)[..., None]
    hi_b = np.broadcast_to(np.asarray(hi, dtype=float), th.shape)[..., None]
    k0 = np.floor((lo_b - th[..., None]) / _TWO_PI)
    t = th[..., None] + (k0 + np.arange(-1.0, 3.0)) * _TWO_PI                 # the four candidates
    gap = np.maximum(np.maximum(lo_b - tol - t, t - hi_b - tol), 0.0)
    inside = gap == 0.0
    nearest = np.argmin(np.where(inside, np.abs(t - th[..., None]), np.inf), axis=-1)
    pick = np.where(inside.any(axis=-1), nearest, np.argmin(gap, axis=-1))
    return np.take_along_axis(t, pick[..., None], axis=-1)[..., 0]


def _elbow(value: Any) -> int:
    if value not in ELBOW_SIGN:
        raise ValueError(f'elbow: expected "up" or "down", got {value!r}')
    return ELBOW_SIGN[value]


@register('rr2')
class Rr2(MechanismBase):
    """Planar serial 2R arm (neck-brace report, "Planar RR").

    :param link_lengths: ``(l1, l2)`` proximal and distal link lengths, m, both > 0.
    :param joint_range: ``(lo, hi)`` joint range in rad, each a scalar or two values
        (per joint); ``hi - lo`` at most ``2 pi``.
    :param base: the shoulder joint ``(x0, y0)`` in the base frame, m.
    :param elbow: ``'up'`` or ``'down'`` (see the module docstring): the branch
        :meth:`inverse` returns by default.
    :param actuator_names: two distinct names (shoulder, elbow).
    :param home_pose: a rest end point ``(x, y)``, m, reachable on the ``elbow`` branch;
        default: the end point of the mid-range joint angles.
    :param singularity_condition_max: ``cond(J)`` above this is treated as singular.
    :raises ValueError: malformed lengths/range/names/branch, an unreachable home pose.
    """

    dof: int = 2
    pose_kind: str = 'xy'
    n_actuators: int = 2
    _singular_hint = ' (arm stretched or folded)'
    wrench_axes = ('Fx', 'Fy')
    wrench_units = ('N', 'N')

    def __init__(self, link_lengths: Sequence[float], joint_range: tuple[Any, Any] | Sequence[Any], *,
                 base: Sequence[float] = (0.0, 0.0), elbow: str = 'up',
                 actuator_names: Sequence[str] = ('j1', 'j2'),
                 home_pose: Sequence[float] | None = None,
                 singularity_condition_max: float = 1e4) -> None:
        lengths = as_vector(link_lengths, 2, 'link_lengths')
        if np.any(lengths <= 0.0):
            raise ValueError(f'link_lengths: need l1 > 0 and l2 > 0 m, got {lengths.tolist()}')
        self.l1, self.l2 = float(lengths[0]), float(lengths[1])
        self.base = as_vector(base, 2, 'base')
        self._lo, self._hi = as_range(joint_range, 2, 'joint_range', unit='rad', max_turn_tol=1e-12)
        self.elbow = str(elbow)
        self._sigma = _elbow(elbow)
        self.actuator_names: tuple[str, ...] = as_actuator_names(actuator_names, 2)
        self.singularity_condition_max = as_condition_max(singularity_condition_max)
        if home_pose is None:
            self._home = self._default_home()
        else:
            self._home = as_vector(home_pose, 2, 'home_pose')
            self.inverse(self._home)     # raises UnreachablePose (a ValueError) when unreachable

    # ------------------------------------------------------------------ properties
    # actuator_limits (joint angles, rad) and home_pose (end point x, y, m): MechanismBase
    @property
    def reach(self) -> tuple[float, float]:
        """``(r_min, r_max) = (|l1 - l2|, l1 + l2)``: the workspace annulus about ``base`` (m)."""
        return abs(self.l1 - self.l2), self.l1 + self.l2

    def __repr__(self) -> str:
        return (f'Rr2(link_lengths=({self.l1}, {self.l2}), joint_range=({self._lo.tolist()}, '
                f'{self._hi.tolist()}), base={self.base.tolist()}, elbow={self.elbow!r})')

    def _default_home(self) -> np.ndarray:
        """Mid-range shoulder angle with the elbow at the mid-range angle or at +-90 deg
        (whichever is in range and better conditioned)."""
        mid = 0.5 * (self._lo + self._hi)
        best, best_cond = None, math.inf
        for t2 in (mid[1], self._sigma * 0.5 * math.pi):
            p = self.forward([mid[0], t2])[0]
            try:
                self.inverse(p)
                c = self.condition(p)
            except UnreachablePose:
                continue
            if best is None or c < best_cond:
                best, best_cond = p, c
        if best is None:
            raise ValueError('home_pose: none given and the mid-range joint angles are not on the '
                             f'{self.elbow!r} branch within range; set home_pose explicitly')
        return best

    # ------------------------------------------------------------------ kinematics
    def _sigma_of(self, elbow: str | None) -> int:
        return self._sigma if elbow is None else _elbow(elbow)

    def _angles(self, p: np.ndarray, sigma: int) -> tuple[float, float]:
        """Report's cosine-rule inverse (no joint-range check); raises outside the annulus."""
        dx, dy = float(p[0] - self.base[0]), float(p[1] - self.base[1])
        r = math.hypot(dx, dy)
        r_min, r_max = self.reach
        tol = 1e-12 * (self.l1 + self.l2)
        if not (r_min - tol <= r <= r_max + tol):
            raise UnreachablePose(
                f'end point ({p[0]:.4f}, {p[1]:.4f}) m is {r:.4f} m from the shoulder joint, '
                f'the arm reaches {r_min:.4f}–{r_max:.4f} m (annulus)',
                actuator=None, value=r, limits=(r_min, r_max))
        if r <= tol:
            raise SingularPose(f'end point ({p[0]:.4f}, {p[1]:.4f}) m is on the shoulder joint '
                               '(l1 = l2): the shoulder angle is undefined')
        c2 = (r * r - self.l1 ** 2 - self.l2 ** 2) / (2.0 * self.l1 * self.l2)
        c2 = min(1.0, max(-1.0, c2))
        t2 = sigma * math.acos(c2)
        t1 = math.atan2(dy, dx) - math.atan2(self.l2 * math.sin(t2), self.l1 + self.l2 * math.cos(t2))
        return wrap_angle(t1), t2

    def inverse(self, pose: Sequence[float], *, elbow: str | None = None) -> np.ndarray:
        """Joint angles ``(theta1, theta2)`` (rad) putting the end point at ``pose = (x, y)``.

        :param elbow: ``'up'`` / ``'down'``; default the configured branch.
        :returns: angles moved by whole turns into the joint ranges where possible.
        :raises ValueError: malformed ``pose`` or ``elbow``.
        :raises UnreachablePose: outside the annulus (``actuator`` is ``None``, ``value`` the
            distance in m, ``limits`` the annulus), or a joint outside its range (naming it).
        """
        p = as_vector(pose, 2, 'pose')
        t1, t2 = self._angles(p, self._sigma_of(elbow))
        q = np.array([angle_into_range(t1, self._lo[0], self._hi[0]),
                      angle_into_range(t2, self._lo[1], self._hi[1])])
        check_limits(q, self._lo, self._hi, self.actuator_names, unit='rad')
        return q

    def _angles_batch(self, p: np.ndarray, sigma: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`_angles` for validated poses (N, 2): ``(theta1 wrapped, theta2, inside annulus)``."""
        dx, dy = p[:, 0] - self.base[0], p[:, 1] - self.base[1]
        r = np.hypot(dx, dy)
        r_min, r_max = self.reach
        tol = 1e-12 * (self.l1 + self.l2)
        inside = (r_min - tol <= r) & (r <= r_max + tol)
        c2 = np.clip((r * r - self.l1 ** 2 - self.l2 ** 2) / (2.0 * self.l1 * self.l2), -1.0, 1.0)
        t2 = sigma * np.arccos(c2)
        t1 = np.arctan2(dy, dx) - np.arctan2(self.l2 * np.sin(t2), self.l1 + self.l2 * np.cos(t2))
        return wrap_angle(t1), t2, inside

    def inverse_batch(self, poses: np.ndarray, *, limits: bool = True, elbow: str | None = None) -> np.ndarray:
        """Vectorised :meth:`inverse`: joint angles (N, 2) (rad) for end points (N, 2) (m).

        A NaN row outside the annulus, or (with ``limits``) with a joint outside its range —
        where :meth:`inverse` raises :class:`~.base.UnreachablePose`. An end point on the
        shoulder joint (``l1 = l2``, where :meth:`inverse` raises ``SingularPose``: the
        shoulder angle is undefined) gets the formula's angles.

        :param limits: ``False``: no joint-range check (angles still moved by whole turns
            towards the ranges).
        :param elbow: ``'up'`` / ``'down'``; default the configured branch.
        :raises ValueError: not an (N, 2) array, a non-finite value, a bad ``elbow``.
        """
        p = as_poses(poses, 2)
        t1, t2, inside = self._angles_batch(p, self._sigma_of(elbow))
        q = angles_into_range(np.column_stack([t1, t2]), self._lo, self._hi)
        bad = ~inside
        if limits:
            bad |= ~within_limits(q, self._lo, self._hi)
        q[bad] = np.nan
        return q

    def _serial_batch(self, p: np.ndarray, sigma: int) -> tuple[np.ndarray, np.ndarray]:
        """``J_s`` (N, 2, 2) at validated poses and the annulus mask."""
        t1, t2, inside = self._angles_batch(p, sigma)
        s1, c1 = np.sin(t1), np.cos(t1)
        s12, c12 = np.sin(t1 + t2), np.cos(t1 + t2)
        js = np.stack([np.stack([-self.l1 * s1 - self.l2 * s12, -self.l2 * s12], -1),
                       np.stack([self.l1 * c1 + self.l2 * c12, self.l2 * c12], -1)], -2)
        return js, inside

    def jacobian_batch(self, poses: np.ndarray, *, limits: bool = True, elbow: str | None = None) -> np.ndarray:
        """Vectorised :meth:`jacobian`: ``J = J_s^-1`` (N, 2, 2) (rad/m).

        A NaN matrix where :meth:`inverse_batch` has a NaN row; non-finite where the arm is
        stretched or folded (:meth:`jacobian` raises ``SingularPose``).
        """
        p = as_poses(poses, 2)
        sigma = self._sigma_of(elbow)
        js, _ = self._serial_batch(p, sigma)
        det = js[:, 0, 0] * js[:, 1, 1] - js[:, 0, 1] * js[:, 1, 0]
        adj = np.stack([np.stack([js[:, 1, 1], -js[:, 0, 1]], -1), np.stack([-js[:, 1, 0], js[:, 0, 0]], -1)], -2)
        with np.errstate(divide='ignore', invalid='ignore'):
            jac = adj / np.where(np.abs(det) <= 1e-12 * self.l1 * self.l2, 0.0, det)[:, None, None]
        jac[np.isnan(self.inverse_batch(p, limits=limits, elbow=elbow)).any(axis=1)] = np.nan
        return jac

    def _statics_batch(self, p: np.ndarray, *, elbow: str | None = None) -> Statics:
        """``W = J_s^-T tau``: ``G = J_s^-T``, ``H = J_s^T`` (finite when stretched or folded:
        a force along the arm then needs no torque)."""
        js, _ = self._serial_batch(p, self._sigma_of(elbow))
        reach = ~np.isnan(self.inverse_batch(p, elbow=elbow)).any(axis=1)
        g = np.swapaxes(self.jacobian_batch(p, elbow=elbow), -1, -2)
        return Statics(reach, g, np.swapaxes(js, -1, -2), reach, np.zeros((p.shape[0], 2)))

    def forward(self, q: Sequence[float]) -> list[np.ndarray]:
        """The end point of joint angles ``q`` (rad): a one-element list (a serial arm has one).

        No joint-range check (a measured angle is what it is).

        :raises ValueError: non-finite or wrong-shape ``q``.
        """
        t1, t2 = as_vector(q, 2, 'q')
        return [np.array([self.base[0] + self.l1 * math.cos(t1) + self.l2 * math.cos(t1 + t2),
                          self.base[1] + self.l1 * math.sin(t1) + self.l2 * math.sin(t1 + t2)])]

    def forward_nearest(self, q: Sequence[float], hint_pose: Sequence[float]) -> np.ndarray:
        """The end point of ``q`` (unique; ``hint_pose`` is validated and otherwise unused)."""
        as_vector(hint_pose, 2, 'hint_pose')
        return self.forward(q)[0]

    # ------------------------------------------------------------------ differential kinematics
    def serial_jacobian(self, q: Sequence[float]) -> np.ndarray:
        """The report's ``J_s = d(x, y)/d(theta1, theta2)`` (2, 2), m/rad: ``x_dot = J_s q_dot``."""
        t1, t2 = as_vector(q, 2, 'q')
        s1, c1 = math.sin(t1), math.cos(t1)
        s12, c12 = math.sin(t1 + t2), math.cos(t1 + t2)
        return np.array([[-self.l1 * s1 - self.l2 * s12, -self.l2 * s12],
                         [self.l1 * c1 + self.l2 * c12, self.l2 * c12]])

    def _serial_at(self, pose: Sequence[float], elbow: str | None) -> np.ndarray:
        p = as_vector(pose, 2, 'pose')
        return self.serial_jacobian(self._angles(p, self._sigma_of(elbow)))

    def jacobian(self, pose: Sequence[float], *, elbow: str | None = None) -> np.ndarray:
        """``J = J_s^-1`` (2, 2), rad/m: ``q_dot = J @ (x_dot, y_dot)`` on the elbow branch.

        No joint-range check (like the parallel mechanisms' Jacobians, it is the model's).

        :raises UnreachablePose: outside the annulus.
        :raises SingularPose: ``sin(theta2) = 0`` (stretched or folded): ``J`` is infinite.
        """
        js = self._serial_at(pose, elbow)
        det = js[0, 0] * js[1, 1] - js[0, 1] * js[1, 0]      # = l1 l2 sin(theta2)
        if abs(det) <= 1e-12 * self.l1 * self.l2:
            raise SingularPose(f'pose {np.asarray(pose, dtype=float).tolist()} is singular '
                               '(arm stretched or folded, sin(theta2) = 0): joint rates are unbounded')
        return np.array([[js[1, 1], -js[0, 1]], [-js[1, 0], js[0, 0]]]) / det

    def condition(self, pose: Sequence[float], *, elbow: str | None = None) -> float:
        """``cond(J_s) = cond(J)`` (2-norm, dimensionless: both columns in m/rad); ``inf`` when singular."""
        return condition_number(self._serial_at(pose, elbow), rtol=1e-15)

    def check_singularity(self, pose: Sequence[float], *, elbow: str | None = None) -> None:
        """Raise :class:`~.base.SingularPose` when ``cond(J) > singularity_condition_max``."""
        self._check_singularity(pose, elbow=elbow)

    def wrench(self, pose: Sequence[float], forces: Sequence[float], *, elbow: str | None = None) -> np.ndarray:
        """Force ``(Fx, Fy)`` (N) at the end point from joint torques ``forces = (tau1, tau2)`` (N·m).

        ``F = J^T tau = J_s^-T tau`` (virtual work); counter-clockwise torques positive.

        :raises SingularPose: at a singularity (a torque there can hold an unbounded force).
        """
        tau = as_vector(forces, 2, 'forces')
        return self.jacobian(pose, elbow=elbow).T @ tau

    def in_workspace(self, pose: Sequence[float], *, elbow: str | None = None) -> bool:
        """Within the annulus and the joint ranges on the elbow branch, and ``cond(J)`` below the limit.

        :raises ValueError: malformed ``pose`` (never a quiet ``False``).
        """
        return self._in_workspace(pose, elbow=elbow)

    # ------------------------------------------------------------------ configuration
    @classmethod
    def from_config(cls, section: Mapping[str, Any]) -> 'Rr2':
        """Build from the YAML's ``mechanism`` section.

        Reads ``type`` (``rr2``), ``link_lengths`` ``[l1, l2]`` (m), ``joint_min``,
        ``joint_max`` (rad, scalar or per joint), ``base`` ``[x0, y0]`` (m, optional),
        ``elbow`` (``up``/``down``), ``actuator_names``, ``home_pose`` ``[x, y]``,
        ``singularity_condition_max``.

        :raises ConfigError: a missing or malformed value, naming the parameter.
        """
        check_section(section, 'rr2', 'Rr2', ('link_lengths', 'joint_min', 'joint_max'))
        kwargs = section_kwargs(section, present=('base', 'elbow', 'actuator_names', 'singularity_condition_max'),
                                given=('home_pose',))
        with config_errors():
            return cls(section['link_lengths'], (section['joint_min'], section['joint_max']), **kwargs)
