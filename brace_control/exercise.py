"""The bundled exercise: a rosbag2 (mcap) of pose goals for the lumbar brace.

``python -m brace_control.exercise OUT [--config lumbar_brace]`` (also
``scripts/make_exercise_bag.py``) writes a bag of ``geometry_msgs/PoseStamped`` goals on
``/brace/pose_goal`` in the device's ``base_frame``: a vertical lift (+20 mm), a lowering
(-20 mm), a coronal rotation to 10 deg in two steps and a combined lift and rotation, each
returning to the neutral pose, with a pause between goals so that every motion
(minimum-jerk, Fitts' law duration) ends before the next goal: human pace.

Only goals the brace can really hold against the simulated body: no lateral shift for the
paper's brace (``lumbar_brace_v2``, laid out to push sideways, adds a 15 mm shift each way:
:func:`holds_lateral_shift`). The lumbar brace's legs are nearly parallel (the 3-RPR's anchor rows are collinear), so it
can push the thoracic ring sideways with very little force: its lateral wrench capacity
(``mech.wrench_capacity(pose, 250.0)``, the largest ``|Fx|`` the actuators hold within
their 250 N) is 0.711 N at the neutral pose (theta = 5 deg) and 1.58 N at 10 deg, limited
by a2 both times. The torso resists a lateral shift with 2000 N/m (``sim.stiffness``): a
15 mm shift needs 30 N, forty times the capacity, so the ring does not move sideways;
the legs compress and the ring rotates instead, and the goal is aborted, honestly,
because the platform did not follow. The lift, the lowering and the rotations need at
most 31 N per leg.

The neutral pose is the home pose turned to ``NEUTRAL_TILT`` in the coronal plane (the
YAML's home pose is already there). The 3-RPR lumbar brace is singular at every
``theta = 0`` pose (its two anchor rows are parallel there and the leg lines meet in one
point: a rotation about it is not resisted, see ``Rpr3.check_singularity``), so the
exercise stays on the ``theta > 0`` side.

The bag is written with ``rosbags`` (its own CDR serializer): no ROS graph is needed.
"""
from __future__ import annotations

import argparse
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .config import load_device_config
from .nodes import topics

__all__ = ['Goal', 'exercise_goals', 'device_exercise', 'holds_lateral_shift', 'write_goal_bag',
           'build_exercise_bag', 'NEUTRAL_TILT', 'LATERAL_SHIFT', 'GOAL_TOPIC']

GOAL_TOPIC = topics.POSE_GOAL
POSE_TYPE = 'geometry_msgs/msg/PoseStamped'
#: coronal tilt of the neutral pose (rad): clear of the theta = 0 singularity (cond(J) ~ 800
#: there; at 2 deg it is ~2000 and encoder-quantised lengths may not close the loop)
NEUTRAL_TILT = math.radians(5.0)
#: lateral shift of the exercise (m) on a 3-RPR brace that can hold it: the issue's 15 mm
#: coronal correction (30 N against the simulated trunk's 2000 N/m)
LATERAL_SHIFT = 0.015


@dataclass(frozen=True)
class Goal:
    """A pose goal ``pose = (x, y, theta)`` sent ``t`` seconds after the start; ``label`` for plots."""

    t: float
    pose: tuple[float, ...]
    label: str


def exercise_goals(home_pose: Sequence[float], *, spacing: float = 4.0,
                   lift: float = 0.020, lowering: float = 0.020,
                   rotation: float = math.radians(10.0),
                   combined: tuple[float, float] = (0.015, math.radians(7.5)),
                   neutral_tilt: float | None = None, lateral: float = 0.0) -> list[Goal]:
    """The lumbar brace's exercise about ``home_pose`` (x, y, theta): nine goals, ``spacing`` apart.

    Neutral, vertical lift, neutral, lowering, neutral, coronal rotation halfway to
    ``rotation``, ``rotation``, lift and rotation together (``combined``), neutral. No
    lateral shift by default: the paper's brace cannot hold one against the body (module
    docstring); ``lateral`` > 0 adds a shift right, neutral, a shift left, neutral after the
    first neutral (thirteen goals).

    With the defaults and the lumbar brace's geometry (strokes 0.340-0.440 m, neutral
    lengths 373.7 / 390.0 / 407.6 mm) every goal and every straight path between two goals
    keeps at least 8.9 mm from the stroke ends and at most 31 N on a leg under the
    simulated body (``test_demo_report``).

    :param spacing: seconds between goals (a 20 mm motion lasts 2.6 s at the demo's
        Fitts' law intercept of 2 s).
    :param lift: vertical lift (m, up).
    :param lowering: vertical lowering (m, down).
    :param rotation: largest coronal rotation (rad).
    :param combined: ``(lift m, rotation rad)`` of the combined goal.
    :param neutral_tilt: coronal tilt of the neutral pose (rad); default: the home pose's,
        or :data:`NEUTRAL_TILT` when the home pose is upright (singular).
    :raises ValueError: a non-positive spacing or a non-finite amount.
    """
    amounts = (spacing, lift, lowering, rotation, *combined, lateral)
    if not all(math.isfinite(float(a)) for a in amounts) or spacing <= 0.0 or lateral < 0.0:
        raise ValueError(f'exercise: expected finite amounts, a positive spacing (s) and a '
                         f'non-negative lateral shift (m), got spacing={spacing}, lift={lift}, '
                         f'lowering={lowering}, rotation={rotation}, combined={combined}, '
                         f'lateral={lateral}')
    x0, y0 = float(home_pose[0]), float(home_pose[1])
    if neutral_tilt is None:
        neutral_tilt = float(home_pose[2]) if abs(float(home_pose[2])) > 1e-9 else NEUTRAL_TILT
    n = (x0, y0, neutral_tilt)
    c_lift, c_rot = (float(v) for v in combined)
    shift = [] if lateral == 0.0 else [
        ((x0 + lateral, y0, neutral_tilt), f'lateral shift +{lateral * 1e3:.0f} mm'), (n, 'neutral'),
        ((x0 - lateral, y0, neutral_tilt), f'lateral shift -{lateral * 1e3:.0f} mm'), (n, 'neutral')]
    steps = [
        (n, 'neutral'), *shift,
        ((x0, y0 + lift, neutral_tilt), f'vertical lift +{lift * 1e3:.0f} mm'),
        (n, 'neutral'),
        ((x0, y0 - lowering, neutral_tilt), f'lowering -{lowering * 1e3:.0f} mm'),
        (n, 'neutral'),
        ((x0, y0, 0.5 * (neutral_tilt + rotation)),
         f'coronal rotation {math.degrees(0.5 * (neutral_tilt + rotation)):.1f} deg'),
        ((x0, y0, rotation), f'coronal rotation {math.degrees(rotation):.0f} deg'),
        ((x0, y0 + c_lift, c_rot), f'lift +{c_lift * 1e3:.0f} mm, {math.degrees(c_rot):.1f} deg'),
        (n, 'neutral (back)'),
    ]
    return [Goal(1.0 + k * spacing, tuple(p), label) for k, (p, label) in enumerate(steps)]


def device_exercise(config: str | Path = 'lumbar_brace', *, spacing: float = 4.0) -> list[Goal]:
    """The bundled exercise of a device (its YAML or name): goals near its home pose.

    * planar 3-RPR brace (lumbar): :func:`exercise_goals` (lift, lowering, coronal rotation,
      both together), with a :data:`LATERAL_SHIFT` each way when the brace can hold it
      against its body (:func:`holds_lateral_shift`: ``lumbar_brace_v2``, not the paper's);
    * other planar devices (3-RRR, 4-RPR neck braces): the same moves, small (±5 mm, +5 mm,
      up to 4 deg) about the home pose, which is their neutral pose;
    * two-coordinate devices (2R neck brace, continuum robot): ±10 mm in x, +10 mm in y;
    * upper-limb trainer (Hoeken four-bar): points along the coupler curve, the crank at
      home, +20, +40, +60 deg and back (the straight reach);
    * shoulder: the three typical motions and back, flexion–extension (15 deg),
      abduction–adduction and internal–external rotation (20 deg) (the YAML's S-curve: 2 s
      each).

    Every exercise holds only goals the device can reach against its simulated body: each
    goal and each straight path between two goals within the actuators' ranges, with the
    static load below 0.8 x ``actuator.max_force`` (``test_demo_report``).
    """
    from .mechanisms import mechanism_from_config
    cfg = load_device_config(config)
    mech = mechanism_from_config(cfg)
    home = np.asarray(mech.home_pose, dtype=float)
    kind = str(cfg.get_path('mechanism.type', ''))
    steps: list[tuple[Sequence[float], str]]
    if kind == 'rpr3':
        lateral = LATERAL_SHIFT if holds_lateral_shift(cfg, mech, home, LATERAL_SHIFT) else 0.0
        return exercise_goals(home, spacing=spacing, lateral=lateral)
    if mech.pose_kind == 'spherical':
        # flexion 15 deg, the others 20 deg: the built joint's transmission worsens with
        # flexion (k(J) 32 at 20 deg, 149 at 25 deg; the YAML's limit is 100) and holding the
        # simulated arm at 20 deg flexion takes 23.1 N·m on m2, above the soft force limit
        # (0.8 x 25 N·m): the driver would stop the motion. 15 deg takes 11.2 N·m.
        d = math.radians(20.0)
        flexion = math.radians(15.0)
        n = tuple(home)
        steps = [(n, 'neutral'),
                 (home + (0.0, -flexion, 0.0), 'flexion 15 deg'), (n, 'extension back'),
                 (home + (d, 0.0, 0.0), 'abduction 20 deg'), (n, 'adduction back'),
                 (home + (0.0, 0.0, d), 'internal rotation 20 deg'), (n, 'rotation back')]
        spacing = max(spacing, 3.0)
    elif kind == 'hoeken_fourbar':
        crank = float(mech.inverse(home)[0])

        def point(deg: float) -> np.ndarray:
            sols = mech.forward([crank + math.radians(deg)])
            return np.asarray(sols[0], dtype=float)
        steps = [(home, 'start of the reach')] + [
            (point(a), f'crank +{a:.0f} deg') for a in (20.0, 40.0, 60.0)] + [
            (point(20.0), 'crank +20 deg (back)'), (home, 'start of the reach (back)')]
    elif mech.dof == 3:
        d, r = 0.005, math.radians(4.0)
        n = tuple(home)
        steps = [(n, 'neutral'), (home + (d, 0, 0), 'shift right'), (home - (d, 0, 0), 'shift left'),
                 (n, 'neutral'), (home + (0, d, 0), 'lift'), (n, 'neutral'),
                 (home + (0, 0, r), f'rotation {math.degrees(r):.0f} deg'),
                 (home - (0, 0, r), f'rotation -{math.degrees(r):.0f} deg'), (n, 'neutral (back)')]
    else:
        d = 0.010
        n = tuple(home)
        steps = [(n, 'neutral'), (home + (d, 0), 'x +10 mm'), (home - (d, 0), 'x -10 mm'),
                 (n, 'neutral'), (home + (0, d), 'y +10 mm'), (n, 'neutral (back)')]
    return [Goal(1.0 + k * spacing, tuple(float(v) for v in p), label)
            for k, (p, label) in enumerate(steps)]


def holds_lateral_shift(cfg: Any, mech: Any, home: np.ndarray, shift: float, *,
                        margin: float = 2.0, samples: int = 21) -> bool:
    """Whether the actuators can hold a lateral shift of ``shift`` (m) each way from ``home``
    against the YAML's body: along both straight paths, the lateral wrench capacity
    (``mech.wrench_capacity``, ``actuator.max_force`` per actuator) is at least ``margin``
    times the body's lateral force there, ``|K_xx (x - x_rest)|`` (``sim.stiffness``,
    ``sim.rest_pose``). The paper's lumbar brace: 0.71 N of capacity against 30 N, no;
    ``lumbar_brace_v2``: >= 261 N, yes."""
    try:
        K = np.asarray(cfg.get_path('sim.stiffness'), dtype=float).reshape(mech.dof, mech.dof)
        rest = np.asarray(cfg.get_path('sim.rest_pose'), dtype=float)
        f_max = float(cfg.get_path('actuator.max_force'))
    except (KeyError, ValueError):
        return False
    s = np.linspace(-1.0, 1.0, 2 * samples - 1)[:, None]
    poses = home + s * np.array([shift] + [0.0] * (mech.dof - 1))
    capacity = np.asarray(mech.wrench_capacity_batch(poses, f_max), dtype=float)[:, 0]
    load = np.abs((poses - rest) @ K.T)[:, 0]
    return bool(np.all(np.isfinite(capacity)) and np.all(capacity >= margin * load))


def write_goal_bag(out: str | Path, goals: Sequence[Goal], *, frame_id: str,
                   topic: str = GOAL_TOPIC, start_ns: int = 0, storage: str = 'mcap',
                   version: int = 9, mechanism: Any = None) -> Path:
    """Write ``goals`` as PoseStamped messages to a rosbag2 bag directory ``out``.

    Poses may hold NaN (to test rejections). Stamps are the bag times. Planar poses
    ``(x, y, theta)`` become position + yaw quaternion, ``(x, y)`` position only,
    ``(x,)`` position.x; for a spherical device (``mechanism.pose_kind == 'spherical'``)
    the pose is its motion angles and the orientation is
    ``mechanism.quaternion_from_pose(pose)``.

    :param storage: ``'mcap'`` or ``'sqlite3'``.
    """
    spherical = mechanism is not None and mechanism.pose_kind == 'spherical'
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore
    store = get_typestore(Stores.ROS2_HUMBLE)
    T = store.types
    plugin = StoragePlugin.MCAP if storage == 'mcap' else StoragePlugin.SQLITE3
    out = Path(out)
    with Writer(out, version=version, storage_plugin=plugin) as writer:
        conn = writer.add_connection(topic, POSE_TYPE, typestore=store)
        for g in goals:
            t_ns = start_ns + round(g.t * 1e9)
            if spherical:
                qx, qy, qz, qw = (float(v) for v in mechanism.quaternion_from_pose(g.pose))
                p = [0.0, 0.0]
            else:
                p = list(g.pose) + [0.0] * (3 - len(g.pose))
                qx, qy, qz, qw = 0.0, 0.0, math.sin(p[2] / 2.0), math.cos(p[2] / 2.0)
            msg = T[POSE_TYPE](
                header=T['std_msgs/msg/Header'](
                    stamp=T['builtin_interfaces/msg/Time'](sec=t_ns // 10**9, nanosec=t_ns % 10**9),
                    frame_id=frame_id),
                pose=T['geometry_msgs/msg/Pose'](
                    position=T['geometry_msgs/msg/Point'](x=float(p[0]), y=float(p[1]), z=0.0),
                    orientation=T['geometry_msgs/msg/Quaternion'](x=qx, y=qy, z=qz, w=qw)))
            writer.write(conn, t_ns, bytes(store.serialize_cdr(msg, POSE_TYPE)))
    return out


def build_exercise_bag(out: str | Path, config: str | Path = 'lumbar_brace', *,
                       spacing: float = 4.0) -> tuple[Path, list[Goal]]:
    """Write the exercise for ``config`` to the bag directory ``out``; returns (path, goals)."""
    from .mechanisms import mechanism_from_config
    cfg = load_device_config(config)
    goals = device_exercise(config, spacing=spacing)
    path = write_goal_bag(out, goals, frame_id=str(cfg.get('base_frame', 'brace_base')),
                          mechanism=mechanism_from_config(cfg))
    return path, goals


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog='make_exercise_bag', description=__doc__.split('\n\n')[0])
    ap.add_argument('out', help='bag directory to create (must not exist)')
    ap.add_argument('--config', default='lumbar_brace', help='device YAML or name')
    ap.add_argument('--spacing', type=float, default=4.0, help='seconds between goals')
    args = ap.parse_args(argv)
    path, goals = build_exercise_bag(args.out, args.config, spacing=args.spacing)
    for g in goals:
        print(f'{g.t:6.1f} s  {g.label:28s} ' + ' '.join(f'{v:+.4f}' for v in g.pose))
    print(f'wrote {len(goals)} goals to {path}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
