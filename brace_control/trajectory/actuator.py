"""A planned pose motion in actuator coordinates: what the IK node sends the driver.

The whole motion is converted at once (ARCHITECTURE.md, "Data flow": ``ik_node`` turns
``/brace/pose_trajectory`` into ``/brace/actuator_trajectory``), vectorised over its knots:

* ``q = IK(x)`` (``mech.inverse_batch``),
* ``q_dot = J(x) x_dot`` (``mech.jacobian_batch``),
* ``q_ddot = J(x) x_ddot + (d/dt J) x_dot``, the second derivative of ``q`` along the
  path, from the central second difference of ``IK(x +- x_dot h + x_ddot h^2 / 2)``
  (exact to O(h^2): the odd terms cancel),

then knots are added (:func:`~.knots.refine`) until the actuator motion rebuilt by quintic
Hermite interpolation matches the IK of the pose motion at every segment midpoint within
``tol`` (1 um by default), so the drives follow the IK of the planned poses, not an
approximation of it.

Pure numpy: no ROS.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from .base import TrajectoryError
from .hermite import KnotTrajectory
from .knots import MAX_KNOTS, refine

if TYPE_CHECKING:  # pragma: no cover
    from ..mechanisms.base import Mechanism

__all__ = ['actuator_knots', 'ACTUATOR_TOLERANCE', 'UnreachableKnot']

#: largest |rebuilt - IK(pose)| at a segment midpoint (m or rad)
ACTUATOR_TOLERANCE = 1e-6
#: s, the step of the second difference along the path
_H = 1e-3


class UnreachableKnot(TrajectoryError):
    """A pose of the motion has no inverse kinematics (outside the stroke or the workspace)."""

    def __init__(self, message: str, time: float) -> None:
        super().__init__(message)
        self.time = time


def actuator_knots(mech: 'Mechanism', poses: KnotTrajectory, *,
                   tol: float = ACTUATOR_TOLERANCE, max_knots: int = MAX_KNOTS) -> KnotTrajectory:
    """``poses`` (pose knots) -> actuator knots rebuilding ``IK(poses(t))`` within ``tol``.

    :raises UnreachableKnot: a pose of the motion (at a knot or a checked midpoint) is
        unreachable; the message names the time and the pose.
    :raises TrajectoryError: the tolerance cannot be met within ``max_knots`` knots.
    """
    if poses.dim != mech.dof:
        raise TrajectoryError(f'pose knots have {poses.dim} coordinates, the mechanism has '
                              f'{mech.dof}')

    def evaluate(ts: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        P, V, A = poses.sample_many(ts)
        Q = np.asarray(mech.inverse_batch(P), dtype=float)
        bad = np.flatnonzero(~np.all(np.isfinite(Q), axis=1))
        if bad.size:
            i = int(bad[0])
            raise UnreachableKnot(f'the pose {np.round(P[i], 6).tolist()} at t = {ts[i]:.3f} s '
                                  f'has no inverse kinematics', float(ts[i]))
        J = np.asarray(mech.jacobian_batch(P), dtype=float)
        QD = np.einsum('kij,kj->ki', J, V)
        half = 0.5 * A * _H * _H
        Qp = np.asarray(mech.inverse_batch(P + V * _H + half), dtype=float)
        Qm = np.asarray(mech.inverse_batch(P - V * _H + half), dtype=float)
        QDD = (Qp - 2.0 * Q + Qm) / (_H * _H)
        # at a stroke end a neighbour may fall outside: the curvature term is dropped there
        lost = ~np.all(np.isfinite(QDD), axis=1)
        if np.any(lost):
            QDD[lost] = np.einsum('kij,kj->ki', J[lost], A[lost])
        # a motion at rest stays exactly at rest (no rounding noise from the differences)
        still = np.all(V == 0.0, axis=1) & np.all(A == 0.0, axis=1)
        QD[still] = 0.0
        QDD[still] = 0.0
        return Q, QD, QDD

    return refine(evaluate, poses.times, tol=tol, max_knots=max_knots)
