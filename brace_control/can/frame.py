"""A CAN frame that is cheap to copy: what the master and the simulated drives send.

python-can's ``virtual`` interface gives every other bus on the channel its own copy of a
frame, by ``copy.deepcopy`` (``VirtualBus.send``). ``can.Message.__deepcopy__`` rebuilds
the message through ``Message.__init__`` and deep-copies its channel and data through
the copy module: tens of microseconds per frame and receiver. The simulated brace shares
the driver's process and a cycle puts about ten frames on the bus every 2 ms, so that copy
alone took a sixth of a core. :class:`Frame` copies its slots directly (the payload as a
new ``bytearray``, as python-can would). It is a ``can.Message`` in every other respect;
real interfaces (``socketcan``) never copy it.
"""
from __future__ import annotations

import time
from typing import Any

import can
import canopen

__all__ = ['Frame', 'StampedNetwork']

_SLOTS = tuple(s for s in can.Message.__slots__ if s != '__weakref__')


class Frame(can.Message):
    """``can.Message`` with a slot-wise ``__deepcopy__`` (see the module docstring)."""

    __slots__ = ()

    def __deepcopy__(self, memo: dict[int, Any] | None) -> 'Frame':
        new = Frame.__new__(Frame)
        for name in _SLOTS:
            setattr(new, name, getattr(self, name))
        new.data = bytearray(self.data)
        return new


class StampedNetwork(canopen.Network):
    """``canopen.Network`` whose own frames (SDO requests, NMT commands) carry their send time.

    canopen builds them with python-can's default timestamp, 0.0. A ``virtual`` bus opened
    with ``preserve_timestamps`` (the master's, so that the frame log and the simulated drives
    see one clock read per SYNC) passes that 0.0 on, and python-can's log writers put such a
    frame at the log's first frame's time: a log whose last frame is the shutdown's NMT
    command then seemed to last no time at all, and its replay lost the boot's timing. Every
    frame the master sends now has the wall-clock time it was sent (as the cycle's own have).
    """

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        if not self.bus:
            raise RuntimeError('Not connected to CAN bus')
        msg = Frame(is_extended_id=can_id > 0x7FF, arbitration_id=can_id, data=data,
                    is_remote_frame=remote)
        with self.send_lock:
            msg.timestamp = time.time()
            self.bus.send(msg)
        self.check()
