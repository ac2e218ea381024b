"""Opening a python-can bus, with a cheaper frame copy on the ``virtual`` interface.

python-can's :class:`~can.interfaces.virtual.VirtualBus` hands every other bus on its
channel its own copy of a sent frame, made with :func:`copy.deepcopy`: 12 us per copy on
this machine (the memo dictionaries of a generic deep copy), for a frame whose only mutable
part is its data. Every frame the master and the simulated drives put on the channel is
copied once per other bus: SYNC and the TPDO1s at every SYNC (500 Hz) at rest, the RPDOs as
well in motion (bench/RESULTS.md: about 0.7 % of a core at rest).

:class:`VirtualBus` makes the same copy field by field (its own ``bytearray`` of the data,
the receiving side's ``timestamp``, ``channel`` and ``is_rx`` set as python-can sets them),
about 2 us. Its receive queue, unbounded as python-can's is by default, is a
:class:`queue.SimpleQueue` (implemented in C) rather than a :class:`queue.Queue` (Python, a
condition variable and three locks): a frame's put and get cost ~0.3 us instead of ~8 us,
twice per frame at 2000 frames/s at rest. It is python-can's class otherwise: the same
channel registry, so its frames reach plain ``can.Bus(interface='virtual')`` buses on the
channel and theirs reach it.

A receiver may instead take each frame in its sender's thread
(:meth:`VirtualBus.receive_inline`, :class:`InlineDelivery`): the simulated drives do, as a
frame reaches a real drive while it crosses the wire, without a receive thread to wake for
every SYNC and RPDO (bench/RESULTS.md).
Every other interface (``socketcan``, ``pcan``, ...) is opened by :class:`can.Bus` itself.
"""
from __future__ import annotations

import collections
import logging
import queue
import threading
import time
from collections.abc import Callable
from typing import Any

import can
import can.interfaces.virtual as _virtual
from can.interfaces.virtual import VirtualBus as _PythonCanVirtualBus

__all__ = ['InlineDelivery', 'RxQueue', 'VirtualBus', 'open_bus']

log = logging.getLogger(__name__)


class RxQueue(queue.SimpleQueue):
    """A virtual bus's receive queue: :class:`queue.SimpleQueue` (C), and the frames not yet
    taken out, oldest first (:meth:`oldest`), which a C queue does not show: the simulated
    drives judge the master's silence up to the oldest frame still waiting for them
    (:meth:`brace_control.sim.host.SimBus._heard_until`)."""

    def __init__(self) -> None:
        super().__init__()
        self._waiting: collections.deque[Any] = collections.deque()

    def put(self, item: Any, block: bool = True, timeout: float | None = None) -> None:
        self._waiting.append(item)
        super().put(item)

    def put_nowait(self, item: Any) -> None:
        self.put(item)

    def get(self, block: bool = True, timeout: float | None = None) -> Any:
        item = super().get(block, timeout)
        self._waiting.popleft()
        return item

    def get_nowait(self) -> Any:
        return self.get(False)

    def oldest(self) -> Any:
        """The oldest frame not yet taken out, ``None`` if there is none."""
        try:
            return self._waiting[0]
        except IndexError:
            return None


class InlineDelivery:
    """A virtual bus's receive side that hands each frame to its receiver in the sender's
    thread, in place of a queue and a thread that takes from it (:meth:`VirtualBus.receive_inline`).

    A receiver's exception is logged, never raised into the sender (a drive's firmware fault
    does not reach the master's ``send``). Nothing waits in it: :meth:`oldest` is ``None`` and
    :meth:`get` finds nothing (after ``timeout``).
    """

    def __init__(self, handler: Callable[[can.Message], None]) -> None:
        self._handler = handler
        self._closed = threading.Event()

    def put(self, item: can.Message, block: bool = True, timeout: float | None = None) -> None:
        try:
            self._handler(item)
        except Exception:  # noqa: BLE001 - the sender is another node
            log.exception('inline receiver failed on frame %03Xh', item.arbitration_id)

    def put_nowait(self, item: can.Message) -> None:
        self.put(item)

    def get(self, block: bool = True, timeout: float | None = None) -> can.Message:
        if block:
            self._closed.wait(timeout)
        raise queue.Empty

    def get_nowait(self) -> can.Message:
        raise queue.Empty

    def oldest(self) -> None:
        return None

    def qsize(self) -> int:
        return 0

    def empty(self) -> bool:
        return True

    def close(self) -> None:
        self._closed.set()


class VirtualBus(_PythonCanVirtualBus):
    """python-can's virtual bus with a field-by-field frame copy and a C receive queue
    (module docstring)."""

    def __init__(self, channel: Any = None, **kwargs: Any) -> None:
        super().__init__(channel=channel, **kwargs)
        if kwargs.get('rx_queue_size', 0):
            return                       # a bounded queue (drops the oldest): python-can's
        self._take_over_queue(RxQueue())

    def receive_inline(self, handler: Callable[[can.Message], None]) -> bool:
        """Hand every frame sent to this bus to ``handler`` in the sender's thread
        (:class:`InlineDelivery`) instead of queueing it for :meth:`recv`; ``False`` (and
        nothing changed) when another bus on the channel already receives inline: two such
        receivers would call into each other, each holding its own locks."""
        return self._take_over_queue(
            InlineDelivery(handler),
            unless=lambda queues: any(isinstance(q, InlineDelivery) for q in queues))

    def _take_over_queue(self, new: Any, unless: Callable[[list[Any]], bool] | None = None) -> bool:
        """``new`` in place of this bus's receive queue in the channel's registry (not if
        ``unless(the channel's queues)``); the frames the old one held are put into it."""
        with _virtual.channels_lock:
            if unless is not None and unless(self.channel):
                return False
            old = self.queue
            self.channel[self.channel.index(old)] = new
            self.queue = new
        while True:
            try:
                new.put(old.get_nowait())
            except queue.Empty:
                return True

    def shutdown(self) -> None:
        if isinstance(self.queue, InlineDelivery):
            self.queue.close()
        super().shutdown()

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self._check_if_open()
        timestamp = msg.timestamp if self.preserve_timestamps else time.time()
        data = msg.data
        all_sent = True
        for bus_queue in self.channel:
            if bus_queue is self.queue and not self.receive_own_messages:
                continue
            copy = can.Message(
                timestamp=timestamp, arbitration_id=msg.arbitration_id,
                is_extended_id=msg.is_extended_id, is_remote_frame=msg.is_remote_frame,
                is_error_frame=msg.is_error_frame, channel=self.channel_id, dlc=msg.dlc,
                data=bytearray(data), is_fd=msg.is_fd, is_rx=bus_queue is not self.queue,
                bitrate_switch=msg.bitrate_switch,
                error_state_indicator=msg.error_state_indicator)
            try:
                bus_queue.put(copy, block=True, timeout=timeout)
            except queue.Full:
                all_sent = False
        if not all_sent:
            raise can.CanOperationError('Could not send message to one or more recipients')


def open_bus(interface: str, channel: Any, **kwargs: Any) -> can.BusABC:
    """``can.Bus(interface=interface, channel=channel, **kwargs)``; on ``'virtual'``,
    :class:`VirtualBus` (the same bus, a cheaper frame copy)."""
    if interface == 'virtual':
        return VirtualBus(channel=channel, **kwargs)
    return can.Bus(interface=interface, channel=channel, **kwargs)
