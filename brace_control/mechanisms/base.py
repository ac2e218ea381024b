"""The protocol every mechanism model follows, and the errors they raise.

Pure numpy/scipy: no ROS, no CAN. See ARCHITECTURE.md ("Python API contract").
A *pose* is the platform's coordinates (planar: ``(x, y, theta)``, platform point ``b``
of the platform frame at ``(x, y) + R(theta) b``); ``q`` are the actuator coordinates
(lengths in m or joint angles in rad).

Besides the protocol, the pieces every model shares (one copy, used by all):

* input validators — :func:`as_vector`, :func:`as_points`, :func:`as_per_actuator`,
  :func:`as_range`, :func:`as_actuator_names`, :func:`as_condition_max`, :func:`as_positive`;
* :class:`MechanismBase` — the ``actuator_limits`` / ``home_pose`` properties and the
  bodies behind ``check_singularity`` / ``in_workspace``;
* ``from_config`` plumbing — :func:`check_section`, :func:`section_kwargs`,
  :func:`section_points`, :func:`config_errors`.
"""
from __future__ import annotations

import math
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from typing import Any, Protocol, Sequence, runtime_checkable

import numpy as np

from ..config import ConfigError, points

__all__ = [
    'Mechanism', 'MechanismBase', 'UnreachablePose', 'SingularPose',
    'as_vector', 'as_points', 'as_per_actuator', 'as_range', 'as_actuator_names', 'as_condition_max',
    'as_positive',
    'condition_number', 'check_limits', 'rot2',
    'check_section', 'section_kwargs', 'section_points', 'config_errors',
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


@runtime_checkable
class Mechanism(Protocol):
    """What the nodes, the trajectory planner and the simulator rely on."""

    dof: int
    n_actuators: int
    actuator_names: tuple[str, ...]

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


def rot2(theta: float | np.ndarray) -> np.ndarray:
    """Planar rotation matrix R(theta) (shape (2, 2), or (..., 2, 2) for an array)."""
    c, s = np.cos(theta), np.sin(theta)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


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
    """The YAML ``mechanism`` section is a mapping of ``type_name`` holding every ``required`` key.

    :raises ConfigError: naming what is wrong.
    """
    if not isinstance(section, Mapping):
        raise ConfigError(f'mechanism: expected a mapping, got {type(section).__name__}')
    kind = section.get('type', type_name)
    if kind != type_name:
        raise ConfigError(f'mechanism.type is {kind!r}, {cls_name} needs "{type_name}"')
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
    """Re-raise a constructor's ``ValueError`` / ``TypeError`` as ``ConfigError('mechanism: ...')``."""
    try:
        yield
    except ConfigError:
        raise
    except (ValueError, TypeError) as exc:
        raise ConfigError(f'mechanism: {exc}') from exc
