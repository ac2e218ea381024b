"""Independent oracles shared by the tests: the lumbar paper's eq. 3, a forward-kinematics
root count (test_rpr3.py, test_rrr3.py), and the minimum-jerk motion (Flash-Hogan).

Written out from the loop equations, not from the code under test: ``g(theta)`` is legs
2 and 3 minus leg 1 solved for ``B1 - A1`` by Cramer's rule, leg 1 times ``det^2``; its
sign changes over a dense ``theta`` grid, refined by brentq, are the assembly modes.
(A 3-RRR with its motors fixed is a 3-RPR with the elbows as base anchors.)
"""
from __future__ import annotations

import math

import numpy as np
from scipy.optimize import brentq


def fk_residual(base, plat, lengths, theta: np.ndarray) -> np.ndarray:
    """g(theta): legs 2, 3 minus leg 1 solved for B1 - A1 by Cramer, leg 1 times det^2."""
    a = np.asarray(base, float) - base[0]
    b = np.asarray(plat, float) - plat[0]
    l1, l2, l3 = lengths
    c, s = np.cos(theta), np.sin(theta)
    rows, rhs = [], []
    for i, li in ((1, l2), (2, l3)):
        rbx, rby = c * b[i, 0] - s * b[i, 1], s * b[i, 0] + c * b[i, 1]
        rows.append((rbx - a[i, 0], rby - a[i, 1]))
        rhs.append(0.5 * (li ** 2 - l1 ** 2 - a[i] @ a[i] - b[i] @ b[i] + 2 * (a[i, 0] * rbx + a[i, 1] * rby)))
    (m2x, m2y), (m3x, m3y) = rows
    det = m2x * m3y - m2y * m3x
    px = rhs[0] * m3y - rhs[1] * m2y
    py = m2x * rhs[1] - m3x * rhs[0]
    return px ** 2 + py ** 2 - l1 ** 2 * det ** 2


def fk_thetas_by_sampling(base, plat, lengths, n: int = 200_001) -> list[float]:
    """The roots of :func:`fk_residual` on ``[-pi, pi]``: sign changes on ``n`` samples, brentq."""
    th = np.linspace(-math.pi, math.pi, n)
    g = fk_residual(base, plat, lengths, th)
    idx = np.flatnonzero(np.sign(g[1:]) != np.sign(g[:-1]))
    return [brentq(lambda t: fk_residual(base, plat, lengths, np.array([t]))[0], th[i], th[i + 1], xtol=1e-14)
            for i in idx]


#: the lumbar brace (seed 001): r1 = 217 mm, r2 = 195 mm
R1, R2 = 0.217, 0.195


def lumbar_eq3(pose) -> np.ndarray:
    """Paper eq. 3: the lumbar brace's actuator lengths l1, l2, l3 of pose (x, y, theta)."""
    x, y, t = pose
    return np.array([
        math.sqrt((x - R2 * math.cos(t) + R1) ** 2 + (y - R2 * math.sin(t)) ** 2),
        math.sqrt(x ** 2 + y ** 2),
        math.sqrt((x + R2 * math.cos(t) - R1) ** 2 + (y + R2 * math.sin(t)) ** 2),
    ])


def eq3_jacobian(pose, h: float = 1e-7) -> np.ndarray:
    """dq/dpose of eq. 3 by central differences (3x3): ``J^T f`` is the platform wrench."""
    pose = np.asarray(pose, dtype=float)
    cols = [(lumbar_eq3(pose + h * e) - lumbar_eq3(pose - h * e)) / (2 * h) for e in np.eye(3)]
    return np.array(cols).T


def min_jerk(q0, q1, duration: float, n: int):
    """Flash-Hogan minimum jerk from ``q0`` to ``q1`` over ``duration`` (thesis 002 eq. 2.2),
    at ``n`` evenly spaced times: ``(t, Q, V, A)``, rows per time, columns per coordinate."""
    q0, q1 = np.atleast_1d(np.asarray(q0, dtype=float)), np.atleast_1d(np.asarray(q1, dtype=float))
    t = np.linspace(0.0, duration, n)
    s = t / duration
    d = q1 - q0
    p = 10 * s ** 3 - 15 * s ** 4 + 6 * s ** 5
    v = (30 * s ** 2 - 60 * s ** 3 + 30 * s ** 4) / duration
    a = (60 * s - 180 * s ** 2 + 120 * s ** 3) / duration ** 2
    return t, q0 + np.outer(p, d), np.outer(v, d), np.outer(a, d)


def cable_lengths_4rpr(cfg, pose) -> np.ndarray:
    """4-RPR cable lengths at a pose, from the YAML geometry written out:
    ``|p + R(psi) r (cos d_n, sin d_n) - A_n|`` (report §"FOUR RPR", eq. 1)."""
    m = cfg['mechanism']
    A = np.asarray(m['base_anchors'], float).reshape(4, 2)
    r = float(m['platform_radius'])
    d = np.asarray(m['anchor_angles'], float)
    x, y, psi = pose
    B = np.column_stack([r * np.cos(d + psi), r * np.sin(d + psi)])
    return np.linalg.norm(np.array([x, y]) + B - A, axis=1)
