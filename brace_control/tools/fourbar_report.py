"""``brace-fourbar-report``: torque curves and spring optimisation of the upper-limb trainer.

``brace-fourbar-report config/upper_limb_trainer.yaml --out DIR`` prints, for the thesis's
two exercises (seed 002, §4.1 straight line / App. A, §4.2 curved reach / App. B):

* the *replica*: the Appendix A/B MATLAB computation re-done line by line
  (:func:`thesis_replica`), with its slips, and then with them fixed one at a time (the
  "slip ladder"), next to the thesis's reported maxima;
* the *physics*: :class:`~brace_control.mechanisms.fourbar.HoekenFourBar` on the device
  YAML (Table 3.1 links), the minimum-jerk reach from :mod:`brace_control.trajectory`,
  the patient's imaginary spring (eq. 3.20), ``T2`` (eq. 3.19) and ``T4`` (eq. 3.20);
* the springs of eq. 4.1 fitted to ``T4`` by differential evolution (fixed seed), and the
  thesis's Table 4.1 / 4.3 springs evaluated on the same curve;

and writes ``fourbar_<exercise>.png`` (torques and angles) and ``fourbar_springs.png`` to DIR.

The slips of the thesis's code (App. A / App. B), as :func:`thesis_replica` names them:

``tau``          ``VPx = (x0 - xf)(-30 tau^2 + 60 tau^3 - 30 tau^4)`` is ``dx/dtau``, not ``dx/dt``
                 (and ``APx`` is ``d2x/dtau^2``): velocities 1/tf = 2x, accelerations 4x too small.
``force_sign``   ``FP = k (x_MJM - x_hand)``: the imaginary spring pushes ``P`` *away* from the hand;
                 a spring between hand and ``P`` pulls it towards the hand.
``force_dir``    App. A: ``FPx = FPy = F / sqrt(2)`` although the deviation is horizontal
                 (App. B and §4.2: force along x only).
``g3``           App. A: ``ACG3 = AA + ABA`` with ``ABA`` from the ``2 L3`` rows, i.e. the
                 acceleration of ``P``, while ``G3`` is at ``B`` (App. B uses ``L3``: right).
``r14``          ``R14x = +R14 cos(theta4)`` (with ``R14y = -R14 sin(theta4)``): the vector from
                 ``G4`` to ``O4`` is ``-R14 (cos, sin)``. Harmless in App. A (rocker near
                 vertical, 1.5 %); as printed, App. B's ``T2`` would peak at 234 N·m, so the
                 thesis's own App. B run cannot have had it (the replica of B fixes it always).
``flip``         App. B: ``w3, w4, a3, a4`` negated after the velocity / acceleration solves.

Not fixable inside the replica (the physics handles them): App. B's path is up to 5.3 mm
off the coupler curve, and ``theta2, theta3`` (from the crank side) and ``theta4`` (from the
rocker side) then leave the loop open by up to 9 mm; eq. 3.19 prints ``+R34x`` in row 9
(the code's ``-R34x`` is right).
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from types import SimpleNamespace
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ['THESIS_MAXIMA', 'ReplicaResult', 'thesis_replica', 'physics_exercise', 'exercise_config',
           'fit_springs', 'main']

#: the thesis's reported maxima: (value N·m, where) — where is theta2/theta4 (deg) for A, t (s) for B
THESIS_MAXIMA = {
    ('straight_line', 't2'): (1.038, 136.5),    # theta2 (deg)
    ('straight_line', 't4'): (1.7493, 105.1),   # theta4 (deg)
    ('curved', 't2'): (3.195, 0.175),           # t (s)
    ('curved', 't4'): (3.838, 0.15),            # t (s)
}

#: the App. A/B mass data (the device YAML holds the same)
_M2, _M3, _M4, _MF, _RF, _W = 0.03, 0.1, 0.06, 2.5, 0.08, 0.02


@dataclass
class ReplicaResult:
    """Arrays over the replica's time grid (App. A: 100 samples, App. B: 101)."""

    t: np.ndarray
    theta2: np.ndarray
    theta3: np.ndarray
    theta4: np.ndarray
    torque: np.ndarray
    stiffness: float
    loop_gap: np.ndarray       #: |B(crank side) - B(rocker side)| (m): the thesis's loop closure

    def peak(self) -> tuple[float, int]:
        i = int(np.argmax(self.torque))
        return float(self.torque[i]), i

    def peak_abs(self) -> tuple[float, int]:
        i = int(np.argmax(np.abs(self.torque)))
        return float(self.torque[i]), i


def _mjm_straight(x0: float, xf: float, t: np.ndarray, tf: float) -> tuple[np.ndarray, ...]:
    """Eq. 2.2 and the App. A derivative lines (with respect to tau, as printed)."""
    tau = t / tf
    x = x0 + (x0 - xf) * (-10 * tau ** 3 + 15 * tau ** 4 - 6 * tau ** 5)
    v = (x0 - xf) * (-30 * tau ** 2 + 60 * tau ** 3 - 30 * tau ** 4)
    a = (x0 - xf) * (-60 * tau + 180 * tau ** 2 - 120 * tau ** 3)
    return x, v, a


def _mjm_via(a0: float, a1: float, af: float, t: np.ndarray, tf: float, t1: float) -> tuple[np.ndarray, ...]:
    """Eqs. 2.4-2.11 and the App. B derivative lines (d/dtau, as printed), per coordinate."""
    tau1 = t1 / tf
    c = 1 / (tf ** 5 * tau1 ** 2 * (1 - tau1) ** 5) * (
        (af - a0) * (300 * tau1 ** 5 - 1200 * tau1 ** 4 + 1600 * tau1 ** 3)
        + tau1 ** 2 * (-720 * af + 120 * a1 + 600 * a0) + (a0 - a1) * (300 * tau1 - 200))
    p = 1 / (tf ** 5 * tau1 ** 5 * (1 - tau1) ** 5) * (
        (af - a0) * (120 * tau1 ** 5 - 300 * tau1 ** 4 + 200 * tau1 ** 3) - 20 * (a1 - a0))
    k = tf ** 5 / 720
    tau = t / tf
    before = t <= t1 + 1e-12
    x = np.where(before,
                 k * (p * (tau1 ** 4 * (15 * tau ** 4 - 30 * tau ** 3) + tau1 ** 3 * (80 * tau ** 3 - 30 * tau ** 4)
                           - 60 * tau ** 3 * tau1 ** 2 + 30 * tau ** 4 * tau1 - 6 * tau ** 5)
                      + c * (15 * tau ** 4 - 10 * tau ** 3 - 6 * tau ** 5)) + a0,
                 k * (p * (tau1 ** 4 * (15 * tau ** 4 - 30 * tau ** 3 + 30 * tau - 15)
                           + tau1 ** 3 * (-30 * tau ** 4 + 80 * tau ** 3 - 60 * tau ** 2 + 10))
                      + c * (-6 * tau ** 5 + 15 * tau ** 4 - 10 * tau ** 3 + 1)) + af)
    v = np.where(before,
                 k * (p * (tau1 ** 4 * (60 * tau ** 3 - 90 * tau ** 2) + tau1 ** 3 * (240 * tau ** 2 - 120 * tau ** 3)
                           - 180 * tau ** 2 * tau1 ** 2 + 120 * tau ** 3 * tau1 - 30 * tau ** 4)
                      + c * (60 * tau ** 3 - 30 * tau ** 2 - 30 * tau ** 4)),
                 k * (p * (tau1 ** 4 * (60 * tau ** 3 - 90 * tau ** 2 + 30)
                           + tau1 ** 3 * (-120 * tau ** 3 + 240 * tau ** 2 - 120 * tau))
                      + c * (-30 * tau ** 4 + 60 * tau ** 3 - 30 * tau ** 2)))
    a = np.where(before,
                 k * (p * (tau1 ** 4 * (180 * tau ** 2 - 180 * tau) + tau1 ** 3 * (480 * tau - 360 * tau ** 2)
                           - 360 * tau * tau1 ** 2 + 360 * tau ** 2 * tau1 - 120 * tau ** 3)
                      + c * (180 * tau ** 2 - 60 * tau - 120 * tau ** 3)),
                 k * (p * (tau1 ** 4 * (180 * tau ** 2 - 180 * tau) + tau1 ** 3 * (-360 * tau ** 2 + 480 * tau - 120))
                      + c * (-120 * tau ** 3 + 180 * tau ** 2 - 60 * tau)))
    return x, v, a


def _half_angle(a: np.ndarray, b: np.ndarray, c: np.ndarray, sign: float) -> np.ndarray:
    """Eq. 3.12: ``2 atan((-B +- sqrt(B^2 - 4 A C)) / (2 A))``."""
    return 2 * np.arctan((-b + sign * np.sqrt(b ** 2 - 4 * a * c)) / (2 * a))


def thesis_replica(case: str, ex: Mapping[str, Any], *, drive: str = 'crank',
                   fixes: Iterable[str] = ()) -> ReplicaResult:
    """The App. A (``case='A'``) or App. B (``'B'``) computation, as printed, with ``fixes``.

    ``drive='rocker'`` moves the torque unknown to link 4's moment row (eq. 3.20; the
    thesis prints no code for it). ``fixes``: any of ``tau, force_sign, force_dir, g3, r14,
    flip`` (module docstring). App. B always gets ``r14`` (see there).
    """
    fx = set(fixes)
    unknown = fx - {'tau', 'force_sign', 'force_dir', 'g3', 'r14', 'flip'}
    if unknown or case not in ('A', 'B') or drive not in ('crank', 'rocker'):
        raise ValueError(f'thesis_replica: bad case/drive/fixes {case!r}, {drive!r}, {sorted(unknown)}')
    if case == 'B':
        fx.add('r14')
    l1, l2, l3 = (float(v) for v in ex['thesis_links'])
    l4 = l3
    ig2 = _M2 * (l2 ** 2 + _W ** 2) / 12 + _MF * _RF ** 2
    ig3 = _M3 * (l3 ** 2 + _W ** 2) / 12
    ig4 = _M4 * (l4 ** 2 + _W ** 2) / 12
    tf = float(ex['duration'])
    (x0, y0), (xf, yf) = ex['start'], ex['goal']
    if case == 'A':
        t = np.linspace(0, tf, 100)
        rx, vpx, apx = _mjm_straight(x0, xf, t, tf)
        ry, _, _ = _mjm_straight(y0, yf, t, tf)
        vpy = np.zeros_like(t)
        roots = (1.0, 1.0, -1.0)
    else:
        t1 = float(ex['t_via'])
        t = np.concatenate([np.arange(0, t1 + 1e-9, 0.005), np.arange(t1 + 0.005, tf + 1e-9, 0.005)])
        (x1, y1) = ex['via']
        rx, vpx, apx = _mjm_via(x0, x1, xf, t, tf, t1)
        ry, vpy, _ = _mjm_via(y0, y1, yf, t, tf, t1)
        roots = (-1.0, -1.0, -1.0)
    if 'tau' in fx:
        vpx, vpy, apx = vpx / tf, vpy / tf, apx / tf ** 2
    # the impaired hand and the imaginary spring (eq. 3.20)
    hand = np.polyval(np.polyfit(np.asarray(ex['hand_t'], float), np.asarray(ex['hand_x'], float), 5), t)
    diff = rx - hand
    dmax = float(np.max(diff)) if case == 'A' else float(np.max(np.abs(diff)))
    k = float(ex['max_patient_force']) / dmax
    force = k * diff * (-1.0 if 'force_sign' in fx else 1.0)
    if case == 'A' and 'force_dir' not in fx:
        fpx, fpy = force / math.sqrt(2), force / math.sqrt(2)
    else:
        fpx, fpy = force, np.zeros_like(force)
    # position analysis, eqs. 3.8-3.12 and the App. code's theta3, theta4 quadratics
    th2 = _half_angle(rx ** 2 + 2 * rx * l2 + l2 ** 2 + ry ** 2 - 4 * l3 ** 2, -4 * ry * l2,
                      rx ** 2 + ry ** 2 + l2 ** 2 - 4 * l3 ** 2 - 2 * rx * l2, roots[0])
    if case == 'A':
        th2 = np.unwrap(th2)
    th3 = _half_angle(-rx ** 2 - 4 * rx * l3 + l2 ** 2 - ry ** 2 - 4 * l3 ** 2, 8 * ry * l3,
                      -rx ** 2 - ry ** 2 + l2 ** 2 - 4 * l3 ** 2 + 4 * rx * l3, roots[1])
    th4 = _half_angle(-rx ** 2 + 2 * rx * l1 - l4 ** 2 - ry ** 2 + l3 ** 2 - l1 ** 2 - 2 * rx * l4 + 2 * l4 * l1,
                      4 * ry * l4,
                      -rx ** 2 - ry ** 2 + l3 ** 2 - l4 ** 2 + 2 * rx * l1 + 2 * rx * l4 - 2 * l4 * l1 - l1 ** 2,
                      roots[2])
    gap = np.abs(l2 * np.exp(1j * th2) + l3 * np.exp(1j * th3) - (l1 + l4 * np.exp(1j * th4)))
    torque = np.empty_like(t)
    rel = 2.0 if (case == 'A' and 'g3' not in fx) else 1.0     # App. A rows 5-6: 2 L3 (P), App. B: L3 (B)
    for i in range(t.size):
        s2, c2, s3, c3 = math.sin(th2[i]), math.cos(th2[i]), math.sin(th3[i]), math.cos(th3[i])
        s4, c4 = math.sin(th4[i]), math.cos(th4[i])
        if case == 'A':
            m1 = np.array([[-l2 * s2, -l3 * s3, l4 * s4, 0, 0, 0, 0, 0], [l2 * c2, l3 * c3, -l4 * c4, 0, 0, 0, 0, 0],
                           [l2 * s2, 0, 0, 1, 0, 0, 0, 0], [-l2 * c2, 0, 0, 0, 1, 0, 0, 0],
                           [0, 2 * l3 * s3, 0, 0, 0, 1, 0, 0], [0, -2 * l3 * c3, 0, 0, 0, 0, 1, 0],
                           [-l2 * s2, -2 * l3 * s3, 0, 0, 0, 0, 0, 0], [-l2 * c2, -2 * l3 * c3, 0, 0, 0, 0, 0, 1]])
            x1 = np.linalg.solve(m1, [0, 0, 0, 0, 0, 0, vpx[i], 0])
            w2, w3, w4 = x1[:3]
        else:
            m1 = np.array([[-l2 * s2, -l3 * s3, l4 * s4, 0, 0, 0, 0], [2 * l2 * c2, 3 * l3 * c3, -l4 * c4, 0, 0, 0, 0],
                           [l2 * s2, 0, 0, 1, 0, 0, 0], [-l2 * c2, 0, 0, 0, 1, 0, 0],
                           [0, l3 * s3, 0, 0, 0, 1, 0], [0, -l3 * c3, 0, 0, 0, 0, 1],
                           [-l2 * s2, -2 * l3 * s3, 0, 0, 0, 0, 0]])
            x1 = np.linalg.solve(m1, [0, vpy[i], 0, 0, 0, 0, vpx[i]])
            sg = 1.0 if 'flip' in fx else -1.0
            w2, w3, w4 = x1[0], sg * x1[1], sg * x1[2]
        m2 = np.array([[-l2 * s2, -l3 * s3, l4 * s4, 0, 0, 0, 0, 0], [l2 * c2, l3 * c3, -l4 * c4, 0, 0, 0, 0, 0],
                       [l2 * s2, 0, 0, 1, 0, 0, 0, 0], [-l2 * c2, 0, 0, 0, 1, 0, 0, 0],
                       [0, rel * l3 * s3, 0, 0, 0, 1, 0, 0], [0, -rel * l3 * c3, 0, 0, 0, 0, 1, 0],
                       [-l2 * s2, -2 * l3 * s3, 0, 0, 0, 0, 0, 0], [-l2 * c2, -2 * l3 * c3, 0, 0, 0, 0, 0, 1]])
        y2 = [l2 * w2 ** 2 * c2 + l3 * w3 ** 2 * c3 - l4 * w4 ** 2 * c4,
              l2 * w2 ** 2 * s2 + l3 * w3 ** 2 * s3 - l4 * w4 ** 2 * s4,
              -l2 * w2 ** 2 * c2, -l2 * w2 ** 2 * s2, -rel * l3 * w3 ** 2 * c3, -rel * l3 * w3 ** 2 * s3,
              apx[i] + l2 * w2 ** 2 * c2 + 2 * l3 * w3 ** 2 * c3, -l2 * w2 ** 2 * s2 - 2 * l3 * w3 ** 2 * s3]
        x2 = np.linalg.solve(m2, y2)
        a2, a3, a4 = x2[:3]
        if case == 'B' and 'flip' not in fx:
            a3, a4 = -a3, -a4
        ag3x, ag3y = x2[3] + x2[5], x2[4] + x2[6]
        ag4x = -0.5 * l4 * a4 * s4 - 0.5 * l4 * w4 ** 2 * c4
        ag4y = 0.5 * l4 * a4 * c4 - 0.5 * l4 * w4 ** 2 * s4
        # v = [1 0 0.5]: R12 = 0, R32 = L2, R23 = L3, R43 = 0, R34 = R14 = L4 / 2
        r32x, r32y = l2 * c2, l2 * s2
        r23x, r23y = -l3 * c3, -l3 * s3
        r34x, r34y = 0.5 * l4 * c4, 0.5 * l4 * s4
        r14x = (-1.0 if 'r14' in fx else 1.0) * 0.5 * l4 * c4
        r14y = -0.5 * l4 * s4
        rpx, rpy = l3 * c3, l3 * s3
        m3 = np.array([[1, 0, 1, 0, 0, 0, 0, 0, 0], [0, 1, 0, 1, 0, 0, 0, 0, 0],
                       [0, 0, -r32y, r32x, 0, 0, 0, 0, 1.0 if drive == 'crank' else 0.0],
                       [0, 0, -1, 0, 1, 0, 0, 0, 0], [0, 0, 0, -1, 0, 1, 0, 0, 0],
                       [0, 0, r23y, -r23x, 0, 0, 0, 0, 0], [0, 0, 0, 0, -1, 0, 1, 0, 0],
                       [0, 0, 0, 0, 0, -1, 0, 1, 0],
                       [0, 0, 0, 0, r34y, -r34x, -r14y, r14x, 1.0 if drive == 'rocker' else 0.0]])
        y3 = [0, 0, ig2 * a2, _M3 * ag3x - fpx[i], _M3 * ag3y - fpy[i], ig3 * a3 - rpx * fpy[i] + rpy * fpx[i],
              _M4 * ag4x, _M4 * ag4y, ig4 * a4]
        torque[i] = np.linalg.solve(m3, y3)[8]
    return ReplicaResult(t, th2, th3, th4, torque, k, gap)


# ---------------------------------------------------------------------------------- physics
def exercise_config(cfg: Mapping[str, Any], name: str) -> dict[str, Any]:
    """The ``exercises.<name>`` section of a device config (``ConfigError`` if absent)."""
    from ..config import ConfigError
    exs = cfg.get('exercises')
    if not isinstance(exs, Mapping) or not isinstance(exs.get(name), Mapping):
        raise ConfigError(f'parameter exercises.{name} is missing')
    return dict(exs[name])


def physics_exercise(mech: Any, ex: Mapping[str, Any], *, samples: int | None = None) -> Any:
    """Run one exercise on the device model (:func:`~brace_control.mechanisms.fourbar.run_exercise`)."""
    from ..mechanisms.fourbar import run_exercise
    from ..trajectory import MinimumJerk, ViaPointMinimumJerk
    tf = float(ex['duration'])
    if 'via' in ex:
        traj = ViaPointMinimumJerk(ex['start'], ex['via'], ex['goal'], tf, t_via=float(ex['t_via']))
    else:
        traj = MinimumJerk(ex['start'], ex['goal'], tf)
    n = int(samples or ex.get('samples', 501))
    coeff = np.polyfit(np.asarray(ex['hand_t'], float), np.asarray(ex['hand_x'], float), 5)
    return run_exercise(mech, traj.sample, np.linspace(0.0, tf, n), hand=lambda t: np.polyval(coeff, t),
                        max_patient_force=float(ex['max_patient_force']), follow=str(ex.get('follow', 'nearest')))


def transmission(profile: Any) -> np.ndarray:
    """``|sin(theta2 - theta3)|``: 0 at a dead point for the rocker drive (crank and coupler aligned)."""
    return np.abs(np.sin(profile.state.theta2 - profile.state.theta3))


def fit_springs(profile: Any, ex: Mapping[str, Any], *, margin: float, seed: int, maxiter: int,
                popsize: int, unilateral: bool = True) -> tuple[Any, np.ndarray]:
    """Eq. 4.1 on the physics ``T4`` where ``transmission >= margin``; returns ``(SpringFit, mask)``."""
    from ..config import points
    from ..mechanisms.fourbar import optimise_springs
    bounds = [tuple(b) for b in points(ex['spring_bounds'], 'spring_bounds')]
    mask = (transmission(profile) >= margin) & np.isfinite(profile.t4)
    fit = optimise_springs(profile.state.theta4[mask], profile.t4[mask], bounds, seed=seed, maxiter=maxiter,
                           popsize=popsize, unilateral=unilateral)
    return fit, mask


# ---------------------------------------------------------------------------------- report
_LADDER = {
    'A': [(), ('tau',), ('tau', 'force_sign'), ('tau', 'force_sign', 'force_dir'),
          ('tau', 'force_sign', 'force_dir', 'g3'), ('tau', 'force_sign', 'force_dir', 'g3', 'r14')],
    'B': [(), ('flip',), ('flip', 'tau'), ('flip', 'tau', 'force_sign')],
}


def _where(name: str, which: str, rep_or_prof: Any, i: int) -> str:
    if name == 'straight_line':
        ang = rep_or_prof.theta2 if which == 't2' else rep_or_prof.theta4
        return f'theta{which[1]} = {math.degrees(float(ang[i])):6.1f} deg'
    return f't = {float(rep_or_prof.t[i]):.3f} s'


def _plot(path: Path, name: str, prof: Any, reps: dict[str, ReplicaResult]) -> None:
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(1, 3, figsize=(15, 4.2))
    tr = transmission(prof)
    t4 = np.where(tr >= 0.05, prof.t4, np.nan)
    ax[0].plot(prof.t, prof.t2, label='T2 physics (eq. 3.19)')
    ax[0].plot(prof.t, t4, label='T4 physics (eq. 3.20), |sin(t2-t3)|>=0.05')
    for lab, rep in reps.items():
        ax[0].plot(rep.t, rep.torque, '--', label=lab)
    lo = np.nanmin([np.nanmin(prof.t2)] + [np.nanmin(r.torque) for r in reps.values()])
    hi = np.nanmax([np.nanmax(prof.t2)] + [np.nanmax(r.torque) for r in reps.values()])
    ax[0].set_ylim(lo - 0.5 * (hi - lo) - 0.5, hi + 0.5 * (hi - lo) + 0.5)
    ax[0].set_xlabel('t (s)')
    ax[0].set_ylabel('torque (N·m)')
    ax[0].set_title(f'{name}: required torques')
    ax[0].legend(fontsize=7)
    ax[0].grid(True)
    st = prof.state
    for lab, arr in (('theta2', st.theta2), ('theta3', st.theta3), ('theta4', st.theta4)):
        ax[1].plot(prof.t, np.degrees(arr), label=lab)
    ax[1].set_xlabel('t (s)')
    ax[1].set_ylabel('deg')
    ax[1].legend(fontsize=8)
    ax[1].grid(True)
    ax[1].set_title('link angles')
    ax[2].plot(st.p.real, st.p.imag, label='P (coupler curve)')
    ax[2].plot(prof.hand_x, st.p.imag, ':', label='hand x (impaired)')
    ax[2].set_aspect('equal', adjustable='datalim')
    ax[2].set_xlabel('x (m)')
    ax[2].set_ylabel('y (m)')
    ax[2].legend(fontsize=8)
    ax[2].grid(True)
    ax[2].set_title(f'path (max {prof.path_offset.max() * 1e3:.2f} mm off the MJM path)')
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _plot_springs(path: Path, fits: dict[str, tuple[Any, Any, np.ndarray, np.ndarray | None]]) -> None:
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, len(fits), figsize=(6.5 * len(fits), 4.2), squeeze=False)
    for ax, (name, (prof, fit, mask, table)) in zip(axes[0], fits.items()):
        t = prof.t[mask]
        ax.plot(t, prof.t4[mask], label='required T4 (physics)')
        ax.plot(t, fit.torque, label=f'springs, DE fit (rms {fit.rms:.3f} N·m)')
        if table is not None:
            ax.plot(t, table, ':', label='thesis table springs')
        ax.set_xlabel('t (s)')
        ax.set_ylabel('N·m')
        ax.set_title(f'{name}: eq. 4.1 springs on the rocker')
        ax.grid(True)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    """``brace-fourbar-report config/upper_limb_trainer.yaml --out DIR [--maxiter N --popsize N]``."""
    parser = argparse.ArgumentParser(
        prog='brace-fourbar-report',
        description='Upper-limb trainer (Hoeken four-bar): thesis torque maxima, physics torques, springs (PNG).')
    parser.add_argument('device', help='device YAML (e.g. config/upper_limb_trainer.yaml) or device name')
    parser.add_argument('--out', default='.', help='directory for the PNGs (default: %(default)s)')
    parser.add_argument('--maxiter', type=int, default=None, help='differential evolution generations (YAML default)')
    parser.add_argument('--popsize', type=int, default=None, help='differential evolution population factor')
    parser.add_argument('--no-plots', action='store_true', help='print only')
    args = parser.parse_args(argv)

    from ..config import ConfigError, load_device_config
    from ..mechanisms.fourbar import HoekenFourBar, spring_torques
    from ..mechanisms.loader import mechanism_from_config
    t_start = time.perf_counter()
    try:
        cfg = load_device_config(args.device)
        mech = mechanism_from_config(cfg)
        if not isinstance(mech, HoekenFourBar):
            raise ConfigError(f'{args.device} is not a hoeken_fourbar device')
        exs = cfg.get('exercises', {})
        names = list(exs.get('names', ['straight_line', 'curved']))
        exercises = {n: exercise_config(cfg, n) for n in names}
    except ConfigError as exc:
        print(f'brace-fourbar-report: {exc}', file=sys.stderr)
        return 2
    opt = dict(exs.get('optimiser', {}))
    seed = int(opt.get('seed', 1))
    maxiter = int(args.maxiter if args.maxiter is not None else opt.get('maxiter', 200))
    popsize = int(args.popsize if args.popsize is not None else opt.get('popsize', 15))
    unilateral = bool(opt.get('unilateral', True))
    margin = float(exs.get('dead_point_margin', 0.2))
    out = Path(args.out)
    if not args.no_plots:
        out.mkdir(parents=True, exist_ok=True)
    print(f'{args.device}: {mech!r}')
    print(f'  L1 = {mech.L1 * 1e3:.3f} mm, L2 = {mech.L2 * 1e3:.3f} mm, L3 = L4 = BP = {mech.L3 * 1e3:.3f} mm; '
          f'crank inertia with flywheel {mech.crank_inertia:.5f} kg m^2 about O2')
    fits: dict[str, tuple[Any, Any, np.ndarray, np.ndarray | None]] = {}
    for name, ex in exercises.items():
        case = 'B' if 'via' in ex else 'A'
        print(f'\n== {name} (App. {case}) ==')
        prof = physics_exercise(mech, ex)
        reps: dict[str, ReplicaResult] = {}
        print(f'  thesis maxima vs the App. {case} replica (slips fixed cumulatively):')
        for which, drive in (('t2', 'crank'), ('t4', 'rocker')):
            val, where = THESIS_MAXIMA[(name, which)]
            unit = 'deg' if case == 'A' else 's'
            print(f'   {which.upper()}: thesis {val:.4f} N·m at {where} {unit}')
            for fixes in _LADDER[case]:
                rep = thesis_replica(case, ex, drive=drive, fixes=fixes)
                pv, i = rep.peak()
                av, j = rep.peak_abs()
                label = '+'.join(fixes) if fixes else 'as printed'
                print(f'     {label:38s} peak {pv:9.4f} N·m ({_where(name, which, rep, i)})  '
                      f'|max| {av:9.4f} ({_where(name, which, rep, j)})  {100 * (pv / val - 1):+7.1f} %')
                if not fixes:
                    reps[f'{which.upper()} replica as printed'] = rep
        k_loop = thesis_replica(case, ex).loop_gap.max()
        print(f'   replica loop closure gap (crank-side vs rocker-side B): max {k_loop * 1e3:.3f} mm; '
              f'imaginary spring k = {thesis_replica(case, ex).stiffness:.4f} N/m')
        tr = transmission(prof)
        ns = SimpleNamespace(theta2=prof.state.theta2, theta4=prof.state.theta4, t=prof.t)
        print(f'  physics ({mech.branch} branch, follow = {ex.get("follow", "nearest")}, {prof.t.size} samples, '
              f'path off the curve by <= {prof.path_offset.max() * 1e3:.3f} mm, k_PU = {prof.stiffness:.4f} N/m):')
        for which in ('t2', 't4'):
            arr = getattr(prof, which)
            ok = tr >= margin if which == 't4' else np.ones_like(tr, bool)
            i = int(np.nanargmax(np.where(ok, arr, -np.inf)))
            j = int(np.nanargmax(np.where(ok, np.abs(arr), -np.inf)))
            note = f' (|sin(theta2 - theta3)| >= {margin})' if which == 't4' else ''
            at_t = f', t = {prof.t[i]:.3f} s' if case == 'A' else ''
            print(f'   {which.upper()}{note}: peak {arr[i]:8.4f} N·m ({_where(name, which, ns, i)}{at_t})  '
                  f'|max| {arr[j]:8.4f} N·m (t = {prof.t[j]:.3f} s)')
        for which in ('t2', 't4'):
            val, where = THESIS_MAXIMA[(name, which)]
            arr = getattr(prof, which)
            if case == 'A':
                ang = prof.state.theta2 if which == 't2' else prof.state.theta4
                # the first crossing of the thesis's angle (theta4 is monotonic on the stroke)
                j = int(np.argmax(np.degrees(ang) >= where))
                at = f'theta{which[1]} = {where} deg'
            else:
                j = int(np.argmin(np.abs(prof.t - where)))
                at = f't = {where} s'
            print(f'   {which.upper()} at the thesis\'s {at}: {arr[j]:8.4f} N·m (thesis {val} N·m)')
        kmin = int(np.argmin(tr))
        print(f'   rocker drive dead point: |sin(theta2 - theta3)| = {tr[kmin]:.4f} at t = {prof.t[kmin]:.3f} s '
              f'(T4 there {prof.t4[kmin]:.1f} N·m)')
        fit, mask = fit_springs(prof, ex, margin=margin, seed=seed, maxiter=maxiter, popsize=popsize,
                                unilateral=unilateral)
        table = None
        if ex.get('thesis_springs') is not None:
            table = spring_torques(prof.state.theta4[mask], ex['thesis_springs'], unilateral=unilateral)
            trms = float(np.sqrt(np.mean((prof.t4[mask] - table) ** 2)))
        req = float(np.sqrt(np.mean(prof.t4[mask] ** 2)))
        print(f'  springs (eq. 4.1, differential evolution seed {seed}, maxiter {maxiter}, popsize {popsize}, '
              f'{"contact" if unilateral else "two-sided"} springs, {int(mask.sum())} samples): '
              f'rms {fit.rms:.4f} N·m of a {req:.4f} N·m rms T4 ({fit.nfev} evaluations)')
        print('   ' + ', '.join(f'{k} = {math.degrees(v):.2f} deg' if k.startswith('beta') else
                               (f'{k} = {v:.2f} N/m' if k.startswith('k') else f'{k} = {v * 1e3:.1f} mm')
                               for k, v in fit.as_dict().items()))
        if table is not None:
            print(f'   thesis table springs on the same T4: rms {trms:.4f} N·m')
        fits[name] = (prof, fit, mask, table)
        if not args.no_plots:
            png = out / f'fourbar_{name}.png'
            _plot(png, name, prof, reps)
            print(f'  wrote {png}')
    if not args.no_plots and fits:
        png = out / 'fourbar_springs.png'
        _plot_springs(png, fits)
        print(f'\nwrote {png}')
    print(f'done in {time.perf_counter() - t_start:.1f} s')
    return 0


if __name__ == '__main__':
    sys.exit(main())
