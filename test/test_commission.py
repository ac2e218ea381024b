"""brace-commission on the simulated bus (issue 24): each mistake a lab makes, made on purpose.

The simulator's ``sim.*`` keys say how the hardware really is (node ids, polarity, counts per
revolution, load-cell gain and offset, foreign nodes); ``can.*`` / ``actuator.*`` say what
the user believes. The oracle is the truth the test itself gave the simulator: the tool must
propose exactly the correction that undoes it. With the corrected file the brace runs goals
to the simulator's true ring (``/brace/sim/*`` through :class:`SimulatedBrace.truth`).
"""
from __future__ import annotations

import itertools
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from brace_control.commission import main as commission
from rpr_oracles import min_jerk

REPO = Path(__file__).resolve().parent.parent
_ids = itertools.count()
DEVICES = ['lumbar_brace', 'lumbar_brace_v2', 'neck_brace_4rpr', 'neck_brace_3rrr', 'neck_brace_2r',
           'shoulder', 'upper_limb_trainer', 'continuum']


def device_file(tmp_path: Path, device: str = 'lumbar_brace', **sim) -> Path:
    """``config/<device>.yaml`` with the hardware's truth ``sim.*`` and a channel of its own."""
    doc = yaml.safe_load((REPO / 'config' / f'{device}.yaml').read_text())
    params = doc['/**']['ros__parameters']
    params['can']['eds'] = str(REPO / 'config' / params['can']['eds'])
    params['can']['channel'] = f'commission{os.getpid()}x{next(_ids)}'
    params['sim'].update(sim)
    path = tmp_path / f'{device}_{next(_ids)}.yaml'
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def run(capsys, *args) -> tuple[int, str, dict]:
    """The tool's exit code, output and the YAML patch it printed."""
    rc = commission([str(a) for a in args])
    out = capsys.readouterr()
    text = out.out + out.err
    patch = {}
    if 'corrections (YAML patch):' in text:
        for line in text.split('corrections (YAML patch):', 1)[1].splitlines()[1:]:
            if not line.startswith('  ') or ':' not in line:
                break
            key, value = line.strip().split(': ', 1)
            patch[key] = yaml.safe_load(value)
    return rc, text, patch


# ------------------------------------------------------------------ plan (no bus)

def test_plan_lists_every_write_for_drives_that_serve_and_sends_nothing(capsys, monkeypatch):
    """``plan`` on the Nanotec brace: exit 0, each drive's writes (6060h = 8 for CSP, the TPDO1
    mapping with the analog input 3220h:1), and no bus opened (a lab runs it before wiring)."""
    import can

    def no_bus(*args, **kwargs):
        raise AssertionError('plan opened a CAN bus')
    monkeypatch.setattr(can, 'Bus', no_bus)
    rc, text, _ = run(capsys, REPO / 'config' / 'lumbar_brace_nanotec.yaml', 'plan')
    assert rc == 0, text
    for name in ('a1 (node 1', 'a2 (node 2', 'a3 (node 3'):
        assert name in text, text
    assert '6060h:0 = 0x8' in text and '1A00h:3 = 0x32200110' in text, text


def test_plan_refuses_drives_that_cannot_serve_with_the_reason(tmp_path, capsys):
    """The same brace on Faulhaber's 605.3150.69 (no cyclic synchronous position, by its file):
    exit 2 and the one message naming the missing mode."""
    path = device_file(tmp_path)
    doc = yaml.safe_load(path.read_text())
    doc['/**']['ros__parameters']['can']['eds'] = str(REPO / 'test' / 'data' / 'eds' / '605.3150.69-B-EK-2-60.eds')
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    rc, text, _ = run(capsys, path, 'plan')
    assert rc == 2, text
    assert 'cyclic synchronous position' in text and 'cannot drive the brace' in text, text


# ------------------------------------------------------------------ scan

def test_scan_of_a_healthy_bus_matches_and_takes_under_a_second(tmp_path, capsys):
    path = device_file(tmp_path)
    t0 = time.monotonic()
    rc, text, patch = run(capsys, path, 'scan')
    assert rc == 0, text
    assert time.monotonic() - t0 < 5.0
    assert '3 node(s)' in text and patch == {}
    for node in (1, 2, 3):
        assert f'\n     {node}  00020192h (CiA 402)' in text          # CiA 402 servo drive


def test_scan_finds_a_missing_drive_and_a_foreign_node(tmp_path, capsys):
    path = device_file(tmp_path, **{'node_ids': [1, 2, 0], 'extra_node_ids': [20]})
    rc, text, patch = run(capsys, path, 'scan')
    assert rc == 1, text
    assert 'a3: node 3 (can.node_ids) does not answer' in text
    assert 'node 20' in text and 'foreign node' in text and '(CiA 401)' in text
    assert patch == {}                    # nothing answers in its place: power or wiring


def test_scan_proposes_the_id_a_drive_really_has(tmp_path, capsys):
    path = device_file(tmp_path, node_ids=[1, 2, 9])
    rc, text, patch = run(capsys, path, 'scan')
    assert rc == 1 and patch == {'can.node_ids': [1, 2, 9]}, text


def test_check_refuses_to_move_with_a_drive_missing(tmp_path, capsys):
    path = device_file(tmp_path, node_ids=[1, 2, 0])
    rc, text, _ = run(capsys, path, 'check', '--yes')
    assert rc == 2 and 'cannot move the brace with a drive missing' in text, text


# ------------------------------------------------------------------ check: one mistake at a time

MISTAKES = {
    'swapped node ids a1-a2': ({'node_ids': [2, 1, 3]}, {'can.node_ids': [2, 1, 3]}),
    'swapped node ids a1-a3': ({'node_ids': [3, 2, 1]}, {'can.node_ids': [3, 2, 1]}),
    'one inverted drive': ({'polarity': [1, -1, 1]}, {'actuator.polarity': [1, -1, 1]}),
    'wrong counts per revolution': ({'encoder_counts_per_rev': [8192, 8192, 2048]},
                                    {'actuator.encoder_counts_per_rev': [8192, 8192, 2048]}),
}


@pytest.mark.parametrize('mistake', sorted(MISTAKES))
def test_check_finds_the_mistake_and_proposes_its_exact_correction(tmp_path, capsys, mistake):
    truth, expected = MISTAKES[mistake]
    path = device_file(tmp_path, **truth)
    rc, text, patch = run(capsys, path, 'check', '--yes', '--report', tmp_path / 'report')
    assert rc == 1, text
    assert patch == expected, text
    assert (tmp_path / 'report' / 'report.txt').is_file()
    assert sorted(p.name for p in (tmp_path / 'report').glob('jog_*.png')) == ['jog_a1.png', 'jog_a2.png', 'jog_a3.png']


def test_check_finds_a_load_cell_offset_and_a_5_percent_gain_error(tmp_path, capsys):
    path = device_file(tmp_path, load_cell_gain=[1.0, 1.05, 1.0], load_cell_offset=[0.0, 0.0, 3.5])
    rc, text, patch = run(capsys, path, 'check', '--yes', '--report', tmp_path / 'r')
    assert rc == 1, text
    assert set(patch) == {'actuator.load_cell_gain', 'actuator.load_cell_offset'}, text
    np.testing.assert_allclose(patch['actuator.load_cell_gain'], [1.0, 1.05, 1.0], atol=0.002)
    # the tare: within the noise of 150 readings of 0.05 N
    np.testing.assert_allclose(patch['actuator.load_cell_offset'], [0.0, 0.0, 3.5], atol=0.03)


def test_calibrate_load_cell_with_the_simulators_reference_load(tmp_path, capsys):
    path = device_file(tmp_path, load_cell_gain=[1.0, 1.05, 1.0], load_cell_offset=[0.0, 1.5, 0.0])
    out = tmp_path / 'calibrated.yaml'
    rc, text, patch = run(capsys, path, 'calibrate-load-cell', '--axis', 'a2', '--known-force', '49.05',
                          '--yes', '--write', out)
    assert rc == 1, text
    np.testing.assert_allclose(patch['actuator.load_cell_gain'], [1.0, 1.05, 1.0], atol=0.002)
    np.testing.assert_allclose(patch['actuator.load_cell_offset'], [0.0, 1.5, 0.0], atol=0.03)
    written = yaml.safe_load(out.read_text())['/**']['ros__parameters']['actuator']
    assert written['load_cell_gain'] == patch['actuator.load_cell_gain']


@pytest.mark.parametrize('measured, believed, proposed, also', [
    (4040.0, 8192, 4096, [4000]),      # a scale off by 1 % (a full run on a busy host): 2x, not 4000
    (4096.0, 8192, 4096, [4000]),
    (16300.0, 8192, 16384, [16000]),
    (3600.0, 8192, 3600, []),          # no resolution of the table within 8 %: as measured
    (2500.0, 8192, 2500, []),
    (10000.0, 4096, 10000, []),
    (7700.0, 8192, 8000, []),          # no power of two within 3 %: the usual 2000 x 4
    (7000.0, 8192, 7000, []),
])
def test_a_measured_counts_per_revolution_snaps_to_a_power_of_two_of_the_believed_first(measured, believed,
                                                                                        proposed, also):
    from brace_control.commission import _snap_cpr
    assert _snap_cpr(measured, believed) == (proposed, also)


# ------------------------------------------------------------------ everything at once, and the corrected file at work

ALL_AT_ONCE = {'node_ids': [3, 1, 9], 'polarity': [1, -1, 1], 'encoder_counts_per_rev': [8192, 8192, 4096],
               'load_cell_gain': [1.05, 1.0, 1.0], 'load_cell_offset': [0.0, 2.0, 0.0], 'extra_node_ids': [20]}


def test_every_mistake_at_once_is_found_and_the_corrected_file_runs_goals_on_the_true_ring(tmp_path, capsys):
    from brace_control.can import ActuatorTrajectory, BraceMaster, MasterConfig
    from brace_control.config import load_device_config
    from brace_control.mechanisms import mechanism_from_config
    from brace_control.sim import SimulatedBrace
    path = device_file(tmp_path, **ALL_AT_ONCE)
    fixed = tmp_path / 'fixed' / 'brace.yaml'
    fixed.parent.mkdir()
    rc, text, patch = run(capsys, path, 'check', '--yes', '--report', tmp_path / 'r', '--write', fixed)
    assert rc == 1, text
    assert 'node 20' in text and 'foreign node' in text
    assert patch['can.node_ids'] == [3, 1, 9]
    assert patch['actuator.polarity'] == [1, -1, 1]
    assert patch['actuator.encoder_counts_per_rev'] == [8192, 8192, 4096]
    np.testing.assert_allclose(patch['actuator.load_cell_gain'], [1.05, 1.0, 1.0], atol=0.003)
    np.testing.assert_allclose(patch['actuator.load_cell_offset'], [0.0, 2.0, 0.0], atol=0.03)
    # the corrected file passes check, and moves the TRUE ring to its goal
    rc, text, patch = run(capsys, fixed, 'check', '--yes', '--report', tmp_path / 'r2')
    assert rc == 0 and patch == {}, text
    cfg = load_device_config(fixed)
    mech = mechanism_from_config(cfg)
    sim = SimulatedBrace(cfg)
    master = BraceMaster(MasterConfig.from_device_config(cfg))
    try:
        master.boot()
        master.home()
        master.enable()
        home = np.asarray(mech.home_pose, float)
        goal = home + np.array([0.0, 0.012, 0.03])
        q0, q1 = mech.inverse(home), mech.inverse(goal)
        assert master.execute(ActuatorTrajectory(*min_jerk(q0, q1, 1.2, 49)),
                              start=time.perf_counter() + 0.05, tag=1) is None
        end = time.monotonic() + 5
        tol = np.asarray(cfg['safety']['pose_tolerance'], float)
        while time.monotonic() < end and not np.all(np.abs(sim.truth().pose - goal) <= tol):
            time.sleep(0.02)
        assert np.all(np.abs(sim.truth().pose - goal) <= tol), (sim.truth().pose, goal)
        assert not master.supervisor.latched, master.supervisor.summary()
        # the master's forces are the legs' true ones (gain and offset undone)
        np.testing.assert_allclose(master.feedback().force, sim.truth().forces, atol=0.3)
    finally:
        master.shutdown()
        sim.shutdown()


@pytest.mark.parametrize('device', DEVICES)
def test_every_device_passes_check_on_its_healthy_simulator(tmp_path, capsys, device):
    rc, text, patch = run(capsys, device_file(tmp_path, device), 'check', '--yes', '--report', tmp_path / 'r')
    assert rc == 0 and patch == {}, text


# ------------------------------------------------------------------ the wrong YAML before commissioning

WRONG = {'swapped a1-a2': {'node_ids': [2, 1, 3]}, 'inverted a2': {'polarity': [1, -1, 1]},
         'inverted a1': {'polarity': [-1, 1, 1]}, 'wrong counts a2': {'encoder_counts_per_rev': [8192, 4096, 8192]}}


@pytest.mark.parametrize('mistake', sorted(WRONG))
def test_a_brace_with_the_wrong_yaml_stops_within_1_mm_of_unexpected_motion(tmp_path, mistake):
    """The master believes the YAML, the drives are as ``sim.*`` says: a goal's legs fight each
    other and the body, and the force tiers stop it before the TRUE ring (``truth().pose``) is
    1 mm away from where the master's own estimate says it is; the goal never finishes."""
    from brace_control.can import ActuatorTrajectory, BraceMaster, MasterConfig
    from brace_control.config import load_device_config
    from brace_control.mechanisms import mechanism_from_config
    from brace_control.sim import SimulatedBrace
    cfg = load_device_config(device_file(tmp_path, **WRONG[mistake]))
    mech = mechanism_from_config(cfg)
    sim = SimulatedBrace(cfg)
    master = BraceMaster(MasterConfig.from_device_config(cfg))
    anchors = np.asarray(cfg['mechanism']['platform_anchors'], float).reshape(-1, 2)

    def points(pose):
        c, s = math.cos(pose[2]), math.sin(pose[2])
        return pose[:2] + anchors @ np.array([[c, s], [-s, c]])
    try:
        master.boot()
        master.home()
        master.enable()
        home = np.asarray(mech.home_pose, float)
        goal = home + np.array([0.0, 0.015, 0.03])
        q0, q1 = mech.inverse(home), mech.inverse(goal)
        master.execute(ActuatorTrajectory(*min_jerk(q0, q1, 1.5, 61)), start=time.perf_counter() + 0.05, tag=1)
        worst = 0.0
        events: list = []
        end = time.monotonic() + 4.0
        while time.monotonic() < end and not master.supervisor.latched and 'stopped' not in events:
            believed = mech.forward_nearest(master.feedback().position, home)
            worst = max(worst, float(np.max(np.linalg.norm(points(sim.truth().pose) - points(believed), axis=1))))
            events += [e.kind for e in master.execution_events() if e.tag == 1]
            time.sleep(0.002)
        # a protective stop, or the soft force tier braking the motion (nothing latched)
        assert master.supervisor.latched or 'stopped' in events, f'{mistake}: no stop ({events})'
        assert worst <= 1e-3, f'{mistake}: the true ring was {worst * 1e3:.2f} mm off the estimate'
        time.sleep(0.5)
        events += [e.kind for e in master.execution_events() if e.tag == 1]
        assert 'finished' not in events, events
    finally:
        master.shutdown()
        sim.shutdown()


@pytest.mark.slow
def test_the_command_line_runs_as_a_process(tmp_path):
    path = device_file(tmp_path)
    done = subprocess.run([sys.executable, '-m', 'brace_control.commission', str(path), 'scan'], cwd=REPO,
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    bad = subprocess.run([sys.executable, '-m', 'brace_control.commission', str(path), 'check'], cwd=REPO,
                         capture_output=True, text=True, timeout=60, stdin=subprocess.DEVNULL)
    assert bad.returncode == 2 and '--yes' in bad.stderr, bad.stderr


@pytest.mark.parametrize('scale, stderr, wrong', [
    (1.101, 0.075, False),   # the healthy trainer's crank beside two busy loops: 1.35 standard errors
    (1.101, 0.010, True),    # the same scale measured tightly: a wrong counts per revolution
    (0.5, 0.075, True),      # a factor of two stands out even from a loose measurement
    (4.0, 0.5, True),        # x4 evaluation forgotten
    (1.06, 0.001, False),    # within the tolerance, however tight
    (0.92, 0.01, False),
])
def test_a_scale_counts_as_wrong_only_beyond_the_tolerance_and_its_own_uncertainty(scale, stderr, wrong):
    """|scale - 1| > SCALE_TOLERANCE (0.1) and > SCALE_SIGMAS (4) standard errors, the
    thresholds written out here."""
    from brace_control.commission import scale_is_wrong
    assert scale_is_wrong(scale, stderr) is (abs(scale - 1) > 0.1 and abs(scale - 1) > 4 * stderr) is wrong
