"""The protocol every mechanism model follows, and the errors they raise.

Pure numpy/scipy: no ROS, no CAN. See ARCHITECTURE.md ("Python API contract").
A *pose* is the platform's coordinates (planar: ``(x, y, theta)``, platform point ``b``
of the platform frame at ``(x, y) + R(theta) b``); ``q`` are the actuator coordinates
(lengths in m or joint angles in rad).

Besides the protocol, the pieces every model shares (one copy, used by all):

* input validators — :func:`as_vector`, :func:`as_poses`, :func:`as_points`,
  :func:`as_per_actuator`, :func:`as_range`, :func:`as_actuator_names`,
  :func:`as_condition_max`, :func:`as_positive`, :func:`as_force_limits`;
* :class:`MechanismBase` — the ``actuator_limits`` / ``home_pose`` properties, the bodies
  behind ``check_singularity`` / ``in_workspace``, loop fallbacks of ``inverse_batch`` /
  ``jacobian_batch`` (every model here overrides them with numpy), and
  ``wrench_capacity`` / ``wrench_capacity_batch`` (the math in :mod:`.capacity`);
* ``from_config`` plumbing — :func:`check_section`, :func:`section_kwargs`,
  :func:`section_points`, :func:`config_errors`.
"""
from __future__ import annotations

import math
from collections.abc import Iterator, Mapping
from contextlib import contextmanager, suppress
from typing import Any, NamedTuple, Protocol, Sequence, runtime_checkable

import numpy as np

from .. import schema
from ..config import ConfigError, points
from .capacity import (capacity_closed_form, capacity_lp, capacity_one_redundancy, regular_inverse,
                       unsupported_axes)

__all__ = [
    'Mechanism', 'MechanismBase', 'UnreachablePose', 'SingularPose', 'Statics', 'check_workspace', 'workspace_mask',
    'as_vector', 'as_poses', 'as_points', 'as_per_actuator', 'as_range', 'as_actuator_names', 'as_condition_max',
    'as_positive', 'as_force_limits',
    'condition_number', 'check_limits', 'within_limits', 'rot2',
    'check_section', 'section_kwargs', 'section_points', 'config_errors', 'warm_up', 'POSE_KINDS',
]

_COUNT_WORDS = {1: 'one', 2: 'two', 3: 'three', 4: 'four'}
#: what one number of a unit is, for the messages ("a length in m or three of them")
_QUANTITY = {'m': 'a length', 'rad': 'an angle'}


def _count(n: int) -> str:
    return _COUNT_WORDS.get(n, str(n))


class UnreachablePose(ValueError):
    """A pose the mechanism cannot take; the message names the actuator and the numbers.

    ``actuator`` is the offending actuator's name (or ``None`` when the reason is not a
    single actuator, e.g. a leg that cannot close), ``value`` what it would need and
    ``limits`` its ``(lo, hi)`` range.
    """

    def __init__(self, message: str, *, actuator: str | None = None,
                 value: float | None = None, limits: tuple[float, float] | None = None) -> None:
        super().__init__(message)
        self.actuator = actuator
        self.value = value
        self.limits = limits


class SingularPose(UnreachablePose):
    """A pose at (or too close to) a singularity: the Jacobian's condition number is too high."""


def workspace_mask(mech: Any, poses: np.ndarray) -> np.ndarray:
    """``mech.in_workspace`` of each row of ``poses`` (its ``in_workspace_batch`` where it has
    one); all true for a mechanism without ``in_workspace``."""
    P = np.asarray(poses, dtype=float)
    batch = getattr(mech, 'in_workspace_batch', None)
    if callable(batch):
        return np.asarray(batch(P), dtype=bool)
    inside = getattr(mech, 'in_workspace', None)
    if not callable(inside):
        return np.ones(len(P), dtype=bool)
    return np.array([bool(inside(p)) for p in P], dtype=bool)


def check_workspace(mech: Any, pose: Sequence[float]) -> None:
    """Raise :class:`UnreachablePose` when ``mech.in_workspace(pose)`` is false, with the
    mechanism's reason where it gives one (``workspace_reason``: a cable brace's tensions);
    nothing for a mechanism without ``in_workspace``. What the trajectory planner refuses as
    outside the workspace, the IK node refuses too (a setpoint, a pose trajectory)."""
    inside = getattr(mech, 'in_workspace', None)
    if not callable(inside) or inside(pose):
        return
    why = getattr(mech, 'workspace_reason', None)
    reason = why(pose) if callable(why) else ''
    text = ', '.join(f'{float(x):.4g}' for x in np.asarray(pose, dtype=float).ravel())
    raise UnreachablePose(f'pose [{text}] is outside the workspace' + (f': {reason}' if reason else ''))


@runtime_checkable
class Mechanism(Protocol):
    """What the nodes, the trajectory planner and the simulator rely on.

    Batch methods (a whole planned motion at once; every model here vectorises them):

    * ``inverse_batch(poses)`` -> (N, n_actuators): the numbers of ``inverse``; a NaN row
      where ``inverse`` raises :class:`UnreachablePose` (outside a stroke or joint range,
      no real solution), never an exception. Singular poses are *not* unreachable (the
      caller checks conditioning). Same keyword arguments as ``inverse`` (working mode,
      branch), plus ``limits=False`` for the raw values without the range check.
    * ``jacobian_batch(poses)`` -> (N, n_actuators, dof): ``jacobian`` per pose, a NaN
      matrix where the pose is unreachable.
    * ``wrench_capacity(pose, force_limits)`` -> (m,), ``wrench_capacity_batch(poses,
      force_limits)`` -> (N, m): the largest wrench per axis of ``wrench_axes`` that
      efforts within ``force_limits`` hold in both directions (``return_limiting=True``
      adds the limiting actuator per axis), see :meth:`MechanismBase.wrench_capacity`.

    Malformed input (wrong shape, a non-finite value) is a ``ValueError`` naming what is
    wrong, in every method.
    """

    dof: int
    #: how the pose vector maps onto a ``geometry_msgs/Pose`` (one of :data:`POSE_KINDS`):
    #: ``'planar'`` (x, y m, theta rad about z), ``'xy'`` (x, y m), ``'path'`` (one
    #: coordinate, position.x), ``'spherical'`` (three angles, a rotation)
    pose_kind: str
    n_actuators: int
    actuator_names: tuple[str, ...]
    #: the wrench components ``wrench_capacity`` reports (e.g. ``('Fx', 'Fy', 'Mz')``)
    wrench_axes: tuple[str, ...]

    @property
    def actuator_limits(self) -> tuple[np.ndarray, np.ndarray]: ...

    @property
    def home_pose(self) -> np.ndarray: ...

    def inverse(self, pose: Sequence[float]) -> np.ndarray: ...

    def forward(self, q: Sequence[float]) -> list[np.ndarray]: ...

    def forward_nearest(self, q: Sequence[float], hint_pose: Sequence[float]) -> np.ndarray: ...

    def jacobian(self, pose: Sequence[float]) -> np.ndarray: ...

    def wrench(self, pose: Sequence[float], forces: Sequence[float]) -> np.ndarray: ...

    def in_workspace(self, pose: Sequence[float]) -> bool: ...

    def inverse_batch(self, poses: np.ndarray, **branch: Any) -> np.ndarray: ...

    def jacobian_batch(self, poses: np.ndarray, **branch: Any) -> np.ndarray: ...

    def wrench_capacity(self, pose: Sequence[float], force_limits: Any, **kwargs: Any) -> Any: ...

    def wrench_capacity_batch(self, poses: np.ndarray, force_limits: Any, **kwargs: Any) -> Any: ...


def as_vector(value: Sequence[float] | np.ndarray, length: int, name: str) -> np.ndarray:
    """``value`` as a finite float vector of ``length``, else ``ValueError`` saying what is wrong.

    Used for every input of every mechanism: NaN/inf and wrong shapes never pass.
    """
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ValueError(f'{name}: expected {length} numbers, got {value!r}') from exc
    if arr.shape != (length,):
        raise ValueError(f'{name}: expected shape ({length},), got shape {arr.shape}')
    if not np.all(np.isfinite(arr)):
        bad = [i for i in range(length) if not np.isfinite(arr[i])]
        raise ValueError(f'{name}: non-finite value at index {bad}: {arr.tolist()}')
    return arr


def as_poses(value: Any, dof: int, name: str = 'poses') -> np.ndarray:
    """``value`` as a finite float array of shape (N, dof) (``N >= 0``), else ``ValueError``.

    The batch counterpart of :func:`as_vector`: a wrong shape or a non-finite entry is an
    error naming the rows, never a NaN row of the result (NaN rows mean *unreachable*).
    """
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ValueError(f'{name}: expected an (N, {dof}) array of poses, got {value!r}') from exc
    if arr.ndim != 2 or arr.shape[1] != dof:
        raise ValueError(f'{name}: expected shape (N, {dof}), got shape {arr.shape}')
    finite = np.isfinite(arr).all(axis=1)
    if not finite.all():
        rows = np.flatnonzero(~finite)
        more = ' ...' if rows.size > 10 else ''
        raise ValueError(f'{name}: non-finite value in rows {rows[:10].tolist()}{more} '
                         f'(first: {arr[rows[0]].tolist()})')
    return arr


def as_force_limits(value: Any, n: int, name: str = 'force_limits') -> np.ndarray:
    """Effort limit magnitudes (N or N·m), a scalar or ``n`` values, each ``> 0`` (``inf`` allowed).

    :raises ValueError: naming ``name``, what was expected and what was got.
    """
    try:
        arr = np.array(value, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ValueError(f'{name}: expected a limit in N (or N·m) or {_count(n)} of them, got {value!r}') from exc
    if arr.ndim == 0:
        arr = np.full(n, float(arr))
    if arr.shape != (n,):
        raise ValueError(f'{name}: expected a scalar or {n} limits (N or N·m), got shape {arr.shape}: '
                         f'{arr.tolist()}')
    if not np.all(arr > 0.0):        # also rejects NaN
        raise ValueError(f'{name}: every limit must be a positive number of N (or N·m), got {arr.tolist()}')
    return arr


def as_points(value: Any, n: int, name: str, *, unit: str = 'm') -> np.ndarray:
    """``value`` as ``n`` finite (x, y) points, shape (n, 2): nested (n, 2) or flat (2 n,).

    :raises ValueError: naming ``name``, what was expected and what was got.
    """
    word = _count(n)
    try:
        arr = np.array(value, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ValueError(f'{name}: expected {word} (x, y) points in {unit}, got {value!r}') from exc
    if arr.shape == (2 * n,):
        arr = arr.reshape(n, 2)
    if arr.shape != (n, 2):
        raise ValueError(f'{name}: expected {word} (x, y) points (shape ({n}, 2)), got shape {arr.shape}')
    if not np.all(np.isfinite(arr)):
        raise ValueError(f'{name}: contains a non-finite value: {arr.tolist()}')
    return arr


def as_per_actuator(value: Any, n: int, name: str, *, unit: str) -> np.ndarray:
    """``value`` as ``n`` finite numbers (shape (n,)); a scalar is broadcast to all ``n``.

    :raises ValueError: naming ``name``, what was expected and what was got.
    """
    word = _count(n)
    try:
        arr = np.array(value, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ValueError(f'{name}: expected {_QUANTITY.get(unit, "a value")} in {unit} or {word} of them, '
                         f'got {value!r}') from exc
    if arr.ndim == 0:
        arr = np.full(n, float(arr))
    if arr.shape != (n,):
        raise ValueError(f'{name}: expected a scalar or {n} values in {unit}, got shape {arr.shape}: '
                         f'{arr.tolist()}')
    if not np.all(np.isfinite(arr)):
        raise ValueError(f'{name}: contains a non-finite value (expected finite numbers in {unit}): '
                         f'{arr.tolist()}')
    return arr


def as_range(value: Any, n: int, name: str, *, unit: str, lo_min: float | None = None,
             max_turn_tol: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A ``(lo, hi)`` actuator range, each a scalar or ``n`` values -> two arrays of shape (n,).

    Always ``lo < hi``; with ``lo_min`` also ``lo >= lo_min`` (a stroke: ``0``); with
    ``max_turn_tol`` also ``hi <= lo + 2 pi + max_turn_tol`` (a joint that turns).

    :raises ValueError: not a pair, a malformed bound, or bounds out of order, naming ``name``.
    """
    if isinstance(value, (str, bytes)) or len(value) != 2:
        raise ValueError(f'{name}: expected (lo, hi) in {unit}, got {value!r}')
    lo = as_per_actuator(value[0], n, f'{name} (lo)', unit=unit)
    hi = as_per_actuator(value[1], n, f'{name} (hi)', unit=unit)
    bad = bool(np.any(hi <= lo))
    need = 'lo < hi' if lo_min is None else f'{lo_min:g} <= lo < hi'
    if lo_min is not None:
        bad = bad or bool(np.any(lo < lo_min))
    if max_turn_tol is not None:
        bad = bad or bool(np.any(hi - lo > 2.0 * math.pi + max_turn_tol))
        need += ' <= lo + 2 pi'
    if bad:
        raise ValueError(f'{name}: need {need} for every actuator, got lo={lo.tolist()} {unit}, '
                         f'hi={hi.tolist()} {unit}')
    return lo, hi


def as_actuator_names(value: Any, n: int) -> tuple[str, ...]:
    """``n`` distinct non-empty names (a lone string is one name), else ``ValueError``."""
    names = (value,) if isinstance(value, str) else tuple(value)
    if len(names) != n or not all(isinstance(v, str) and v for v in names) or len(set(names)) != n:
        what = 'one non-empty name' if n == 1 else f'{_count(n)} distinct non-empty names'
        raise ValueError(f'actuator_names: expected {what}, got {value!r}')
    return names


def as_positive(value: Any, name: str, *, unit: str | None = None, allow_inf: bool = False,
                allow_zero: bool = False) -> float:
    """``value`` as a float > 0 (``>= 0`` with ``allow_zero``; ``inf`` allowed with ``allow_inf``).

    :raises ValueError: naming ``name``, the unit and what was got.
    """
    try:
        v = float(value)
    except (TypeError, ValueError):
        v = math.nan
    ok = (v >= 0.0 if allow_zero else v > 0.0) and (math.isfinite(v) or (allow_inf and v == math.inf))
    if not ok:
        kind = 'non-negative' if allow_zero else 'positive'
        raise ValueError(f'{name}: expected a {kind} number{f" in {unit}" if unit else ""}, got {value!r}')
    return v


def as_condition_max(value: Any) -> float:
    """``singularity_condition_max`` as a finite float > 1, else ``ValueError``."""
    try:
        cmax = float(value)
    except (TypeError, ValueError):
        cmax = math.nan
    if not (math.isfinite(cmax) and cmax > 1.0):
        raise ValueError(f'singularity_condition_max: expected a finite number > 1, got {value!r}')
    return cmax


def condition_number(matrix: np.ndarray, *, rtol: float = 0.0) -> float:
    """2-norm condition number ``s_max / s_min``; ``inf`` when ``s_min <= rtol * s_max``."""
    sv = np.linalg.svd(matrix, compute_uv=False)
    return float(sv[0] / sv[-1]) if sv[-1] > rtol * sv[0] else math.inf


def check_limits(q: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                 names: Sequence[str], *, unit: str = 'm', tol: float = 1e-12) -> None:
    """Raise :class:`UnreachablePose` naming the first actuator outside ``[lo, hi]``."""
    for i, name in enumerate(names):
        if not (lo[i] - tol <= q[i] <= hi[i] + tol):
            raise UnreachablePose(
                f'actuator {name} would need {q[i]:.4f} {unit}, '
                f'its range is {lo[i]:.4f}–{hi[i]:.4f} {unit}',
                actuator=name, value=float(q[i]), limits=(float(lo[i]), float(hi[i])))


def within_limits(q: np.ndarray, lo: np.ndarray, hi: np.ndarray, *, tol: float = 1e-12) -> np.ndarray:
    """Row mask of ``q`` (..., n): every actuator within ``[lo, hi]`` with the tolerance of
    :func:`check_limits` (NaN is outside)."""
    return np.all((q >= lo - tol) & (q <= hi + tol), axis=-1)


def rot2(theta: float | np.ndarray) -> np.ndarray:
    """Planar rotation matrix R(theta) (shape (2, 2), or (..., 2, 2) for an array)."""
    c, s = np.cos(theta), np.sin(theta)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


class Statics(NamedTuple):
    """Statics of a stack of N poses in the capacity axes (see :mod:`.capacity`).

    ``W = G (f - b)``: ``g`` (N, m, n) the wrench map, ``bias`` (N, n) the unloaded efforts
    ``b``; ``h`` (N, n, m) the effort map ``G^-1`` of a square mechanism, valid on the
    ``regular`` rows (computed by the model in the form that stays finite at its serial
    singularities), ``None`` for a redundant one; ``reach`` (N,) the reachable rows.
    """

    reach: np.ndarray
    g: np.ndarray
    h: np.ndarray | None
    regular: np.ndarray
    bias: np.ndarray


class MechanismBase:
    """What the mechanism models share besides the protocol (a mixin, no ``__init__``).

    The subclass sets ``_lo``, ``_hi`` (actuator range arrays), ``_home`` (the rest pose)
    and, when it tests singularity, ``singularity_condition_max``. Its public
    ``check_singularity`` / ``in_workspace`` keep their own signatures and documentation
    and call :meth:`_check_singularity` / :meth:`_in_workspace`.
    """

    _lo: np.ndarray
    _hi: np.ndarray
    _home: np.ndarray
    dof: int
    singularity_condition_max: float
    #: name of the planar pose's angle in messages (``theta``, ``psi``, ``phi``)
    _angle_name: str = 'theta'
    #: the measure compared with ``singularity_condition_max``, in messages
    _measure_name: str = 'cond(J)'
    #: why a pose is singular, in messages (e.g. `` (arm stretched or folded)``)
    _singular_hint: str = ''
    #: the capacity axes: the components of :meth:`wrench` that :meth:`wrench_capacity`
    #: reports, and their units (planar default; other models set their own)
    wrench_axes: tuple[str, ...] = ('Fx', 'Fy', 'Mz')
    wrench_units: tuple[str, ...] = ('N', 'N', 'N·m')

    @property
    def actuator_limits(self) -> tuple[np.ndarray, np.ndarray]:
        """Actuator range ``(lo, hi)``, arrays of shape (n_actuators,), in the actuators'
        unit (m for a length, rad for an angle)."""
        return self._lo.copy(), self._hi.copy()

    @property
    def home_pose(self) -> np.ndarray:
        """The rest pose (from the YAML, or the model's default), within the actuator ranges."""
        return self._home.copy()

    def unloaded_forces(self, q: Sequence[float]) -> np.ndarray:
        """Actuator efforts that hold the mechanism with no external load at ``q``.

        Zero for rigid links (gravity is not modelled); a mechanism with elastic members
        (the continuum robot's bent bars) overrides it. The simulator adds it to the
        efforts that balance the body's wrench.
        """
        return np.zeros(np.size(self._lo))

    # ------------------------------------------------------------------ batch kinematics
    def inverse_batch(self, poses: np.ndarray, *, limits: bool = True, **branch: Any) -> np.ndarray:
        """Actuator coordinates (N, n_actuators) for poses (N, dof); a NaN row where unreachable.

        The contract of every model: same numbers as :meth:`inverse` (same keyword arguments:
        working mode / branch); a pose where the scalar raises :class:`UnreachablePose`
        (outside the stroke or joint range, no real solution) is a NaN row, never an
        exception. A *singular* pose is not unreachable: where a model's scalar
        :meth:`inverse` raises :class:`SingularPose` (an undefined joint angle), its
        vectorised version returns the formula's value (within range); conditioning is the
        caller's check (``condition`` / ``in_workspace``).

        This is the loop fallback (:meth:`inverse` per pose, and NaN there also for a
        ``SingularPose``, which has no value); every model here overrides it with numpy.

        :param poses: (N, dof) array.
        :param limits: ``False``: the raw inverse kinematics, NaN only where there is no
            real solution (vectorised models only; the fallback needs ``True``).
        :raises ValueError: not an (N, dof) array, a non-finite entry (naming the rows).
        """
        p = as_poses(poses, self.dof)
        if not limits:
            raise ValueError(f'{type(self).__name__}.inverse_batch: limits=False needs a vectorised '
                             'inverse (the per-pose fallback checks the ranges)')
        out = np.full((p.shape[0], self.n_actuators), np.nan)
        for k, pose in enumerate(p):
            try:
                out[k] = self.inverse(pose, **branch)  # type: ignore[attr-defined]
            except UnreachablePose:
                pass
        return out

    def jacobian_batch(self, poses: np.ndarray, *, limits: bool = True, **branch: Any) -> np.ndarray:
        """``J`` (N, n_actuators, dof) for poses (N, dof): :meth:`jacobian` per pose.

        A NaN matrix where :meth:`inverse_batch` has a NaN row (unreachable); non-finite
        (``inf``) entries where the scalar raises :class:`SingularPose` (an unbounded rate,
        e.g. a leg stretched). The loop fallback; every model here overrides it.

        :raises ValueError: not an (N, dof) array, a non-finite entry.
        """
        p = as_poses(poses, self.dof)
        q = self.inverse_batch(p, limits=limits, **branch)
        out = np.full((p.shape[0], self.n_actuators, self.dof), np.nan)
        for k in np.flatnonzero(np.isfinite(q).all(axis=1)):
            try:
                out[k] = self.jacobian(p[k], **branch)  # type: ignore[attr-defined]
            except SingularPose:
                out[k] = np.inf
        return out

    # ------------------------------------------------------------------ wrench capacity
    def _effort_bounds(self, limits: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Effort range ``(lo, hi)`` for limit magnitudes: push/pull ``[-limit, limit]``."""
        return -limits, limits.copy()

    def _capacity_axes(self, pose: np.ndarray, **branch: Any) -> np.ndarray | None:
        """Rows (m, dof) mapping :meth:`wrench` to the capacity axes; ``None``: the identity."""
        return None

    def _statics_batch(self, p: np.ndarray, **branch: Any) -> Statics:
        """Default statics ``W = J^T f`` (rigid links, ``b = 0``) from :meth:`jacobian_batch`;
        ``H = G^-1`` where regular (square). Models with another convention override it."""
        jac = self.jacobian_batch(p, **branch)
        g = np.swapaxes(jac, -1, -2)
        reach = ~np.isnan(jac).any(axis=(1, 2))
        n = self.n_actuators
        if n == len(self.wrench_axes):
            h, regular = regular_inverse(g)
        else:
            h, regular = None, np.zeros(p.shape[0], dtype=bool)
        return Statics(reach, g, h, regular & reach, np.zeros((p.shape[0], n)))

    def _statics_from_wrench(self, p: np.ndarray, q: np.ndarray, **branch: Any) -> tuple[np.ndarray, np.ndarray]:
        """``(G, b)`` at one pose from the public :meth:`wrench` itself: ``b`` =
        :meth:`unloaded_forces`, column ``i`` of ``G`` = ``wrench(b + e_i) - wrench(b)``."""
        wrench = self.wrench  # type: ignore[attr-defined]
        bias = np.asarray(self.unloaded_forces(q), dtype=float)
        w0 = np.asarray(wrench(p, bias, **branch), dtype=float)
        eye = np.eye(self.n_actuators)
        g = np.column_stack([np.asarray(wrench(p, bias + eye[i], **branch), dtype=float) - w0
                             for i in range(self.n_actuators)])
        axes = self._capacity_axes(p, **branch)
        return (g if axes is None else axes @ g), bias

    def wrench_capacity(self, pose: Sequence[float], force_limits: Any, *, return_limiting: bool = False,
                        **branch: Any) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
        """The largest wrench per axis the actuators can hold at ``pose`` (force transmission).

        For each axis of :attr:`wrench_axes` alone (other components zero), the largest
        ``w`` such that both ``+w`` and ``-w`` — hence every wrench between them — are
        balanced by actuator efforts within their limits, in the model's own :meth:`wrench`
        convention (planar: ``Fx, Fy`` N and ``Mz`` N·m about the platform origin, in the
        base frame; see each model for its frame). Exact: closed form for a square,
        regular mechanism (``f = b + G^-1 W``, ``w = min_i limit_i / |(G^-1)_i,axis|`` when
        ``b = 0``); an LP for a redundant or cable-driven one or at a singular pose, where
        the unsupported direction has capacity 0. See :mod:`.capacity`.

        This scalar version is the reference: ``G`` and ``b`` come from probing
        :meth:`wrench` with unit efforts (and :meth:`unloaded_forces`); the batch version
        uses the model's vectorised statics.

        :param pose: a reachable pose.
        :param force_limits: effort limit magnitudes (N for linear actuators and cables, N·m
            for rotary joints), a scalar or one per actuator; ``|f_i| <= limit_i``, a cable
            pulls only (``-limit_i <= f_i <= 0``, thrust = minus tension).
        :param return_limiting: also return, per axis, the index of the actuator whose limit
            binds (the largest shadow price; ``-1`` when none does: an unsupported
            direction, an unbounded capacity). Its name: ``actuator_names[index]``.
        :returns: capacity (m,) in :attr:`wrench_units`; with ``return_limiting`` the pair
            ``(capacity, limiting)``.
        :raises ValueError: malformed pose or limits.
        :raises UnreachablePose: the pose is unreachable (as :meth:`inverse`).
        """
        p = as_vector(pose, self.dof, 'pose')
        lim = as_force_limits(force_limits, self.n_actuators)
        q = self.inverse(p, **branch)  # type: ignore[attr-defined]
        lo, hi = self._effort_bounds(lim)
        try:
            g, bias = self._statics_from_wrench(p, q, **branch)
        except SingularPose:
            # a serial singularity: wrench() has no finite map, the model's effort map does
            cap2, which2 = self.wrench_capacity_batch(p[None], lim, return_limiting=True, **branch)
            cap, which = cap2[0], which2[0]
        else:
            lo_c, hi_c = lo - bias, hi - bias
            regular = False
            if g.shape[0] == g.shape[1]:
                h, ok = regular_inverse(g[None])
                regular = bool(ok[0])
            if regular:
                c, w = capacity_closed_form(h, lo_c[None], hi_c[None])
                cap, which = c[0], w[0]
            else:
                cap, which = capacity_lp(g, lo_c, hi_c)
        return (cap, which) if return_limiting else cap

    def wrench_capacity_batch(self, poses: np.ndarray, force_limits: Any, *, return_limiting: bool = False,
                              **branch: Any) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
        """:meth:`wrench_capacity` for poses (N, dof) -> (N, m); a NaN row where unreachable.

        Vectorised for square mechanisms (closed form) and for one degree of redundancy
        (exact two-variable LP by its vertices, e.g. the 4-RPR); singular poses and higher
        redundancy fall back to one LP per pose, axis and direction.

        :param return_limiting: also return the limiting actuator per pose and axis (N, m)
            (``-1`` where none, or unreachable).
        :raises ValueError: malformed poses or limits.
        """
        p = as_poses(poses, self.dof)
        lim = as_force_limits(force_limits, self.n_actuators)
        lo, hi = self._effort_bounds(lim)
        m, n, rows = len(self.wrench_axes), self.n_actuators, p.shape[0]
        cap = np.full((rows, m), np.nan)
        which = np.full((rows, m), -1, dtype=int)
        if rows:
            st = self._statics_batch(p, **branch)
            lo_c, hi_c = lo - st.bias, hi - st.bias
            todo = st.reach.copy()
            if st.h is not None and st.regular.any():
                r = st.regular
                cap[r], which[r] = capacity_closed_form(st.h[r], lo_c[r], hi_c[r])
                todo &= ~r
            if n == m + 1 and todo.any():
                idx = np.flatnonzero(todo)
                c, w, ok = capacity_one_redundancy(st.g[idx], lo_c[idx], hi_c[idx])
                cap[idx[ok]], which[idx[ok]] = c[ok], w[ok]
                todo[idx[ok]] = False
            todo &= np.isfinite(st.g).all(axis=(1, 2))      # serial and parallel singular at once: NaN
            if todo.any():
                # singular (or more redundant): unsupported axes are 0 without an LP; an LP
                # for each pose with a supported axis left
                idx = np.flatnonzero(todo)
                gone = unsupported_axes(st.g[idx])
                cap[idx], which[idx] = np.where(gone, 0.0, np.nan), -1
                for k in idx[~gone.all(axis=1)]:
                    cap[k], which[k] = capacity_lp(st.g[k], lo_c[k], hi_c[k])
        return (cap, which) if return_limiting else cap

    # ------------------------------------------------------------------ singularity, workspace
    def _singularity_measure(self, pose: Sequence[float], **branch: Any) -> float:
        """The number compared with ``singularity_condition_max``: ``cond(J)`` by default."""
        return self.condition(pose, **branch)  # type: ignore[attr-defined]

    def _pose_text(self, pose: Sequence[float]) -> str:
        """A planar pose for messages: ``pose (x=... m, y=... m[, theta=... deg])``."""
        p = np.asarray(pose, dtype=float)
        text = f'pose (x={p[0]:.4f} m, y={p[1]:.4f} m'
        if self.dof == 3:
            text += f', {self._angle_name}={math.degrees(p[2]):.3f} deg'
        return text + ')'

    def _check_singularity(self, pose: Sequence[float], **branch: Any) -> None:
        """Raise :class:`SingularPose` when the measure exceeds ``singularity_condition_max``."""
        c = self._singularity_measure(pose, **branch)
        if not c <= self.singularity_condition_max:
            raise SingularPose(f'{self._pose_text(pose)} is at or near a singularity{self._singular_hint}: '
                               f'{self._measure_name} = {c:.3g} > {self.singularity_condition_max:.3g}')

    def _in_workspace(self, pose: Sequence[float], *, singularity: bool = True, **branch: Any) -> bool:
        """``inverse`` succeeds (and, with ``singularity``, the measure is within the limit).

        :raises ValueError: malformed ``pose`` (never a quiet ``False``).
        """
        p = as_vector(pose, self.dof, 'pose')
        try:
            self.inverse(p, **branch)  # type: ignore[attr-defined]
            return not singularity or self._singularity_measure(p, **branch) <= self.singularity_condition_max
        except UnreachablePose:
            return False


# ---------------------------------------------------------------------- from_config plumbing
def check_section(section: Any, type_name: str, cls_name: str, required: Sequence[str]) -> None:
    """The YAML ``mechanism`` section is a mapping of ``type_name`` holding every ``required`` key,
    and no key, type or range that :data:`brace_control.schema.MECHANISM_SCHEMAS` does not allow
    for ``type_name`` (every ``from_config`` passes here: the one check of a section built in
    Python).

    :raises ConfigError: naming what is wrong.
    """
    if not isinstance(section, Mapping):
        raise ConfigError(f'mechanism: expected a mapping, got {type(section).__name__}')
    kind = section.get('type', type_name)
    if kind != type_name:
        raise ConfigError(f'mechanism.type is {kind!r}, {cls_name} needs "{type_name}"')
    schema.validate({'mechanism': {**section, 'type': type_name}})
    for key in required:
        if key not in section:
            raise ConfigError(f'parameter mechanism.{key} is missing')


def section_kwargs(section: Mapping[str, Any], present: Sequence[str] = (),
                   given: Sequence[str] = ()) -> dict[str, Any]:
    """Constructor keywords from the section: each key of ``present`` that is in it (even
    as ``null``), each key of ``given`` that is in it and not ``null``."""
    kwargs = {key: section[key] for key in present if key in section}
    kwargs.update({key: section[key] for key in given if section.get(key) is not None})
    return kwargs


def section_points(section: Mapping[str, Any], key: str, n: int, label: str) -> np.ndarray:
    """``mechanism.<key>``, a (flattened) point list of exactly ``n`` points, as (n, 2).

    :raises ConfigError: malformed, or another number of points ("a 3-RPR needs 3 points").
    """
    arr = points(section[key], f'mechanism.{key}')
    if arr.shape != (n, 2):
        raise ConfigError(f'mechanism.{key}: a {label} needs {n} points ({2 * n} numbers), got {arr.shape[0]}')
    return arr


@contextmanager
def config_errors() -> Iterator[None]:
    """Re-raise a constructor's ``ValueError`` / ``TypeError`` as ``ConfigError('mechanism: ...')``
    (an :class:`UnreachablePose`: the home pose the constructor checks, ``mechanism.home_pose``)."""
    try:
        yield
    except ConfigError:
        raise
    except UnreachablePose as exc:
        raise ConfigError(f'mechanism.home_pose is not reachable: {exc}') from exc
    except (ValueError, TypeError) as exc:
        raise ConfigError(f'mechanism: {exc}') from exc


#: the pose kinds a mechanism may declare (:attr:`Mechanism.pose_kind`) and their dof
POSE_KINDS = {'planar': 3, 'xy': 2, 'path': 1, 'spherical': 3}


def warm_up(mechanism: Any) -> None:
    """Run once, at home, each model path a control cycle calls (``inverse``,
    ``forward_nearest``, ``jacobian``, ``wrench``, ``wrench_capacity``, and the capacity's linear programme
    whatever the pose), so that what they import on first use (scipy's ``linprog``, the
    continuum robot's elliptic integrals and root finds) is imported by the caller, not by a
    SYNC thread. A first import there (``linprog``, for a soft stop's reason on the 4-RPR
    neck brace) held the cycle for over 100 ms, and the drives' heartbeat consumers (1016h,
    twice the master's period) stopped them. Errors are the model's to report elsewhere:
    a path that raises here has still imported what it needs.
    """
    home = np.asarray(mechanism.home_pose, dtype=float)
    failures = (ValueError, TypeError, ArithmeticError, AttributeError)
    with suppress(*failures):
        q = np.asarray(mechanism.inverse(home), dtype=float)
        mechanism.forward_nearest(q, home)
    with suppress(*failures):
        mechanism.jacobian(home)
    with suppress(*failures):
        mechanism.wrench(home, np.zeros(int(mechanism.n_actuators)))
    with suppress(*failures):
        mechanism.wrench_capacity(home, 1.0)
    capacity_lp(np.eye(2), -np.ones(2), np.ones(2))

