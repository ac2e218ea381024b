"""An independent CiA 402 servo drive for the tests, on top of someone else's CANopen stack.

:class:`DurandDrive` is one `durand <https://pypi.org/project/durand/>`_ ``Node`` (a CANopen
responder library nobody here wrote: SDO server, NMT slave, heartbeat producer, SYNC
consumer, RPDOs/TPDOs, EMCY) on its own python-can bus object, with the object dictionary of
a CiA 402 servo drive and a small CiA 402 device behind it. The point: our master's frames
are read by a CiA 301 implementation that is not ours (``brace_control/sim`` and
``brace_control/can`` were written together), so an SDO, NMT or PDO detail both got wrong
in the same way shows up here. Everything of CiA 301 goes through durand: SDO
(expedited / segmented / block, its abort codes), NMT, heartbeat producer (1017h), the
SYNC-driven RPDOs and TPDOs, configured only by the master's SDO writes to
1400h-1403h / 1600h-1603h / 1800h-1803h / 1A00h-1A03h. What is ours, on top:

* the object dictionary of a CiA 402 drive (:data:`OBJECTS`), and validate callbacks
  on the PDO mapping entries that abort the SDO write of an object that does not
  exist (06020000h), cannot be mapped or has the wrong length (06040041h), or a PDO
  longer than 64 bits (06040042h), as a real drive does (durand stores any value);
* the CiA 402 device control state machine (controlword 6040h -> statusword 6041h,
  bits per CiA 402-2 table 30 / IEC 61800-7-201), fault reset on the rising edge of
  controlword bit 7, quick stop 605Ah, abort connection option 6007h on loss of the
  master's heartbeat (1016h sub 1, consumer on ``0x700 + master id``);
* modes 8 (cyclic synchronous position) and 6 (homing, methods 35 and 37: 6064h :=
  607Ch on the rising edge of controlword bit 4, statusword bits 12 + 10);
* on every SYNC (before durand's TPDOs of that SYNC go out, see below) in CSP and
  OPERATION ENABLED a first-order position loop with a speed limit that tracks 607Ah
  (plus the 60B1h velocity offset):
  ``x += clamp(Kp (607Ah - x) + 60B1h, +-v_max) dt``, with ``dt`` = 1006h (us) when
  non-zero, else the measured SYNC interval; sub-stepped so that ``Kp h <= 0.2``;
  positions in encoder counts; 607Dh clamps the target once homed (bit 11);
* a load cell at 2100h sub 1 (INTEGER16, configurable index) reading a spring:
  ``counts = round(k (x - x_rest) / n_per_count)``, saturating at the INTEGER16 range.

Durand's quirks this module works around:

* durand's timers (heartbeat producer, inhibit times) use a process-wide scheduler whose
  default needs a *running* asyncio loop; without one the heartbeat goes out once and
  never again (from a non-main thread the ``get_event_loop()`` error is even swallowed).
  :func:`_scheduler` installs a threaded scheduler (once per process) whose callbacks run
  under :data:`LOCK`.
* durand has no locking at all: its receive thread (one can.Notifier per drive) and the
  scheduler thread both write the object dictionary. Every durand entry point of every
  drive (frame callbacks, timers, our API) runs under the one process-wide :data:`LOCK`.
* ``Node()`` sends its boot-up message from inside its constructor, before its SDO
  server exists; :class:`_DriveNetwork` holds the frames until the whole object dictionary
  is built, then sends them in order (boot-up first, then the first heartbeat).
* the EDS export (``node.eds.content``) swaps ObjectType 8/9 (a Record is written as an
  ARRAY), writes sub-indices in decimal (``[1A00sub10]`` is read back as 10h), marks every
  object >= 2000h PDO-mappable and every object below it not mappable, and exports the
  *live* values as DefaultValue. :meth:`DurandDrive.eds_text` exports a pristine node and
  fixes the three format errors; the drive serves that text at 1021h (Store EDS) too.
  The PDO mapping parameters stay RECORD (CiA 301; canopen's ``PdoMap.save`` writes no
  entry into an ARRAY whose sub 0 it has just set to 0).
* a validate callback that raises a plain exception aborts the SDO download with
  08000020h "data cannot be transferred or stored" (:attr:`DurandDrive.REJECT_ABORT_CODE`);
  one that raises durand's ``SDODomainAbort(code)`` aborts with that code.
* ``CANBusNetwork.remove_subscription`` takes no ``callback`` argument though durand's
  SYNC consumer passes one (a write of 1005h raises TypeError in the update callback,
  which durand swallows: the SYNC consumer silently stays on the old COB-ID); the
  notifier polls with a 1 s timeout (stopping a drive took up to 1 s): both fixed in
  :class:`_DriveNetwork`.
* durand's heartbeat producer sends at once when 1017h is written; right after the
  boot-up message that makes canopen's ``wait_for_bootup`` miss the boot-up (the 7Fh
  heartbeat overwrites it before the waiter wakes). The default 1017h is written one
  period after the boot-up (the boot-up counts as the first heartbeat).

durand behaviour left as it is (our master does not depend on it; a test may):

* SYNC callbacks run in registration order, in the bus's receive thread: our motion step
  (registered first), then the TPDOs whose transmission type was written before NMT start,
  then the RPDO latches (registered at NMT start). A TPDO type written while OPERATIONAL
  goes after the RPDO latches: that SYNC's TPDO then shows the controlword just latched.
* TPDO transmission types 2..240 transmit on every SYNC after the n-th (the counter never
  resets); 1 and 0 are right.
* on NMT start durand resets the COB-IDs of PDOs 1-4 to the defaults (0x180/0x200 +
  0x100 n + id), whatever was written to 1400h/1800h sub 1 (the OD keeps the written value).
* NMT reset node / reset communication reset no object (PDO mappings, 1016h, 1017h stay);
  we restart the 402 application on reset node.
* motion, quick stop ramps and the measured period advance on SYNC only (no own clock):
  without SYNC a quick stop ramp does not progress (at rest it completes at once).
"""
from __future__ import annotations

import enum
import heapq
import itertools
import logging
import math
import re
import threading
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import can
from durand import Array, CANBusNetwork, Node, Record, Variable
from durand.datatypes import DatatypeEnum as DT
from durand.network import NetworkABC, NodeListener
from durand.node import NodeCapabilities
from durand.scheduler import AbstractScheduler, get_scheduler, set_scheduler
from durand.services.nmt import StateEnum
from durand.services.sdo.server import SDODomainAbort

__all__ = ['DurandDrive', 'State402', 'LOCK', 'OBJECTS', 'ObjectSpec', 'fix_durand_eds']

log = logging.getLogger(__name__)

#: one lock for everything durand does in this process (all drives, durand's timers)
LOCK = threading.RLock()

#: CiA 301 SDO abort codes used here
ABORT_NO_OBJECT = 0x06020000          # object does not exist in the object dictionary
ABORT_NOT_MAPPABLE = 0x06040041       # object cannot be mapped to the PDO
ABORT_PDO_LENGTH = 0x06040042         # number and length of mapped objects exceed PDO length
ABORT_VALUE_RANGE = 0x06090030        # invalid value for parameter (download only)
ABORT_CANNOT_STORE = 0x08000020       # data cannot be transferred or stored (durand's default)


# ---------------------------------------------------------------------------- scheduler

class _ThreadScheduler(AbstractScheduler):
    """durand's timers on one daemon thread; each callback runs under :data:`LOCK`.

    Entries are cancelled lazily (a flag checked under the lock right before the call), so
    ``cancel`` under :data:`LOCK` guarantees the callback does not run afterwards: durand's
    heartbeat producer re-arms itself from inside its callback, and cancelling it from
    another thread without that guarantee leaks a second, uncancellable heartbeat chain.
    """

    def __init__(self) -> None:
        self._cond = threading.Condition(threading.Lock())
        self._heap: list[list[Any]] = []
        self._seq = itertools.count()
        self._thread: threading.Thread | None = None

    def add(self, delay: float, callback: Callable, args: tuple = (), kwargs: dict | None = None):
        entry = [time.monotonic() + max(0.0, float(delay)), next(self._seq), callback, tuple(args),
                 dict(kwargs or {}), False]
        with self._cond:
            heapq.heappush(self._heap, entry)
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, name='durand-scheduler', daemon=True)
                self._thread.start()
            self._cond.notify()
        return entry

    def cancel(self, entry) -> None:
        if entry is not None:
            entry[5] = True

    @property
    def lock(self):
        return LOCK

    def _run(self) -> None:
        while True:
            with self._cond:
                while True:
                    while self._heap and self._heap[0][5]:
                        heapq.heappop(self._heap)
                    if not self._heap:
                        self._cond.wait()
                        continue
                    wait = self._heap[0][0] - time.monotonic()
                    if wait <= 0:
                        entry = heapq.heappop(self._heap)
                        break
                    self._cond.wait(wait)
            with LOCK:
                if entry[5]:
                    continue
                try:
                    entry[2](*entry[3], **entry[4])
                except Exception:  # noqa: BLE001 - a timer must not end the thread
                    log.exception('durand timer %r failed', entry[2])


_SCHEDULER: _ThreadScheduler | None = None


def _scheduler() -> _ThreadScheduler:
    """Install the threaded scheduler as durand's (process-wide) scheduler, once."""
    global _SCHEDULER
    with LOCK:
        if _SCHEDULER is None:
            _SCHEDULER = _ThreadScheduler()
        if get_scheduler() is not _SCHEDULER:
            set_scheduler(_SCHEDULER)
        return _SCHEDULER


# ---------------------------------------------------------------------------- networks

class _DriveNetwork(CANBusNetwork):
    """durand's python-can network, with the frame callbacks run under :data:`LOCK`, the
    frames sent during construction held until :meth:`open`, and a fast-stopping notifier.
    """

    def __init__(self, bus: can.BusABC, *, poll: float = 0.02) -> None:
        # CANBusNetwork.__init__ with a shorter notifier timeout (durand: 1 s)
        self._bus = bus
        self._loop = None
        self.lock = threading.Lock()
        self.subscriptions: dict[int, Callable[[int, bytes], None]] = {}
        self._held: list[tuple[int, bytes]] | None = []
        self.closed = False
        self._notifier = can.Notifier(self._bus, (NodeListener(self),), poll)

    def add_subscription(self, cob_id: int, callback) -> None:
        def locked(cob: int, data: bytes, _callback=callback) -> None:
            with LOCK:
                if not self.closed:
                    _callback(cob, data)
        super().add_subscription(cob_id, locked)

    def remove_subscription(self, cob_id: int, callback=None) -> None:  # durand passes callback=
        with self.lock:
            self.subscriptions.pop(cob_id, None)
            self._update_filters()

    def send(self, cob_id: int, msg: bytes) -> None:
        with LOCK:
            if self.closed:
                return
            if self._held is not None:
                self._held.append((cob_id, bytes(msg)))
                return
        try:
            super().send(cob_id, msg)
        except can.CanError as exc:
            log.debug('durand drive: send %03Xh failed: %s', cob_id, exc)

    def open(self) -> None:
        """Send the frames held so far (in order), then send at once."""
        with LOCK:
            held, self._held = self._held or [], None
            for cob_id, data in held:
                super().send(cob_id, data)

    def stop(self) -> None:
        with LOCK:
            self.closed = True
        self._notifier.stop(timeout=2.0)


class _NullNetwork(NetworkABC):
    """A network for a node that only exports its EDS."""

    def add_subscription(self, cob_id: int, callback) -> None:
        pass

    def remove_subscription(self, cob_id: int, callback=None) -> None:
        pass

    def send(self, cob_id: int, msg: bytes) -> None:
        pass


# ---------------------------------------------------------------------------- object dictionary

@dataclass(frozen=True)
class ObjectSpec:
    """One object of the drive: a VAR (``subs`` empty) or a RECORD / ARRAY of ``subs``
    ``(sub, name, datatype, access, default, pdo_mappable)``."""

    index: int
    name: str
    datatype: DT | None = None
    access: str = 'rw'
    default: int | None = 0
    mappable: bool = False
    subs: tuple[tuple[int, str, DT, str, int, bool], ...] = ()
    kind: str = 'var'                    # 'var', 'record', 'array'


#: 402 objects always present (``without`` may not remove them)
MANDATORY = frozenset({0x1000, 0x6040, 0x6041, 0x6064})

#: the drive's objects beyond what durand's Node defines itself (1000h is durand's,
#: replaced for its value; 1001h, 1005h, 1014h, 1015h, 1017h, 1018h, 1200h, 1400h-1403h,
#: 1600h-1603h, 1800h-1803h, 1A00h-1A03h, 1008h-100Ah, 1021h, 1022h are durand's)
OBJECTS: tuple[ObjectSpec, ...] = (
    ObjectSpec(0x1000, 'Device type', DT.UNSIGNED32, 'ro', 0x00020192),
    ObjectSpec(0x1006, 'Communication cycle period', DT.UNSIGNED32, 'rw', 0),
    ObjectSpec(0x1016, 'Consumer heartbeat time', kind='array',
               subs=((1, 'Consumer heartbeat time 1', DT.UNSIGNED32, 'rw', 0, False),)),
    ObjectSpec(0x603F, 'Error code', DT.UNSIGNED16, 'ro', 0, True),
    ObjectSpec(0x6007, 'Abort connection option code', DT.INTEGER16, 'rw', 1),
    ObjectSpec(0x6040, 'Controlword', DT.UNSIGNED16, 'rw', 0, True),
    ObjectSpec(0x6041, 'Statusword', DT.UNSIGNED16, 'ro', 0, True),
    ObjectSpec(0x605A, 'Quick stop option code', DT.INTEGER16, 'rw', 2),
    ObjectSpec(0x6060, 'Modes of operation', DT.INTEGER8, 'rw', 0, True),
    ObjectSpec(0x6061, 'Modes of operation display', DT.INTEGER8, 'ro', 0, True),
    ObjectSpec(0x6062, 'Position demand value', DT.INTEGER32, 'ro', 0, True),
    ObjectSpec(0x6064, 'Position actual value', DT.INTEGER32, 'ro', 0, True),
    ObjectSpec(0x6065, 'Following error window', DT.UNSIGNED32, 'rw', 10000),
    ObjectSpec(0x606C, 'Velocity actual value', DT.INTEGER32, 'ro', 0, True),
    ObjectSpec(0x607A, 'Target position', DT.INTEGER32, 'rw', 0, True),
    ObjectSpec(0x607C, 'Home offset', DT.INTEGER32, 'rw', 0),
    ObjectSpec(0x607D, 'Software position limit', kind='record',
               subs=((1, 'Min position limit', DT.INTEGER32, 'rw', 0, False),
                     (2, 'Max position limit', DT.INTEGER32, 'rw', 0, False))),
    ObjectSpec(0x607F, 'Max profile velocity', DT.UNSIGNED32, 'rw', None),
    ObjectSpec(0x6083, 'Profile acceleration', DT.UNSIGNED32, 'rw', None),
    ObjectSpec(0x6084, 'Profile deceleration', DT.UNSIGNED32, 'rw', None),
    ObjectSpec(0x6085, 'Quick stop deceleration', DT.UNSIGNED32, 'rw', None),
    ObjectSpec(0x6098, 'Homing method', DT.INTEGER8, 'rw', 0),
    ObjectSpec(0x60B1, 'Velocity offset', DT.INTEGER32, 'rw', 0, True),
    ObjectSpec(0x60C2, 'Interpolation time period', kind='record',
               subs=((1, 'Interpolation time period value', DT.UNSIGNED8, 'rw', 1, False),
                     (2, 'Interpolation time index', DT.INTEGER8, 'rw', -3, False))),
    ObjectSpec(0x60F4, 'Following error actual value', DT.INTEGER32, 'ro', 0, True),
    # bit 5 homing (hm), bit 7 cyclic synchronous position (csp)
    ObjectSpec(0x6502, 'Supported drive modes', DT.UNSIGNED32, 'ro', (1 << 7) | (1 << 5)),
)

#: the mapping arrays durand creates (MinimalNode: 4 RPDOs, 4 TPDOs)
_N_PDOS = 4
_CAPABILITIES = NodeCapabilities(sdo_servers=1, rpdos=_N_PDOS, tpdos=_N_PDOS)


class State402(enum.Enum):
    """CiA 402 device control states with their statusword bits 0-3, 5, 6
    (CiA 402-2 table 30; 'x' bits written as 0)."""

    NOT_READY_TO_SWITCH_ON = 0x0000
    SWITCH_ON_DISABLED = 0x0040
    READY_TO_SWITCH_ON = 0x0021
    SWITCHED_ON = 0x0023
    OPERATION_ENABLED = 0x0027
    QUICK_STOP_ACTIVE = 0x0007
    FAULT_REACTION_ACTIVE = 0x000F
    FAULT = 0x0008


_S = State402
_POWERED = frozenset({_S.READY_TO_SWITCH_ON, _S.SWITCHED_ON, _S.OPERATION_ENABLED,
                      _S.QUICK_STOP_ACTIVE})

# controlword commands (bit 7 = 0), CiA 402-2 table 27
_DISABLE_VOLTAGE, _QUICK_STOP, _SHUTDOWN, _SWITCH_ON, _ENABLE = range(5)
_TRANSITIONS = {
    (_S.SWITCH_ON_DISABLED, _SHUTDOWN): _S.READY_TO_SWITCH_ON,           # 2
    (_S.READY_TO_SWITCH_ON, _SWITCH_ON): _S.SWITCHED_ON,                 # 3
    (_S.READY_TO_SWITCH_ON, _ENABLE): _S.OPERATION_ENABLED,              # 3 + 4
    (_S.READY_TO_SWITCH_ON, _DISABLE_VOLTAGE): _S.SWITCH_ON_DISABLED,    # 7
    (_S.READY_TO_SWITCH_ON, _QUICK_STOP): _S.SWITCH_ON_DISABLED,         # 7
    (_S.SWITCHED_ON, _ENABLE): _S.OPERATION_ENABLED,                     # 4
    (_S.SWITCHED_ON, _SHUTDOWN): _S.READY_TO_SWITCH_ON,                  # 6
    (_S.SWITCHED_ON, _DISABLE_VOLTAGE): _S.SWITCH_ON_DISABLED,           # 10
    (_S.SWITCHED_ON, _QUICK_STOP): _S.SWITCH_ON_DISABLED,                # 10
    (_S.OPERATION_ENABLED, _SWITCH_ON): _S.SWITCHED_ON,                  # 5
    (_S.OPERATION_ENABLED, _SHUTDOWN): _S.READY_TO_SWITCH_ON,            # 8
    (_S.OPERATION_ENABLED, _DISABLE_VOLTAGE): _S.SWITCH_ON_DISABLED,     # 9
    (_S.OPERATION_ENABLED, _QUICK_STOP): _S.QUICK_STOP_ACTIVE,           # 11
    (_S.QUICK_STOP_ACTIVE, _DISABLE_VOLTAGE): _S.SWITCH_ON_DISABLED,     # 12
    # QUICK STOP ACTIVE + enable operation -> OPERATION ENABLED (16): once stopped, 605Ah 5..8
}

_SW_VOLTAGE = 1 << 4
_SW_WARNING = 1 << 7
_SW_REMOTE = 1 << 9
_SW_TARGET_REACHED = 1 << 10
_SW_LIMIT = 1 << 11
_SW_12 = 1 << 12
_SW_13 = 1 << 13

MODE_HOMING = 6
MODE_CSP = 8
_MODES = frozenset({0, MODE_HOMING, MODE_CSP})

EMCY_HEARTBEAT = 0x8130
EMCY_FOLLOWING_ERROR = 0x8611


def _command(cw: int) -> int:
    """The device control command of a controlword with bit 7 = 0 (CiA 402-2 table 27)."""
    if not cw & 0x02:
        return _DISABLE_VOLTAGE               # x x 0 x
    if not cw & 0x04:
        return _QUICK_STOP                    # x 0 1 x
    if not cw & 0x01:
        return _SHUTDOWN                      # 0 1 1 0
    if not cw & 0x08:
        return _SWITCH_ON                     # 0 1 1 1 (also: disable operation)
    return _ENABLE                            # 1 1 1 1


def _parse_object(spec: tuple[int, int] | str | None) -> tuple[int, int] | None:
    if spec is None:
        return None
    if isinstance(spec, str):
        index, _, sub = spec.partition(':')
        return int(index, 16 if not index.lower().startswith('0x') else 0), int(sub or '0', 0)
    index, sub = spec
    return int(index), int(sub)


# ---------------------------------------------------------------------------- the drive

class DurandDrive:
    """A CiA 402 servo drive on a durand ``Node`` (see the module docstring).

    :param channel: python-can channel (a unique virtual channel per test).
    :param node_id: CANopen node id 1..127.
    :param interface: python-can interface (``'virtual'``).
    :param without: indices of optional objects to leave out (e.g. ``(0x60B1, 0x1006)``);
        1000h, 6040h, 6041h, 6064h cannot be left out.
    :param load_cell: where the load cell input is: ``(index, sub)`` or ``'0x2100:1'``;
        sub 0 makes it a VAR, sub n >= 1 a RECORD whose sub n is the input; ``None``: none.
    :param counts_per_m: encoder counts per metre (load cell spring and :attr:`position_m`).
    :param position_m: the actuator's true position at power-up (m).
    :param absolute_encoder: 6064h is the true position from power-up on (homed); by
        default (incremental encoder) 6064h reads 0 at power-up and after NMT reset node.
    :param kp: position loop gain (1/s).
    :param v_max: speed limit (counts/s); 607Fh lowers it when non-zero (607Fh defaults
        to it).
    :param acceleration: default of 6083h-6085h (counts/s^2); quick stop ramps use them.
    :param heartbeat_ms: default producer heartbeat time 1017h (0: none until written).
    :param stiffness: spring rate the load cell reads (N/m); ``rest_position_m`` where the
        spring is relaxed (default: the power-up position); ``n_per_count`` N per count.
    :param reject_mapping: objects (index or ``(index, sub)``) the EDS calls PDO-mappable
        but durand refuses to map: a validate callback on the mapping entries raises, and
        durand aborts the SDO download with :attr:`reject_abort_code`.
    :param reject_abort_code: ``None`` (default): the validate callback raises a plain
        exception and durand answers its generic :attr:`REJECT_ABORT_CODE` (08000020h); a
        code: it raises durand's ``SDODomainAbort(code)`` (e.g. 06040041h).
    :param strict_mapping: abort mapping entries of missing / unmappable objects and PDOs
        longer than 8 bytes, as a real drive does (durand alone accepts them and fails at
        NMT start).
    :param following_error_fault: |607Ah - 6064h| > 6065h in CSP is a FAULT (EMCY 8611h);
        by default only statusword bit 13.
    :param bus_kwargs: more arguments for ``can.Bus``.
    """

    #: abort code durand sends when a validate callback raises a plain exception
    REJECT_ABORT_CODE = ABORT_CANNOT_STORE
    DEVICE_TYPE = 0x00020192
    MANDATORY = MANDATORY

    def __init__(self, channel: str, node_id: int = 1, *, interface: str = 'virtual',
                 without: Iterable[int] = (), load_cell: tuple[int, int] | str | None = (0x2100, 1),
                 counts_per_m: float = 8192 / 0.001, position_m: float = 0.0,
                 absolute_encoder: bool = False, kp: float = 2 * math.pi * 30.0,
                 v_max: float = 65e-3 * 8192 / 0.001, acceleration: float = 1.0 * 8192 / 0.001,
                 heartbeat_ms: int = 50, stiffness: float = 5000.0,
                 rest_position_m: float | None = None, n_per_count: float = 0.01,
                 reject_mapping: Iterable[int | tuple[int, int]] = (),
                 reject_abort_code: int | None = None, strict_mapping: bool = True,
                 following_error_fault: bool = False,
                 bus_kwargs: dict[str, Any] | None = None) -> None:
        if not 1 <= node_id <= 127:
            raise ValueError(f'node id {node_id} outside 1..127')
        self.channel = channel
        self.node_id = int(node_id)
        self.interface = interface
        self.bus_kwargs = dict(bus_kwargs or {})
        self.without = frozenset(int(i) for i in without)
        bad = self.without & MANDATORY
        if bad:
            raise ValueError(f'cannot leave out {", ".join(f"{i:04X}h" for i in sorted(bad))}')
        self.load_cell = _parse_object(load_cell)
        if self.load_cell and self.load_cell[0] in {o.index for o in OBJECTS}:
            raise ValueError(f'the load cell cannot be at {self.load_cell[0]:04X}h: a 402 object is there')
        known = {o.index for o in OBJECTS} | ({self.load_cell[0]} if self.load_cell else set())
        unknown = self.without - known
        if unknown:
            raise ValueError(f'no optional object {", ".join(f"{i:04X}h" for i in sorted(unknown))}')
        self.counts_per_m = float(counts_per_m)
        self.absolute_encoder = bool(absolute_encoder)
        self.kp = float(kp)
        self.v_max = float(v_max)
        self.acceleration = float(acceleration)
        self.heartbeat_ms = int(heartbeat_ms)
        self.stiffness = float(stiffness)
        self.rest_position_m = float(position_m if rest_position_m is None else rest_position_m)
        self.n_per_count = float(n_per_count)
        self.reject_mapping = frozenset(
            (r, 0) if isinstance(r, int) else (int(r[0]), int(r[1])) for r in reject_mapping)
        self._reject_code = reject_abort_code
        self.strict_mapping = bool(strict_mapping)
        self.following_error_fault = bool(following_error_fault)
        # the physics (true position in counts) survives power cycles
        self._x = float(position_m) * self.counts_per_m
        self._bus: can.BusABC | None = None
        self._network: _DriveNetwork | None = None
        self.node: Node | None = None
        self._mappable: set[tuple[int, int]] = set()
        self._power_up()

    # ------------------------------------------------------------------ public API

    @property
    def reject_abort_code(self) -> int:
        """The SDO abort code a rejected mapping entry gets."""
        return self.REJECT_ABORT_CODE if self._reject_code is None else self._reject_code

    @property
    def running(self) -> bool:
        return self.node is not None

    def start(self) -> DurandDrive:
        """Power on: open the bus, build the durand node, send the boot-up message, then
        heartbeats per 1017h. Idempotent."""
        _scheduler()
        with LOCK:
            if self.node is not None:
                return self
            self._power_up()
            bus = can.Bus(interface=self.interface, channel=self.channel, **self.bus_kwargs)
            network = _DriveNetwork(bus)
            try:
                node = Node(network, self.node_id, capabilities=_CAPABILITIES)  # boot-up: held
                self._build_od(node)
                self._install(node, network)
                self.node, self._network, self._bus = node, network, bus
                self._publish()
                if self.heartbeat_ms:
                    # the boot-up message is the first heartbeat: durand's producer sends one
                    # at once when 1017h is written, so write it one period later
                    self._hb_start = get_scheduler().add(
                        self.heartbeat_ms * 1e-3, self._start_heartbeat, args=(node,))
            except BaseException:
                network.stop()
                bus.shutdown()
                self.node = self._network = self._bus = None
                raise
            network.open()
        return self

    def stop(self) -> None:
        """Power off: no frame in or out any more, the bus closed. Idempotent. The actuator
        stays where it is (:attr:`position_m`)."""
        with LOCK:
            node, network, bus = self.node, self._network, self._bus
            if node is None:
                return
            self.node = self._network = self._bus = None
            get_scheduler().cancel(self._hb_timer)
            get_scheduler().cancel(self._hb_start)
            self._hb_timer = self._hb_start = None
            network.closed = True
            try:
                node.object_dictionary.write(0x1017, 0, 0)       # cancels durand's heartbeat timer
            except Exception:  # noqa: BLE001
                pass
            self._v = 0.0
        network.stop()
        bus.shutdown()

    def __enter__(self) -> DurandDrive:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def position_m(self) -> float:
        """The actuator's true position (m), whatever the encoder reads."""
        with LOCK:
            return self._x / self.counts_per_m

    @position_m.setter
    def position_m(self, value: float) -> None:
        """Move the actuator by hand (the encoder follows)."""
        with LOCK:
            self._x = float(value) * self.counts_per_m
            if self.node is not None:
                self._publish()

    @property
    def position_counts(self) -> int:
        """What 6064h reads (encoder counts)."""
        with LOCK:
            return self._encoder()

    @property
    def velocity_counts(self) -> float:
        with LOCK:
            return self._v

    @property
    def force_n(self) -> float:
        """The spring force the load cell measures (N, before quantisation)."""
        with LOCK:
            return self._force()

    @property
    def load_cell_counts(self) -> int:
        with LOCK:
            return self._load_cell_counts()

    def set_spring(self, *, stiffness: float | None = None, rest_position_m: float | None = None,
                   n_per_count: float | None = None) -> None:
        with LOCK:
            if stiffness is not None:
                self.stiffness = float(stiffness)
            if rest_position_m is not None:
                self.rest_position_m = float(rest_position_m)
            if n_per_count is not None:
                self.n_per_count = float(n_per_count)
            if self.node is not None:
                self._publish()

    @property
    def state(self) -> State402:
        with LOCK:
            return self._state

    @property
    def statusword(self) -> int:
        with LOCK:
            return self._statusword()

    @property
    def nmt_state(self) -> StateEnum | None:
        with LOCK:
            return None if self.node is None else StateEnum(self.node.nmt.state)

    @property
    def homed(self) -> bool:
        with LOCK:
            return self._homed

    @property
    def sync_count(self) -> int:
        """SYNCs received since power-up."""
        with LOCK:
            return self._syncs

    @property
    def last_dt(self) -> float:
        """The period (s) the last SYNC step integrated over."""
        with LOCK:
            return self._dt

    def read_od(self, index: int, subindex: int = 0):
        """The object's value in durand's object dictionary (running drive)."""
        with LOCK:
            return self._od().read(index, subindex)

    def write_od(self, index: int, subindex: int, value) -> None:
        """Write the object dictionary as the drive itself would (no SDO, no abort)."""
        with LOCK:
            self._od().write(index, subindex, value)

    def inject_fault(self, code: int = 0x5000, *, error_register: int = 0x01) -> None:
        """A drive fault (FAULT REACTION ACTIVE -> FAULT, EMCY ``code``); a fault reset leaves
        FAULT only after :meth:`clear_fault`."""
        with LOCK:
            self._fault(code, error_register, cause='injected')

    def clear_fault(self) -> None:
        """The injected fault's cause is gone (a fault reset can now leave FAULT)."""
        with LOCK:
            self._fault_causes.discard('injected')

    # ------------------------------------------------------------------ EDS

    def eds_text(self) -> str:
        """The drive's EDS, as durand exports it from a pristine node with these options,
        with durand's format errors fixed (ObjectType 8/9 swapped, decimal sub-indices,
        PDOMapping by index range instead of per object)."""
        with LOCK:
            node = Node(_NullNetwork(), self.node_id, capabilities=_CAPABILITIES)
            mappable = self._build_od(node)
            node.eds.file_info.FileName = 'durand_cia402_drive.eds'
            node.eds.file_info.Description = 'CiA 402 servo drive on durand (brace_control tests)'
            node.eds.device_info.VendorName = 'brace_control tests'
            raw = node.eds.content
            return fix_durand_eds(raw, node.object_dictionary, mappable)

    def write_eds(self, path: str | Path) -> Path:
        path = Path(path)
        path.write_text(self.eds_text())
        return path

    # ------------------------------------------------------------------ construction

    def _power_up(self) -> None:
        """Power-up: the application's state (not the physics) and the heartbeat consumer."""
        self._reset_application()
        self._hb_lost = False
        self._hb_timer = None
        self._hb_start = None
        self._hb_cob: int | None = None
        self._last_sync: float | None = None
        self._dt = 0.0
        self._syncs = 0

    def _reset_application(self) -> None:
        """The 402 application restarts (power-up, NMT reset node): SWITCH ON DISABLED
        (transitions 0 and 1), an incremental encoder reads 0, not homed, no fault."""
        self._state = _S.SWITCH_ON_DISABLED
        self._cw_prev = 0
        self._v = 0.0
        self._offset = 0.0 if self.absolute_encoder else -round(self._x)
        self._homed = self.absolute_encoder
        self._homing = 'idle'                      # 'idle', 'attained', 'error'
        self._limited = False
        self._fault_causes: set[str] = set()
        self._enable_after_stop = False

    def _specs(self) -> list[ObjectSpec]:
        specs = [o for o in OBJECTS if o.index not in self.without]
        if self.load_cell and self.load_cell[0] not in self.without:
            index, sub = self.load_cell
            if sub == 0:
                specs.append(ObjectSpec(index, 'Load cell analog input', DT.INTEGER16, 'ro', 0, True))
            else:
                specs.append(ObjectSpec(index, 'Analog input', kind='record', subs=(
                    (sub, 'Load cell analog input', DT.INTEGER16, 'ro', 0, True),)))
        return specs

    def _build_od(self, node: Node) -> set[tuple[int, int]]:
        """Add the 402 objects to durand's dictionary; returns the PDO-mappable (index, sub)."""
        od = node.object_dictionary
        defaults = {0x607F: round(self.v_max), 0x6083: round(self.acceleration),
                    0x6084: round(self.acceleration), 0x6085: round(self.acceleration)}
        mappable: set[tuple[int, int]] = set()
        for spec in self._specs():
            if not spec.subs:
                default = defaults.get(spec.index, spec.default)
                od[spec.index] = Variable(spec.datatype, spec.access, default, name=spec.name)
                if spec.mappable:
                    mappable.add((spec.index, 0))
                continue
            if spec.kind == 'array':
                (sub, name, dtype, access, default, pdo), = spec.subs
                od[spec.index] = Array(Variable(dtype, access, default, name=name),
                                       length=len(spec.subs), name=spec.name)
            else:
                rec = Record(name=spec.name)
                for sub, name, dtype, access, default, pdo in spec.subs:
                    rec[sub] = Variable(dtype, access, default, name=name)
                    if pdo:
                        mappable.add((spec.index, sub))
                od[spec.index] = rec
        # durand's 1017h has no default: give it ours (its update callback stays, keyed by
        # (index, sub)); the producer starts when it is written
        od[0x1017] = Variable(DT.UNSIGNED16, 'rw', self.heartbeat_ms, name='Producer heartbeat time')
        self._mappable = mappable
        for n in range(_N_PDOS):
            for base, rx in ((0x1600, True), (0x1A00, False)):
                for sub in range(1, 9):
                    od.validate_callbacks[(base + n, sub)].add(
                        lambda value, rx=rx, mux=(base + n, sub), od=od:
                        self._validate_entry(od, mux, value, rx))
                od.validate_callbacks[(base + n, 0)].add(
                    lambda value, index=base + n, od=od: self._validate_count(od, index, value))
        return mappable

    def _install(self, node: Node, network: _DriveNetwork) -> None:
        od = node.object_dictionary
        # first SYNC callback: the motion step runs before durand's TPDOs of the SYNC
        # (registered when their transmission type is written) and RPDO latches (registered
        # at NMT start), which run in registration order
        node.sync.callbacks.add(self._on_sync)
        od.download_callbacks[(0x6040, 0)].add(self._on_controlword)
        if 0x6060 in od:
            od.validate_callbacks[(0x6060, 0)].add(self._validate_mode)
            od.download_callbacks[(0x6060, 0)].add(self._on_mode)
        if 0x1016 in od:
            od.download_callbacks[(0x1016, 1)].add(self._on_consumer_heartbeat)
        # 1021h "Store EDS": durand serves its raw export; serve the fixed one
        eds = self.eds_text().encode()
        od.set_read_callback(0x1021, 0, lambda: eds)
        # NMT frames: durand's slave does the work; we see reset node first
        network.add_subscription(0x000, lambda cob, data, nmt=node.nmt: self._on_nmt(nmt, cob, data))

    # ------------------------------------------------------------------ object dictionary helpers

    def _od(self):
        if self.node is None:
            raise RuntimeError('the drive is not running (start() first)')
        return self.node.object_dictionary

    def _has(self, index: int, sub: int = 0) -> bool:
        if self.node is None:
            return False
        od = self.node.object_dictionary
        if index not in od:
            return False
        obj = od[index]
        return isinstance(obj, Variable) or sub in obj

    def _get(self, index: int, sub: int = 0, default: int = 0):
        return self.node.object_dictionary.read(index, sub) if self._has(index, sub) else default

    def _put(self, index: int, sub: int, value: int) -> None:
        """Write our own value (clamped to the type's range) if the object exists and the
        value changed (a write fires durand's TPDO update callbacks)."""
        if not self._has(index, sub):
            return
        od = self.node.object_dictionary
        var = od.lookup(index, sub if not isinstance(od[index], Variable) else None)
        value = int(min(max(value, var.minimum), var.maximum))
        if od.has_value(index, sub) and od.read(index, sub) == value:
            return
        od.write(index, sub, value)

    # ------------------------------------------------------------------ mapping validation

    def _validate_entry(self, od, mux: tuple[int, int], value: int, rx: bool) -> None:
        """A write of PDO mapping entry ``mux``: refuse what a real drive refuses."""
        if value == 0:
            return
        index, sub, bits = value >> 16, (value >> 8) & 0xFF, value & 0xFF
        if (index, sub) in self.reject_mapping:
            if self._reject_code is None:
                # a plain exception: durand answers 08000020h (REJECT_ABORT_CODE)
                raise ValueError(f'{index:04X}h:{sub} refused for PDO mapping')
            raise SDODomainAbort(self._reject_code, mux)
        if not self.strict_mapping:
            return
        obj = od[index] if index in od else None
        if obj is None or (isinstance(obj, Variable) and sub != 0) or \
                (not isinstance(obj, Variable) and sub not in obj):
            raise SDODomainAbort(ABORT_NO_OBJECT, mux)
        var = od.lookup(index, sub)
        if (index, sub) not in self._mappable or var.size is None or bits != 8 * var.size \
                or (rx and not var.writable) or (not rx and not var.readable):
            raise SDODomainAbort(ABORT_NOT_MAPPABLE, mux)

    def _validate_count(self, od, index: int, count: int) -> None:
        """A write of a mapping's sub 0 (number of entries): at most 64 bits."""
        if not self.strict_mapping or count == 0:
            return
        if count > 8:
            raise SDODomainAbort(0x06090031, (index, 0))           # value too high
        bits = 0
        for sub in range(1, count + 1):
            entry = od.read(index, sub)
            if entry == 0:
                raise SDODomainAbort(ABORT_NOT_MAPPABLE, (index, 0))
            bits += entry & 0xFF
        if bits > 64:
            raise SDODomainAbort(ABORT_PDO_LENGTH, (index, 0))

    def _validate_mode(self, value: int) -> None:
        if value not in _MODES:
            raise SDODomainAbort(ABORT_VALUE_RANGE, (0x6060, 0))

    # ------------------------------------------------------------------ 402 device

    def _encoder(self) -> int:
        return round(self._x + self._offset)

    def _force(self) -> float:
        return self.stiffness * (self._x / self.counts_per_m - self.rest_position_m)

    def _load_cell_counts(self) -> int:
        counts = round(self._force() / self.n_per_count) if self.n_per_count else 0
        return max(-32768, min(32767, counts))

    def _mode(self) -> int:
        return self._get(0x6061, 0, MODE_CSP) if self._has(0x6061) else self._get(0x6060, 0, MODE_CSP)

    def _following_error(self) -> int:
        return self._get(0x607A) - self._encoder()

    def _window(self) -> int:
        return self._get(0x6065, 0, 0xFFFFFFFF)

    def _statusword(self) -> int:
        st = self._state
        sw = st.value | _SW_REMOTE
        if st in _POWERED:
            sw |= _SW_VOLTAGE
        if self._hb_lost and st is not _S.FAULT:
            sw |= _SW_WARNING
        if self._limited:
            sw |= _SW_LIMIT
        mode = self._mode()
        if mode == MODE_CSP and st is _S.OPERATION_ENABLED:
            sw |= _SW_12                                       # drive follows the command value
            window = self._window()
            if window != 0xFFFFFFFF:
                sw |= _SW_TARGET_REACHED if abs(self._following_error()) <= window else _SW_13
        elif mode == MODE_HOMING:
            # bits 13 12 10: 0 0 1 not started / interrupted; 0 1 1 completed; 1 0 1 error, v = 0
            sw |= {'idle': _SW_TARGET_REACHED, 'attained': _SW_12 | _SW_TARGET_REACHED,
                   'error': _SW_13 | _SW_TARGET_REACHED}[self._homing]
        return sw

    def _publish(self) -> None:
        """Our values into durand's dictionary (each write updates mapped TPDOs)."""
        if self.node is None:
            return
        enc = self._encoder()
        self._put(0x6064, 0, enc)
        self._put(0x606C, 0, round(self._v))
        self._put(0x60F4, 0, self._following_error() if self._state is _S.OPERATION_ENABLED else 0)
        if self.load_cell:
            self._put(*self.load_cell, self._load_cell_counts())
        self._put(0x6041, 0, self._statusword())

    def _enter(self, new: State402) -> None:
        old = self._state
        if new is old:
            return
        self._state = new
        if new is _S.QUICK_STOP_ACTIVE:
            self._enable_after_stop = False
            if self._v == 0.0:
                self._quick_stop_step(0.0)           # at rest: the quick stop is complete
        elif new is not _S.OPERATION_ENABLED:
            self._v = 0.0                    # disabled: the brake holds
        if new is _S.OPERATION_ENABLED and self._mode() == MODE_CSP:
            self._enter_csp()

    def _enter_csp(self) -> None:
        """Entering CSP control: target := actual, velocity offset := 0 (no jump)."""
        self._put(0x607A, 0, self._encoder())
        self._put(0x6062, 0, self._encoder())
        self._put(0x60B1, 0, 0)
        self._v = 0.0

    def _on_controlword(self, cw: int) -> None:
        prev, self._cw_prev = self._cw_prev, cw
        st = self._state
        if st is _S.FAULT:
            if cw & 0x80 and not prev & 0x80 and not self._fault_causes:
                self._enter(_S.SWITCH_ON_DISABLED)                      # 15
                self._put(0x603F, 0, 0)
                self.node.emcy.set(0x0000, 0x00)
        elif st in (_S.FAULT_REACTION_ACTIVE, _S.NOT_READY_TO_SWITCH_ON) or cw & 0x80:
            pass                                   # bit 7 set: only its rising edge in FAULT counts
        else:
            cmd = _command(cw)
            if st is _S.QUICK_STOP_ACTIVE and cmd != _DISABLE_VOLTAGE:
                # 16 once stopped (605Ah 5..8); the quick stop ramp runs on the SYNC steps
                self._enable_after_stop = cmd == _ENABLE and self._get(0x605A, 0, 2) in (5, 6, 7, 8)
                if self._enable_after_stop and self._v == 0.0:
                    self._enter(_S.OPERATION_ENABLED)                   # 16
            else:
                new = _TRANSITIONS.get((st, cmd))
                if new is not None:
                    self._enter(new)
        # homing: rising edge of bit 4 in OPERATION ENABLED, mode 6
        if cw & 0x10 and not prev & 0x10 and self._state is _S.OPERATION_ENABLED \
                and self._mode() == MODE_HOMING:
            self._home()
        self._publish()

    def _home(self) -> None:
        method = self._get(0x6098, 0, 0)
        if method in (35, 37):                       # homing on the current position
            self._offset = self._get(0x607C) - self._x
            self._homed = True
            self._homing = 'attained'
            self._put(0x6062, 0, self._encoder())
            self._put(0x607A, 0, self._encoder())
        else:
            self._homing = 'error'

    def _on_mode(self, mode: int) -> None:
        old = self._mode()
        self._put(0x6061, 0, mode)
        if mode == MODE_HOMING and old != MODE_HOMING:
            self._homing = 'idle'
        if mode == MODE_CSP and old != MODE_CSP and self._state is _S.OPERATION_ENABLED:
            self._enter_csp()
        self._publish()

    def _fault(self, code: int, error_register: int, *, cause: str) -> None:
        self._fault_causes.add(cause)
        if self._state in (_S.FAULT, _S.FAULT_REACTION_ACTIVE):
            return
        self._enter(_S.FAULT_REACTION_ACTIVE)                           # 13
        self._put(0x603F, 0, code)
        if self.node is not None:
            self.node.emcy.set(code, error_register)
        self._v = 0.0                                # the reaction: stop at once
        self._enter(_S.FAULT)                                           # 14
        self._publish()

    # ------------------------------------------------------------------ SYNC

    def _on_sync(self) -> None:
        now = time.monotonic()
        period_us = self._get(0x1006, 0, 0)
        if period_us:
            dt = period_us * 1e-6
        elif self._last_sync is None:
            dt = 0.0
        else:
            dt = min(max(now - self._last_sync, 0.0), 0.1)
        self._last_sync = now
        self._dt = dt
        self._syncs += 1
        st = self._state
        self._limited = False
        if st is _S.OPERATION_ENABLED and self._mode() == MODE_CSP:
            self._csp_step(dt)
        elif st is _S.QUICK_STOP_ACTIVE:
            self._quick_stop_step(dt)
        else:
            self._v = 0.0
        self._publish()

    def _v_limit(self) -> float:
        limit = self.v_max
        profile = self._get(0x607F, 0, 0)
        return min(limit, float(profile)) if profile else limit

    def _csp_step(self, dt: float) -> None:
        target = self._get(0x607A)
        lo, hi = self._get(0x607D, 1), self._get(0x607D, 2)
        if self._homed and lo < hi and not lo <= target <= hi:
            target = min(max(target, lo), hi)
            self._limited = True
        self._put(0x6062, 0, target)
        goal = target - self._offset                 # in true counts
        v_ff = float(self._get(0x60B1))
        v_lim = self._v_limit()
        n = max(1, math.ceil(self.kp * dt / 0.2))
        h = dt / n
        v = self._v
        for _ in range(n):
            v = min(max(self.kp * (goal - self._x) + v_ff, -v_lim), v_lim)
            self._x += v * h
        self._v = v if dt > 0 else 0.0
        if self.following_error_fault:
            window = self._window()
            if window != 0xFFFFFFFF and abs(self._get(0x607A) - self._encoder()) > window:
                self._fault(EMCY_FOLLOWING_ERROR, 0x01, cause='following error')

    def _quick_stop_step(self, dt: float) -> None:
        option = self._get(0x605A, 0, 2)
        decel = {1: self._get(0x6084), 5: self._get(0x6084),
                 2: self._get(0x6085), 6: self._get(0x6085)}.get(option, 0)
        v = self._v
        if v != 0.0 and not decel:
            v = 0.0                                  # 0, 3, 4, 7, 8: stop at once (our choice)
        elif v != 0.0 and dt > 0:
            v_new = math.copysign(max(abs(v) - decel * dt, 0.0), v)
            self._x += 0.5 * (v + v_new) * dt
            v = v_new
        self._v = v
        if v == 0.0:
            if option in (5, 6, 7, 8):
                if self._enable_after_stop:
                    self._enter(_S.OPERATION_ENABLED)                   # 16
            else:
                self._enter(_S.SWITCH_ON_DISABLED)                      # 12 (automatic)

    # ------------------------------------------------------------------ NMT, heartbeat consumer

    def _on_nmt(self, nmt, cob: int, data: bytes) -> None:
        """NMT frames: durand's slave does the work; a reset node also restarts the 402
        application (durand resets neither the application nor the communication objects)."""
        reset_node = len(data) == 2 and data[0] == 0x81 and data[1] in (0, self.node_id)
        if reset_node:
            self._reset_application()
        nmt.handle_msg(cob, data)
        if reset_node:
            self._publish()

    def _start_heartbeat(self, node: Node) -> None:
        self._hb_start = None
        od = node.object_dictionary
        if node is self.node and not od.has_value(0x1017, 0):      # the master did not write it
            od.write(0x1017, 0, self.heartbeat_ms)

    def _on_consumer_heartbeat(self, value: int) -> None:
        master, ms = (value >> 16) & 0x7F, value & 0xFFFF
        network = self._network
        if network is None:
            return
        if self._hb_cob is not None:
            network.remove_subscription(self._hb_cob)
            self._hb_cob = None
        get_scheduler().cancel(self._hb_timer)
        self._hb_timer = None
        if master and ms and master != self.node_id:
            self._hb_cob = 0x700 + master
            network.add_subscription(self._hb_cob, self._on_master_heartbeat)

    def _on_master_heartbeat(self, cob: int, data: bytes) -> None:
        ms = self._get(0x1016, 1) & 0xFFFF
        if not ms or self.node is None:
            return
        sched = get_scheduler()
        sched.cancel(self._hb_timer)
        self._hb_timer = sched.add(ms * 1e-3, self._heartbeat_lost)
        if self._hb_lost:
            self._hb_lost = False
            self._fault_causes.discard('heartbeat')
            self._publish()

    def _heartbeat_lost(self) -> None:
        """Consumer heartbeat time elapsed (scheduler thread, under LOCK)."""
        self._hb_timer = None
        if self.node is None or self._hb_lost:
            return
        self._hb_lost = True
        option = self._get(0x6007, 0, 1)
        if option == 1:
            self._fault(EMCY_HEARTBEAT, 0x11, cause='heartbeat')
            return
        self.node.emcy.set(EMCY_HEARTBEAT, 0x11)
        st = self._state
        if option == 2 and st in _POWERED:
            self._enter(_S.SWITCH_ON_DISABLED)                          # disable voltage
        elif option == 3:
            new = _TRANSITIONS.get((st, _QUICK_STOP))
            if new is not None:
                self._enter(new)
        self._publish()


# ---------------------------------------------------------------------------- EDS fix-ups

_SECTION = re.compile(r'^\[([0-9A-Fa-f]{4})(?:sub(\d+))?\]\s*$')


def _is_pdo_mapping(index: int) -> bool:
    return 0x1600 <= index <= 0x17FF or 0x1A00 <= index <= 0x1BFF


def fix_durand_eds(text: str, od, mappable: set[tuple[int, int]]) -> str:
    """Fix durand 0.5.0's EDS export: ObjectType of RECORD (9) and ARRAY (8) swapped,
    sub-indices written in decimal (CiA 306: hex), ``PDOMapping`` by index range (< 2000h:
    0, else 1) instead of per object. ``mappable``: the (index, sub) that may be mapped.

    The PDO mapping parameters 1600h-17FFh / 1A00h-1BFFh are RECORDs in CiA 301; durand
    models them as (mutable) Arrays, and its swap happened to export them as RECORD. They
    stay RECORD: canopen's ``PdoMap.save`` iterates an ARRAY's entries up to its sub 0,
    which it has just written 0, and so would write no entry at all."""
    out = []
    current: tuple[int, int | None] | None = None
    for line in text.splitlines():
        m = _SECTION.match(line)
        if m:
            index = int(m.group(1), 16)
            sub = None if m.group(2) is None else int(m.group(2))
            current = (index, sub)
            if sub is not None:
                line = f'[{index:04X}sub{sub:X}]'
        elif current is not None and line.startswith('ObjectType=') and current[1] is None:
            obj = od[current[0]]
            if isinstance(obj, Record) or _is_pdo_mapping(current[0]):
                line = 'ObjectType=0x9'
            elif isinstance(obj, Array):
                line = 'ObjectType=0x8'
        elif current is not None and line.startswith('PDOMapping='):
            index, sub = current
            line = f'PDOMapping={int((index, sub or 0) in mappable)}'
        elif line.startswith('['):
            current = None
        out.append(line)
    return '\n'.join(out) + '\n'
