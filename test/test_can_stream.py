"""SetpointStream's stale-stream report, on its own (no bus): CI run of stop 36 read a count of
stale holds whose warning was not there yet (the SYNC thread was preempted between the two)."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from brace_control.can.stream import SetpointStream


class _Supervisor:
    """Records, at each warning, how many stale holds the stream had already counted."""

    def __init__(self):
        self.stream = None
        self.warned_at: list[tuple[str, int]] = []

    def warn(self, key, message):
        self.warned_at.append((key, self.stream.stale_holds))

    def unwarn(self, key):
        pass

    def report(self, *a, **k):
        raise AssertionError(f'unexpected fault {a} {k}')


def test_a_stale_stream_is_warned_before_it_is_counted():
    supervisor = _Supervisor()
    limits = SimpleNamespace(command_timeout=0.015, v_max=0.05, a_max=0.5, step_max=None)
    life = SimpleNamespace(limits=limits, supervisor=supervisor, config=SimpleNamespace(period=0.002),
                           drives=[])
    stream = SetpointStream(life, lambda: False)
    supervisor.stream = stream
    stale = []
    executor = SimpleNamespace(q=np.zeros(0), stream_stale=lambda: stale.append(True),
                               accept_setpoint=lambda *a, **k: None)
    stream._was_fresh = True                  # a stream was running
    stream.feed(executor, t_wake=1e9)         # and nothing came for command_timeout
    assert stale == [True]
    assert stream.stale_holds == 1
    # a reader that sees the count (another thread, any time after) also sees the warning
    assert supervisor.warned_at == [('setpoint', 0)]
