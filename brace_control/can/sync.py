"""The SYNCs the master sent, and which of them a drive's answer belongs to.

Part of :class:`~.master.BraceMaster`: the cycle (:mod:`.cycle`) stamps each SYNC just before
it sends it (:meth:`SyncClock.stamp`); the receive side (:mod:`.receive`) attributes each
TPDO1 to the SYNC it answered (:meth:`SyncClock.answered`), so that positions taken two
periods apart never look simultaneous.
"""
from __future__ import annotations

import time
from collections import deque
from collections.abc import Reversible
from typing import Any

__all__ = ['SyncClock', 'stamped_after']


def stamped_after(kept: Reversible[Any], stamp: float) -> list[Any]:
    """The items of ``kept`` (ordered by their ``stamp``, a SYNC's wall-clock time, as the
    simulator's truths are) stamped after ``stamp``, oldest first: a walk back from the
    newest, which does not copy the rest of a long record (the caller holds its lock)."""
    out: list[Any] = []
    for item in reversed(kept):
        if item.stamp <= stamp:
            break
        out.append(item)
    out.reverse()
    return out


class SyncClock:
    """Count and times of the SYNCs sent.

    :ivar index: the last SYNC's number (0 before the first).
    :ivar time: its ``perf_counter`` time.
    :ivar log: ``(wall clock, perf_counter, index)`` of the recent SYNCs, oldest first.
    :ivar attribution_window: the most SYNCs a TPDO1 may answer late and still be counted
        (:meth:`answered`).
    """

    def __init__(self, *, keep: int = 128, attribution_window: int = 25) -> None:
        self.index = 0
        self.time = 0.0
        self.log: deque[tuple[float, float, int]] = deque(maxlen=keep)
        self.attribution_window = attribution_window

    def stamp(self) -> float:
        """The next SYNC is about to be sent: count it, note its times; returns its wall-clock
        time (the frame carries it: the frame log keeps it). The index moves first, so a
        TPDO answering it that arrives before ``send`` returns finds it."""
        self.time = time.perf_counter()
        self.index += 1
        wall = time.time()
        self.log.append((wall, self.time, self.index))
        return wall

    def answered(self, timestamp: float, previous: int | None = None) -> tuple[int, float]:
        """(index, perf_counter) of the SYNC a drive's TPDO1 with bus ``timestamp`` answers.

        The bus timestamp bounds it from above: the last SYNC sent before the frame. A
        drive answers every SYNC once and in order (transmission type 1), so the answer
        after the one to SYNC ``previous`` is to ``previous + 1`` unless that bound is
        lower. Counting matters when answers come late in a burst (a simulator or a
        receive thread that did not run for a few periods): by timestamp alone, answers to
        SYNCs n, n+1, n+2 sent together after SYNC n+2 would all be n+2, and positions
        two periods apart would look simultaneous (a false overspeed). After a silence of
        more than :attr:`attribution_window` SYNCs (a lost frame, a restart) the
        timestamp alone decides again.

        Falls back to the latest SYNC when the interface's timestamps are not on the
        wall clock (hardware clocks).
        """
        if not self.log or abs(timestamp - time.time()) > 0.5:
            return self.index, self.time
        log_ = tuple(self.log)      # a C-level copy: the SYNC thread appends meanwhile
        bound = None
        for wall, perf, index in reversed(log_):
            if wall <= timestamp:
                bound = index, perf
                break
        if bound is None:
            return log_[0][2], log_[0][1]
        if previous is None or not 0 <= bound[0] - previous - 1 <= self.attribution_window:
            return bound
        index = previous + 1
        first = log_[0][2]
        return (index, log_[index - first][1]) if 0 <= index - first < len(log_) else bound

    def wall_of(self, index: int) -> float:
        """The wall-clock time SYNC ``index`` was sent (0.0 if it is no longer kept)."""
        for w, _, i in reversed(tuple(self.log)):      # a C-level copy
            if i == index:
                return w
        return 0.0
