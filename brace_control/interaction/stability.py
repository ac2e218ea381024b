"""The admittance loop against the patient's body, one pose axis: stability and design.

The loop (docs/interaction.md has the derivation)::

    e = W_goal - W          admittance  (M s + D) v = e,  x_sp = v / s   (period dt, ZOH)
    x = x_sp delayed by T, through the inner position loop 1 / (tau s + 1)
    W = K (x - r) + c (x_dot - r_dot)   the brace's wrench on the body (spring K, tissue damping c)

Open loop from ``e`` to ``W``::

    L(s) = (K + c s) exp(-s T) / (s (M s + D) (tau s + 1))                          (3)

For ``c = 0``, ``tau = 0``, ``M -> 0`` the crossover is ``w_c = K / D`` and the phase margin
``PM = pi/2 - w_c T``: the loop is stable for ``K T / D < pi / 2`` and well damped (PM >= 45
deg) for ``D >= 2 K T / (pi / 2)``... in general, :func:`phase_margin` evaluates (3) and
:func:`design_damping` picks the smallest ``D`` (the most transparent brace) with the
required margin at the stiffest body of the range; ``M = D tau_m`` keeps the virtual
model's own time constant ``tau_m`` short (it filters the load-cell noise).

:func:`simulate_loop` runs the discrete loop itself (the exact ZOH admittance of
:mod:`.admittance`, an integer number of periods of delay, the first-order inner loop and
the body's spring-damper): what the unit test sweeps.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ['LoopModel', 'phase_margin', 'design_damping', 'simulate_loop']


@dataclass(frozen=True)
class LoopModel:
    """One pose axis of the loop (SI).

    :param stiffness: body stiffness ``K`` (N/m or N·m/rad).
    :param body_damping: tissue damping ``c`` (N·s/m or N·m·s/rad).
    :param mass: virtual mass ``M``.
    :param damping: virtual damping ``D``.
    :param dt: admittance period (s).
    :param delay: pure delay ``T`` from the measured wrench to the commanded motion (s).
    :param lag: time constant ``tau`` of the inner position loop (s).
    """

    stiffness: float
    body_damping: float
    mass: float
    damping: float
    dt: float
    delay: float
    lag: float


def _open_loop(m: LoopModel, w: np.ndarray) -> np.ndarray:
    s = 1j * w
    # the zero-order hold of the admittance's output adds dt / 2 of delay
    t = m.delay + 0.5 * m.dt
    return (m.stiffness + m.body_damping * s) * np.exp(-s * t) / (
        s * (m.mass * s + m.damping) * (m.lag * s + 1.0))


def phase_margin(m: LoopModel) -> tuple[float, float]:
    """``(PM in degrees, crossover in rad/s)`` of (3); PM < 0: unstable."""
    w = np.logspace(-2, math.log10(math.pi / m.dt), 20000)
    mag = np.abs(_open_loop(m, w))
    above = np.flatnonzero(mag >= 1.0)
    if above.size == 0:
        return 180.0, 0.0
    i = int(above[-1])
    wc = float(w[min(i + 1, w.size - 1)])
    phase = float(np.degrees(np.unwrap(np.angle(_open_loop(m, w[:i + 2])))[-1]))
    return 180.0 + phase, wc


def design_damping(stiffness_max: float, *, body_damping: float, dt: float, delay: float,
                   lag: float, tau_m: float, pm_deg: float = 45.0) -> tuple[float, float]:
    """The smallest virtual damping ``D`` (and ``M = D tau_m``) for which (3) has at least
    ``pm_deg`` of phase margin against the stiffest body ``stiffness_max``.

    :returns: ``(M, D)``.
    """
    lo, hi = 1e-6 * stiffness_max, 1e3 * stiffness_max
    for _ in range(100):
        d = math.sqrt(lo * hi)
        pm, _ = phase_margin(LoopModel(stiffness_max, body_damping, d * tau_m, d, dt, delay, lag))
        lo, hi = (d, hi) if pm < pm_deg else (lo, d)
    return hi * tau_m, hi


def simulate_loop(m: LoopModel, *, goal: np.ndarray, rest: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The discrete loop, sample by sample.

    :param goal: the wrench goal per period (N or N·m).
    :param rest: the body's rest position per period (m or rad; the sway).
    :returns: ``(W, x)``: the brace's wrench on the body and the ring's position per period.
    """
    n = len(goal)
    delay_n = int(round(m.delay / m.dt))
    p = math.exp(-m.damping * m.dt / m.mass)
    a_in = 1.0 - math.exp(-m.dt / m.lag) if m.lag > 0 else 1.0
    r_dot = np.gradient(rest, m.dt)
    sp = np.full(n + delay_n + 1, rest[0])      # starts at rest, in equilibrium
    x, x_prev = float(rest[0]), float(rest[0])
    v = 0.0
    out_w, out_x = np.empty(n), np.empty(n)
    for k in range(n):
        w = m.stiffness * (x - rest[k]) + m.body_damping * ((x - x_prev) / m.dt - r_dot[k])
        out_w[k], out_x[k] = w, x
        e = goal[k] - w
        v_inf = e / m.damping
        v_new = v * p + (1.0 - p) * v_inf
        sp[k + delay_n + 1] = sp[k + delay_n] + v_inf * m.dt + (v - v_inf) * (m.mass / m.damping) * (1.0 - p)
        v = v_new
        x_prev = x
        x = x + a_in * (sp[k + 1] - x)
    return out_w, out_x
