"""Force-transmission capacity: the largest wrench per axis that bounded actuator efforts hold.

Statics of every mechanism, in its own ``wrench`` convention (see each module)::

    W = G (f - b)

``G`` (m, n) maps the ``n`` actuator efforts ``f`` (N or N·m) to the ``m`` wrench components
of the capacity axes (planar: ``Fx, Fy, Mz``; the shoulder: its three moments; a 2-DOF
point: ``Fx, Fy``; the four-bar: the force along its path); ``b`` (n,) are the efforts
that hold the mechanism with no external load (zero for rigid links, the bent bars'
push for the continuum robot). Each effort is bounded, ``lo_i <= f_i <= hi_i``: a rod, a
linear or a rotary actuator ``[-limit_i, limit_i]``, a cable (pull only, thrust
``f = -tension``) ``[-limit_i, 0]``.

The capacity along axis ``a`` is the largest ``w >= 0`` such that every wrench
``s e_a`` with ``-w <= s <= w`` (other components zero) is balanced by efforts within the
bounds. The set of balanced wrenches is convex, so that is: zero load, ``+w e_a`` and
``-w e_a`` are all feasible. If even zero load is not (``b`` outside the bounds), the
capacity is 0. Efforts are shifted once, ``c = f - b`` in ``[lo - b, hi - b]``, so below
the box is ``lo_c <= c <= hi_c`` and ``W = G c``.

Three exact methods, chosen by the caller (:class:`~.base.MechanismBase`):

* square and regular (``H = G^-1`` exists): ``c = H W``, so along axis ``a``
  ``c_i = s H_ia`` and ``w_a = min_i margin_i / |H_ia|`` with ``margin_i = min(hi_c_i,
  -lo_c_i)`` (:func:`capacity_closed_form`, vectorised); the limiting actuator is the
  argmin.
* one degree of redundancy (``n = m + 1``, ``G`` of full rank): ``c = s p + lambda n``
  (``p = pinv(G) e_a``, ``n`` the unit null vector) — a two-variable linear programme in
  ``(s, lambda)`` solved exactly by its vertices (:func:`capacity_one_redundancy`,
  vectorised).
* anything else — more redundancy, or a rank-deficient ``G`` (a singular pose):
  :func:`capacity_lp`, one small LP per axis and direction (``scipy.optimize.linprog``,
  HiGHS) on the rank-reduced equalities ``U_r^T G c = s U_r^T e_a``. An axis with a
  component outside the range of ``G`` (the unsupported direction at a singularity)
  has capacity 0, with no limiting actuator.

Limiting actuator: the one whose limit has the largest shadow price — raising it would
raise the capacity most (LP duality; in the closed form the argmin, in the vertex method
the bound of the two active ones with the larger sensitivity). ``-1`` when no actuator
limit binds: an unsupported direction, an unbounded capacity, or a zero load that
cannot be held without an actuator outside its bounds (then the first such actuator is
named instead).
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ['RANK_RTOL', 'regular_inverse', 'unsupported_axes', 'capacity_closed_form', 'capacity_one_redundancy',
           'capacity_lp']

#: singular values below this times the largest count as zero: the pose is singular
RANK_RTOL = 1e-10
#: a component of a capacity axis outside the range of G above this (unit vector): unsupported
_UNSUPPORTED_TOL = 1e-9


def regular_inverse(g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``G^-1`` of a stack of square matrices (K, n, n) and the mask of regular ones.

    Regular: the smallest singular value above :data:`RANK_RTOL` times the largest (and
    every entry finite). The inverse of a non-regular matrix is NaN.
    """
    g = np.asarray(g, dtype=float)
    out = np.full(g.shape, np.nan)
    finite = np.isfinite(g).all(axis=(-2, -1))
    ok = finite.copy()
    if finite.any():
        sv = np.linalg.svd(g[finite], compute_uv=False)
        ok[finite] = sv[:, -1] > RANK_RTOL * sv[:, 0]
    if ok.any():
        out[ok] = np.linalg.inv(g[ok])
    return out, ok


def unsupported_axes(g: np.ndarray) -> np.ndarray:
    """Mask (K, m): capacity axis ``a`` has a component outside the range of ``G`` (K, m, n)
    (rank counted with :data:`RANK_RTOL`): no efforts balance a wrench along it (capacity 0)."""
    u, s, _ = np.linalg.svd(g, full_matrices=True)
    m = g.shape[-2]
    rank = np.sum(s > RANK_RTOL * s[:, :1], axis=-1) if s.shape[-1] else np.zeros(g.shape[0], dtype=int)
    outside = np.arange(m)[None, :] >= rank[:, None]                    # (K, m) columns of U beyond the rank
    return np.sqrt(np.sum((u * outside[:, None, :]) ** 2, axis=-1)) > _UNSUPPORTED_TOL


def _zero_load_culprit(lo_c: np.ndarray, hi_c: np.ndarray) -> np.ndarray:
    """Index of the first actuator whose unloaded effort is outside its bounds, else -1 (K,)."""
    bad = (lo_c > 0.0) | (hi_c < 0.0)
    return np.where(bad.any(axis=-1), np.argmax(bad, axis=-1), -1)


def capacity_closed_form(h: np.ndarray, lo_c: np.ndarray, hi_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Square, regular statics: ``c = H W``.

    :param h: effort per unit wrench ``H = G^-1``, (K, n, m).
    :param lo_c, hi_c: shifted effort bounds ``lo - b``, ``hi - b`` (K, n).
    :returns: ``(capacity (K, m), limiting (K, m) int)``: ``capacity_a = min_i margin_i /
        |H_ia|``, ``margin_i = min(hi_c_i, -lo_c_i)`` (0 when negative: zero load not held).
    """
    margin = np.minimum(hi_c, -lo_c)[:, :, None]                        # (K, n, 1)
    ah = np.abs(h)
    with np.errstate(divide='ignore', invalid='ignore'):
        ratio = np.where(ah > 0.0, margin / ah, np.inf)
    ratio = np.where(margin < 0.0, 0.0, ratio)
    which = np.argmin(ratio, axis=1)                                    # (K, m)
    cap = np.take_along_axis(ratio, which[:, None, :], axis=1)[:, 0, :]
    which = np.where(np.isinf(cap), -1, which)
    return cap, which


def capacity_one_redundancy(g: np.ndarray, lo_c: np.ndarray, hi_c: np.ndarray
                            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One degree of redundancy (``n = m + 1``), vectorised and exact.

    Along ``s e_a`` the efforts are ``c = s p + lambda n`` (``p = pinv(G) e_a``, ``n`` the
    unit null vector of ``G``). Each actuator with ``n_i != 0`` bounds ``lambda`` between two
    lines in ``s``: ``lower_i(s) = alpha_i - r_i s`` and ``upper_i(s) = gamma_i - r_i s``
    (``r_i = p_i / n_i``; ``alpha, gamma`` its bounds over ``n_i``, ordered). A ``lambda``
    exists iff ``lower_j(s) <= upper_k(s)`` for every pair ``(j, k)``, i.e.
    ``(r_k - r_j) s <= gamma_k - alpha_j``; an actuator with ``n_i = 0`` bounds ``s p_i``
    directly. With zero load feasible the feasible ``s >= 0`` are ``[0, s_max]``,
    ``s_max`` the smallest of those bounds: the LP optimum, by its vertices.

    :param g: wrench maps (K, m, m + 1).
    :param lo_c, hi_c: shifted effort bounds (K, m + 1).
    :returns: ``(capacity (K, m), limiting (K, m), ok (K,))``; rows that are not ``ok``
        (rank below ``m``) are NaN / -1 and need :func:`capacity_lp`.
    """
    k_rows, m, n = g.shape
    cap = np.full((k_rows, m), np.nan)
    which = np.full((k_rows, m), -1, dtype=int)
    finite = np.isfinite(g).all(axis=(1, 2))
    ok = finite.copy()
    if not finite.any():
        return cap, which, ok
    u, s, vt = np.linalg.svd(g[finite], full_matrices=True)             # vt (K', n, n)
    ok[finite] = s[:, -1] > RANK_RTOL * s[:, 0]
    sel = ok[finite]
    if not sel.any():
        return cap, which, ok
    u, s, vt = u[sel], s[sel], vt[sel]
    lo, hi = lo_c[ok], hi_c[ok]
    null = vt[:, -1, :]                                                 # (K, n), unit
    # pinv(G) = V_m diag(1/s) U^T: column a is p for axis a -> p[k, a, i]
    p = np.einsum('kji,kj,kaj->kai', vt[:, :m, :], 1.0 / s, u)
    out_cap = np.full((lo.shape[0], m), np.inf)
    out_which = np.full((lo.shape[0], m), -1, dtype=int)
    pinned = np.abs(null) <= 1e-12                                      # (K, n)
    nz = np.where(pinned, 1.0, null)
    pos = null > 0.0
    alpha = np.where(pos, lo, hi) / nz                                  # lambda lower-bound constant
    gamma = np.where(pos, hi, lo) / nz                                  # lambda upper-bound constant
    big = np.abs(np.where(np.isfinite(lo), lo, 0.0)) + np.abs(np.where(np.isfinite(hi), hi, 0.0))
    scale = 1.0 + np.max(big / np.abs(nz), axis=1)                      # (K,)
    # zero load: max_j alpha_j <= min_k gamma_k over the free actuators, pinned ones hold 0
    a_free = np.where(pinned, -np.inf, alpha)
    g_free = np.where(pinned, np.inf, gamma)
    zero_ok = (np.max(a_free, axis=1) <= np.min(g_free, axis=1) + 1e-12 * scale)
    zero_ok &= ~np.any(pinned & ((lo > 0.0) | (hi < 0.0)), axis=1)
    num = g_free[:, None, :] - a_free[:, :, None]                        # [k, j, k'] gamma_k' - alpha_j
    for direction in (1.0, -1.0):
        q = direction * p                                               # (K, m, n)
        r = q / nz[:, None, :]
        den = r[:, :, None, :] - r[:, :, :, None]                      # [k, a, j, k'] r_k' - r_j
        tiny = 1e-12 * (np.abs(r[:, :, None, :]) + np.abs(r[:, :, :, None]))
        free_pair = ~pinned[:, None, :, None] & ~pinned[:, None, None, :]
        use = free_pair & (den > tiny)
        with np.errstate(divide='ignore', invalid='ignore'):
            cand = np.where(use, np.maximum(num[:, None], 0.0) / den, np.inf)
        flat = cand.reshape(cand.shape[0], m, n * n)
        best = np.argmin(flat, axis=-1)
        s_pair = np.take_along_axis(flat, best[..., None], axis=-1)[..., 0]
        j_idx, k_idx = best // n, best % n
        nabs = np.abs(null)
        pick_j = np.take_along_axis(nabs[:, None, :].repeat(m, 1), j_idx[..., None], -1)[..., 0] <= \
            np.take_along_axis(nabs[:, None, :].repeat(m, 1), k_idx[..., None], -1)[..., 0]
        w_pair = np.where(pick_j, j_idx, k_idx)
        # pinned actuators: lo_i <= s q_i <= hi_i
        with np.errstate(divide='ignore', invalid='ignore'):
            cap_pin = np.where(q > 0.0, hi[:, None, :] / q, np.where(q < 0.0, lo[:, None, :] / q, np.inf))
        cap_pin = np.where(pinned[:, None, :], np.maximum(cap_pin, 0.0), np.inf)
        i_pin = np.argmin(cap_pin, axis=-1)
        s_pin = np.take_along_axis(cap_pin, i_pin[..., None], axis=-1)[..., 0]
        s_dir = np.minimum(s_pair, s_pin)
        w_dir = np.where(s_pin < s_pair, i_pin, w_pair)
        w_dir = np.where(np.isinf(s_dir), -1, w_dir)
        better = s_dir < out_cap
        out_cap = np.where(better, s_dir, out_cap)
        out_which = np.where(better, w_dir, out_which)
    culprit = _zero_load_culprit(lo, hi)
    out_cap = np.where(zero_ok[:, None], out_cap, 0.0)
    out_which = np.where(zero_ok[:, None], out_which, culprit[:, None])
    cap[ok] = out_cap
    which[ok] = out_which
    return cap, which, ok


def capacity_lp(g: np.ndarray, lo_c: np.ndarray, hi_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One pose, any shape and rank of ``G`` (m, n): one LP per axis and direction.

    ``maximise s`` subject to ``U_r^T G c = s U_r^T e_a`` and ``lo_c <= c <= hi_c``, ``s >= 0``
    (``U_r`` the left singular vectors of the ``r`` singular values above
    :data:`RANK_RTOL`: the equalities stay well conditioned at a singularity). An axis
    with a component outside the range of ``G`` has capacity 0 (limiting ``-1``).

    :returns: ``(capacity (m,), limiting (m,))``.
    :raises RuntimeError: the LP solver failed for a reason other than infeasible/unbounded.
    """
    from scipy.optimize import linprog
    g = np.asarray(g, dtype=float)
    m, n = g.shape
    cap = np.zeros(m)
    which = np.full(m, -1, dtype=int)
    u, s, _ = np.linalg.svd(g)
    rank = int(np.sum(s > RANK_RTOL * s[0])) if s.size and s[0] > 0.0 else 0
    ur = u[:, :rank]
    a_eq = ur.T @ g
    bounds = [(None if math.isinf(lo) else float(lo), None if math.isinf(hi) else float(hi))
              for lo, hi in zip(lo_c, hi_c)] + [(0.0, None)]
    cost = np.zeros(n + 1)
    cost[-1] = -1.0
    culprit = int(_zero_load_culprit(lo_c[None], hi_c[None])[0])
    for a in range(m):
        e = np.zeros(m)
        e[a] = 1.0
        if rank < m and float(np.linalg.norm(u[:, rank:].T @ e)) > _UNSUPPORTED_TOL:
            continue                                                    # unsupported: 0, no actuator
        best, best_which = math.inf, -1
        for direction in (1.0, -1.0):
            col = -direction * (ur.T @ e)
            res = linprog(cost, A_eq=np.column_stack([a_eq, col]), b_eq=np.zeros(rank), bounds=bounds,
                          method='highs')
            if res.status == 2:                                         # zero load infeasible
                value, lim = 0.0, culprit
            elif res.status == 3:                                       # unbounded
                value, lim = math.inf, -1
            elif res.status == 0:
                value = float(res.x[-1])
                price = np.abs(res.lower.marginals[:n]) + np.abs(res.upper.marginals[:n])
                lim = int(np.argmax(price)) if float(np.max(price)) > 0.0 else -1
            else:
                raise RuntimeError(f'wrench capacity LP failed: {res.message}')
            if value < best:
                best, best_which = value, lim
        cap[a], which[a] = best, best_which
    return cap, which
