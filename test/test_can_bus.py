"""brace_control.can.bus.VirtualBus against python-can's own VirtualBus (the oracle).

Our bus only replaces the per-receiver frame copy (a field-by-field copy instead of
``copy.deepcopy``) and its receive queue (a C queue that shows its oldest frame, or a
receiver called in the sender's thread): what every receiver gets must be what python-can's
bus gives it, each receiver its own frame and its own data, and the two kinds of bus share a
channel.
"""
from __future__ import annotations

import itertools
import queue
import threading
import time

import can
import pytest

from brace_control.can.bus import VirtualBus, open_bus

_channels = itertools.count()

FRAMES = [
    can.Message(arbitration_id=0x80, data=b'', is_extended_id=False, timestamp=1.25),
    can.Message(arbitration_id=0x201, data=bytes(range(8)), is_extended_id=False, timestamp=2.5),
    can.Message(arbitration_id=0x1ABCDEF, data=b'\x01\x02\x03', is_extended_id=True),
    can.Message(arbitration_id=0x601, is_remote_frame=True, dlc=8, is_extended_id=False),
    can.Message(arbitration_id=0x7FF, is_error_frame=True, is_extended_id=False),
    can.Message(arbitration_id=0x123, data=bytes(range(64)), is_fd=True, bitrate_switch=True,
                error_state_indicator=True, is_extended_id=False),
]
FIELDS = ('arbitration_id', 'is_extended_id', 'is_remote_frame', 'is_error_frame', 'channel',
          'dlc', 'data', 'is_fd', 'is_rx', 'bitrate_switch', 'error_state_indicator')


def _received(sender_cls, preserve: bool, receive_own: bool) -> list[list[can.Message]]:
    """Each frame sent by a ``sender_cls`` bus, as two python-can receivers and (with
    ``receive_own``) the sender itself got it."""
    channel = f'bus-test-{next(_channels)}'
    sender = sender_cls(channel=channel, preserve_timestamps=preserve,
                        receive_own_messages=receive_own)
    others = [can.Bus(interface='virtual', channel=channel) for _ in range(2)]
    try:
        out = []
        for frame in FRAMES:
            sender.send(frame)
            got = [bus.recv(1.0) for bus in others + ([sender] if receive_own else [])]
            assert all(g is not None for g in got)
            out.append(got)
        assert all(bus.recv(0) is None for bus in others + [sender])
        return out
    finally:
        for bus in [sender, *others]:
            bus.shutdown()


@pytest.mark.parametrize('preserve', [False, True])
@pytest.mark.parametrize('receive_own', [False, True])
def test_every_receiver_gets_what_python_cans_virtual_bus_gives(preserve, receive_own):
    ours = _received(VirtualBus, preserve, receive_own)
    theirs = _received(can.interfaces.virtual.VirtualBus, preserve, receive_own)
    for frame, got_ours, got_theirs in zip(FRAMES, ours, theirs):
        for a, b in zip(got_ours, got_theirs):
            for name in FIELDS:
                va, vb = getattr(a, name), getattr(b, name)
                if name == 'channel':                 # each run its own channel name
                    va, vb = va.rsplit('-', 1)[0], vb.rsplit('-', 1)[0]
                assert va == vb, (frame, name, va, vb)
            if preserve:
                assert a.timestamp == b.timestamp == frame.timestamp
            else:
                assert a.timestamp != frame.timestamp or frame.timestamp == 0.0


def test_each_receiver_has_its_own_frame_and_data():
    channel = f'bus-test-{next(_channels)}'
    sender = open_bus('virtual', channel)
    assert isinstance(sender, VirtualBus)
    receivers = [can.Bus(interface='virtual', channel=channel) for _ in range(2)]
    try:
        frame = can.Message(arbitration_id=0x181, data=bytearray(b'\x01\x02'), is_extended_id=False)
        sender.send(frame)
        a, b = (r.recv(1.0) for r in receivers)
        assert a is not b and a is not frame and a.data is not b.data and a.data is not frame.data
        a.data[0] = 0xFF
        assert b.data == frame.data == bytearray(b'\x01\x02')
        # and the other way: a plain python-can bus's frames reach ours
        receivers[0].send(frame)
        got = sender.recv(1.0)
        assert got is not None and got.data == frame.data and got.is_rx
    finally:
        for bus in [sender, *receivers]:
            bus.shutdown()


def test_a_closed_bus_refuses_to_send():
    bus = open_bus('virtual', f'bus-test-{next(_channels)}')
    bus.shutdown()
    with pytest.raises(can.CanOperationError):
        bus.send(FRAMES[1])


def test_other_interfaces_are_python_cans_own():
    with pytest.raises((can.CanError, ValueError, ImportError, OSError)):
        open_bus('no_such_interface', 'x')


def test_the_receive_queue_shows_its_oldest_frame_until_it_is_received():
    """What the simulated drives' heartbeat consumer reads (sim/host.py ``_heard_until``):
    the oldest frame not yet received, in the order sent, from any kind of bus."""
    channel = f'bus-test-{next(_channels)}'
    ours = open_bus('virtual', channel)
    theirs = can.Bus(interface='virtual', channel=channel)
    try:
        assert ours.queue.oldest() is None
        for frame in FRAMES[:3]:
            theirs.send(frame)
        ids = []
        while (head := ours.queue.oldest()) is not None:
            got = ours.recv(1.0)
            assert got is head
            ids.append(got.arbitration_id)
        assert ids == [f.arbitration_id for f in FRAMES[:3]]
        assert ours.recv(0.01) is None and ours.queue.oldest() is None
        theirs.send(FRAMES[1])
        assert ours.queue.get_nowait().arbitration_id == FRAMES[1].arbitration_id
        assert ours.queue.oldest() is None
        with pytest.raises(queue.Empty):
            ours.queue.get_nowait()
    finally:
        ours.shutdown()
        theirs.shutdown()
    assert channel not in can.interfaces.virtual.channels     # both queues gone from the registry


def test_a_bounded_receive_queue_stays_python_cans():
    bus = open_bus('virtual', f'bus-test-{next(_channels)}', rx_queue_size=2)
    try:
        assert type(bus.queue) is queue.Queue and bus.queue.maxsize == 2
    finally:
        bus.shutdown()


def test_an_inline_receiver_gets_every_frame_in_the_senders_thread_as_a_queue_would():
    """receive_inline (the simulated drives, sim/host.py): each frame reaches the handler
    before ``send`` returns, in the sender's thread, with what python-can's own receiver on
    the channel gets; ``recv`` then finds nothing, and a closed bus leaves the channel."""
    channel = f'bus-test-{next(_channels)}'
    ours = open_bus('virtual', channel)
    theirs = can.Bus(interface='virtual', channel=channel)
    witness = can.Bus(interface='virtual', channel=channel)
    got: list[tuple[int, can.Message]] = []
    try:
        assert ours.receive_inline(lambda m: got.append((threading.get_ident(), m)))
        for i, frame in enumerate(FRAMES):
            theirs.send(frame)
            assert len(got) == i + 1                           # before send returned
        for thread, m in got:
            assert thread == threading.get_ident()
            expected = witness.recv(1.0)
            assert {f: getattr(m, f) for f in FIELDS} == {f: getattr(expected, f) for f in FIELDS}
        t0 = time.monotonic()
        assert ours.recv(0.05) is None and time.monotonic() - t0 >= 0.04
        assert ours.queue.oldest() is None
    finally:
        ours.shutdown()
    theirs.send(FRAMES[1])
    assert len(got) == len(FRAMES)                              # no longer on the channel
    theirs.shutdown()
    witness.shutdown()
    assert channel not in can.interfaces.virtual.channels


def test_a_second_inline_receiver_on_a_channel_is_refused_and_keeps_its_queue():
    """Two inline receivers would call into each other, each holding its own locks: the
    second one stays a queue (its owner starts a receive thread)."""
    channel = f'bus-test-{next(_channels)}'
    first, second = open_bus('virtual', channel), open_bus('virtual', channel)
    sender = can.Bus(interface='virtual', channel=channel)
    got = []
    try:
        assert first.receive_inline(got.append)
        assert not second.receive_inline(got.append)
        sender.send(FRAMES[1])
        assert len(got) == 1
        assert second.recv(1.0).arbitration_id == FRAMES[1].arbitration_id
    finally:
        for b in (first, second, sender):
            b.shutdown()


def test_an_inline_receivers_failure_is_logged_not_raised_into_the_sender(caplog):
    channel = f'bus-test-{next(_channels)}'
    ours = open_bus('virtual', channel)
    sender = can.Bus(interface='virtual', channel=channel)
    got = []

    def handler(m):
        if m.arbitration_id == 0x80:
            raise RuntimeError('firmware bug')
        got.append(m.arbitration_id)
    try:
        ours.receive_inline(handler)
        with caplog.at_level('ERROR', logger='brace_control.can.bus'):
            sender.send(FRAMES[0])                  # 0x80: raises inside the receiver
        assert 'inline receiver failed on frame 080h' in caplog.text
        sender.send(FRAMES[1])
        assert got == [FRAMES[1].arbitration_id]
    finally:
        ours.shutdown()
        sender.shutdown()
