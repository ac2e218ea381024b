"""Exceptions of the CAN layer, shaped like python-can's (``CanError`` and its children).

Every error of :mod:`brace_control.can` derives from :class:`DriverError`, itself a
:class:`can.CanError`, so a caller that already handles python-can errors handles ours::

    can.CanError
     └── DriverError                      anything the CiA 402 master reports
          ├── DriverInitializationError   bus cannot open, a drive never boots, SDO set-up fails
          │    └── DictionaryError        a drive's dictionary lacks what the brace needs
          ├── DriverOperationError        a command the master refuses or a drive does not follow
          │    └── FaultLatchedError      refused because a protective stop is latched
          └── DriverTimeoutError          a 402 transition / homing did not finish in time
"""
from __future__ import annotations

import can

__all__ = ['DriverError', 'DriverInitializationError', 'DictionaryError', 'DriverOperationError',
           'FaultLatchedError', 'DriverTimeoutError']


class DriverError(can.CanError):
    """Base of the CiA 402 master's errors; the message says what to do."""


class DriverInitializationError(DriverError, can.CanInitializationError):
    """The bus could not be opened, a drive did not boot (``boot_timeout``) or rejected its set-up."""


class DictionaryError(DriverInitializationError):
    """A drive's object dictionary lacks what the brace needs, or the YAML asks for what the
    dictionary does not offer (the message lists all of it; nothing was sent). Raised by
    :mod:`.plan` (``brace_control.can.plan.DictionaryError`` is this class)."""


class DriverOperationError(DriverError, can.CanOperationError):
    """A command was refused (not booted, faulted, bad target) or a drive did not follow it."""


class FaultLatchedError(DriverOperationError):
    """Refused because a protective stop is latched: call ``recover()`` once the cause is gone."""


class DriverTimeoutError(DriverError, can.CanTimeoutError):
    """A CiA 402 transition or homing did not complete within its time limit."""
