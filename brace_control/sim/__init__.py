"""The simulated brace: CiA 402 drives and the physics of device and body, on the bus.

>>> from brace_control.sim import SimulatedBrace
>>> sim = SimulatedBrace('config/lumbar_brace.yaml', channel='mytest')   # boots the drives
>>> sim.truth().pose, sim.faults.stall_actuator(2)
>>> sim.shutdown()

* :class:`SimulatedBrace` (:mod:`.brace`): all drives + physics, driven by the master's SYNC.
* :class:`SimulatedDrive` (:mod:`.drive`): one CiA 402 drive (transport-free).
* :class:`SimBus` (:mod:`.host`): drives on a python-can bus (on ``virtual`` they take a
  frame in its sender's thread, elsewhere from a Notifier; one timer thread).
* :class:`FaultInjector` (:mod:`.faults`): ``SimulatedBrace.faults``.

The contract with the master is docs/can.md.
"""
from .brace import BraceTruth, SimulatedBrace
from .drive import (MODE_CSP, MODE_HOMING, DriveLimits, EmcyCode, NmtState, SimulatedDrive,
                    State402)
from .faults import CtrlStatus, ErrorClass, FaultInjector, error_frame
from .host import SimBus

__all__ = [
    'SimulatedBrace', 'BraceTruth', 'SimulatedDrive', 'DriveLimits', 'SimBus',
    'FaultInjector', 'EmcyCode', 'NmtState', 'State402', 'ErrorClass', 'CtrlStatus',
    'error_frame', 'MODE_CSP', 'MODE_HOMING',
]
