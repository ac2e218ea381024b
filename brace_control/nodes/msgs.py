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

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import PoseStamped, WrenchStamped
from sensor_msgs.msg import JointState

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
    """How a mechanism's pose maps onto a ``Pose``: ``'planar'``, ``'xy'``, ``'path'``, ``'spherical'``.

    A mechanism may say so itself with a ``pose_kind`` attribute; otherwise it is
    inferred from ``dof`` (3 -> planar, 2 -> xy, 1 -> path).
    """
    kind = getattr(mechanism, 'pose_kind', None)
    if kind:
        return str(kind)
    return {3: 'planar', 2: 'xy', 1: 'path'}.get(int(mechanism.dof), 'planar')


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
    p = np.asarray(pose, dtype=float).ravel()
    if kind is None:
        kind = pose_kind(mechanism) if mechanism is not None else \
            {3: 'planar', 2: 'xy', 1: 'path'}.get(p.size, 'planar')
    msg = PoseStamped()
    msg.header.frame_id = frame_id
    if stamp is not None:
        msg.header.stamp = stamp
    o = msg.pose.orientation
    if kind == 'spherical':
        conv = getattr(mechanism, 'quaternion_from_pose', None)
        o.x, o.y, o.z, o.w = (float(v) for v in (conv(p) if conv else quaternion_from_rotvec(p)))
        return msg
    msg.pose.position.x = float(p[0])
    if kind in ('planar', 'xy'):
        msg.pose.position.y = float(p[1])
    o.w = 1.0
    if kind == 'planar':
        o.x, o.y, o.z, o.w = yaw_quaternion(float(p[2]))
    return msg


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
        vals = [float(v) for v in values]
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
