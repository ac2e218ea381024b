"""SetpointStream's stale-stream report, on its own (no bus): CI run of stop 36 read a count of
stale holds whose warning was not there yet (the SYNC thread was preempted between the two)."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from brace_control.can.stream import SetpointStream
from brace_control.can.supervision import Limits


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


class _Warnings:
    def __init__(self):
        self.active: dict[str, str] = {}

    def warn(self, key, message):
        self.active[key] = message

    def unwarn(self, key):
        self.active.pop(key, None)

    def report(self, *a, **k):
        raise AssertionError(f'unexpected fault {a} {k}')


def _stream_rig():
    supervisor = _Warnings()
    limits = Limits(period=0.002, v_max=0.065, a_max=0.5, stroke=(-0.1, 0.1), step_margin=0.0005,
                    path_tolerance=0.005, force_limit=250.0, saturation_counts=30000,
                    stale_periods=3, heartbeat_timeout=0.1, boot_timeout=1.0, command_timeout=0.015)
    drives = [SimpleNamespace(name='a1', index=0)]
    life = SimpleNamespace(limits=limits, supervisor=supervisor, config=SimpleNamespace(period=0.002),
                           drives=drives)
    taken = []
    executor = SimpleNamespace(q=np.zeros(1), stream_stale=lambda: None,
                               set_stream=lambda q, v, t: taken.append(float(q[0])))
    return SetpointStream(life, lambda: False), supervisor, executor, taken


def test_a_burst_of_one_stamp_within_a_period_is_judged_in_the_order_it_was_sent():
    """Run 1002: a stream's first setpoint and a second one of the same stamp (0.2 mm on)
    reached the driver within one SYNC period; the cycle looked only at the newest, took it as
    the stream's first, and the brace moved. The second one is not a newer command whenever it
    arrives: refused, counted and reported; the cycle takes the first."""
    stream, supervisor, executor, taken = _stream_rig()
    stream.receive(np.array([0.0]), 5.0, None)
    stream.receive(np.array([0.0002]), 5.0, None)           # same stamp, before the cycle looked
    stream.feed(executor, t_wake=1.0)
    assert taken == [0.0]
    assert stream.rejected == 1 and stream.accepted == 1
    assert 'stamps not increasing' in supervisor.active.get('setpoint_stamps', '')
    for k in range(1, 6):                                   # one at a time: refused too
        stream.receive(np.array([0.0002 * k]), 5.0 - k, None)
        stream.feed(executor, t_wake=1.0 + 0.002 * k)
    assert taken == [0.0] and stream.rejected == 6
    assert supervisor.active['setpoint_stamps'].startswith('6 setpoint(s) rejected')
    # a newer stamp is a command again, and clears the warning
    stream.receive(np.array([0.0001]), 5.01, None)
    stream.feed(executor, t_wake=1.02)
    assert taken == [0.0, 0.0001] and 'setpoint_stamps' not in supervisor.active
