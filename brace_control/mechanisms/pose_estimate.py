"""Load-aware forward kinematics: where the platform is, from encoders and load cells.

Pure numpy (no ROS). Any mechanism of the protocol (:class:`~.base.Mechanism`: ``inverse``,
``jacobian``, ``forward_nearest``) works; the kinetics node runs it on every joint state.

Leg model
---------
Each actuator is the encoder-measured stroke ``q_i`` in series with an axial compliance of
stiffness ``k_i`` (load cell, pins, straps, shells; a rotary joint's gear train and
coupling). The effort ``F_i`` (N, or N·m for a rotary joint) is what the actuator applies to
the mechanism, positive along ``+q_i`` (a linear actuator: push positive; a cable pulls,
``F < 0``). The compliance then carries ``F_i = k_i (q_i - L_i)``, so the rigid-mechanism
coordinate ("leg length") ``L_i`` the platform really sits on is (eq. 1)::

    L_i = q_i - F_i / k_i

the model of the simulator (``SimulatedBrace._equilibrium``: ``f = k (q - L(pose))``). Near a
singular pose a few micrometres of ``F / k`` are millimetres of pose (the lumbar brace's
nearly parallel legs: 10 um of leg ~ 3 mm of x), so the encoder lengths alone are not the
pose, and loaded encoder lengths may admit no assembly at all.

Estimate
--------
The pose ``p`` minimises the weighted inverse-kinematics residual (eq. 2)::

    p = argmin sum_i (L_i - l_i(p))^2 / sigma_i^2,    l(p) = inverse kinematics,

by Levenberg-Marquardt from the previous estimate (Gauss-Newton steps ``J_w^+ r_w``,
``J_w = diag(1/sigma) J``; bent by the geodesic acceleration where the cost's valley curves,
damped when a step would leave the trust radius ``max_step`` or not lower the residual),
see :meth:`PoseEstimator._least_squares`. Starting from the last estimate keeps the
solution on the assembly mode the device is in: the iterate descends from there, at most
``max_step`` per step, and never jumps to another mode. When the lengths admit no exact
assembly the result is the least-squares pose continuous with the previous one (reported
with its residual, never an exception). Three exceptions to "only descend":

* lost track: the solver settled (moved less than ``max_step`` this update) on a
  least-squares minimum while ``forward_nearest(L, last exact estimate)`` finds an
  assembly that closes (a spurious local minimum after a jump in the readings, or a
  solution sliding faster than the iterations follow): that assembly, reported as
  *reacquired*;
* fallen behind: the iterations ran out on steps cut to ``max_step`` (a jump in the
  readings longer than they can follow, as when the kinetics node skips joint states
  during a fast move). The iterate is then somewhere on the way, and on the lumbar brace's
  nearly parallel legs the way bends far along the barely observed x (up to 87 mm off
  after a 30 mm jump): the assembly ``forward_nearest`` finds nearest the last exact
  estimate, when it closes, also reported as *reacquired*;
* leaving a least-squares episode, which sits where two assembly modes meet (the lumbar
  brace's theta = 0): both are next to it, the mode of the last exact estimate is kept.

An under-actuated mechanism (fewer actuators than pose coordinates, the one-motor
four-bar) has its pose as a function of ``q``: ``forward_nearest(L, previous)``.

Stroke: a loaded leg may sit slightly outside the actuator's stroke (``L = q - F/k``), and
the iterates may too; the geometry is evaluated on a copy of the mechanism with the range
widened by ``stroke_margin`` (as the simulator widens the stroke for its physics), see
:func:`stroke_free`.

Covariance
----------
Per leg, independent errors (eq. 3)::

    sigma_i^2 = res^2 / 6  +  (sigma_F^2 + res_F^2 / 12) / k^2  +  (F_i sigma_k,rel / k)^2

``res`` the encoder quantum (linear: ``screw_lead / counts_per_rev``; rotary:
``2 pi / (counts_per_rev x gear_ratio)``). The encoder's error is two uniform quantisation
errors of one count, ``res^2 / 12`` each: the reading (the count says the position is
somewhere in one count) and the zero the homing set (the count's edge is somewhere within
the home count; the simulator's floor-counting encoder after homing reads up to one count
low or high, by leg). ``sigma_F`` the load cell's noise, ``res_F`` its quantum,
``sigma_k,rel`` the stiffness's relative uncertainty (``dL/dk = F / k^2``). Without a force
reading the force is only known to lie within ``+-force_limit`` (uniform):
``(force_limit / k)^2 / 3`` replaces the force terms. A cable reading no tension
(``F > -3 sigma_F``) may be slack: its length only bounds the platform (``L <= q``), so it
gets the variance of its whole stroke (it no longer weighs). Propagated to the pose to
first order (eq. 4)::

    Sigma_p = J_w^+ J_w^+T    (= (J^T Sigma_L^-1 J)^-1 for a full column rank J)

the covariance of the weighted least-squares estimate; ``J_w^+`` the pseudo-inverse
(redundant devices: the weighted least squares; an under-actuated device: rank ``n``, the
pose moves only along its path). A direction the lengths do not observe (a singular ``J``)
gets a huge, not a zero, variance. Not in the budget: the homing accuracy of the real
device (its parked length against the YAML's home pose), a load-cell offset, backlash.

Example::

    >>> from brace_control.mechanisms import load_mechanism
    >>> mech = load_mechanism('config/lumbar_brace.yaml')
    >>> model = MeasurementModel(stiffness=1e6, resolution=0.001 / 8192, force_noise=0.05,
    ...                          stiffness_rel_std=0.05)
    >>> est = PoseEstimator(mech, model)
    >>> q = mech.inverse(mech.home_pose) + 100.0 / 1e6     # 100 N in every leg
    >>> e = est.update(q, [100.0, 100.0, 100.0])
    >>> bool(abs(e.pose - mech.home_pose).max() < 1e-9), e.exact
    (True, True)
"""
from __future__ import annotations

import copy
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from .base import Mechanism, as_per_actuator, as_positive, as_vector
from .planar_floats import PlanarRprFloats

__all__ = ['MeasurementModel', 'PoseEstimate', 'PoseEstimator', 'stroke_free',
           'weighted_covariance']

_TWO_PI = 2.0 * math.pi
#: a singular value below this fraction of the largest counts as this fraction (the
#: unobserved direction then gets a variance ~1e30 x the observed ones, not zero)
_SINGULAR_FLOOR = 1e-15
#: the tolerance of the models' stroke check (:func:`~.base.check_limits`)
_REACH_TOL = 1e-12
#: a leg this short has no direction (the models' ``jacobian`` raises)
_ZERO_LEG = 1e-12


@dataclass(frozen=True)
class MeasurementModel:
    """What one reading of the actuators says about the leg lengths (eqs. 1 and 3), SI.

    :param stiffness: ``k`` (N/m, or N·m/rad for rotary joints), a scalar or one per actuator.
    :param resolution: encoder quantum (m or rad), a scalar or one per actuator.
    :param force_noise: ``sigma_F``, standard deviation of a force reading (N or N·m).
    :param stiffness_rel_std: ``sigma_k / k``, relative uncertainty of the stiffness.
    :param force_resolution: quantum of the force reading (N or N·m per count); adds
        ``res_F^2 / 12`` to ``sigma_F^2``.
    :param force_limit: bound on ``|F|`` (N or N·m) used when no force is measured.
    """

    stiffness: Any
    resolution: Any
    force_noise: float
    stiffness_rel_std: float
    force_resolution: float = 0.0
    force_limit: float = math.inf

    def __post_init__(self) -> None:
        for name in ('force_noise', 'stiffness_rel_std', 'force_resolution'):
            as_positive(getattr(self, name), name, allow_zero=True)
        as_positive(self.force_limit, 'force_limit', allow_inf=True)
        for name in ('stiffness', 'resolution'):
            arr = np.atleast_1d(np.asarray(getattr(self, name), dtype=float))
            if arr.ndim != 1 or not np.all(np.isfinite(arr)) or not np.all(arr > 0.0):
                raise ValueError(f'{name}: expected positive finite numbers, got {getattr(self, name)!r}')

    @property
    def force_variance(self) -> float:
        """Variance of one force reading: ``sigma_F^2 + res_F^2 / 12`` ((N or N·m)^2)."""
        return self.force_noise ** 2 + self.force_resolution ** 2 / 12.0

    def arrays(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """``(k, res)`` broadcast to ``n`` actuators (read-only arrays, built once per ``n``).

        :raises ValueError: a per-actuator list of another length.
        """
        memo = self.__dict__.setdefault('_arrays', {})
        if n not in memo:
            k = as_per_actuator(self.stiffness, n, 'stiffness', unit='N/m or N·m/rad')
            res = as_per_actuator(self.resolution, n, 'resolution', unit='m or rad')
            k.flags.writeable = res.flags.writeable = False
            memo[n] = (k, res)
        return memo[n]

    def leg_lengths(self, q: np.ndarray, forces: np.ndarray | None) -> np.ndarray:
        """Eq. 1: ``L = q - F / k`` (``q`` when no force is measured)."""
        q = np.asarray(q, dtype=float)
        if forces is None:
            return q.copy()
        k, _ = self.arrays(q.size)
        return q - np.asarray(forces, dtype=float) / k

    def leg_variance(self, forces: np.ndarray | None, n: int) -> np.ndarray:
        """Eq. 3: the variance of each ``L_i`` (m^2 or rad^2), shape (n,)."""
        k, res = self.arrays(n)
        if forces is None:
            var = res ** 2 / 6.0               # reading + homing reference, res^2 / 12 each
            if not math.isfinite(self.force_limit):
                raise ValueError('no force reading and force_limit = inf: the leg deflection is '
                                 'unbounded; give the load cells or a finite force_limit')
            return var + (self.force_limit / k) ** 2 / 3.0
        f = np.asarray(forces, dtype=float)
        return self._reading_variance(n) + (f * self.stiffness_rel_std / k) ** 2

    def _reading_variance(self, n: int) -> np.ndarray:
        """The part of eq. 3 that does not depend on the force: ``res^2 / 6 + (sigma_F^2 +
        res_F^2 / 12) / k^2`` (computed once per ``n``, read-only)."""
        memo = self.__dict__.setdefault('_reading_var', {})
        if n not in memo:
            k, res = self.arrays(n)
            reading = res ** 2 / 6.0 + self.force_variance / k ** 2
            reading.flags.writeable = False
            memo[n] = reading
        return memo[n]


@dataclass(frozen=True)
class PoseEstimate:
    """One estimate (SI: m, rad; pose coordinates as the mechanism's).

    :ivar pose: the estimated pose (dof,).
    :ivar covariance: its covariance (dof, dof), eq. 4.
    :ivar leg_lengths: ``L = q - F/k`` (n,), eq. 1.
    :ivar leg_sigma: standard deviation of each ``L_i`` (n,), eq. 3.
    :ivar residual: ``L - l(pose)`` (n,), m or rad (angles wrapped to (-pi, pi]).
    :ivar exact: the legs close within the measurement noise (every
        ``|residual_i| <= residual_sigmas * leg_sigma_i``); ``False``: a least-squares pose.
    :ivar condition: ``cond(J)`` at the pose (2-norm; ``inf`` at a singularity).
    :ivar iterations: solver steps this update took (0: the last estimate still fits).
    :ivar step_limited: a step was cut to ``max_step`` (the lengths pointed farther than one
        step from the previous estimate: another assembly mode, or a jump in the readings).
    :ivar converged: the last step was below the tolerance (``False``: ``max_iterations`` ran
        out; the next update continues from here).
    :ivar slack: names of cables read as slack (no tension), not weighed.
    :ivar reacquired: the solver had settled on a least-squares minimum although the lengths
        close elsewhere, or its step-limited iterations ran out before reaching them; the
        estimate took the assembly ``forward_nearest`` found nearest the last exact one.
    """

    pose: np.ndarray
    covariance: np.ndarray
    leg_lengths: np.ndarray
    leg_sigma: np.ndarray
    residual: np.ndarray
    exact: bool
    condition: float
    iterations: int
    step_limited: bool
    converged: bool
    slack: tuple[str, ...] = ()
    reacquired: bool = False

    @property
    def residual_max(self) -> float:
        """``max |residual_i|`` (m or rad)."""
        return float(np.abs(self.residual).max())

    @property
    def residual_sigmas(self) -> float:
        """``max |residual_i| / leg_sigma_i``: the residual in units of the length noise."""
        return float((np.abs(self.residual) / self.leg_sigma).max())


def stroke_free(mechanism: Mechanism, margin: Sequence[float] | float) -> Mechanism:
    """A copy of ``mechanism`` whose actuator range is widened by ``margin`` on each side.

    The estimator evaluates the geometry of legs that may be slightly outside their stroke
    (a loaded leg, ``L = q - F/k``; an iterate); ``inverse`` would raise
    :class:`~.base.UnreachablePose` there. The models keep their range in ``_lo``/``_hi``
    (:class:`~.base.MechanismBase`); a mechanism without them is returned unchanged (its
    stroke stays checked). The original is not modified.
    """
    if not (hasattr(mechanism, '_lo') and hasattr(mechanism, '_hi')):
        return mechanism
    lo, hi = (np.asarray(v, dtype=float) for v in mechanism.actuator_limits)
    m = as_per_actuator(margin, lo.size, 'stroke_margin', unit='m or rad')
    wide = copy.copy(mechanism)
    if np.ndim(getattr(mechanism, '_lo')) == 0:       # a one-actuator model keeps floats
        wide._lo, wide._hi = float(lo[0] - m[0]), float(hi[0] + m[0])  # type: ignore[attr-defined]
    else:
        wide._lo, wide._hi = lo - m, hi + m            # type: ignore[attr-defined]
    return wide


def weighted_covariance(jacobian: np.ndarray, variance: np.ndarray) -> np.ndarray:
    """Eq. 4: ``Sigma_p = J_w^+ J_w^+T``, ``J_w = diag(variance)^-1/2 J``.

    Through the SVD ``J_w = U S V^T``: ``Sigma_p = V_r S^-2 V_r^T`` over the ``min(n, dof)``
    singular directions (an under-actuated device's pose moves only along them); a
    singular value below ``1e-15`` of the largest counts as that (huge variance, not zero).
    Symmetric positive semi-definite by construction.
    """
    jw = np.asarray(jacobian, dtype=float) / np.sqrt(np.asarray(variance, dtype=float))[:, None]
    _, s, vt = np.linalg.svd(jw, full_matrices=False)
    s = np.maximum(s, _SINGULAR_FLOOR * max(float(s[0]), 1e-300))
    v = vt.T / s
    cov = v @ v.T
    return 0.5 * (cov + cov.T)


class PoseEstimator:
    """Load-aware forward kinematics with a covariance, continuous with its last estimate.

    :param mechanism: the device's model (the protocol).
    :param model: the measurement model (stiffness, resolutions, noise).
    :param rotary: actuator coordinates are angles (residuals wrapped to (-pi, pi]).
    :param max_step: trust radius (pose norm, m and rad as the pose's coordinates): no
        solver step is longer; longer Gauss-Newton steps are damped (Levenberg-Marquardt).
    :param max_iterations: solver iterations per update (one or two when the lengths
        changed little; the next update continues where this one stopped).
    :param residual_sigmas: the estimate is *exact* when every ``|residual_i|`` is within
        this many ``sigma_i``.
    :param stroke_margin: widening of the actuator range for the geometry (m or rad, a
        scalar or per actuator); default 10 % of each range (see :func:`stroke_free`).
    :param tolerance: a Gauss-Newton step whose predicted decrease of the weighted cost (in
        units of ``sigma^2``) is below this ends the iterations.
    :param jacobian_step: ``J`` is evaluated again after an accepted step longer than this
        (pose norm); shorter steps keep it.
    :param fast_geometry: evaluate a planar RPR's lengths, ``J`` and wrench in plain floats
        (:class:`~.planar_floats.PlanarRprFloats`, checked against the model at start-up; the
        model decides every pose outside its reach); ``False``: always the model's own
        ``inverse`` / ``jacobian`` / ``wrench`` (numpy). The two agree to rounding.
    :raises ValueError: a parameter out of range, or a model that does not fit the mechanism.
    """

    def __init__(self, mechanism: Mechanism, model: MeasurementModel, *, rotary: bool = False,
                 max_step: float = 0.02, max_iterations: int = 8, residual_sigmas: float = 3.0,
                 stroke_margin: Sequence[float] | float | None = None,
                 tolerance: float = 1e-9, jacobian_step: float = 1e-5,
                 fast_geometry: bool = True) -> None:
        self.mechanism = mechanism
        self.model = model
        self.rotary = bool(rotary)
        self.max_step = as_positive(max_step, 'max_step', unit='m or rad')
        if int(max_iterations) != max_iterations or max_iterations < 1:
            raise ValueError(f'max_iterations: expected an integer >= 1, got {max_iterations!r}')
        self.max_iterations = int(max_iterations)
        self.residual_sigmas = as_positive(residual_sigmas, 'residual_sigmas')
        self.tolerance = as_positive(tolerance, 'tolerance')
        self.jacobian_step = as_positive(jacobian_step, 'jacobian_step', allow_zero=True)
        self.n = int(mechanism.n_actuators)
        self.dof = int(mechanism.dof)
        self.names = tuple(mechanism.actuator_names)
        model.arrays(self.n)                           # per-actuator lists must fit
        lo, hi = (np.asarray(v, dtype=float) for v in mechanism.actuator_limits)
        self._span = hi - lo
        margin = 0.1 * self._span if stroke_margin is None else stroke_margin
        #: the mechanism with its range widened: the geometry of loaded legs and iterates
        self.geometry: Mechanism = stroke_free(mechanism, margin)
        #: the geometry in plain floats (a planar RPR), ``None``: the model's methods
        self._floats: PlanarRprFloats | None = None
        self._reach: tuple[list[float], list[float]] = ([], [])
        if fast_geometry and not self.rotary:
            self._floats = self._float_geometry()
        self._cable = getattr(mechanism, 'actuation', None) == 'cable'
        self._square_or_redundant = self.n >= self.dof
        self._pose: np.ndarray | None = None
        self._lambda = 0.0
        #: ``(pose, l(pose), J)`` of the last estimate (``J`` within ``jacobian_step`` of it)
        self._cache: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        #: the last estimate whose lengths closed
        self._last_exact: np.ndarray | None = None
        #: ``(s, V^T)`` of ``J_w`` at the last estimate, when the solver has it
        self._svd: tuple[np.ndarray, np.ndarray] | None = None
        #: the last estimate (``None`` before the first update)
        self.last: PoseEstimate | None = None
        #: ``cond(J)`` of the Jacobian object it was computed for (the solver keeps ``J``
        #: between updates unless the pose moved more than ``jacobian_step``)
        self._cond_of: np.ndarray | None = None
        self._cond = math.inf

    # ------------------------------------------------------------------ state
    @property
    def pose(self) -> np.ndarray | None:
        """The last estimated pose (``None`` before the first update or after :meth:`reset`)."""
        return None if self._pose is None else self._pose.copy()

    def reset(self, pose: Sequence[float] | None = None) -> None:
        """Forget the track. The next update starts from ``pose`` (validated), or else from
        ``forward_nearest(L, home_pose)`` (the home pose when that has no solution)."""
        self._pose = None if pose is None else as_vector(pose, self.dof, 'pose').copy()
        self._lambda = 0.0
        self._cache = None
        self._last_exact = None
        self.last = None

    # ------------------------------------------------------------------ update
    def update(self, q: Sequence[float], forces: Sequence[float] | None = None) -> PoseEstimate:
        """The pose for encoder positions ``q`` (m or rad) and efforts ``forces`` (N or N·m,
        along ``+q``; ``None``: no force reading), continuous with the last estimate.

        :raises ValueError: malformed ``q`` or ``forces`` (wrong length, non-finite).
        """
        qv = as_vector(q, self.n, 'q')
        fv = None if forces is None else as_vector(forces, self.n, 'forces')
        legs = self.model.leg_lengths(qv, fv)
        var = self.model.leg_variance(fv, self.n)
        slack: tuple[str, ...] = ()
        if self._cable and fv is not None:
            # a cable with no measurable tension may be slack: L <= q only (no weight)
            sigma_f = math.sqrt(self.model.force_variance)
            loose = fv > -3.0 * sigma_f
            if np.any(loose):
                var = np.where(loose, np.maximum(var, self._span ** 2), var)
                slack = tuple(n for n, s in zip(self.names, loose) if s)
        start = self._pose if self._pose is not None else self._first_guess(legs)
        sigma = np.sqrt(var)
        reacquired = False
        if self._square_or_redundant:
            pose, jac, resid, its, limited, converged = self._least_squares(legs, var, start)
            closes = self._closes(resid, sigma)
            moved = pose - start
            settled = math.sqrt(float(moved @ moved)) < self.max_step       # |pose - start|
            # leaving a least-squares episode: it sat where two assembly modes meet (e.g. the
            # lumbar brace's theta = 0), both now next to it; the mode of the last exact
            # estimate is kept
            leaving = closes and self.last is not None and not self.last.exact
            # fallen behind: the iterations ran out on steps cut to max_step (a jump in the
            # readings longer than they follow; the iterate is somewhere on the way)
            behind = limited and not converged
            if (settled and not closes) or behind or (leaving and self._last_exact is not None):
                hint = self._last_exact if self._last_exact is not None else pose
                found = self._reacquire(legs, sigma, hint, near=pose if leaving else None)
                if found is not None:
                    pose, jac, resid = found
                    reacquired = not leaving
                    self._cache = self._svd = None
        else:
            self._svd = None
            pose, jac, resid, its, limited, converged = self._along_path(legs, start)
        if self._svd is not None:
            sv, vt = self._svd
            v = vt.T / sv
            cov = v @ v.T
            cov = 0.5 * (cov + cov.T)
        else:
            cov = weighted_covariance(jac, var)
        if jac is not self._cond_of:                   # J not re-evaluated: the same cond(J)
            sv = np.linalg.svd(jac, compute_uv=False)
            self._cond_of, self._cond = jac, float(sv[0] / sv[-1]) if sv[-1] > 0.0 else math.inf
        cond = self._cond
        self._pose = pose
        exact = self._closes(resid, sigma)
        if exact:
            self._last_exact = pose.copy()
        self.last = PoseEstimate(pose.copy(), cov, legs, sigma, resid, exact,
                                 cond, its, limited, converged, slack, reacquired)
        return self.last

    def wrench(self, pose: Sequence[float], forces: Sequence[float]) -> np.ndarray:
        """The mechanism's ``wrench(pose, forces)`` on the stroke-free geometry (a loaded
        pose may be just outside the stroke); ``J^T f`` in plain floats for a planar RPR
        (``fast_geometry``)."""
        floats = self._floats
        if (floats is not None and isinstance(pose, np.ndarray) and isinstance(forces, np.ndarray)
                and pose.shape == (3,) and forces.shape == (self.n,)
                and pose.dtype == np.float64 and forces.dtype == np.float64):
            rows = self._float_rows(pose)
            if rows is not None and np.isfinite(forces).all():
                return np.array(floats.wrench(rows, forces.tolist()))
        return np.asarray(self.geometry.wrench(pose, forces), dtype=float)

    # ------------------------------------------------------------------ internals
    def _first_guess(self, legs: np.ndarray) -> np.ndarray:
        home = np.asarray(self.mechanism.home_pose, dtype=float)
        try:
            return np.asarray(self.geometry.forward_nearest(legs, home), dtype=float)
        except ValueError:
            return home

    def _closes(self, resid: np.ndarray, sigma: np.ndarray) -> bool:
        return bool((np.abs(resid) <= self.residual_sigmas * sigma).all())

    def _reacquire(self, legs: np.ndarray, sigma: np.ndarray, hint: np.ndarray,
                   near: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The assembly nearest ``hint`` when the lengths close there and (with ``near``) it
        lies within ``max_step`` of ``near``; ``None`` otherwise."""
        try:
            found = np.asarray(self.geometry.forward_nearest(legs, hint), dtype=float)
            lengths, jac = self._evaluate(found)
        except ValueError:                              # no assembly: the least squares stands
            return None
        if near is not None and float(np.linalg.norm(found - near)) > self.max_step:
            return None
        resid = self._difference(legs, lengths)
        return (found, jac, resid) if self._closes(resid, sigma) else None

    def _difference(self, legs: np.ndarray, lengths: np.ndarray) -> np.ndarray:
        d = legs - lengths
        if self.rotary:
            d = (d + math.pi) % _TWO_PI - math.pi
        return d

    def _evaluate(self, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self._inverse(pose), self._jacobian(pose)

    # -- the geometry: the model's methods, or the same in plain floats (a planar RPR)
    def _float_geometry(self) -> PlanarRprFloats | None:
        """:meth:`PlanarRprFloats.of <.planar_floats.PlanarRprFloats.of>` the geometry (a
        planar RPR that agrees with its model), and the reach its float lengths are checked
        against: the stroke with the tolerance of :func:`~.base.check_limits`."""
        floats = PlanarRprFloats.of(self.geometry)
        if floats is None:
            return None
        lo, hi = (np.asarray(v, dtype=float) for v in self.geometry.actuator_limits)
        self._reach = ((lo - _REACH_TOL).tolist(), (hi + _REACH_TOL).tolist())
        return floats

    def _float_pose(self, pose: np.ndarray) -> tuple[float, float, float] | None:
        """``(x, y, theta)`` of a finite planar pose array, else ``None`` (the model decides)."""
        if isinstance(pose, np.ndarray) and pose.shape == (3,):
            x, y, th = pose.tolist()
            if math.isfinite(x) and math.isfinite(y) and math.isfinite(th):
                return x, y, th
        return None

    def _float_rows(self, pose: np.ndarray) -> list[tuple[float, float, float]] | None:
        """The rows of ``J`` in floats; ``None`` where the model must decide (a leg of
        zero length: it raises)."""
        xyt = self._float_pose(pose)
        if xyt is None:
            return None
        try:
            lengths, rows = self._floats.lengths_and_rows(*xyt)   # type: ignore[union-attr]
        except ZeroDivisionError:
            return None
        return rows if min(lengths) > _ZERO_LEG else None

    def _inverse(self, pose: np.ndarray) -> np.ndarray:
        """``geometry.inverse(pose)``: in floats when they serve and every length is within
        reach; otherwise (and so for every pose it rejects) the model."""
        floats = self._floats
        if floats is not None:
            xyt = self._float_pose(pose)
            if xyt is not None:
                lengths = floats.lengths(*xyt)
                lo, hi = self._reach
                if all(a <= v <= b for v, a, b in zip(lengths, lo, hi)):
                    return np.array(lengths)
        return np.asarray(self.geometry.inverse(pose), dtype=float)

    def _jacobian(self, pose: np.ndarray) -> np.ndarray:
        """``geometry.jacobian(pose)``, in floats when they serve."""
        if self._floats is not None:
            rows = self._float_rows(pose)
            if rows is not None:
                return np.array(rows)
        return np.asarray(self.geometry.jacobian(pose), dtype=float)

    def _least_squares(self, legs: np.ndarray, var: np.ndarray, start: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, bool, bool]:
        """Eq. 2 by Levenberg-Marquardt from ``start``, every step within ``max_step``.

        Each iteration first takes the Gauss-Newton step ``J_w^+ r_w`` (through the SVD of
        ``J_w``); its predicted decrease of the cost below :attr:`tolerance` ends the
        iterations (converged). A step that does not lower the cost is first bent by the
        geodesic acceleration (Transtrum & Sethna, "Improvements to the Levenberg-Marquardt
        algorithm for nonlinear least-squares minimization", 2012: ``dp + a / 2``, ``a``
        from the residual's second derivative along ``dp``, taken from that very trial;
        kept when ``|a| <= 0.75 |dp|``): near a singular pose the cost's valley is an arc
        (the lumbar brace: a rotation about the leg lines' meeting point 3.9 m away) and
        straight steps fall off it. A step longer than ``max_step``, one that leaves the
        geometry's reach, or one that still does not lower the cost is damped (Marquardt:
        ``(A + lambda diag A) dp = g``) until one is accepted; none within 30 dampings: a
        (least-squares) minimum, stop.

        Cost: the lengths ``l(p)`` and ``J(p)`` of the last estimate are kept from the last
        update, so a joint state costs one inverse kinematics per accepted step, and a
        Jacobian only after a step longer than :attr:`jacobian_step` (a slightly stale ``J``
        only slows the convergence; the residual is always exact). Returns the number of
        accepted steps.
        """
        inv_sigma = 1.0 / np.sqrt(var)
        cache = self._cache
        if cache is not None and (cache[0] is start or np.array_equal(cache[0], start)):
            p, lengths, jac = cache
        else:
            p = np.asarray(start, dtype=float).copy()
            try:
                lengths, jac = self._evaluate(p)
            except ValueError:
                p = self._first_guess(legs)
                lengths, jac = self._evaluate(p)
        resid = self._difference(legs, lengths)
        rw = resid * inv_sigma
        cost = float(rw @ rw)
        lam = self._lambda
        limited = converged = False
        steps = 0

        def trial_at(dp: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, float] | None:
            try:
                t_lengths = self._inverse(p + dp)
            except ValueError:                        # beyond the reach, even widened
                return None
            t_resid = self._difference(legs, t_lengths)
            t_rw = t_resid * inv_sigma
            return t_lengths, t_resid, t_rw, float(t_rw @ t_rw)

        svd_of = None                                  # the J whose SVD (of J_w) is at hand
        for _ in range(self.max_iterations):
            if svd_of is not jac:
                jw = jac * inv_sigma[:, None]
                u, sv, vt = np.linalg.svd(jw, full_matrices=False)
                sv = np.maximum(sv, _SINGULAR_FLOOR * max(float(sv[0]), 1e-300))
                svd_of = jac
            ur = u.T @ rw
            gauss_newton = vt.T @ (ur / sv)
            if float(ur @ ur) <= self.tolerance:      # the decrease a Gauss-Newton step promises
                converged = True
                break
            a = g = scale = None
            accepted = bent = False
            for _ in range(30):                       # damping until a step is accepted
                if lam == 0.0:
                    dp = gauss_newton
                else:
                    if a is None:
                        a, g = jw.T @ jw, jw.T @ rw
                        d = np.diag(a)
                        scale = np.diag(np.maximum(d, 1e-12 * max(float(d.max()), 1e-300)))
                    dp = np.linalg.solve(a + lam * scale, g)
                size = math.sqrt(float(dp @ dp))
                if not math.isfinite(size) or size > self.max_step:
                    limited = limited or math.isfinite(size)
                    lam = max(lam * 10.0, 1e-6)
                    continue
                predicted = cost - float(((rw - jw @ dp) ** 2).sum())
                if predicted <= self.tolerance:
                    break                               # damped to nothing: no descent left
                trial = trial_at(dp)
                if trial is not None and trial[3] >= cost and not bent:
                    # the residual curves away from its linear model over dp (near a singular
                    # pose the valley of the cost is an arc): geodesic acceleration, the second
                    # derivative along dp from this trial, r'' = 2 (r(p) - r(p + dp) - J_w dp)
                    bent = True
                    curve = 2.0 * (rw - trial[2] - jw @ dp)
                    accel = -(vt.T @ ((u.T @ curve) / sv) if lam == 0.0
                              else np.linalg.solve(a + lam * scale, jw.T @ curve))
                    bent_dp = dp + 0.5 * accel
                    if (math.sqrt(float(accel @ accel)) <= 0.75 * size
                            and math.sqrt(float(bent_dp @ bent_dp)) <= self.max_step):
                        bent_trial = trial_at(bent_dp)
                        if bent_trial is not None and bent_trial[3] < cost:
                            dp, trial = bent_dp, bent_trial
                            size = math.sqrt(float(dp @ dp))
                if trial is not None and trial[3] < cost:
                    if size > self.jacobian_step:
                        try:
                            jac = self._jacobian(p + dp)
                        except ValueError:
                            lam = max(lam * 10.0, 1e-6)
                            continue
                    p = p + dp
                    lengths, resid, rw, cost = trial
                    lam = 0.0 if lam <= 1e-6 else lam / 10.0
                    accepted = True
                    steps += 1
                    break
                lam = max(lam * 10.0, 1e-6)
            if not accepted:
                break
        self._lambda = lam
        self._cache = (p, lengths, jac)
        # eq. 4 from the SVD at hand when it is of the final J
        self._svd = (sv, vt) if svd_of is jac else None
        return p, jac, resid, steps, limited, converged

    def _along_path(self, legs: np.ndarray, start: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, bool, bool]:
        """Under-actuated (fewer actuators than pose coordinates): the pose is a function of
        the lengths, ``forward_nearest(L, previous)`` (the branch the device is on); no
        solution keeps the previous pose (its residual says by how much)."""
        try:
            pose = np.asarray(self.geometry.forward_nearest(legs, start), dtype=float)
        except ValueError:
            pose = np.asarray(start, dtype=float).copy()
        lengths, jac = self._evaluate(pose)
        return pose, jac, self._difference(legs, lengths), 1, False, True
