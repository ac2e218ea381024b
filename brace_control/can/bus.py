"""Opening a python-can bus, with a cheaper frame copy on the ``virtual`` interface.

python-can's :class:`~can.interfaces.virtual.VirtualBus` hands every other bus on its
channel its own copy of a sent frame, made with :func:`copy.deepcopy`: 12 us per copy on
this machine (the memo dictionaries of a generic deep copy), for a frame whose only mutable
part is its data. Every frame the master and the simulated drives put on the channel is
copied once per other bus: SYNC and the TPDO1s at every SYNC (500 Hz) at rest, the RPDOs as
well in motion (bench/RESULTS.md: about 0.7 % of a core at rest).

:class:`VirtualBus` makes the same copy field by field (its own ``bytearray`` of the data,
the receiving side's ``timestamp``, ``channel`` and ``is_rx`` set as python-can sets them),
about 2 us. It is python-can's class otherwise: the same channel registry, so its frames
reach plain ``can.Bus(interface='virtual')`` buses on the channel and theirs reach it.
Every other interface (``socketcan``, ``pcan``, ...) is opened by :class:`can.Bus` itself.
"""
from __future__ import annotations

import queue
import time
from typing import Any

import can
from can.interfaces.virtual import VirtualBus as _PythonCanVirtualBus

__all__ = ['VirtualBus', 'open_bus']


class VirtualBus(_PythonCanVirtualBus):
    """python-can's virtual bus with a field-by-field frame copy (module docstring)."""

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
