"""The protocol every mechanism model follows, and the errors they raise.

Pure numpy/scipy: no ROS, no CAN. See ARCHITECTURE.md ("Python API contract").
A *pose* is the platform's coordinates (planar: ``(x, y, theta)``, platform point ``b``
of the platform frame at ``(x, y) + R(theta) b``); ``q`` are the actuator coordinates
(lengths in m or joint angles in rad).
"""
from __future__ import annotations

from typing import Protocol, Sequence, runtime_checkable

import numpy as np

__all__ = [
    'Mechanism', 'UnreachablePose', 'SingularPose',
    'as_vector', 'check_limits', 'rot2',
]


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
