"""``brace-kinematics``: IK, every FK assembly mode, cond(J) and the wrench of a planar device.

``brace-kinematics config/lumbar_brace.yaml [--pose x y theta_deg] [--forces F1 F2 F3 ...]``

Planar devices, pose ``(x, y, theta)``: the lumbar brace (3-RPR), the neck braces 4-RPR
(redundant: its forward kinematics is the least-squares fit of four lengths) and 3-RRR.
Other devices (the 2R neck brace, the four-bar trainer, the spherical shoulder, the
continuum robot) are refused with exit code 2: their tools are ``brace-workspace``,
``brace-fourbar-report``, ``brace-spm-study`` and ``brace-continuum-plot``.

The default sample pose is the YAML's home pose, moved to ``theta = 10 deg`` if it is not in
the workspace (the brace's ``theta = 0`` poses are singular: the three leg lines meet in
the rings' homothety centre). Actuator positions print in mm (linear actuators) or deg
(rotary), the default efforts are (100, 50, -100, -50 ...) N or N·m, one per actuator.
"""
from __future__ import annotations

import argparse
import math
import sys

import numpy as np

__all__ = ['main']


def main(argv: list[str] | None = None) -> int:
    """Print the kinematics of one sample pose; exit code 0, or 2 on a bad device/pose."""
    parser = argparse.ArgumentParser(
        prog='brace-kinematics',
        description='Inverse/forward kinematics, singularity measure and wrench of a planar '
                    'device (pose x, y, theta).')
    parser.add_argument('device', help='device YAML (e.g. config/lumbar_brace.yaml) or device name')
    parser.add_argument('--pose', nargs=3, type=float, metavar=('X_M', 'Y_M', 'THETA_DEG'),
                        help='sample pose: x (m), y (m), theta (deg); default: the home pose')
    parser.add_argument('--forces', nargs='+', type=float, metavar='F',
                        help='actuator efforts, one per actuator (N push positive, or N·m); '
                             'default 100, 50, -100, -50, ...')
    args = parser.parse_args(argv)

    from ..can.units import actuator_kind
    from ..config import ConfigError, load_device_config
    from ..mechanisms import SingularPose, UnreachablePose, mechanism_from_config
    from ..nodes.msgs import pose_kind
    try:
        cfg = load_device_config(args.device)
        mech = mechanism_from_config(cfg)
    except ConfigError as exc:
        print(f'brace-kinematics: {exc}', file=sys.stderr)
        return 2
    names = mech.actuator_names
    kind = pose_kind(mech)
    if kind != 'planar':
        print(f'brace-kinematics: {args.device} is a {type(mech).__name__} (pose kind {kind!r}, '
              f'{int(mech.dof)} coordinates); this tool takes planar devices with the pose '
              f'(x, y, theta): 3-RPR, 4-RPR, 3-RRR', file=sys.stderr)
        return 2
    forces = (np.resize([100.0, 50.0, -100.0, -50.0], len(names)) if args.forces is None
              else np.asarray(args.forces, dtype=float))
    if forces.shape != (len(names),):
        print(f'brace-kinematics: --forces: {forces.size} value(s) given, expected one per actuator '
              f'({len(names)}: {", ".join(names)})', file=sys.stderr)
        return 2
    rotary = actuator_kind(cfg) == 'rotary'
    unit, scale, effort = ('deg', math.degrees(1.0), 'N·m') if rotary else ('mm', 1e3, 'N')
    if args.pose is None:
        pose = mech.home_pose
        if not mech.in_workspace(pose):          # e.g. a theta = 0 home: singular for the brace
            pose = np.array([pose[0], pose[1], math.radians(10.0)])
    else:
        pose = np.array([args.pose[0], args.pose[1], math.radians(args.pose[2])])
    lo, hi = mech.actuator_limits
    arch = getattr(mech, 'architecture', None)
    print(f'device {args.device}: {type(mech).__name__}{f" ({arch} architecture)" if arch else ""}, '
          f'actuators {", ".join(names)}, range {lo.min() * scale:.1f}..{hi.max() * scale:.1f} {unit}')
    print(f'pose: x = {pose[0] * 1e3:.2f} mm, y = {pose[1] * 1e3:.2f} mm, theta = {math.degrees(pose[2]):.3f} deg')
    try:
        q = mech.inverse(pose)
    except (UnreachablePose, ValueError) as exc:
        print(f'brace-kinematics: {exc}', file=sys.stderr)
        return 2
    print('inverse kinematics: ' + ', '.join(f'{n} = {v * scale:.3f} {unit}' for n, v in zip(names, q)))
    sols = mech.forward(q)
    print(f'forward kinematics: {len(sols)} assembly modes')
    for k, s in enumerate(sols, 1):
        err = np.max(np.abs(mech.inverse_batch(s[None], limits=False)[0] - q))
        mark = ' <- sample pose' if np.allclose(s, pose, atol=1e-9) else ''
        print(f'  {k}: x = {s[0] * 1e3:9.3f} mm, y = {s[1] * 1e3:9.3f} mm, theta = {math.degrees(s[2]):8.3f} deg'
              f'   (actuator error {err:.1e} {"rad" if rotary else "m"}){mark}')
    nearest = mech.forward_nearest(q, pose)
    print(f'forward_nearest(q, pose): x = {nearest[0] * 1e3:.3f} mm, y = {nearest[1] * 1e3:.3f} mm, '
          f'theta = {math.degrees(nearest[2]):.3f} deg')
    cond = mech.condition(pose)
    try:
        mech.check_singularity(pose)
        state = 'ok'
    except SingularPose:
        state = 'SINGULAR'
    print(f'Jacobian (q_dot = J x_dot), cond(J) = {cond:.4g} '
          f'(limit {mech.singularity_condition_max:.3g}: {state}):')
    for row in mech.jacobian(pose):
        print('  [' + ', '.join(f'{v:9.5f}' for v in row) + ']')
    w = mech.wrench(pose, forces)
    print('wrench J^T f for f = (' + ', '.join(f'{f:g}' for f in forces) + f') {effort}: '
          f'Fx = {w[0]:.3f} N, Fy = {w[1]:.3f} N, M = {w[2]:.4f} N·m (about P, counter-clockwise)')
    print(f'in_workspace: {mech.in_workspace(pose)}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
