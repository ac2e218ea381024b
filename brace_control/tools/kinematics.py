"""``brace-kinematics``: IK, every FK assembly mode, cond(J) and the wrench of a 3-RPR device.

``brace-kinematics config/lumbar_brace.yaml [--pose x y theta_deg] [--forces F1 F2 F3]``

The default sample pose is the YAML's home pose, moved to ``theta = 10 deg`` if it is not in
the workspace (the brace's ``theta = 0`` poses are singular: the three leg lines meet in
the rings' homothety centre).
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
        description='Inverse/forward kinematics, singularity measure and wrench of a 3-RPR device.')
    parser.add_argument('device', help='device YAML (e.g. config/lumbar_brace.yaml) or device name')
    parser.add_argument('--pose', nargs=3, type=float, metavar=('X_M', 'Y_M', 'THETA_DEG'),
                        help='sample pose: x (m), y (m), theta (deg); default: the home pose')
    parser.add_argument('--forces', nargs=3, type=float, metavar=('F1', 'F2', 'F3'),
                        default=(100.0, 50.0, -100.0), help='actuator thrusts (N, push positive)')
    args = parser.parse_args(argv)

    from ..config import ConfigError
    from ..mechanisms import SingularPose, UnreachablePose, load_mechanism
    try:
        mech = load_mechanism(args.device)
    except ConfigError as exc:
        print(f'brace-kinematics: {exc}', file=sys.stderr)
        return 2
    if args.pose is None:
        pose = mech.home_pose
        if not mech.in_workspace(pose):          # e.g. a theta = 0 home: singular for the brace
            pose = np.array([pose[0], pose[1], math.radians(10.0)])
    else:
        pose = np.array([args.pose[0], args.pose[1], math.radians(args.pose[2])])
    names = mech.actuator_names
    lo, hi = mech.actuator_limits
    print(f'device {args.device}: {type(mech).__name__} ({getattr(mech, "architecture", "?")} architecture), '
          f'actuators {", ".join(names)}, stroke {lo.min() * 1e3:.1f}-{hi.max() * 1e3:.1f} mm')
    print(f'pose: x = {pose[0] * 1e3:.2f} mm, y = {pose[1] * 1e3:.2f} mm, theta = {math.degrees(pose[2]):.3f} deg')
    try:
        q = mech.inverse(pose)
    except (UnreachablePose, ValueError) as exc:
        print(f'brace-kinematics: {exc}', file=sys.stderr)
        return 2
    print('inverse kinematics (eq. 3): ' + ', '.join(f'{n} = {v * 1e3:.3f} mm' for n, v in zip(names, q)))
    sols = mech.forward(q)
    print(f'forward kinematics: {len(sols)} assembly modes')
    for k, s in enumerate(sols, 1):
        err = np.max(np.abs(mech.inverse_batch(s[None], limits=False)[0] - q))
        mark = ' <- sample pose' if np.allclose(s, pose, atol=1e-9) else ''
        print(f'  {k}: x = {s[0] * 1e3:9.3f} mm, y = {s[1] * 1e3:9.3f} mm, theta = {math.degrees(s[2]):8.3f} deg'
              f'   (length error {err:.1e} m){mark}')
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
    w = mech.wrench(pose, args.forces)
    print('wrench J^T f for f = (' + ', '.join(f'{f:g}' for f in args.forces) + ') N: '
          f'Fx = {w[0]:.3f} N, Fy = {w[1]:.3f} N, M = {w[2]:.4f} N·m (about P, counter-clockwise)')
    print(f'in_workspace: {mech.in_workspace(pose)}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
