"""CAN scaling, per-actuator limits and the simulator's physics for the devices beyond the
lumbar brace (no rclpy, no bus traffic: the simulator is built with ``start=False``).

Oracles: the YAML's numbers (counts per radian, the rated torque from current x kt x
gear) and the body's stiffness, not the code under test.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from brace_control.can.dictionary import ObjectRef
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
    assert mc.load_cell_object == ObjectRef(TORQUE_ACTUAL) and mc.limits.unit == "rad"


@pytest.mark.parametrize('device', ROTARY + LINEAR)
def test_master_limits_are_the_mechanisms_actuator_limits(device):
    cfg = load_device_config(device)
    lo, hi = mechanism_from_config(cfg).actuator_limits
    mc = MasterConfig.from_device_config(cfg, channel='unused')
    assert mc.limits.strokes == tuple(zip(lo.tolist(), hi.tolist()))
    if device in LINEAR:
        assert mc.load_cell_object == ObjectRef(LOAD_CELL_INPUT) and mc.limits.unit == "m"


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


@pytest.mark.parametrize('device', ROTARY + ['continuum'])
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
    if sim.rotary:
        for d, f in zip(sim.drives, t.forces):
            assert d.force_n == pytest.approx(f, abs=5 * sim.noise_n + sim.n_per_count)


def _cables(cfg, pose, q, k):
    """Independent 4-RPR cable model from the YAML: anchors a_n, platform points
    p + R(psi) r (cos d_n, sin d_n); tension k (|b_n - a_n| - q_n) when positive, else slack;
    the wrench of the tensions on the platform (force, moment about its centre)."""
    m = cfg['mechanism']
    a = np.asarray(m['base_anchors'], float).reshape(4, 2)
    r, d = float(m['platform_radius']), np.asarray(m['anchor_angles'], float)
    x, y, psi = pose
    rb = r * np.column_stack([np.cos(d + psi), np.sin(d + psi)])
    v = a - (np.array([x, y]) + rb)                  # platform point -> base anchor
    dist = np.linalg.norm(v, axis=1)
    u = v / dist[:, None]
    t = k * np.maximum(dist - q, 0.0)
    F = (t[:, None] * u).sum(axis=0)
    M = float(np.sum(t * (rb[:, 0] * u[:, 1] - rb[:, 1] * u[:, 0])))
    return dist, t, np.array([F[0], F[1], M])


def test_cables_pushed_go_slack_and_the_taut_ones_hold_the_body():
    """The body pulls the head ring back towards its rest pose; the cables on the far
    side hold it, the ones it would push go slack (zero tension, paid out longer than
    their anchors' distance), and the ring settles where the taut cables' stretch balances
    the body: sum of tension forces = K (pose - rest), from an independent cable model."""
    cfg = load_device_config('neck_brace_4rpr')
    sim = SimulatedBrace('neck_brace_4rpr', channel='unit_4rpr_slack', start=False)
    k = float(cfg['sim']['leg_stiffness'])
    K = np.asarray(cfg['sim']['stiffness'], float).reshape(3, 3)
    rest = np.asarray(cfg['sim']['rest_pose'], float)
    target = rest + np.array([0.012, 0.004, 0.0])
    t = _settle(sim, target, n=40)
    q = t.lengths
    dist, tension, wrench = _cables(cfg, t.pose, q, k)
    np.testing.assert_allclose(wrench, K @ (t.pose - rest), atol=1e-3)       # equilibrium
    np.testing.assert_allclose(-t.forces, tension, atol=1e-3)                 # pull only
    assert np.all(t.forces <= 0.0)
    slack = [n for n, f in zip(sim.mechanism.actuator_names, t.forces) if f == 0.0]
    assert slack and set(slack) == set(sim.slack), (slack, sim.slack)
    assert all(dist[i] < q[i] for i in range(4) if t.forces[i] == 0.0)       # paid out > distance
    assert np.max(tension) > 5.0, 'the taut cables carry the body'
    # the ring is pulled back from the commanded pose by the taut cables' stretch only
    assert 0.0 < np.linalg.norm(t.pose[:2] - target[:2]) < 2 * np.max(tension) / k
    # the load cells read the tensions (push positive: -tension), slack ones about 0
    counts_n = t.load_cell_counts * sim.n_per_count
    np.testing.assert_allclose(counts_n, t.forces, atol=5 * sim.noise_n + sim.n_per_count)