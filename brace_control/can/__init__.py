"""CiA 402 master over python ``canopen`` on a python-can bus (see docs/can.md).

>>> from brace_control.config import load_device_config
>>> from brace_control.can import BraceMaster
>>> master = BraceMaster.from_device_config(load_device_config('lumbar_brace'), channel='t1')
>>> master.boot(); master.home(); master.enable(); master.set_targets([0.39, 0.39, 0.39])

* :mod:`.master`: :class:`BraceMaster`, made of :mod:`.state` (:class:`MasterConfig`,
  states, snapshots), :mod:`.boot` (SDO configuration, PDO mapping, NMT, homing),
  :mod:`.sync` (the SYNCs sent, a part of its own), :mod:`.receive` (TPDOs, heartbeats,
  EMCY, error frames: a part of its own), :mod:`.cycle` (the SYNC thread),
  :mod:`.monitors` (per-cycle supervision).
* :mod:`.plan` / :mod:`.dictionary`: the boot planned against the drive's own EDS/DCF.
* :mod:`brace_control.control.execution`: the commanded motion, one time base for all
  axes: :class:`ActuatorTrajectory` (quintic Hermite), :class:`PathExecutor`.
* :mod:`.units`: every SI <-> device-unit conversion.
* :mod:`.cia402`: statusword / controlword / NMT / EMCY codes.
* :mod:`.supervision`: fault kinds, latching, monitors, error-frame decoding.
* :mod:`.timing`: absolute-deadline periodic loop and its statistics.
* :mod:`.framelog`: python-can frame log of the bus and its replay.
* :mod:`.errors`: the exception hierarchy (python-can style).
"""
import importlib
from typing import TYPE_CHECKING, Any

#: each public name and the module it lives in: imported on first use (PEP 562), so that a
#: node that needs only :mod:`.units` (kinetics, trajectory, ik, interaction) does not load
#: the master, its cycle, boot and monitors (76 ms of import at every such node's start)
_HOMES = {
    **dict.fromkeys(('Controlword', 'NmtState', 'OpMode', 'State402', 'Statusword', 'decode_state',
                     'emcy_description'), '.cia402'),
    **dict.fromkeys(('DriverError', 'DriverInitializationError', 'DriverOperationError',
                     'DriverTimeoutError', 'FaultLatchedError'), '.errors'),
    **dict.fromkeys(('ActuatorTrajectory', 'ExecutionEvent', 'PathExecutor', 'TrajectoryInvalid'),
                    '..control.execution'),
    # CiA402Master: an alias of BraceMaster (the master is a generic CiA 402 CSP master; the
    # brace is its only user so far)
    **dict.fromkeys(('BraceMaster', 'CiA402Master'), '.master'),
    **dict.fromkeys(('BusStatus', 'DriveStatus', 'Feedback', 'MasterConfig', 'MasterState',
                     'MasterStatus'), '.state'),
    **dict.fromkeys(('Fault', 'FaultKind', 'Limits', 'Supervisor'), '.supervision'),
    **dict.fromkeys(('PeriodStats', 'TimingReport'), '.timing'),
    **dict.fromkeys(('AxisScaling', 'scaling_from_config'), '.units'),
}

if TYPE_CHECKING:
    from ..control.execution import ActuatorTrajectory, ExecutionEvent, PathExecutor, TrajectoryInvalid
    from .cia402 import Controlword, NmtState, OpMode, State402, Statusword, decode_state, emcy_description
    from .errors import (DriverError, DriverInitializationError, DriverOperationError,
                         DriverTimeoutError, FaultLatchedError)
    from .master import BraceMaster
    from .state import BusStatus, DriveStatus, Feedback, MasterConfig, MasterState, MasterStatus
    from .supervision import Fault, FaultKind, Limits, Supervisor
    from .timing import PeriodStats, TimingReport
    from .units import AxisScaling, scaling_from_config


def __getattr__(name: str) -> Any:
    home = _HOMES.get(name)
    if home is None:
        raise AttributeError(f'module {__name__!r} has no attribute {name!r}')
    module = importlib.import_module(home, __name__)
    value = module.BraceMaster if name == 'CiA402Master' else getattr(module, name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_HOMES))


__all__ = [
    'BraceMaster', 'CiA402Master', 'ActuatorTrajectory', 'ExecutionEvent', 'PathExecutor',
    'TrajectoryInvalid', 'MasterConfig', 'MasterState', 'MasterStatus', 'DriveStatus',
    'BusStatus', 'Feedback', 'AxisScaling', 'scaling_from_config', 'State402', 'Statusword',
    'Controlword', 'NmtState', 'OpMode', 'decode_state', 'emcy_description', 'Fault', 'FaultKind',
    'Limits', 'Supervisor', 'PeriodStats', 'TimingReport', 'DriverError',
    'DriverInitializationError', 'DriverOperationError', 'DriverTimeoutError', 'FaultLatchedError',
]
