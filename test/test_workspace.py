"""``brace-workspace``: per-angle areas and the union map against a brute-force oracle.

Oracle: every grid point tested against the three annuli of the paper (section IV-B,
centres ``(r2 cos t - r1, r2 sin t)``, ``(0, 0)``, ``(r1 - r2 cos t, -r2 sin t)``, radii the
stroke limits), written out here point by point. The capacity map: the closed form
``min_i limit / |(J^-T)_i,x|`` with the brace's leg Jacobian written out here.
"""
from __future__ import annotations

import math
import re

import numpy as np
import pytest

from brace_control.mechanisms import load_mechanism
from brace_control.tools.workspace import annulus_centres, capacity_map, main, workspace_map

R1, R2 = 0.217, 0.195
LO, HI = 0.340, 0.440
BASE = np.array([[-R1, 0.0], [0.0, 0.0], [R1, 0.0]])
PLATFORM = np.array([[-R2, 0.0], [0.0, 0.0], [R2, 0.0]])


def brute_mask(theta: float, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Paper Fig. 9/10 by brute force: grid points inside all three annuli, y > 0."""
    centres = [(R2 * math.cos(theta) - R1, R2 * math.sin(theta)), (0.0, 0.0),
               (R1 - R2 * math.cos(theta), -R2 * math.sin(theta))]
    xx, yy = np.meshgrid(x, y)
    inside = yy > 0
    for cx, cy in centres:
        d = np.hypot(xx - cx, yy - cy)
        inside &= (d >= LO) & (d <= HI)
    return inside


def test_annulus_centres_are_the_papers():
    t = np.radians([0.0, 12.5, 30.0])
    c = annulus_centres(BASE, PLATFORM, t)
    for k, th in enumerate(t):
        np.testing.assert_allclose(c[k], [[R2 * math.cos(th) - R1, R2 * math.sin(th)], [0, 0],
                                          [R1 - R2 * math.cos(th), -R2 * math.sin(th)]], atol=1e-15)


@pytest.mark.parametrize('theta_deg', [0.0, 7.3, 15.0, 30.0])
def test_area_per_angle_matches_brute_force_count(theta_deg):
    grid = 0.001
    ws = workspace_map(BASE, PLATFORM, [LO] * 3, [HI] * 3, np.radians([theta_deg]), grid=grid)
    mask = brute_mask(math.radians(theta_deg), ws.x, ws.y)
    brute_area = mask.sum() * grid ** 2
    assert ws.area[0] == pytest.approx(brute_area, rel=2e-3)
    # single angle: the union raster is that angle's workspace, point for point
    disagree = np.count_nonzero(ws.union != mask)
    assert disagree <= 10          # points on a boundary, within rounding


def test_union_matches_brute_force_union_on_coarse_grid():
    theta = np.radians(np.arange(0.0, 30.0 + 1e-9, 1.0))
    ws = workspace_map(BASE, PLATFORM, [LO] * 3, [HI] * 3, theta, grid=0.004)
    brute = np.zeros_like(ws.union)
    for t in theta:
        brute |= brute_mask(float(t), ws.x, ws.y)
    assert brute.any()
    assert np.count_nonzero(ws.union != brute) <= 0.002 * brute.sum()
    # the map covers every brute-force point: the grid box is not too small
    assert ws.x[0] <= -HI + 0.03 and ws.x[-1] >= HI - 0.03 and ws.y[-1] >= HI - 0.004
    assert np.all(ws.y > 0)


def test_area_decreases_with_rotation_for_the_brace():
    ws = workspace_map(BASE, PLATFORM, [LO] * 3, [HI] * 3, np.radians([0.0, 10.0, 20.0, 30.0]), grid=0.002)
    assert np.all(np.diff(ws.area) < 0)


def test_cli_writes_plot_and_prints_area_table(tmp_path, capsys):
    out = tmp_path / 'ws.png'
    rc = main(['config/lumbar_brace.yaml', '--out', str(out), '--step-deg', '1', '--grid', '0.004'])
    assert rc == 0
    assert out.stat().st_size > 1000 and out.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'
    text = capsys.readouterr().out
    assert 'area (cm^2)' in text and 'union:' in text
    assert re.search(r'^\s+30\.0 \|\s+\d+\.\d\d$', text, re.MULTILINE)


def lumbar_fx_capacity(pose, limit: float) -> float:
    """Closed form: J rows (u_i, rho_i x u_i) of the paper's anchors, f = J^-T (1, 0, 0)."""
    x, y, t = pose
    rows = []
    for ax, bx in ((-R1, -R2), (0.0, 0.0), (R1, R2)):
        rx, ry = bx * math.cos(t), bx * math.sin(t)
        dx, dy = x + rx - ax, y + ry
        n = math.hypot(dx, dy)
        rows.append((dx / n, dy / n, (rx * dy - ry * dx) / n))
    f = np.linalg.solve(np.array(rows).T, [1.0, 0.0, 0.0])
    return limit / float(np.max(np.abs(f)))


def test_capacity_map_at_the_home_pose_is_the_closed_form():
    mech = load_mechanism('config/lumbar_brace.yaml')
    home = mech.home_pose
    ws = workspace_map(BASE, PLATFORM, [LO] * 3, [HI] * 3, np.array([home[2]]), grid=0.002)
    cm = capacity_map(mech, ws.x, ws.y, home[2], 250.0)
    assert cm.capacity.shape == (ws.y.size, ws.x.size) and cm.axis == 'Fx'
    i, j = int(np.argmin(np.abs(ws.x - home[0]))), int(np.argmin(np.abs(ws.y - home[1])))
    assert abs(ws.x[i] - home[0]) < 1e-9 and abs(ws.y[j] - home[1]) < 1e-9
    expected = lumbar_fx_capacity((ws.x[i], ws.y[j], home[2]), 250.0)
    assert cm.capacity[j, i] == pytest.approx(expected, rel=1e-12)
    assert cm.capacity[j, i] == pytest.approx(0.711, abs=5e-4)          # the middle leg binds
    assert mech.actuator_names[cm.limiting[j, i]] == 'a2'
    # defined exactly on this angle's workspace (brute-force annuli), NaN elsewhere
    np.testing.assert_array_equal(np.isfinite(cm.capacity), brute_mask(home[2], ws.x, ws.y))
    # a few more points of the map against the closed form
    rng = np.random.default_rng(5)
    jj, ii = np.nonzero(np.isfinite(cm.capacity))
    for k in rng.choice(jj.size, 20, replace=False):
        pose = (ws.x[ii[k]], ws.y[jj[k]], home[2])
        assert cm.capacity[jj[k], ii[k]] == pytest.approx(lumbar_fx_capacity(pose, 250.0), rel=1e-9)


def test_cli_prints_the_home_capacity_with_the_yaml_force_limit(tmp_path, capsys):
    out = tmp_path / 'ws.png'
    rc = main(['config/lumbar_brace.yaml', '--out', str(out), '--step-deg', '5', '--grid', '0.004',
               '--capacity-theta-deg', '5', '20'])
    assert rc == 0 and out.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'
    text = capsys.readouterr().out
    assert re.search(r'capacity \|Fx\| at theta = 5\.0 deg \(250 N per actuator', text)
    assert re.search(r'capacity \|Fx\| at theta = 20\.0 deg', text)
    home = re.search(r'at the home pose .*: ([0-9.]+) N, limited by actuator a2', text)
    assert home and float(home.group(1)) == pytest.approx(0.711, abs=1e-3)


def test_cli_rejects_missing_device(tmp_path, capsys):
    assert main([str(tmp_path / 'nope.yaml'), '--out', str(tmp_path / 'x.png')]) == 2
    assert 'not found' in capsys.readouterr().err
