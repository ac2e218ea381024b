"""``brace-kinematics``: the planar devices' IK, FK and wrench as a user runs it.

Oracles: seed 001's inverse kinematics and statics written out here from the YAML's anchors
(the lumbar brace, 3-RPR), and the neck brace 4-RPR's symmetry (square base, anchors
mirrored about the y axis: at home equal thrusts give no wrench). Devices whose pose is not
(x, y, theta) are refused with exit code 2, saying which pose they have.
"""
from __future__ import annotations

import math
import re

import numpy as np
import pytest

from brace_control.tools.kinematics import main
from ros_helpers import LUMBAR_YAML
from seed001 import leg_lengths, leg_matrix

NUM = r'(-?\d+\.\d+)'


def lumbar_oracle(pose, forces):
    """Seed 001: the leg lengths and the wrench ``G f`` of the leg forces (test/seed001.py)."""
    return leg_lengths(pose), leg_matrix(pose) @ np.asarray(forces, float)


def wrench_of(out: str) -> np.ndarray:
    m = re.search(rf'Fx = {NUM} N, Fy = {NUM} N, M = {NUM} N·m', out)
    assert m, out
    return np.array([float(v) for v in m.groups()])


def test_lumbar_brace_ik_and_wrench_match_the_paper(capsys):
    pose = (0.004, 0.400, math.radians(8.0))
    forces = (120.0, -40.0, 75.0)
    rc = main([str(LUMBAR_YAML), '--pose', '0.004', '0.400', '8.0',
               '--forces', *(str(f) for f in forces)])
    out = capsys.readouterr().out
    assert rc == 0
    lengths, wrench = lumbar_oracle(pose, forces)
    ik = re.search(rf'a1 = {NUM} mm, a2 = {NUM} mm, a3 = {NUM} mm', out)
    assert ik, out
    np.testing.assert_allclose([float(v) for v in ik.groups()], lengths * 1e3, atol=1e-3)
    np.testing.assert_allclose(wrench_of(out), wrench, atol=2e-3)        # the printed digits
    assert '<- sample pose' in out                 # one assembly mode is the sample pose


def test_neck_brace_4rpr_four_legs_and_no_wrench_from_equal_thrusts_at_home(capsys):
    rc = main(['neck_brace_4rpr', '--pose', '0', '0', '0', '--forces', '50', '50', '50', '50'])
    out = capsys.readouterr().out
    assert rc == 0
    ik = re.search(rf'c1 = {NUM} mm, c2 = {NUM} mm, c3 = {NUM} mm, c4 = {NUM} mm', out)
    assert ik, out
    lengths = np.array([float(v) for v in ik.groups()])
    np.testing.assert_allclose(lengths, lengths[0], atol=1e-3)       # the square's symmetry
    np.testing.assert_allclose(wrench_of(out), 0.0, atol=2e-3)


def test_rotary_actuators_print_in_degrees(capsys):
    assert main(['neck_brace_3rrr']) == 0
    out = capsys.readouterr().out
    assert re.search(rf'm1 = {NUM} deg, m2 = {NUM} deg, m3 = {NUM} deg', out), out
    assert ') N·m:' in out                         # the efforts are torques


@pytest.mark.parametrize('device, kind', [('shoulder', 'spherical'), ('neck_brace_2r', 'xy'),
                                          ('upper_limb_trainer', 'xy'), ('continuum', 'xy')])
def test_devices_without_a_planar_pose_are_refused_naming_their_pose(device, kind, capsys):
    assert main([device]) == 2
    err = capsys.readouterr().err
    assert f"pose kind '{kind}'" in err and '(x, y, theta)' in err, err


def test_a_wrong_number_of_efforts_is_refused_naming_the_actuators(capsys):
    assert main([str(LUMBAR_YAML), '--forces', '1', '2']) == 2
    err = capsys.readouterr().err
    assert '2 value(s) given' in err and 'a1, a2, a3' in err, err
