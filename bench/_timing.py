"""Timing helpers shared by the mechanism benchmarks (bench_kinematics.py, bench_spherical.py).

Imported as ``from _timing import ...``: a script's own folder is first on ``sys.path``.
"""
from __future__ import annotations

import os
import platform
import statistics
import time
from collections.abc import Callable, Iterable, Sequence
from typing import Any

import numpy as np

__all__ = ['machine_line', 'per_call_us', 'repeat_seconds', 'summary_us']


def machine_line() -> str:
    """Python and numpy versions, machine, cpu count and load: the first line of every report."""
    return (f'python {platform.python_version()}, numpy {np.__version__}, {platform.machine()}, '
            f'{os.cpu_count()} cpus, load avg {os.getloadavg()[0]:.2f}')


def per_call_us(fn: Callable[..., Any], args_list: Iterable[Sequence[Any]]) -> list[float]:
    """Wall time of each call ``fn(*args)`` in microseconds."""
    out = []
    clock = time.perf_counter
    for args in args_list:
        t0 = clock()
        fn(*args)
        out.append((clock() - t0) * 1e6)
    return out


def repeat_seconds(fn: Callable[[], Any], repeat: int) -> list[float]:
    """Wall time (s) of each of ``repeat`` calls ``fn()``."""
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return times


def summary_us(samples: list[float], width: int = 7) -> str:
    """Median, p10, p90 (us, ``width`` wide) and the sample count."""
    s = sorted(samples)
    return (f'median {statistics.median(s):{width}.1f} us, p10 {s[len(s) // 10]:{width}.1f} us, '
            f'p90 {s[9 * len(s) // 10]:{width}.1f} us, n = {len(s)}')
