"""Small helpers shared by the planar mechanism models (pure numpy).

* :func:`wrap_angle` — an angle wrapped to ``(-pi, pi]``;
* :func:`cross2` — the planar cross product ``u x v = u_x v_y - u_y v_x`` (scalar);
* :class:`RprLegs` — leg vectors and Jacobian of a planar n-RPR (``Rpr3``, ``Rpr4``);
* :func:`trig_poly_coefficients` / :func:`trig_poly_real_roots` — the real roots of a
  band-limited trigonometric polynomial ``g(theta) = sum_{k=-n..n} c_k e^{i k theta}``:
  ``g`` is sampled at ``2 n + 2`` equally spaced angles, its coefficients are read off
  with an FFT, and the roots of ``z^n g(z)`` on the unit circle ``|z| = 1`` are the real
  angles. With ``z = e^{i theta}`` no angle is special (a tan-half-angle substitution
  loses the root ``theta = pi`` when the degree drops; this does not).
"""
from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from .base import UnreachablePose, rot2

_TWO_PI = 2.0 * math.pi

__all__ = ['wrap_angle', 'cross2', 'trig_poly_coefficients', 'trig_poly_real_roots', 'RprLegs']


def wrap_angle(theta: float | np.ndarray) -> float | np.ndarray:
    """``theta`` wrapped to ``(-pi, pi]`` (rad)."""
    if isinstance(theta, (float, int)):
        t = float(theta)
        return t if -math.pi < t <= math.pi else math.pi - (math.pi - t) % _TWO_PI
    t = np.asarray(theta, dtype=float)
    wrapped = np.where((t > -np.pi) & (t <= np.pi), t, np.pi - np.mod(np.pi - t, 2.0 * np.pi))
    return float(wrapped) if np.ndim(wrapped) == 0 else wrapped


def cross2(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Planar cross product ``u x v`` over the last axis (shape ``(..., 2)`` -> ``(...)``)."""
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]


def trig_poly_coefficients(g: Callable[[np.ndarray], np.ndarray],
                           degree: int) -> tuple[np.ndarray, float]:
    """Coefficients ``c_{-n..n}`` (complex, length ``2 n + 1``) of a real trigonometric
    polynomial of degree ``n = degree``, from ``2 n + 2`` samples and an FFT.

    :param g: vectorised real function of ``theta`` (rad) known to be band-limited to
        ``degree`` harmonics.
    :param degree: ``n``.
    :returns: ``(c, aliasing)``: ``c[j]`` multiplies ``e^{i (j - n) theta}``; ``aliasing``
        is the magnitude of the Nyquist bin relative to ``max |c|`` (≈ 0 when ``g`` really
        is of that degree; a sanity measure, not used for the roots).
    """
    n_samples = 2 * degree + 2
    theta = 2.0 * np.pi * np.arange(n_samples) / n_samples
    spectrum = np.fft.fft(g(theta)) / n_samples
    c = np.concatenate([spectrum[n_samples - degree:], spectrum[:degree + 1]])
    scale = float(np.max(np.abs(c))) if c.size else 0.0
    aliasing = float(abs(spectrum[degree + 1])) / scale if scale > 0 else 0.0
    return c, aliasing


def trig_poly_real_roots(c: np.ndarray, *, unit_circle_tol: float = 2e-2,
                         trim_rel: float = 1e-11) -> np.ndarray:
    """Candidate real roots ``theta`` of ``sum_k c_k e^{i k theta}`` (``c`` from
    :func:`trig_poly_coefficients`).

    The roots of the polynomial ``z^n g(z)`` within ``unit_circle_tol`` of ``|z| = 1`` are
    returned as angles. Double (tangent) roots split into a pair near the circle and are
    both returned: callers polish and verify every candidate and drop duplicates. Leading
    (and, by the symmetry ``c_{-k} = conj(c_k)``, trailing) coefficients below
    ``trim_rel * max |c|`` are dropped first (the degree drops; no root is lost).

    :returns: angles (rad) in ``(-pi, pi]``; empty when ``c`` vanishes identically
        (callers check that case before, it means infinitely many roots).
    """
    c = np.asarray(c, dtype=complex)
    scale = float(np.max(np.abs(c))) if c.size else 0.0
    if scale == 0.0:
        return np.empty(0)
    lo, hi = 0, c.size - 1
    while hi > lo and abs(c[hi]) <= trim_rel * scale and abs(c[lo]) <= trim_rel * scale:
        lo += 1
        hi -= 1
    trimmed = c[lo:hi + 1]
    if trimmed.size <= 1:
        return np.empty(0)
    z = np.roots(trimmed[::-1])      # highest power first
    z = z[np.abs(np.abs(z) - 1.0) <= unit_circle_tol]
    return np.angle(z)


class RprLegs:
    """Mixin for a planar n-RPR (prismatic legs ``A_i -> B_i``, ``B_i = P + R(theta) b_i``).

    Uses the subclass's ``base_anchors``, ``platform_anchors`` ((n, 2), m),
    ``actuator_names`` and ``_lo``, ``_hi`` (stroke, for the error's limits).
    """

    base_anchors: np.ndarray
    platform_anchors: np.ndarray
    actuator_names: tuple[str, ...]
    _lo: np.ndarray
    _hi: np.ndarray

    def _check_legs(self, why: str = '') -> None:
        """Reject two legs with the same base and platform anchors (``why`` ends the message);
        set ``_platform_size`` (weighs the angle against position when comparing poses) and
        ``_length_scale`` (m)."""
        a, b = self.base_anchors, self.platform_anchors
        names = self.actuator_names
        for i in range(len(a)):
            for j in range(i + 1, len(a)):
                if np.allclose(a[i], a[j], atol=1e-12) and np.allclose(b[i], b[j], atol=1e-12):
                    raise ValueError(f'legs {names[i]} and {names[j]} are the same leg '
                                     f'(same base and platform anchors){why}')
        self._platform_size = max(float(np.max(np.linalg.norm(b - b.mean(axis=0), axis=1))), 1e-3)
        self._length_scale = max(float(np.max(np.ptp(a, axis=0))), float(np.max(np.ptp(b, axis=0))), 1e-3)

    def _legs(self, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Leg vectors ``B_i - A_i`` (n, 2) and ``rho_i = R b_i`` (n, 2) of a validated pose."""
        rho = self.platform_anchors @ rot2(pose[2]).T
        return pose[:2] + rho - self.base_anchors, rho

    def _leg_jacobian(self, p: np.ndarray) -> np.ndarray:
        """``J`` (n, 3), row ``(u_i, rho_i x u_i)``, of a validated pose ``p``.

        :raises UnreachablePose: a leg of zero length (its direction is undefined).
        """
        d, rho = self._legs(p)
        n = np.linalg.norm(d, axis=1)
        if np.any(n <= 1e-12):
            i = int(np.argmin(n))
            raise UnreachablePose(f'actuator {self.actuator_names[i]} has zero length at pose {p.tolist()}: '
                                  'its direction is undefined', actuator=self.actuator_names[i],
                                  value=float(n[i]), limits=(float(self._lo[i]), float(self._hi[i])))
        u = d / n[:, None]
        return np.column_stack([u, cross2(rho, u)])
