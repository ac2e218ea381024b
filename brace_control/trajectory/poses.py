"""Arrival times of a ``nav_msgs/Path`` goal, validated (docs/safety.md §6).

The node reads the stamps (s) and poses (with :mod:`brace_control.nodes.msgs`); the
timing rules live here so they are testable without ROS.
"""
from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

__all__ = ['PoseError', 'arrival_times']


class PoseError(ValueError):
    """A path whose timing cannot be used; the message says what is wrong."""


def arrival_times(header_stamp: float, pose_stamps: Sequence[float]) -> tuple[
        float | None, np.ndarray | None]:
    """Path timing: ``(duration, t_via)`` from a ``nav_msgs/Path``'s stamps (s).

    Each pose's stamp is its arrival time; times count from the path's ``header.stamp``
    (``t_i = stamp_i - header.stamp``), so a client may send absolute times (header =
    now) or relative ones (header = 0). All pose stamps zero: the path carries no timing
    and ``(None, None)`` is returned (Fitts' law, optimal via times). Otherwise the times
    must be finite, > 0 and strictly increasing; the last is the duration, the others
    the via times.

    :raises PoseError: an empty path, stamps not after the header, or not increasing.
    """
    stamps = np.asarray(pose_stamps, dtype=float)
    if stamps.size == 0:
        raise PoseError('empty path: no poses')
    if not (math.isfinite(header_stamp) and np.all(np.isfinite(stamps))):
        raise PoseError('non-finite stamp in the path')
    if np.all(stamps == 0.0):
        return None, None
    t = stamps - float(header_stamp)
    if t[0] <= 0.0:
        raise PoseError(f'the first pose arrives {t[0]:.3f} s after the path header: '
                        'arrival times must be after header.stamp')
    if np.any(np.diff(t) <= 0.0):
        i = int(np.argmax(np.diff(t) <= 0.0))
        raise PoseError(f'non-increasing stamps: pose {i + 1} arrives at {t[i + 1]:.3f} s, '
                        f'not after pose {i} at {t[i]:.3f} s')
    return float(t[-1]), (t[:-1].copy() if t.size > 1 else None)
