"""End to end on drives simulated from dictionaries nobody here wrote (issue 23).

The lumbar brace with each node its own process (``test_e2e.process_bring_up``, as
``ros2 run`` starts them), on drives simulated from a vendor's EDS, the simulated drives
answering as that dictionary says (objects, types, PDO counts, modes):

* ``config/lumbar_brace_nanotec.yaml``: Nanotec CL3-E drives, the load cells on the drives'
  analog input 3220h:1;
* ``test/data/lumbar_brace_cia402_slave.yaml``: ros2_canopen's fake CiA 402 slave (no
  6007h, 1006h, 607Fh; 60B1h not PDO-mappable: no velocity feed-forward), the load cells on
  a separate CiA 401 analog-input module (node 10, 6401h:1..3).

Each homes, enables and completes ordinary goals; the oracle is the simulator's TRUE ring
pose (``/brace/sim/pose``), within ``safety.pose_tolerance`` of each goal, and no protective
stop. The measured forces (``/brace/joint_states`` effort) follow the simulator's true leg
forces (``/brace/sim/joint_states`` effort) within the load cell's noise and one count:
the load cell really is read from the object the YAML names.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from brace_control.config import load_device_config
from brace_control.mechanisms import mechanism_from_config
from brace_control.nodes.msgs import pose_from_msg
from test_e2e import _extra_args, process_bring_up

pytestmark = [pytest.mark.ros, pytest.mark.e2e, pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[1]
DEG = math.pi / 180
VENDOR_DEVICES = {
    'nanotec': ROOT / 'config' / 'lumbar_brace_nanotec.yaml',
    'cia402_slave': ROOT / 'test' / 'data' / 'lumbar_brace_cia402_slave.yaml',
}


@pytest.mark.parametrize('device', sorted(VENDOR_DEVICES))
def test_lumbar_brace_on_vendor_drives_reaches_goals_on_the_true_ring(device):
    path = VENDOR_DEVICES[device]
    cfg = load_device_config(path)
    mech = mechanism_from_config(cfg)
    home = np.asarray(cfg['mechanism']['home_pose'], float)
    tol = np.asarray(cfg['safety']['pose_tolerance'], float)
    goals = [home + (0.0, 0.010, 2 * DEG), home + (0.0, -0.006, 4 * DEG), home]
    for g in goals:
        mech.inverse(g)                         # within the stroke (raises otherwise)
    noise = float(cfg['sim']['load_cell_noise'])
    count = float(cfg['actuator']['load_cell_n_per_count'])
    with process_bring_up(path, _extra_args()) as (group, node, probe):
        for k, goal in enumerate(goals, start=1):
            probe.send(goal)
            probe.wait(lambda: len(probe.terminal()) >= k, 30, f'goal {k} of {device} to end')
            end = probe.terminal()[-1]
            assert end['state'] == 'succeeded', (device, k, end)
            probe.wait_fresh(probe.sim_poses, 5, 5, 'true poses after the goal')
            with probe.lock:
                true = pose_from_msg(probe.sim_poses[-1], mechanism=mech)
            assert np.all(np.abs(true - goal) <= tol), (device, k, true, goal)
        # the forces the master reads (from 3220h:1, or the CiA 401 module) are the legs' true ones
        probe.wait_fresh(probe.joints, 20, 5, 'joint states at rest')
        probe.wait_fresh(probe.sim_joints, 5, 5, 'true joint states at rest')
        with probe.lock:
            measured = np.mean([np.asarray(m.effort, float) for m in probe.joints[-20:]], axis=0)
            true = np.asarray(probe.sim_joints[-1].effort, float)
        assert np.all(np.abs(measured - true) <= 4 * noise + 2 * count), (device, measured, true)
        assert probe.stops() == [], probe.stops()
