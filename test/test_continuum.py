"""Continuum parallel robot (seed paper 003): elliptic-integral elastica against an independent BVP.

Oracle: the same physics written independently in the *global* frame, as a boundary-value
problem solved by ``scipy.integrate.solve_bvp`` — bar 1 clamped at 45 deg at the origin,
``theta' = M / EI``, ``M' = H sin(theta)`` (a horizontal force ``H`` of bar 2 at the weld),
``theta(0) = theta(L) = 45 deg`` (the weld does not rotate, by symmetry), end at
``x(L) = d``; unknowns the shape and ``H``. No elliptic integrals, no ``psi``, no ``k``.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.integrate import solve_bvp

from brace_control.mechanisms import UnreachablePose, load_mechanism
from brace_control.mechanisms.continuum import (PSI_COMPRESSION, Continuum2, bar_end, solve_bar)

L = 0.2
E = 4.0e9
W, T = 0.01, 0.001
EI = E * W * T ** 3 / 12.0


@pytest.fixture(scope='module')
def robot() -> Continuum2:
    return Continuum2(L, E, W, T, (-0.3, 0.3))


def bvp_weld(d: float, amplitude: float = 0.3) -> tuple[float, float, np.ndarray]:
    """Independent oracle: (y at the weld, H, theta samples) for slider half-distance ``d``."""
    def f(s, y, p):
        th, m = y[0], y[1]
        return np.vstack([m, p[0] / EI * np.sin(th), np.cos(th), np.sin(th)])

    def bc(ya, yb, p):
        return np.array([ya[0] - math.pi / 4, yb[0] - math.pi / 4, ya[2], ya[3], yb[2] - d])

    s = np.linspace(0.0, L, 201)
    th = math.pi / 4 + amplitude * np.sin(math.pi * s / L)           # mode-1 shaped guess
    guess = np.vstack([th, amplitude * math.pi / L * np.cos(math.pi * s / L),
                       np.cumsum(np.cos(th)) * (s[1] - s[0]), np.cumsum(np.sin(th)) * (s[1] - s[0])])
    h0 = -EI * 20.0 / L ** 2 if d < L / math.sqrt(2) else EI * 1.0 / L ** 2
    sol = solve_bvp(f, bc, s, guess, p=[h0], tol=1e-10, bc_tol=1e-12, max_nodes=100000)
    assert sol.success, sol.message
    return float(sol.sol(L)[3]), float(sol.p[0]), sol.sol(np.linspace(0.0, L, 400))[0]


# ---------------------------------------------------------------- elliptic vs boundary-value problem
@pytest.mark.parametrize('y', [0.03, 0.08, 0.12, 0.14, 0.145, 0.16, 0.175, 0.185])
def test_elliptic_solution_matches_independent_bvp(robot, y):
    st = robot.solve_height(y)
    y_bvp, h_bvp, theta = bvp_weld(st.d)
    assert y_bvp == pytest.approx(y, rel=1e-6)
    assert st.horizontal == pytest.approx(h_bvp, rel=1e-6)
    # mode 1: the slope deviation keeps one sign inside the bar (one inflection of the curvature)
    dev = theta[1:-1] - math.pi / 4
    assert np.all(dev > 0) or np.all(dev < 0)
    # branch: compression (H < 0) raises the end effector, tension lowers it (Fig. 1.4)
    assert (h_bvp < 0) == (y > L / math.sqrt(2))


def test_bar_end_single_bar_matches_bvp_in_bar_frame():
    # one bar, bar frame, compression psi = 135 deg: the end of the elliptic solution and a BVP
    # with the same end force (R, psi) agree
    for k in (0.45, 0.6, 0.75):
        xp, yp, r = bar_end(k, PSI_COMPRESSION, L, EI)
        fx, fy = r * math.cos(PSI_COMPRESSION), r * math.sin(PSI_COMPRESSION)

        def f(s, y):
            th = y[0]
            return np.vstack([y[1], (fx * np.sin(th) - fy * np.cos(th)) / EI, np.cos(th), np.sin(th)])

        def bc(ya, yb):
            return np.array([ya[0], yb[0], ya[2], ya[3]])

        s = np.linspace(0.0, L, 201)
        # the mode-1 slope of the clamped-clamped bar: one hump, sign from the elliptic curvature
        amp = 0.5 * (1 if yp > 0 else -1)
        th = amp * np.sin(math.pi * s / L)
        guess = np.vstack([th, amp * math.pi / L * np.cos(math.pi * s / L), s, np.cumsum(np.sin(th)) * (s[1] - s[0])])
        sol = solve_bvp(f, bc, s, guess, tol=1e-10, bc_tol=1e-12, max_nodes=100000)
        assert sol.success
        assert sol.sol(L)[2] == pytest.approx(float(xp), rel=1e-6, abs=1e-9)
        assert sol.sol(L)[3] == pytest.approx(float(yp), rel=1e-6, abs=1e-9)


def test_paper_general_procedure_recovers_psi_135_from_a_robot_configuration(robot):
    st = robot.solve_height(0.16)
    # the bar end in the bar frame (the robot rotated 45 deg clockwise)
    a, b = (st.d + st.y) / math.sqrt(2), (st.y - st.d) / math.sqrt(2)
    psi, k, r = solve_bar(a, b, L, EI, psi0=math.radians(125.0), k0=st.k + 0.02)
    assert math.degrees(psi) == pytest.approx(135.0, abs=1e-7)
    assert k == pytest.approx(st.k, rel=1e-8)
    assert r == pytest.approx(st.force, rel=1e-7)


# ---------------------------------------------------------------- inverse / forward
def test_forward_of_inverse_is_identity_on_both_branches(robot):
    ylo, yhi = robot.height_range
    for y in np.linspace(ylo + 1e-4, yhi - 1e-6, 41):
        for x in (-0.05, 0.0, 0.02):
            q = robot.inverse([x, y])
            assert q[0] < q[1]
            sols = robot.forward(q)
            assert len(sols) == 1
            np.testing.assert_allclose(sols[0], [x, y], atol=1e-12)
    # and the straight, undeformed robot exactly at home
    np.testing.assert_allclose(robot.inverse([0.0, L / math.sqrt(2)]), [-L / math.sqrt(2), L / math.sqrt(2)])


def test_inverse_of_forward_is_identity(robot):
    dlo, dhi = robot.half_distance_range
    for d in np.linspace(dlo + 1e-5, dhi - 1e-6, 25):
        q = np.array([0.01 - d, 0.01 + d])
        pose, st = robot.forward_state(q)
        np.testing.assert_allclose(robot.inverse(pose), q, atol=1e-11)
        # compression (sliders together) raises the end effector
        assert (pose[1] > L / math.sqrt(2)) == (d < L / math.sqrt(2))
        assert st.branch == ('compression' if d < L / math.sqrt(2) else 'tension')


def test_height_beyond_mode_1_reach_is_rejected_with_the_reason(robot):
    ylo, yhi = robot.height_range
    # the compression branch's highest point: y rises, then falls as the sliders keep closing
    assert yhi == pytest.approx(0.18987, abs=1e-4)
    with pytest.raises(UnreachablePose, match="beyond mode 1's reach: above the highest point"):
        robot.inverse([0.0, yhi + 1e-4])
    with pytest.raises(UnreachablePose, match="below the lowest point of the tension branch"):
        robot.inverse([0.0, ylo - 1e-4])
    assert robot.forward([-0.001, 0.001]) == []          # sliders closer than mode 1's reach
    with pytest.raises(UnreachablePose, match='stroke|range'):
        Continuum2(L, E, W, T, ([-0.3, 0.0], [0.0, 0.3])).inverse([0.2, 0.16])


def test_bad_inputs_raise_value_error(robot):
    for bad in ([math.nan, 0.1], [0.0, math.inf], [0.1], [[0.0, 0.1]], 'ab'):
        with pytest.raises(ValueError):
            robot.inverse(bad)
    with pytest.raises(ValueError, match='s1 < s2'):
        robot.forward_state([0.1, -0.1])
    with pytest.raises(ValueError):
        robot.forward([0.0, math.nan])
    with pytest.raises(ValueError):
        Continuum2(-0.2, E, W, T, (-0.3, 0.3))


# ---------------------------------------------------------------- jacobian and wrench
def test_jacobian_matches_finite_differences_of_the_bvp(robot):
    for y in (0.12, 0.16):
        q = robot.inverse([0.0, y])
        d = 0.5 * (q[1] - q[0])
        h = 1e-5
        y_plus, _, _ = bvp_weld(d + h)
        y_minus, _, _ = bvp_weld(d - h)
        dd_dy = 2 * h / (y_plus - y_minus)
        jac = robot.jacobian([0.0, y])
        np.testing.assert_allclose(jac, [[1.0, -dd_dy], [1.0, dd_dy]], rtol=1e-5)


def test_wrench_is_zero_with_the_no_load_slider_forces(robot):
    pose = [0.0, 0.16]
    q = robot.inverse(pose)
    f0 = robot.slider_forces_no_load(q)
    assert f0[0] > 0 > f0[1]                      # compression: the sliders push the bars together
    np.testing.assert_allclose(robot.wrench(pose, f0), [0.0, 0.0], atol=1e-12)
    jac = robot.jacobian(pose)
    np.testing.assert_allclose(robot.wrench(pose, f0 + [1.0, 1.0]), jac.T @ [1.0, 1.0], atol=1e-12)


def test_load_mechanism_on_the_device_yaml():
    mech = load_mechanism('config/continuum.yaml')
    assert isinstance(mech, Continuum2)
    assert mech.dof == 2 and mech.n_actuators == 2 and mech.actuator_names == ('s1', 's2')
    assert mech.youngs_modulus == 4.0e9
    q = mech.inverse(mech.home_pose)
    lo, hi = mech.actuator_limits
    assert np.all((lo <= q) & (q <= hi))
    np.testing.assert_allclose(mech.forward(q)[0], mech.home_pose, atol=1e-12)


def test_branch_plot_tool_writes_the_figure(tmp_path):
    from brace_control.tools import continuum_plot
    out = tmp_path / 'branches.png'
    assert continuum_plot.main(['config/continuum.yaml', '--out', str(out)]) == 0
    assert out.stat().st_size > 1000
    robot = load_mechanism('config/continuum.yaml')
    cur = continuum_plot.branch_curves(robot, n=50)
    # Fig. 1.6: both curves start at the straight bar; compression goes up, tension down
    for name, sign in (('compression', 1), ('tension', -1)):
        assert cur[name]['y'][0] == pytest.approx(L / math.sqrt(2), abs=1e-9)
        assert sign * (cur[name]['y'][-1] - cur[name]['y'][0]) > 0


def test_unloaded_slider_forces_are_the_bars_push_from_the_bvp(robot):
    """With no load the sliders hold the bent bars: ``(-H, H)`` with ``H`` from the
    independent boundary-value solution (the simulator adds these to the efforts that
    balance the body, so the load cells read them)."""
    for d in (0.05, 0.12, 0.17):
        _, h_bvp, _ = bvp_weld(d)
        f0 = robot.unloaded_forces([-d, d])
        np.testing.assert_allclose(f0, [-h_bvp, h_bvp], rtol=1e-6)


def test_scalar_and_vectorised_bar_ends_agree(robot):
    """The per-call path (plain floats) and the vectorised reference, on both branches."""
    from brace_control.mechanisms.continuum import PSI_TENSION, _bar_end_scalar
    for psi in (PSI_COMPRESSION, PSI_TENSION):
        kmin = abs(math.cos(psi / 2))
        k = np.linspace(kmin + 1e-6, 0.999, 50)
        xp, yp, force = bar_end(k, psi, L, EI)
        got = np.array([_bar_end_scalar(float(v), psi, L, EI) for v in k])
        np.testing.assert_allclose(got[:, 0], (xp - yp) / math.sqrt(2), rtol=1e-13, atol=1e-15)
        np.testing.assert_allclose(got[:, 1], (xp + yp) / math.sqrt(2), rtol=1e-13, atol=1e-15)
        np.testing.assert_allclose(got[:, 2], force, rtol=1e-13)
