"""The bundled exercise: a rosbag2 (mcap) of pose goals for the lumbar brace.

``python -m brace_control.exercise OUT [--config lumbar_brace]`` (also
``scripts/make_exercise_bag.py``) writes a bag of ``geometry_msgs/PoseStamped`` goals on
``/brace/pose_goal`` in the device's ``base_frame``: a lateral shift (±15 mm), a vertical
lift (+20 mm), a coronal rotation up to 10° and back, each returning to the neutral
pose, with a pause between goals so that every motion (minimum-jerk, Fitts' law
duration, about 1 s) ends before the next goal: human speed.

The neutral pose is the home pose turned to ``NEUTRAL_TILT`` in the coronal plane. The
3-RPR lumbar brace is singular at every ``theta = 0`` pose (its two anchor rows are
parallel there and the leg lines meet in one point: a rotation about it is not resisted,
see ``Rpr3.check_singularity``), so the exercise stays on the ``theta > 0`` side.

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

__all__ = ['Goal', 'exercise_goals', 'device_exercise', 'write_goal_bag', 'build_exercise_bag', 'NEUTRAL_TILT',
           'GOAL_TOPIC']

GOAL_TOPIC = '/brace/pose_goal'
POSE_TYPE = 'geometry_msgs/msg/PoseStamped'
#: coronal tilt of the neutral pose (rad): clear of the theta = 0 singularity (cond(J) ~ 800
#: there; at 2 deg it is ~2000 and encoder-quantised lengths may not close the loop)
NEUTRAL_TILT = math.radians(5.0)


@dataclass(frozen=True)
class Goal:
    """A pose goal ``pose = (x, y, theta)`` sent ``t`` seconds after the start; ``label`` for plots."""

    t: float
    pose: tuple[float, ...]
    label: str


def exercise_goals(home_pose: Sequence[float], *, spacing: float = 3.0,
                   lateral: float = 0.015, lift: float = 0.020,
                   rotation: float = math.radians(10.0),
                   neutral_tilt: float | None = None) -> list[Goal]:
    """The exercise for a planar device whose home pose is ``home_pose`` (x, y, theta).

    :param spacing: seconds between goals (each motion lasts about 1 s).
    :param lateral: lateral shift amplitude (m), both sides.
    :param lift: vertical lift (m).
    :param rotation: largest coronal rotation (rad).
    :param neutral_tilt: coronal tilt of the neutral pose (rad); default: the home pose's,
        or :data:`NEUTRAL_TILT` when the home pose is upright (singular).
    """
    x0, y0 = float(home_pose[0]), float(home_pose[1])
    if neutral_tilt is None:
        neutral_tilt = float(home_pose[2]) if abs(float(home_pose[2])) > 1e-9 else NEUTRAL_TILT
    n = (x0, y0, neutral_tilt)
    steps = [
        (n, 'neutral'),
        ((x0 + lateral, y0, neutral_tilt), 'lateral shift right'),
        ((x0 - lateral, y0, neutral_tilt), 'lateral shift left'),
        (n, 'neutral'),
        ((x0, y0 + lift, neutral_tilt), 'vertical lift'),
        (n, 'neutral'),
        ((x0, y0, 0.5 * (neutral_tilt + rotation)), 'coronal rotation'),
        ((x0, y0, rotation), f'coronal rotation {math.degrees(rotation):.0f} deg'),
        (n, 'neutral (back)'),
    ]
    return [Goal(1.0 + k * spacing, tuple(p), label) for k, (p, label) in enumerate(steps)]


def device_exercise(config: str | Path = 'lumbar_brace', *, spacing: float = 4.0) -> list[Goal]:
    """The bundled exercise of a device (its YAML or name): goals near its home pose.

    * planar 3-RPR brace (lumbar): :func:`exercise_goals` (shift, lift, coronal rotation);
    * other planar devices (3-RRR, 4-RPR neck braces): the same moves, small (±5 mm, +5 mm,
      up to 4 deg) about the home pose, which is their neutral pose;
    * two-coordinate devices (2R neck brace, continuum robot): ±10 mm in x, +10 mm in y;
    * upper-limb trainer (Hoeken four-bar): points along the coupler curve, the crank at
      home, +20, +40, +60 deg and back (the straight reach);
    * shoulder: the three typical motions, 20 deg each and back, flexion–extension,
      abduction–adduction, internal–external rotation (the YAML's S-curve: 2 s each).
    """
    from .mechanisms import mechanism_from_config
    cfg = load_device_config(config)
    mech = mechanism_from_config(cfg)
    home = np.asarray(mech.home_pose, dtype=float)
    kind = str(cfg.get_path('mechanism.type', ''))
    steps: list[tuple[Sequence[float], str]]
    if kind == 'rpr3':
        return exercise_goals(home, spacing=spacing)
    if getattr(mech, 'pose_kind', None) == 'spherical':
        # 20 deg: flexion beyond ~22 deg from the hanging arm nears a singularity of the built
        # joint (k(J) 32 at 20 deg, 149 at 25 deg; the YAML's limit is 100)
        d = math.radians(20.0)
        n = tuple(home)
        steps = [(n, 'neutral'),
                 (home + (0.0, -d, 0.0), 'flexion 20 deg'), (n, 'extension back'),
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
    spherical = getattr(mechanism, 'pose_kind', None) == 'spherical'
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
                       spacing: float = 3.0) -> tuple[Path, list[Goal]]:
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
    ap.add_argument('--spacing', type=float, default=3.0, help='seconds between goals')
    args = ap.parse_args(argv)
    path, goals = build_exercise_bag(args.out, args.config, spacing=args.spacing)
    for g in goals:
        print(f'{g.t:6.1f} s  {g.label:28s} ' + ' '.join(f'{v:+.4f}' for v in g.pose))
    print(f'wrote {len(goals)} goals to {path}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
