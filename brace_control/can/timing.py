"""Periodic timing for the SYNC thread: absolute deadlines, sleep then spin, statistics.

The loop keeps absolute deadlines ``t0 + k·period`` on :func:`time.perf_counter` (no
drift), sleeps until ``spin_s`` before each deadline and busy-waits the rest (Linux
``sleep`` overshoots by ~50–100 µs). A cycle whose work ends after the next deadline
is an *overrun*: the missed deadlines are skipped (no burst of catch-up SYNCs).
:func:`run_periodic` is the loop both the master and the bench's bare floor use.
"""
from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

__all__ = ['PeriodStats', 'TimingReport', 'sleep_until', 'run_periodic']


@dataclass(frozen=True)
class TimingReport:
    """Period error |measured − nominal| of the wake-ups, in seconds, and overruns."""

    cycles: int
    overruns: int
    p50: float
    p99: float
    max: float
    period: float

    @property
    def overrun_fraction(self) -> float:
        return self.overruns / self.cycles if self.cycles else 0.0

    def as_dict(self) -> dict[str, float]:
        return {'cycles': self.cycles, 'overruns': self.overruns,
                'period_error_p50_us': self.p50 * 1e6, 'period_error_p99_us': self.p99 * 1e6,
                'period_error_max_us': self.max * 1e6}


class PeriodStats:
    """Ring buffer of the last ``window`` period errors (thread-safe enough: one writer)."""

    def __init__(self, period: float, *, window: int = 5000) -> None:
        self.period = period
        self._buf = np.zeros(window)
        self._n = 0
        self.cycles = 0
        self.overruns = 0
        self._last_wake: float | None = None

    def wake(self, t: float) -> None:
        """Record a wake-up at ``t`` (perf_counter)."""
        if self._last_wake is not None:
            self._buf[self._n % self._buf.size] = abs(t - self._last_wake - self.period)
            self._n += 1
        self._last_wake = t
        self.cycles += 1

    def reset(self) -> None:
        self._n = 0
        self.cycles = 0
        self.overruns = 0
        self._last_wake = None

    def samples(self) -> np.ndarray:
        """The recorded period errors (s), at most the last ``window``."""
        return self._buf[:min(self._n, self._buf.size)].copy()

    def report(self) -> TimingReport:
        n = min(self._n, self._buf.size)
        if n == 0:
            return TimingReport(self.cycles, self.overruns, math.nan, math.nan, math.nan, self.period)
        data = self._buf[:n].copy()
        p50, p99 = np.percentile(data, [50, 99])
        return TimingReport(self.cycles, self.overruns, float(p50), float(p99), float(data.max()),
                            self.period)


def sleep_until(deadline: float, *, spin_s: float) -> float:
    """Sleep until ``spin_s`` before ``deadline`` (perf_counter), then spin; returns the wake time."""
    remaining = deadline - time.perf_counter() - spin_s
    if remaining > 0.0:
        time.sleep(remaining)
    now = time.perf_counter()
    while now < deadline:
        now = time.perf_counter()
    return now


def run_periodic(period: float, body: Callable[[int, float], None], stop: threading.Event, *,
                 stats: PeriodStats | None = None, spin_s: float = 0.0003,
                 max_cycles: int | None = None) -> None:
    """Call ``body(k, t_wake)`` every ``period`` s until ``stop`` is set (or ``max_cycles``)."""
    t0 = time.perf_counter() + period
    k = 0
    deadline = t0
    while not stop.is_set():
        wake = sleep_until(deadline, spin_s=spin_s)
        if stats is not None:
            stats.wake(wake)
        body(k, wake)
        k += 1
        if max_cycles is not None and k >= max_cycles:
            return
        deadline += period
        now = time.perf_counter()
        if now > deadline:
            missed = math.ceil((now - deadline) / period)
            if stats is not None:
                stats.overruns += missed
            deadline += missed * period
