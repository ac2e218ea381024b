"""Seed 001's planar 3-RPR, the lumbar brace, from its YAML's anchors alone: the tests'
independent oracle for leg lengths and statics (never the mechanism code under test).

Leg ``j`` runs from the base anchor ``A_j`` to the platform anchor ``B_j = p + R(theta) b_j``:
its length is ``|B_j - A_j|``; a leg force ``f_j`` along the unit vector ``u_j`` (from
``A_j`` to ``B_j``) puts the wrench ``(f_j u_j, f_j (R b_j) x u_j)`` on the platform
(moment about the platform origin ``p``).
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import yaml

LUMBAR_YAML = Path(__file__).resolve().parents[1] / 'config' / 'lumbar_brace.yaml'
_M = yaml.safe_load(LUMBAR_YAML.read_text())['/**']['ros__parameters']['mechanism']
#: base anchors A_j and platform anchors b_j (platform frame), m, one row per leg
A = np.reshape(np.asarray(_M['base_anchors'], float), (3, 2))
B = np.reshape(np.asarray(_M['platform_anchors'], float), (3, 2))


def leg_vectors(pose) -> tuple[np.ndarray, np.ndarray]:
    """``(B_j - A_j, R b_j)`` per leg (rows): the leg vectors and the platform anchors in
    world orientation, at ``pose`` (x, y m; theta rad)."""
    x, y, th = pose
    c, s = math.cos(th), math.sin(th)
    rb = B @ np.array([[c, s], [-s, c]])
    return np.array([x, y]) + rb - A, rb


def leg_lengths(pose) -> np.ndarray:
    """Leg lengths (m) at ``pose`` (x, y m; theta rad)."""
    return np.linalg.norm(leg_vectors(pose)[0], axis=1)


def leg_matrix(pose) -> np.ndarray:
    """``G`` (3x3): the platform wrench ``(Fx, Fy, Mz)`` of unit leg forces, one column per
    leg ``(u_j, (R b_j) x u_j)``; the wrench of leg forces ``f`` is ``G f``."""
    d, rb = leg_vectors(pose)
    u = d / np.linalg.norm(d, axis=1)[:, None]
    return np.vstack([u[:, 0], u[:, 1], rb[:, 0] * u[:, 1] - rb[:, 1] * u[:, 0]])
