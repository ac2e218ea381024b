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

from typing import Any

import can

__all__ = ['Frame']

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
