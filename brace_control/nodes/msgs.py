"""Conversions between ROS messages and the plain arrays the math uses.

Shared by every node (and by the bag / demo tools), so that a pose, a set of actuator
values or a stamp is read and validated in exactly one place. No math beyond the
conversions; no node state.

Pose conventions (ARCHITECTURE.md, "Data flow"):

* planar devices (``pose = (x, y, theta)``): ``position.x``, ``position.y`` and a yaw
  quaternion ``(0, 0, sin(theta/2), cos(theta/2))``; ``position.z`` must be 0 and the
  quaternion must be a rotation about z only (:func:`planar_pose_from_msg`).
* 2-DOF planar devices (``pose = (x, y)``): ``position.x``, ``position.y``, identity
  orientation.
* one-DOF devices (``pose = (s,)``): ``position.x`` is the coordinate along the path.
* the spherical shoulder: the orientation quaternion; the mechanism converts it to its
  own pose coordinates with ``pose_from_quaternion(q)`` / ``quaternion_from_pose(pose)``
  when it has them, else the pose is the rotation vector (axis × angle, rad).

Every reader raises :class:`MalformedMessage` (a ``ValueError``) with a message a
technician can act on; nothing is clamped or guessed.

>>> from brace_control.nodes.msgs import pose_msg, pose_from_msg
>>> msg = pose_msg([0.0, 0.39, 0.05], frame_id='brace_base')
>>> pose_from_msg(msg, dof=3, frame_id='brace_base')
array([0.  , 0.39, 0.05])
"""
from __future__ import annotations

import array
import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from geometry_msgs.msg import (PoseStamped, PoseWithCovarianceStamped, Transform, Twist,
                               WrenchStamped)
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import (JointTrajectory, JointTrajectoryPoint, MultiDOFJointTrajectory,
                                 MultiDOFJointTrajectoryPoint)

__all__ = [
    'MalformedMessage',
    # stamps
    'stamp_to_sec', 'sec_to_stamp', 'stamp_to_ns', 'ns_to_stamp', 'now_stamp',
    # quaternions
    'yaw_quaternion', 'quaternion_yaw', 'quaternion_from_rotvec', 'rotvec_from_quaternion',
    # poses
    'pose_kind', 'pose_msg', 'pose_from_msg', 'planar_pose_msg', 'planar_pose_from_msg',
    # joint states
    'joint_state', 'joint_state_arrays',
    # wrench
    'wrench_msg',
    # trajectories (knots)
    'pose_trajectory_msg', 'pose_knots_from_msg', 'joint_trajectory_msg', 'joint_knots_from_msg',
    'duration_to_sec',
    # status events
    'status_msg', 'status_values',
    # pose with covariance
    'POSE_COVARIANCE_AXES', 'UNOBSERVED_VARIANCE', 'pose_covariance_6x6', 'pose_with_covariance_msg',
]

#: tolerance on |q| - 1 and on the non-yaw components of a planar quaternion
QUATERNION_TOL = 1e-3
#: tolerance on position.z of a planar pose (m)
PLANAR_Z_TOL = 1e-6


class MalformedMessage(ValueError):
    """A message that cannot be turned into a valid command or measurement.

    ``reason`` is a short machine-friendly tag (``'non_finite'``, ``'frame'``,
    ``'non_planar'``, ``'names'``, ``'length'``, ``'quaternion'``); ``str(exc)`` is the
    human message.
    """

    def __init__(self, message: str, *, reason: str = 'malformed') -> None:
        super().__init__(message)
        self.reason = reason


# --------------------------------------------------------------------------- stamps

def stamp_to_ns(stamp: Time) -> int:
    """``builtin_interfaces/Time`` -> integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def stamp_to_sec(stamp: Time) -> float:
    """``builtin_interfaces/Time`` -> float seconds."""
    return stamp_to_ns(stamp) * 1e-9


def ns_to_stamp(ns: int) -> Time:
    """Integer nanoseconds -> ``builtin_interfaces/Time`` (``sec`` floor, ``nanosec`` in [0, 1e9))."""
    sec, nanosec = divmod(int(ns), 1_000_000_000)
    return Time(sec=sec, nanosec=nanosec)


def sec_to_stamp(t: float) -> Time:
    """Float seconds -> ``builtin_interfaces/Time``."""
    return ns_to_stamp(round(t * 1e9))


def now_stamp(node: Any) -> Time:
    """The node's clock now as a message stamp (honours ``use_sim_time``)."""
    return node.get_clock().now().to_msg()


# --------------------------------------------------------------------- quaternions

def yaw_quaternion(theta: float) -> tuple[float, float, float, float]:
    """Rotation by ``theta`` (rad) about z as ``(x, y, z, w)``."""
    return (0.0, 0.0, math.sin(theta / 2.0), math.cos(theta / 2.0))


def _quat_tuple(q: Any) -> np.ndarray:
    arr = np.array([q.x, q.y, q.z, q.w], dtype=float) if hasattr(q, 'w') else np.asarray(q, float)
    if arr.shape != (4,) or not np.all(np.isfinite(arr)):
        raise MalformedMessage(f'orientation is not a finite quaternion: {arr.tolist()}',
                               reason='non_finite')
    n = float(np.linalg.norm(arr))
    if abs(n - 1.0) > QUATERNION_TOL:
        raise MalformedMessage(f'orientation quaternion has norm {n:.6f}, expected 1',
                               reason='quaternion')
    return arr / n


def quaternion_yaw(q: Any, *, tol: float = QUATERNION_TOL) -> float:
    """Yaw (rad, in (-pi, pi]) of a quaternion that must be a rotation about z only.

    :param q: a ``geometry_msgs/Quaternion`` or ``(x, y, z, w)``.
    :raises MalformedMessage: non-finite, not unit, or with a roll/pitch component
        (|x| or |y| above ``tol``): a planar device cannot take it.
    """
    x, y, z, w = _quat_tuple(q)
    if abs(x) > tol or abs(y) > tol:
        raise MalformedMessage(
            f'orientation ({x:.4f}, {y:.4f}, {z:.4f}, {w:.4f}) is not a rotation about z: '
            'a planar device takes a yaw-only quaternion', reason='non_planar')
    return math.atan2(2.0 * w * z, 1.0 - 2.0 * z * z)


def quaternion_from_rotvec(rv: Sequence[float]) -> tuple[float, float, float, float]:
    """Rotation vector (axis × angle, rad) -> ``(x, y, z, w)``."""
    rv = np.asarray(rv, dtype=float)
    angle = float(np.linalg.norm(rv))
    if angle < 1e-12:
        return (0.5 * rv[0], 0.5 * rv[1], 0.5 * rv[2], 1.0)
    axis = rv / angle
    s = math.sin(angle / 2.0)
    return (axis[0] * s, axis[1] * s, axis[2] * s, math.cos(angle / 2.0))


def rotvec_from_quaternion(q: Any) -> np.ndarray:
    """Quaternion (message or ``(x, y, z, w)``) -> rotation vector (rad), angle in [0, pi]."""
    x, y, z, w = _quat_tuple(q)
    if w < 0.0:
        x, y, z, w = -x, -y, -z, -w
    s = math.sqrt(x * x + y * y + z * z)
    if s < 1e-12:
        return np.array([2.0 * x, 2.0 * y, 2.0 * z])
    angle = 2.0 * math.atan2(s, w)
    return np.array([x, y, z]) / s * angle


# ------------------------------------------------------------------------- poses

def pose_kind(mechanism: Any) -> str:
    """How a mechanism's pose maps onto a ``Pose``: its ``pose_kind`` (``'planar'``, ``'xy'``,
    ``'path'``, ``'spherical'``: :data:`brace_control.mechanisms.base.POSE_KINDS`).

    :raises TypeError: the mechanism declares none.
    """
    kind = getattr(mechanism, 'pose_kind', None)
    if not isinstance(kind, str) or not kind:
        raise TypeError(f'{type(mechanism).__name__} declares no pose_kind (one of planar, xy, path, '
                        'spherical: brace_control.mechanisms.base.Mechanism)')
    return kind


def _check_frame(msg: PoseStamped, frame_id: str | None) -> None:
    if frame_id is not None and msg.header.frame_id != frame_id:
        raise MalformedMessage(
            f'pose is in frame {msg.header.frame_id!r}, expected {frame_id!r}', reason='frame')


def _finite_position(msg: PoseStamped) -> np.ndarray:
    p = msg.pose.position
    arr = np.array([p.x, p.y, p.z], dtype=float)
    if not np.all(np.isfinite(arr)):
        raise MalformedMessage(f'position is not finite: {arr.tolist()}', reason='non_finite')
    return arr


def planar_pose_from_msg(msg: PoseStamped, *, frame_id: str | None = None) -> np.ndarray:
    """``PoseStamped`` -> planar pose ``(x, y, theta)``.

    :param frame_id: the frame the pose must be in (``None``: any).
    :raises MalformedMessage: wrong frame, NaN/inf, ``position.z`` not 0, or an
        orientation that is not a unit yaw-only quaternion.
    """
    _check_frame(msg, frame_id)
    xyz = _finite_position(msg)
    theta = quaternion_yaw(msg.pose.orientation)
    if abs(xyz[2]) > PLANAR_Z_TOL:
        raise MalformedMessage(f'position.z = {xyz[2]:.6f} m: a planar pose has z = 0',
                               reason='non_planar')
    return np.array([xyz[0], xyz[1], theta])


def planar_pose_msg(pose: Sequence[float], *, frame_id: str, stamp: Time | None = None) -> PoseStamped:
    """Planar pose ``(x, y, theta)`` -> ``PoseStamped`` (z = 0, yaw quaternion)."""
    return pose_msg(pose, frame_id=frame_id, stamp=stamp, kind='planar')


def pose_from_msg(msg: PoseStamped, *, dof: int | None = None, frame_id: str | None = None,
                  kind: str | None = None, mechanism: Any = None) -> np.ndarray:
    """``PoseStamped`` -> the mechanism's pose vector, validated.

    Give ``mechanism`` (its :func:`pose_kind` decides), or ``kind``, or ``dof``.

    :raises MalformedMessage: see :func:`planar_pose_from_msg`; for ``'xy'`` and
        ``'path'`` the unused coordinates must be 0 and the orientation the identity.
    """
    if kind is None:
        kind = pose_kind(mechanism) if mechanism is not None else \
            {3: 'planar', 2: 'xy', 1: 'path'}[int(dof or 3)]
    if kind == 'planar':
        return planar_pose_from_msg(msg, frame_id=frame_id)
    _check_frame(msg, frame_id)
    if kind == 'spherical':
        q = _quat_tuple(msg.pose.orientation)
        _finite_position(msg)
        conv = getattr(mechanism, 'pose_from_quaternion', None)
        return np.asarray(conv(q), dtype=float) if conv else rotvec_from_quaternion(q)
    xyz = _finite_position(msg)
    theta = quaternion_yaw(msg.pose.orientation)
    if abs(theta) > QUATERNION_TOL:
        raise MalformedMessage(f'orientation has yaw {theta:.4f} rad: this device has no rotation',
                               reason='non_planar')
    if kind == 'xy':
        if abs(xyz[2]) > PLANAR_Z_TOL:
            raise MalformedMessage(f'position.z = {xyz[2]:.6f}: a planar pose has z = 0',
                                   reason='non_planar')
        return xyz[:2].copy()
    if kind == 'path':
        if abs(xyz[1]) > PLANAR_Z_TOL or abs(xyz[2]) > PLANAR_Z_TOL:
            raise MalformedMessage('a one-DOF pose uses position.x only (y = z = 0)',
                                   reason='non_planar')
        return xyz[:1].copy()
    raise ValueError(f'unknown pose kind {kind!r}')


def pose_msg(pose: Sequence[float], *, frame_id: str, stamp: Time | None = None,
             kind: str | None = None, mechanism: Any = None) -> PoseStamped:
    """A mechanism pose vector -> ``PoseStamped`` in ``frame_id`` (inverse of :func:`pose_from_msg`).

    ``kind`` defaults to the mechanism's :func:`pose_kind`, else to the vector's length.
    """
    msg = PoseStamped()
    msg.header.frame_id = frame_id
    if stamp is not None:
        msg.header.stamp = stamp
    _write_pose(msg.pose, pose, kind, mechanism)
    return msg


def _write_pose(out: Any, pose: Sequence[float], kind: str | None, mechanism: Any) -> None:
    """Write a mechanism pose vector into a ``geometry_msgs/Pose`` (see :func:`pose_msg`)."""
    p = np.asarray(pose, dtype=float).ravel()
    if kind is None:
        kind = pose_kind(mechanism) if mechanism is not None else \
            {3: 'planar', 2: 'xy', 1: 'path'}.get(p.size, 'planar')
    o = out.orientation
    if kind == 'spherical':
        conv = getattr(mechanism, 'quaternion_from_pose', None)
        o.x, o.y, o.z, o.w = (float(v) for v in (conv(p) if conv else quaternion_from_rotvec(p)))
        return
    out.position.x = float(p[0])
    if kind in ('planar', 'xy'):
        out.position.y = float(p[1])
    o.w = 1.0
    if kind == 'planar':
        o.x, o.y, o.z, o.w = yaw_quaternion(float(p[2]))


# ------------------------------------------------------------------- joint states

def joint_state(names: Sequence[str], *, position: Sequence[float] | None = None,
                velocity: Sequence[float] | None = None, effort: Sequence[float] | None = None,
                stamp: Time | None = None, frame_id: str = '') -> JointState:
    """Build a ``JointState`` with one entry per name (arrays may be omitted -> empty)."""
    msg = JointState()
    msg.name = list(names)
    if stamp is not None:
        msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    n = len(msg.name)
    for field, values in (('position', position), ('velocity', velocity), ('effort', effort)):
        if values is None:
            continue
        # the message keeps a double array ('d'): given one, its setter takes it as it is
        # (a list is checked value by value, then converted); a float64 vector's doubles
        # are copied as they are, anything else goes through float() as before
        if isinstance(values, np.ndarray) and values.dtype == np.float64 and values.ndim == 1:
            vals = array.array('d', values.tobytes())
        else:
            vals = array.array('d', [float(v) for v in values])
        if len(vals) != n:
            raise ValueError(f'{field}: {len(vals)} values for {n} names')
        setattr(msg, field, vals)
    return msg


def joint_state_arrays(msg: JointState, names: Sequence[str],
                       fields: Sequence[str] = ('position',), *,
                       optional: Sequence[str] = ()) -> dict[str, np.ndarray | None]:
    """Read ``fields`` of a ``JointState`` into arrays ordered as ``names``.

    The message may list the joints in any order and may hold extra joints; every name
    in ``names`` must be present. A field in ``optional`` may be empty (-> ``None``).

    :raises MalformedMessage: a missing name, duplicate names, an array whose length is not
        the number of names, or a non-finite value (the message names the joint).
    """
    index: dict[str, int] = {}
    for i, name in enumerate(msg.name):
        if name in index:
            raise MalformedMessage(f'joint {name!r} listed twice', reason='names')
        index[name] = i
    missing = [n for n in names if n not in index]
    if missing:
        raise MalformedMessage(f'joint state lacks {missing} (has {list(msg.name)})', reason='names')
    order = [index[n] for n in names]
    out: dict[str, np.ndarray | None] = {}
    for field in fields:
        values = np.asarray(getattr(msg, field), dtype=float)
        if values.size == 0 and field in optional:
            out[field] = None
            continue
        if values.size != len(msg.name):
            raise MalformedMessage(
                f'{field} has {values.size} values for {len(msg.name)} names', reason='length')
        arr = values[order]
        bad = [names[i] for i in range(len(names)) if not math.isfinite(arr[i])]
        if bad:
            raise MalformedMessage(f'{field} of {bad} is not finite', reason='non_finite')
        out[field] = arr
    return out


# ------------------------------------------------------------------------ wrench

def wrench_msg(wrench: Sequence[float], *, frame_id: str, stamp: Time | None = None,
               kind: str = 'planar') -> WrenchStamped:
    """A mechanism-space wrench -> ``WrenchStamped``.

    ``planar``: ``(Fx, Fy, Mz)``; ``xy``: ``(Fx, Fy)``; ``path``: ``(F,)`` along x;
    ``spherical``: ``(Mx, My, Mz)``.
    """
    w = np.asarray(wrench, dtype=float).ravel()
    msg = WrenchStamped()
    msg.header.frame_id = frame_id
    if stamp is not None:
        msg.header.stamp = stamp
    f, t = msg.wrench.force, msg.wrench.torque
    if kind == 'spherical':
        t.x, t.y, t.z = (float(v) for v in w[:3])
    else:
        f.x = float(w[0])
        if kind in ('planar', 'xy'):
            f.y = float(w[1])
        if kind == 'planar':
            t.z = float(w[2])
    return msg


# ------------------------------------------------------------ pose with covariance

#: the order of ``geometry_msgs/PoseWithCovariance.covariance`` (6x6, row-major): position,
#: then rotations about the fixed axes of the header frame
POSE_COVARIANCE_AXES = ('x', 'y', 'z', 'rot_x', 'rot_y', 'rot_z')
#: variance (m^2, rad^2) given to a coordinate the device does not measure: "unknown" for a
#: consumer that fuses every entry (the robot_pose_ekf practice of inflating it); a
#: robot_localization user turns those entries off in the sensor's ``*_config`` instead
UNOBSERVED_VARIANCE = 1e6


def _quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product of ``(x, y, z, w)`` quaternions."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return np.array([aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw,
                     aw * bw - ax * bx - ay * by - az * bz])


def _rotation_jacobian(pose: np.ndarray, mechanism: Any, step: float = 1e-6) -> np.ndarray:
    """``G`` (3, dof): the rotation ``delta`` (rad, about the header frame's fixed axes) per
    unit change of each pose coordinate, ``Q(p + dp) = exp(delta) Q(p)``, ``delta = G dp``
    (central differences of the pose's quaternion)."""
    conv = getattr(mechanism, 'quaternion_from_pose', None)

    def quat(p: np.ndarray) -> np.ndarray:
        return np.asarray(conv(p) if conv else quaternion_from_rotvec(p), dtype=float)

    inverse = quat(pose) * np.array([-1.0, -1.0, -1.0, 1.0])
    g = np.empty((3, pose.size))
    for i in range(pose.size):
        dp = np.zeros(pose.size)
        dp[i] = step
        plus = rotvec_from_quaternion(_quat_mul(quat(pose + dp), inverse))
        minus = rotvec_from_quaternion(_quat_mul(quat(pose - dp), inverse))
        g[:, i] = (plus - minus) / (2.0 * step)
    return g


def pose_covariance_6x6(pose: Sequence[float], covariance: np.ndarray, *, kind: str | None = None,
                        mechanism: Any = None, unobserved_variance: float = UNOBSERVED_VARIANCE
                        ) -> np.ndarray:
    """A mechanism pose covariance -> the 6x6 of ``PoseWithCovariance`` (``POSE_COVARIANCE_AXES``).

    ``planar`` ``(x, y, theta)``: rows/columns x, y, rot_z; ``xy``: x, y; ``path`` ``(s,)``:
    x; ``spherical``: ``G Sigma G^T`` in the rotation block (``G`` the rotation about the
    header frame's axes per pose coordinate, :func:`_rotation_jacobian`). Every other
    diagonal entry (what the device does not measure) is ``unobserved_variance``, its
    off-diagonal entries 0.

    :raises ValueError: a covariance that is not (dof, dof), finite and symmetric.
    """
    p = np.asarray(pose, dtype=float).ravel()
    cov = np.asarray(covariance, dtype=float)
    if cov.shape != (p.size, p.size) or not np.isfinite(cov).all():
        raise ValueError(f'covariance: expected a finite ({p.size}, {p.size}) matrix for a pose of '
                         f'{p.size} coordinates, got shape {cov.shape}')
    # an exactly symmetric matrix (the estimator's is) is within any tolerance
    if not ((cov == cov.T).all() or np.allclose(cov, cov.T, rtol=1e-9, atol=0.0)):
        raise ValueError('covariance: not symmetric')
    if kind is None:
        kind = pose_kind(mechanism) if mechanism is not None else \
            {3: 'planar', 2: 'xy', 1: 'path'}.get(p.size, 'planar')
    out = np.zeros((6, 6))
    out.flat[::7] = float(unobserved_variance)
    if kind == 'spherical':
        g = _rotation_jacobian(p, mechanism)
        out[3:, 3:] = g @ cov @ g.T
        return out
    index = _COVARIANCE_INDEX.get(kind)
    if index is None or index[0].size != p.size:
        raise ValueError(f'pose kind {kind!r} does not fit a pose of {p.size} coordinates')
    out[index] = cov
    return out


#: the rows/columns of POSE_COVARIANCE_AXES a pose kind's coordinates occupy (``np.ix_``)
_COVARIANCE_INDEX = {kind: np.ix_(axes, axes)
                     for kind, axes in (('planar', [0, 1, 5]), ('xy', [0, 1]), ('path', [0]))}


def pose_with_covariance_msg(pose: Sequence[float], covariance: np.ndarray, *, frame_id: str,
                             stamp: Time | None = None, kind: str | None = None,
                             mechanism: Any = None,
                             unobserved_variance: float = UNOBSERVED_VARIANCE
                             ) -> PoseWithCovarianceStamped:
    """A pose and its covariance -> ``PoseWithCovarianceStamped`` (pose as :func:`pose_msg`,
    covariance as :func:`pose_covariance_6x6`, row-major)."""
    msg = PoseWithCovarianceStamped()
    msg.header.frame_id = frame_id
    if stamp is not None:
        msg.header.stamp = stamp
    _write_pose(msg.pose.pose, pose, kind, mechanism)
    # the field is a float64 array of 36: handed the row-major array itself (no list)
    msg.pose.covariance = pose_covariance_6x6(
        pose, covariance, kind=kind, mechanism=mechanism,
        unobserved_variance=unobserved_variance).ravel()
    return msg


# ------------------------------------------------------------------ trajectories (knots)
#
# A planned motion travels once, whole, as knots (ARCHITECTURE.md "Data flow"):
#
# * ``/brace/pose_trajectory`` (``trajectory_msgs/MultiDOFJointTrajectory``): one joint, the
#   platform (``joint_names = [platform_frame]``), ``header.frame_id`` = the base frame,
#   ``header.stamp`` = when the motion starts (its first knot), each point's
#   ``transforms[0]`` / ``velocities[0]`` / ``accelerations[0]`` at ``time_from_start``.
#   The pose is written as in :func:`pose_msg` (planar: translation x, y and a yaw
#   quaternion; xy: translation; path: translation.x; spherical: the rotation). Rates are
#   the pose coordinates' own derivatives: planar ``(x_dot, y_dot)`` in ``linear.x/y`` and
#   ``theta_dot`` in ``angular.z``; xy ``linear.x/y``; path ``linear.x``; spherical the
#   three pose-coordinate rates in ``angular.x/y/z`` (not a body angular velocity).
# * ``/brace/actuator_trajectory`` (``trajectory_msgs/JointTrajectory``): one joint per
#   actuator, positions (m or rad), velocities, accelerations at ``time_from_start``; the
#   same ``header.stamp``.
#
# An empty trajectory (no points) is a stop: decelerate along the running path and hold
# (``header.stamp`` nonzero: only if it is the trajectory with that stamp).


def duration_to_sec(d: Any) -> float:
    """``builtin_interfaces/Duration`` -> float seconds."""
    return int(d.sec) + int(d.nanosec) * 1e-9


def _duration(t: float) -> Any:
    from builtin_interfaces.msg import Duration
    sec, nanosec = divmod(round(float(t) * 1e9), 1_000_000_000)
    return Duration(sec=int(sec), nanosec=int(nanosec))


_RATE_FIELDS = {
    'planar': (('linear', 'x'), ('linear', 'y'), ('angular', 'z')),
    'xy': (('linear', 'x'), ('linear', 'y')),
    'path': (('linear', 'x'),),
    'spherical': (('angular', 'x'), ('angular', 'y'), ('angular', 'z')),
}


def _write_rates(twist: Any, values: np.ndarray, kind: str) -> None:
    for (part, axis), value in zip(_RATE_FIELDS[kind], values):
        setattr(getattr(twist, part), axis, float(value))


def _read_rates(twist: Any, kind: str) -> np.ndarray:
    return np.array([getattr(getattr(twist, part), axis) for part, axis in _RATE_FIELDS[kind]],
                    dtype=float)


def pose_trajectory_msg(times: np.ndarray, poses: np.ndarray, velocities: np.ndarray,
                        accelerations: np.ndarray, *, frame_id: str, joint_name: str,
                        stamp: Time, mechanism: Any = None,
                        kind: str | None = None) -> MultiDOFJointTrajectory:
    """Pose knots -> ``MultiDOFJointTrajectory`` (see the conventions above)."""
    kind = kind or (pose_kind(mechanism) if mechanism is not None else
                    {3: 'planar', 2: 'xy', 1: 'path'}[np.shape(poses)[1]])
    msg = MultiDOFJointTrajectory()
    msg.header.frame_id = frame_id
    msg.header.stamp = stamp
    msg.joint_names = [joint_name]
    points = []
    for t, p, v, a in zip(np.asarray(times, float), np.asarray(poses, float),
                          np.asarray(velocities, float), np.asarray(accelerations, float)):
        pose = pose_msg(p, frame_id=frame_id, kind=kind, mechanism=mechanism).pose
        point = MultiDOFJointTrajectoryPoint()
        tf = point.transforms
        transform = Transform()
        transform.translation.x = pose.position.x
        transform.translation.y = pose.position.y
        transform.translation.z = pose.position.z
        transform.rotation = pose.orientation
        tf.append(transform)
        vel, acc = Twist(), Twist()
        _write_rates(vel, v, kind)
        _write_rates(acc, a, kind)
        point.velocities.append(vel)
        point.accelerations.append(acc)
        point.time_from_start = _duration(t)
        points.append(point)
    msg.points = points
    return msg


def pose_knots_from_msg(msg: MultiDOFJointTrajectory, *, frame_id: str, mechanism: Any = None,
                        kind: str | None = None
                        ) -> tuple[int, np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
    """``MultiDOFJointTrajectory`` -> ``(stamp_ns, times, poses, velocities, accelerations)``.

    Velocities (accelerations) are ``None`` when no point carries them (the motion is then
    rebuilt from the positions); a point without them when others have them is an error.

    :raises MalformedMessage: wrong frame, not one joint, a point without its transform,
        non-finite values, times not increasing.
    """
    if msg.header.frame_id != frame_id:
        raise MalformedMessage(f'trajectory is in frame {msg.header.frame_id!r}, expected '
                               f'{frame_id!r}', reason='frame')
    if len(msg.joint_names) != 1:
        raise MalformedMessage(f'expected one joint (the platform), got {list(msg.joint_names)}',
                               reason='names')
    kind = kind or (pose_kind(mechanism) if mechanism is not None else 'planar')
    n = len(msg.points)
    dof = len(_RATE_FIELDS[kind])
    times = np.empty(n)
    P, V, A = np.zeros((n, dof)), np.zeros((n, dof)), np.zeros((n, dof))
    has_v = [len(point.velocities) > 0 for point in msg.points]
    has_a = [len(point.accelerations) > 0 for point in msg.points]
    for name, has in (('velocities', has_v), ('accelerations', has_a)):
        if any(has) and not all(has):
            raise MalformedMessage(f'{name} on some points only', reason='length')
    for i, point in enumerate(msg.points):
        if len(point.transforms) != 1:
            raise MalformedMessage(f'point {i} has {len(point.transforms)} transforms, expected 1',
                                   reason='length')
        tf = point.transforms[0]
        ps = PoseStamped()
        ps.header.frame_id = frame_id
        ps.pose.position.x, ps.pose.position.y, ps.pose.position.z = \
            tf.translation.x, tf.translation.y, tf.translation.z
        ps.pose.orientation = tf.rotation
        try:
            P[i] = pose_from_msg(ps, frame_id=frame_id, kind=kind, mechanism=mechanism)
        except MalformedMessage as exc:
            raise MalformedMessage(f'point {i}: {exc}', reason=exc.reason) from exc
        for box, values in ((V, point.velocities), (A, point.accelerations)):
            if len(values) > 1:
                raise MalformedMessage(f'point {i}: more than one twist', reason='length')
            if values:
                box[i] = _read_rates(values[0], kind)
        times[i] = duration_to_sec(point.time_from_start)
    if not (np.all(np.isfinite(V)) and np.all(np.isfinite(A)) and np.all(np.isfinite(times))):
        raise MalformedMessage('non-finite time, velocity or acceleration', reason='non_finite')
    if n and (times[0] < 0.0 or np.any(np.diff(times) <= 0.0)):
        raise MalformedMessage('time_from_start must be >= 0 and strictly increasing',
                               reason='time')
    return (stamp_to_ns(msg.header.stamp), times, P, V if all(has_v) and n else None,
            A if all(has_a) and n else None)


def joint_trajectory_msg(names: Sequence[str], times: np.ndarray, positions: np.ndarray,
                         velocities: np.ndarray, accelerations: np.ndarray, *,
                         stamp: Time, frame_id: str = '') -> JointTrajectory:
    """Actuator knots -> ``JointTrajectory`` (one joint per actuator, in ``names`` order)."""
    msg = JointTrajectory()
    msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    msg.joint_names = list(names)
    points = []
    for t, q, v, a in zip(np.asarray(times, float), np.asarray(positions, float),
                          np.asarray(velocities, float), np.asarray(accelerations, float)):
        point = JointTrajectoryPoint()
        point.positions = q.tolist()
        point.velocities = v.tolist()
        point.accelerations = a.tolist()
        point.time_from_start = _duration(t)
        points.append(point)
    msg.points = points
    return msg


def joint_knots_from_msg(msg: JointTrajectory, names: Sequence[str]
                         ) -> tuple[int, np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
    """``JointTrajectory`` -> ``(stamp_ns, times, positions, velocities, accelerations)`` in
    ``names`` order; velocities / accelerations ``None`` when no point has them.

    The message may list the joints in any order; every name must be there exactly once.

    :raises MalformedMessage: missing or duplicate joints, a point whose arrays have the
        wrong length (or velocities on some points only), non-finite values, times not
        increasing.
    """
    index: dict[str, int] = {}
    for i, name in enumerate(msg.joint_names):
        if name in index:
            raise MalformedMessage(f'joint {name!r} listed twice', reason='names')
        index[name] = i
    missing = [nm for nm in names if nm not in index]
    if missing:
        raise MalformedMessage(f'trajectory lacks joints {missing} (has {list(msg.joint_names)})',
                               reason='names')
    order = [index[nm] for nm in names]
    n, m = len(msg.points), len(msg.joint_names)
    times = np.array([duration_to_sec(p.time_from_start) for p in msg.points], dtype=float)

    def field(attr: str, required: bool) -> np.ndarray | None:
        rows = [list(getattr(p, attr)) for p in msg.points]
        if not any(rows) and not required:
            return None
        if any(len(r) != m for r in rows):
            raise MalformedMessage(f'{attr}: every point needs {m} values (one per joint)',
                                   reason='length')
        arr = np.array(rows, dtype=float).reshape(n, m)[:, order]
        if not np.all(np.isfinite(arr)):
            raise MalformedMessage(f'{attr}: non-finite value', reason='non_finite')
        return arr

    positions = field('positions', True)
    velocities = field('velocities', False)
    accelerations = field('accelerations', False)
    if not np.all(np.isfinite(times)) or (n and (times[0] < 0.0 or np.any(np.diff(times) <= 0.0))):
        raise MalformedMessage('time_from_start must be >= 0 and strictly increasing',
                               reason='time')
    return stamp_to_ns(msg.header.stamp), times, positions, velocities, accelerations


# ------------------------------------------------------------------------ status events

def status_msg(name: str, message: str, *, level: int = DiagnosticStatus.OK,
               hardware_id: str = '', **values: Any) -> DiagnosticStatus:
    """A ``diagnostic_msgs/DiagnosticStatus`` event (goal, execution or driver state): the
    ``values`` as key/value strings (floats as ``repr``, sequences comma separated)."""
    def text(v: Any) -> str:
        if isinstance(v, float):
            return repr(v)
        if isinstance(v, (list, tuple, np.ndarray)):
            return ','.join(text(float(x)) if isinstance(x, (float, np.floating)) else str(x)
                            for x in v)
        return str(v)
    return DiagnosticStatus(level=level, name=name, message=message, hardware_id=hardware_id,
                            values=[KeyValue(key=k, value=text(v)) for k, v in values.items()])


def status_values(msg: DiagnosticStatus) -> dict[str, str]:
    """The key/value pairs of a status event."""
    return {kv.key: kv.value for kv in msg.values}
