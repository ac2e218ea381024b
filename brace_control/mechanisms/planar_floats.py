"""Leg lengths and Jacobian of a planar n-RPR in plain floats: the per-sample hot paths.

The formulas of :class:`~.planar.RprLegs` (Rpr3, Rpr4): ``B_i = P + R(theta) b_i``,
``L_i = |B_i - A_i|`` (eq. 3 of the lumbar brace), row ``i`` of ``J`` = ``(u_i, rho_i x u_i)``
with ``u_i`` the unit vector ``A_i -> B_i`` and ``rho_i = R(theta) b_i``; the wrench
``J^T f``. Evaluated on Python floats: on 3-vectors numpy's per-call overhead (and, in a
process that sleeps between samples, the cold caches of its many code paths) is most of
the cost: ~5 us per evaluation instead of ~20-30 us for ``inverse`` / ``jacobian``.

Results agree with the model to rounding, not bit for bit (numpy forms ``R b_i`` as a
matrix product and the length with ``norm``): a user checks them against the model before
relying on them (:meth:`PlanarRprFloats.agrees_with`), and falls back to the model where
they disagree. Used by the simulated brace's physics (:mod:`brace_control.sim.brace`) and
the load-aware pose estimate (:mod:`.pose_estimate`).
"""
from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np

__all__ = ['PlanarRprFloats']


class PlanarRprFloats:
    """A planar n-RPR's legs in plain floats.

    :param base_anchors: ``A_i`` (n, 2), m, base frame.
    :param platform_anchors: ``b_i`` (n, 2), m, platform frame.

    ``a`` and ``b`` are the anchors as lists of ``(x, y)`` float pairs.
    """

    @classmethod
    def of(cls, mechanism: Any) -> 'PlanarRprFloats | None':
        """The legs of a planar RPR model (:class:`~.planar.RprLegs`, pose ``(x, y, theta)``)
        when they reproduce its ``inverse`` and ``jacobian`` (within 1e-12) and its ``wrench``
        as ``J^T f`` (within 1e-9 N, N·m) at the home pose and two poses about it; ``None``
        for any other mechanism or any disagreement."""
        from .planar import RprLegs
        if not isinstance(mechanism, RprLegs) or int(mechanism.dof) != 3:
            return None
        try:
            legs = cls(mechanism.base_anchors, mechanism.platform_anchors)
            home = np.asarray(mechanism.home_pose, dtype=float)
            poses = [home, home + np.array([0.004, -0.003, 0.05]), home + np.array([-0.006, 0.002, -0.08])]
            if len(legs.a) != int(mechanism.n_actuators) or not legs.agrees_with(mechanism, poses):
                return None
            forces = np.linspace(-50.0, 120.0, len(legs.a))
            for pose in poses:
                rows = legs.lengths_and_rows(*pose.tolist())[1]
                if not np.allclose(legs.wrench(rows, forces.tolist()), mechanism.wrench(pose, forces),
                                   rtol=0.0, atol=1e-9):
                    return None
        except (ValueError, TypeError, ZeroDivisionError):
            return None
        return legs

    def __init__(self, base_anchors: Any, platform_anchors: Any) -> None:
        self.a = [(float(x), float(y)) for x, y in np.asarray(base_anchors, dtype=float)]
        self.b = [(float(x), float(y)) for x, y in np.asarray(platform_anchors, dtype=float)]
        if len(self.a) != len(self.b) or not self.a:
            raise ValueError(f'anchors: {len(self.a)} base and {len(self.b)} platform points; '
                             'expected the same number (one per leg), at least one')

    def lengths(self, x: float, y: float, theta: float) -> list[float]:
        """``L_i`` (m) of the pose ``(x, y, theta)`` (stroke not checked)."""
        c, s = math.cos(theta), math.sin(theta)
        hypot = math.hypot
        return [hypot(x + (c * bx - s * by) - ax, y + (s * bx + c * by) - ay)
                for (ax, ay), (bx, by) in zip(self.a, self.b)]

    def lengths_and_rows(self, x: float, y: float, theta: float
                         ) -> tuple[list[float], list[tuple[float, float, float]]]:
        """``L_i`` and the rows ``(u_x, u_y, rho x u)`` of ``J``.

        :raises ZeroDivisionError: a leg of zero length (it has no direction).
        """
        c, s = math.cos(theta), math.sin(theta)
        lengths, rows = [], []
        for (ax, ay), (bx, by) in zip(self.a, self.b):
            rx, ry = c * bx - s * by, s * bx + c * by
            dx, dy = x + rx - ax, y + ry - ay
            n = math.hypot(dx, dy)
            ux, uy = dx / n, dy / n
            lengths.append(n)
            rows.append((ux, uy, rx * uy - ry * ux))
        return lengths, rows

    def __call__(self, pose: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
        """``(L, J)`` as arrays, shapes (n,) and (n, 3)."""
        lengths, rows = self.lengths_and_rows(float(pose[0]), float(pose[1]), float(pose[2]))
        return np.array(lengths), np.array(rows)

    @staticmethod
    def wrench(rows: Sequence[Sequence[float]], forces: Sequence[float]) -> list[float]:
        """``J^T f`` (Fx N, Fy N, M N·m about the platform origin) from the rows of ``J``."""
        fx = fy = m = 0.0
        for (ux, uy, mu), f in zip(rows, forces):
            fx += ux * f
            fy += uy * f
            m += mu * f
        return [fx, fy, m]

    def agrees_with(self, mechanism: Any, poses: Iterable[Sequence[float]], *,
                    atol: float = 1e-12, rtol: float = 0.0) -> bool:
        """Whether ``mechanism.inverse`` and ``mechanism.jacobian`` give these lengths and
        rows (``np.allclose`` with ``atol``, ``rtol``) at every pose of ``poses``; ``False``
        also when the model rejects one of them (a pose to check must be reachable)."""
        try:
            for pose in poses:
                lengths, jac = self(pose)
                if not (np.allclose(lengths, mechanism.inverse(pose), rtol=rtol, atol=atol)
                        and np.allclose(jac, mechanism.jacobian(pose), rtol=rtol, atol=atol)):
                    return False
        except (ValueError, TypeError, ZeroDivisionError):
            return False
        return True
