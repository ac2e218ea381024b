"""CAN scaling, per-actuator limits and the simulator's physics for the devices beyond the
lumbar brace (no rclpy, no bus traffic: the simulator is built with ``start=False``).

Oracles: the YAML's numbers (counts per radian, the rated torque from current x kt x
gear) and the body's stiffness, not the code under test.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from brace_control.can.master import MasterConfig
from brace_control.can.pdo import LOAD_CELL_INPUT, TORQUE_ACTUAL
from brace_control.can.units import scaling_from_config
from brace_control.config import load_device_config
from brace_control.mechanisms import mechanism_from_config
from brace_control.sim import SimulatedBrace

ROTARY = ['neck_brace_2r', 'neck_brace_3rrr', 'upper_limb_trainer', 'shoulder']
LINEAR = ['lumbar_brace', 'neck_brace_4rpr', 'continuum']


@pytest.mark.parametrize('device', ROTARY)
def test_rotary_scaling_counts_per_radian_and_torque_actual(device):
    cfg = load_device_config(device)
    a = cfg['actuator']
    s = scaling_from_config(cfg)
    assert s.counts_per_unit == pytest.approx(a['encoder_counts_per_rev'] * a['gear_ratio'] / (2 * math.pi))
    rated = a['rated_current'] * a['torque_constant'] * a['gear_ratio']
    assert s.force_to_si(1000) == pytest.approx(rated)           # 1000 per mille = rated torque
    assert rated > cfg['safety']['force_limit'] / cfg['safety']['saturation_fraction']
    mc = MasterConfig.from_device_config(cfg, channel='unused')
    assert mc.force_object == TORQUE_ACTUAL and mc.limits.unit == 'rad'


@pytest.mark.parametrize('device', ROTARY + LINEAR)
def test_master_limits_are_the_mechanisms_actuator_limits(device):
    cfg = load_device_config(device)
    lo, hi = mechanism_from_config(cfg).actuator_limits
    mc = MasterConfig.from_device_config(cfg, channel='unused')
    assert mc.limits.strokes == tuple(zip(lo.tolist(), hi.tolist()))
    if device in LINEAR:
        assert mc.force_object == LOAD_CELL_INPUT and mc.limits.unit == 'm'


def test_lumbar_limits_unchanged():
    mc = MasterConfig.from_device_config(load_device_config('lumbar_brace'), channel='unused')
    assert mc.limits.stroke == (0.34, 0.44)
    assert all(s == (0.34, 0.44) for s in mc.limits.strokes)


def _settle(sim, pose, n=20):
    q = sim.mechanism.inverse(pose)
    for d, qi in zip(sim.drives, q):
        d.length_m, d.velocity_mps = float(qi), 0.0
    for _ in range(n):
        t = sim._physics(0.002)
    return t


@pytest.mark.parametrize('device', ROTARY + ['neck_brace_4rpr', 'continuum'])
def test_rigid_physics_balances_the_body(device):
    sim = SimulatedBrace(device, channel=f'unit_{device}', start=False)
    cfg = load_device_config(device)
    m = sim.mechanism
    home = np.asarray(m.home_pose, float)
    if device == 'upper_limb_trainer':
        pose = np.asarray(m.forward([m.inverse(home)[0] + 0.3])[0])
    else:
        pose = home + 0.01 * np.arange(1, m.dof + 1) / m.dof
    t = _settle(sim, pose)
    np.testing.assert_allclose(t.pose, pose, atol=1e-9)
    K = np.asarray(cfg['sim']['stiffness'], float).reshape(m.dof, m.dof)
    rest = np.asarray(cfg['sim']['rest_pose'], float)
    np.testing.assert_allclose(-t.body_wrench, K @ (pose - rest), atol=1e-9)
    J = m.jacobian(pose)
    if device == 'upper_limb_trainer':        # one motor: the part along the coupler curve
        proj = J.T @ np.linalg.lstsq(J.T, -t.body_wrench, rcond=None)[0]
        np.testing.assert_allclose(J.T @ t.forces, proj, atol=1e-9)
    elif device == 'continuum':               # the sliders also hold the bent bars: (-H, H)
        from test_continuum import bvp_weld
        q = m.inverse(pose)
        _, h, _ = bvp_weld(0.5 * (q[1] - q[0]))
        np.testing.assert_allclose(J.T @ (t.forces - np.array([-h, h])), -t.body_wrench, atol=1e-6)
        np.testing.assert_allclose(t.brace_wrench, -t.body_wrench, atol=1e-6)
    else:
        np.testing.assert_allclose(J.T @ t.forces, -t.body_wrench, atol=1e-9)
    if device == 'neck_brace_4rpr':
        tens = -t.forces
        assert np.all(tens >= m.tension_min - 1e-9) and np.all(tens <= m.tension_max + 1e-9)
    if sim.rotary:
        for d, f in zip(sim.drives, t.forces):
            assert d.force_n == pytest.approx(f, abs=5 * sim.noise_n + sim.n_per_count)


def test_cable_wrench_infeasible_saturates_the_load_cells():
    sim = SimulatedBrace('neck_brace_4rpr', channel='unit_4rpr_sat', start=False)
    # far from rest: the torso pulls harder than the cables can hold
    t = _settle(sim, np.array([0.05, 0.05, 0.0]))
    assert sim.infeasible
    full = round(sim.rated_force / sim.n_per_count)
    assert all(abs(int(c)) == full for c in t.load_cell_counts)
