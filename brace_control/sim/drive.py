"""One simulated CiA 402 servo drive: the slave side of docs/can.md.

:class:`SimulatedDrive` is a CANopen device (CiA 301) with the CiA 402 drive profile,
independent of any transport: frames come in through :meth:`SimulatedDrive.on_frame`
and :meth:`SimulatedDrive.on_sync`, frames go out through the ``send(cob_id, data)``
callable it is given. :class:`~brace_control.sim.host.SimBus` puts drives on a python-can
bus; :class:`~brace_control.sim.brace.SimulatedBrace` adds the physics of the device.

What it implements

* CiA 301 §7.3.2 NMT slave: INITIALISING -> boot-up (0x700+id, ``00``) -> PRE-OPERATIONAL;
  start / stop / enter pre-operational / reset node / reset communication, for this id
  or for all (node id 0).
* CiA 301 §7.2.8 heartbeat producer (1017h) and consumer of the master (1016h sub1
  ``(master id << 16) | time ms``; monitoring starts with the first heartbeat received).
  On loss: EMCY 8130h and the CiA 402 abort connection option 6007h
  (0 none, 1 fault, 2 disable voltage, 3 quick stop).
* CiA 301 §7.2.4 SDO server (expedited and segmented; canopen's ``SdoServer`` on this
  device's own object dictionary, read from the EDS).
* CiA 301 §7.2.2 PDOs: 4 RPDOs (1400h-1403h / 1600h-1603h) and 4 TPDOs (1800h-1803h /
  1A00h-1A03h). Mapping changes by SDO change what a TPDO carries and how an RPDO is
  decoded. Synchronous RPDOs (type 0-240) are latched and applied on the next SYNC;
  event-driven RPDOs (254/255) are applied on reception. Synchronous TPDOs (type 1-240)
  are sent every n-th SYNC, only in OPERATIONAL; event-driven TPDOs (254/255) are sent
  when their event timer (sub5, ms) expires.
* CiA 301 §7.2.7 EMCY producer (1014h); 1001h error register; 1003h error history.
* CiA 402 state machine (§ "device control"), statusword 6041h bits exactly as CiA 402:
  0 ready to switch on, 1 switched on, 2 operation enabled, 3 fault, 4 voltage enabled,
  5 quick stop (active low), 6 switch on disabled, 7 warning, 9 remote, 10 target
  reached, 11 internal limit active, 12 operation-mode specific (CSP: drive follows the
  command value; homing: homing attained), 13 operation-mode specific (CSP: following
  error; homing: homing error).
* Modes 6060h/6061h: 8 cyclic synchronous position (CSP), 6 homing (methods 35 and 37:
  the current position becomes the home offset 607Ch; any other method: homing error).
* CSP tracking of 607Ah with the actuator's speed and acceleration limits (and 607Fh),
  software limits 607Dh (checked once homed), hard end stops (the stroke), following
  error 6065h/6066h, quick stop 605Ah/6085h, fault reaction.
* An incremental encoder: 6064h reads 0 at power-up (and after NMT reset node) until
  homed. Positions in counts inside, metres outside.

Faults and their EMCY codes (CiA 301 Table 21 / CiA 402): following error 8611h,
target outside the software position limits 8612h, heartbeat of the master lost 8130h
(error register bit 4, communication); reset (fault cleared) 0000h. A fault is latched
in FAULT until a fault reset (rising edge of controlword bit 7) *and* its cause is gone:
following error: actuator not stalled and |607Ah - 6064h| <= 6065h; limit: 607Ah back
inside 607Dh; heartbeat: master heartbeat received again; injected: cleared by
:meth:`SimulatedDrive.clear_injected_fault`.

Thread safety: every entry point takes the drive's lock (the bus receive thread and the
timer thread both call in).
"""
from __future__ import annotations

import math
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from enum import IntEnum
from pathlib import Path

import canopen
from canopen import objectdictionary as odmod
from canopen.sdo import SdoAbortedError, SdoServer

__all__ = [
    'DriveLimits', 'SimulatedDrive', 'NmtState', 'State402', 'EmcyCode',
    'MODE_CSP', 'MODE_HOMING',
]

MODE_CSP = 8
MODE_HOMING = 6

# CiA 301 SDO abort codes used here
ABORT_NOT_MAPPABLE = 0x06040041
ABORT_PDO_LENGTH = 0x06040042
ABORT_VALUE_RANGE = 0x06090030
ABORT_VALUE_HIGH = 0x06090031

_STRUCT_CODE = {
    odmod.UNSIGNED8: 'B', odmod.INTEGER8: 'b', odmod.UNSIGNED16: 'H',
    odmod.INTEGER16: 'h', odmod.UNSIGNED32: 'I', odmod.INTEGER32: 'i',
    odmod.BOOLEAN: 'B',
}


class NmtState(IntEnum):
    """CiA 301 §7.3.2 NMT states, valued as the heartbeat's state byte."""

    INITIALISING = 0x00
    STOPPED = 0x04
    OPERATIONAL = 0x05
    PRE_OPERATIONAL = 0x7F


class State402(IntEnum):
    """CiA 402 power drive system states (bits 0-3, 5, 6 of the statusword)."""

    NOT_READY_TO_SWITCH_ON = 0x0000
    SWITCH_ON_DISABLED = 0x0040
    READY_TO_SWITCH_ON = 0x0021
    SWITCHED_ON = 0x0023
    OPERATION_ENABLED = 0x0027
    QUICK_STOP_ACTIVE = 0x0007
    FAULT_REACTION_ACTIVE = 0x000F
    FAULT = 0x0008


class EmcyCode(IntEnum):
    """EMCY error codes (CiA 301 Table 21; CiA 402 Annex) the simulated drive produces."""

    NO_ERROR = 0x0000            # error reset / no error
    GENERIC = 0x1000
    HEARTBEAT = 0x8130           # life guard / heartbeat error
    BUS_OFF_RECOVERED = 0x8140
    FOLLOWING_ERROR = 0x8611
    REFERENCE_LIMIT = 0x8612     # target outside the software position limits
    POSITION_SENSOR = 0x7305     # incremental sensor 1 fault
    LOAD_CELL = 0x7300           # sensor


_ERR_REG_GENERIC = 0x01


def _error_register_bit(code: int) -> int:
    """Error register 1001h bit of an EMCY code (CiA 301 Table 47 / Table 21): 2xxxh
    current, 3xxxh voltage, 4xxxh temperature, 81xxh/82xxh communication, 86xxh/87xxh
    device profile; the generic bit 0 is set with any of them."""
    cls = code >> 12
    if cls == 0x2:
        return 0x02
    if cls == 0x3:
        return 0x04
    if cls == 0x4:
        return 0x08
    if code >> 8 in (0x81, 0x82):
        return 0x10
    if code >> 8 in (0x86, 0x87):
        return 0x20
    return 0x00

_POWERED = (State402.READY_TO_SWITCH_ON, State402.SWITCHED_ON,
            State402.OPERATION_ENABLED, State402.QUICK_STOP_ACTIVE)


@dataclass(frozen=True)
class DriveLimits:
    """The actuator behind the drive, in SI units.

    :param counts_per_m: encoder counts per metre of actuator length (8192 / 0.001).
    :param max_velocity: m/s, the actuator's top speed (Table II: 65 mm/s).
    :param max_acceleration: m/s^2.
    :param stroke_min: m, hard end stop (shortest installed length).
    :param stroke_max: m, hard end stop (longest installed length).
    :param max_force: N, rated output force (scales 6077h torque actual, per mille).
    """

    counts_per_m: float = 8192 / 0.001
    max_velocity: float = 0.065
    max_acceleration: float = 0.5
    stroke_min: float = 0.340
    stroke_max: float = 0.440
    max_force: float = 250.0


class _Pdo:
    """One PDO's communication + mapping, compiled for the hot path."""

    __slots__ = ('num', 'cob_id', 'valid', 'trans_type', 'entries', 'codec',
                 'sync_count', 'event_ms', 'next_event', 'pending')

    def __init__(self, num: int) -> None:
        self.num = num
        self.cob_id = 0
        self.valid = False
        self.trans_type = 255
        self.entries: list[tuple[int, int]] = []
        self.codec = struct.Struct('<')
        self.sync_count = 0
        self.event_ms = 0
        self.next_event = 0.0
        self.pending: bytes | None = None


class _Network:
    """The shim canopen's SdoServer sends through."""

    def __init__(self, drive: 'SimulatedDrive') -> None:
        self._drive = drive

    def send_message(self, can_id: int, data: bytes | bytearray) -> None:
        self._drive._tx(can_id, bytes(data))


class SimulatedDrive:
    """A simulated CiA 402 drive with an incremental encoder and a load-cell input (2401h).

    :param node_id: CANopen node id 1..127.
    :param eds: the drive's EDS (``config/lumbar_drive.eds``); the object dictionary of
        the device, its access types and default values.
    :param limits: the actuator (SI).
    :param initial_length_m: the actuator's physical length at power-up (the parked brace).
    :param send: ``send(cob_id, data)`` puts a frame on the bus; ``None`` until a
        :class:`~brace_control.sim.host.SimBus` attaches the drive.
    :param clock: monotonic time source (s), for heartbeats and event timers.

    The drive is inert until :meth:`power_on` (boot-up message, PRE-OPERATIONAL).
    """

    def __init__(self, node_id: int, eds: str | Path, *, limits: DriveLimits | None = None,
                 initial_length_m: float | None = None,
                 send: Callable[[int, bytes], None] | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        if not 1 <= node_id <= 127:
            raise ValueError(f'node id must be 1..127, got {node_id}')
        self.node_id = node_id
        self.eds = str(eds)
        self.od = canopen.import_od(self.eds, node_id)
        self.object_dictionary = self.od     # the name canopen's SdoServer reads
        self.limits = limits or DriveLimits()
        self._send = send
        self._clock = clock
        self.lock = threading.RLock()
        cpm = self.limits.counts_per_m
        self._cpm = cpm
        # ---- physical actuator (SI) ----
        mid = 0.5 * (self.limits.stroke_min + self.limits.stroke_max)
        self.length_m = float(mid if initial_length_m is None else initial_length_m)
        self.velocity_mps = 0.0
        self.load_cell_counts = 0       # 2401h, set by the physics each SYNC
        self.force_n = 0.0              # true actuator force (for 6077h)
        # ---- fault injection state ----
        self.stalled = False            # actuator mechanically blocked
        self.encoder_frozen_at: int | None = None   # 6064h frozen at this value
        self.encoder_jump_counts = 0    # added to 6064h
        self.heartbeat_silenced = False
        self.disconnected = False       # no TX, no RX (cable pulled)
        self.tpdo_muted = False         # TPDOs not sent (stale data at the master)
        self.injected_warning = False
        self._injected_faults: set[int] = set()
        # ---- CANopen state ----
        self.nmt_state = NmtState.INITIALISING
        self._store: dict[tuple[int, int], int] = {}
        self._rpdo = [_Pdo(n) for n in range(1, 5)]
        self._tpdo = [_Pdo(n) for n in range(1, 5)]
        self._rpdo_by_cob: dict[int, _Pdo] = {}
        self._net = _Network(self)
        self._sdo = SdoServer(0x600 + node_id, 0x580 + node_id, self)
        self._sdo.network = self._net  # type: ignore[assignment]
        self.sync_cob_id = 0x80
        self.hb_period_s = 0.0
        self._next_hb = math.inf
        self._hb_consumer_id = 0
        self._hb_consumer_s = 0.0
        self._hb_deadline = math.inf    # inf: not monitoring (no heartbeat received yet)
        self.master_heartbeat_lost = False
        self._err_history: list[int] = []
        self.emcy_log: list[tuple[float, int, int, bytes]] = []  # (t, code, reg, data) sent
        # ---- CiA 402 state ----
        self.state = State402.NOT_READY_TO_SWITCH_ON
        self._controlword = 0
        self._cw_prev_fault_bit = False
        self._cw_prev_homing_bit = False
        self._faults: set[int] = set()
        self._error_code = 0
        self._enc_zero = 0              # raw count at power-up
        self._home_shift = 0            # 6064h = raw + home shift
        self.homed = False
        self._homing_attained = False
        self._homing_error = False
        self._target = 0                # latched 607Ah (counts)
        self._fe_time_s = 0.0           # time spent outside the following error window
        self._fe_counts = 0
        self._at_hard_stop = False
        self._limit_active = False
        self._last_sync_t: float | None = None
        self._reset_application()

    # ------------------------------------------------------------------ public API

    @property
    def position_counts(self) -> int:
        """6064h as the drive reports it (after encoder fault injection)."""
        if self.encoder_frozen_at is not None:
            return self.encoder_frozen_at
        return self._true_position_counts() + self.encoder_jump_counts

    @property
    def statusword(self) -> int:
        """6041h, CiA 402 bits (see the module docstring)."""
        sw = int(self.state) | 0x0200          # bit 9 remote
        if self.state in _POWERED:
            sw |= 0x0010                       # bit 4 voltage enabled
        if self.state == State402.QUICK_STOP_ACTIVE:
            sw &= ~0x0020
        if self.warning:
            sw |= 0x0080
        if self._limit_active or self._at_hard_stop:
            sw |= 0x0800
        mode = self._store[(0x6061, 0)]
        if mode == MODE_HOMING:
            if self._homing_attained:
                sw |= 0x1000 | 0x0400
            if self._homing_error:
                sw |= 0x2000
        elif mode == MODE_CSP:
            if self.state == State402.OPERATION_ENABLED:
                sw |= 0x1000                   # drive follows the command value
                if abs(self._fe_counts) <= self._store[(0x6065, 0)]:
                    sw |= 0x0400
            elif abs(self.velocity_mps) < 1e-9:
                sw |= 0x0400
            if self._fe_time_s > 0.0:
                sw |= 0x2000                   # following error
        return sw

    @property
    def warning(self) -> bool:
        """Statusword bit 7: injected warning, master heartbeat lost (6007h = 0)."""
        return self.injected_warning or (self.master_heartbeat_lost and self.state not in (
            State402.FAULT, State402.FAULT_REACTION_ACTIVE))

    @property
    def faults(self) -> frozenset[int]:
        """EMCY codes of the latched fault causes (empty unless in FAULT)."""
        return frozenset(self._faults)

    def attach(self, send: Callable[[int, bytes], None]) -> None:
        """Give the drive its transmit function (a bus)."""
        self._send = send

    def power_on(self) -> None:
        """CiA 301 initialisation: reset application + communication, boot-up, PRE-OPERATIONAL."""
        with self.lock:
            self._nmt_reset(application=True)

    def read_od(self, index: int, subindex: int = 0) -> int:
        """The current value of an object (as the SDO server would return it)."""
        with self.lock:
            return self._get(index, subindex)

    # fault injection (used by brace_control.sim.faults)
    def send_emcy(self, code: int, data: bytes = b'', *, fault: bool = False) -> None:
        """Send an EMCY; with ``fault`` also enter FAULT with this (injected) cause,
        latched until :meth:`clear_injected_fault`."""
        with self.lock:
            if fault:
                self._injected_faults.add(int(code))
                self._enter_fault(int(code), data)
            else:
                self._emcy(int(code), data)

    def clear_injected_fault(self, code: int | None = None) -> None:
        """Remove an injected fault cause (all when ``code`` is None); fault reset still needed."""
        with self.lock:
            if code is None:
                self._injected_faults.clear()
            else:
                self._injected_faults.discard(int(code))

    # ------------------------------------------------------------------ bus entry points

    def on_frame(self, cob_id: int, data: bytes, t: float) -> None:
        """A received frame other than SYNC (NMT, SDO, RPDO, heartbeats)."""
        if self.disconnected:
            return
        with self.lock:
            if cob_id == 0:
                self._on_nmt(data)
            elif cob_id == 0x600 + self.node_id:
                if self.nmt_state in (NmtState.PRE_OPERATIONAL, NmtState.OPERATIONAL) \
                        and len(data) == 8:
                    self._sdo.on_request(cob_id, data, t)
            elif cob_id == 0x700 + self._hb_consumer_id and self._hb_consumer_s > 0:
                self._hb_deadline = t + self._hb_consumer_s
                if self.master_heartbeat_lost:
                    self.master_heartbeat_lost = False
            else:
                pdo = self._rpdo_by_cob.get(cob_id)
                if pdo is not None and self.nmt_state == NmtState.OPERATIONAL:
                    if len(data) < pdo.codec.size:
                        return  # CiA 301: too short -> not processed (EMCY 8210h)
                    if pdo.trans_type <= 240:
                        pdo.pending = data
                    else:
                        self._apply_rpdo(pdo, data)

    def on_sync(self, dt: float, *, phase: str = 'all') -> None:
        """SYNC (CiA 301 §7.2.5). ``phase``: ``'motion'`` advances the actuator by ``dt``;
        ``'comm'`` sends the synchronous TPDOs and applies the latched RPDOs;
        ``'all'`` both (a :class:`~brace_control.sim.brace.SimulatedBrace` runs the
        physics in between)."""
        if self.disconnected:
            return
        with self.lock:
            if phase in ('motion', 'all'):
                self._motion_step(dt)
            if phase in ('comm', 'all') and self.nmt_state == NmtState.OPERATIONAL:
                for pdo in self._tpdo:
                    if pdo.valid and pdo.trans_type <= 240:
                        pdo.sync_count += 1
                        if pdo.sync_count >= max(1, pdo.trans_type):
                            pdo.sync_count = 0
                            if not self.tpdo_muted:
                                self._tx(pdo.cob_id, self._pack_tpdo(pdo))
                for pdo in self._rpdo:
                    if pdo.pending is not None:
                        data, pdo.pending = pdo.pending, None
                        self._apply_rpdo(pdo, data)

    def tick(self, now: float) -> float:
        """Timers: heartbeat producer, heartbeat consumer, TPDO event timers.

        :returns: the next time (monotonic s) this drive needs a tick.
        """
        if self.disconnected:
            return now + 0.05
        with self.lock:
            if now >= self._next_hb:
                if not self.heartbeat_silenced:
                    self._tx(0x700 + self.node_id, bytes((int(self.nmt_state),)))
                if self.hb_period_s > 0:
                    nxt_hb = self._next_hb + self.hb_period_s
                    self._next_hb = nxt_hb if nxt_hb > now else now + self.hb_period_s
                else:
                    self._next_hb = math.inf
            if now >= self._hb_deadline:
                self._hb_deadline = math.inf
                self._on_master_heartbeat_lost()
            nxt = min(self._next_hb, self._hb_deadline)
            if self.nmt_state == NmtState.OPERATIONAL:
                for pdo in self._tpdo:
                    if pdo.valid and pdo.trans_type >= 254 and pdo.event_ms > 0:
                        if now >= pdo.next_event:
                            if not self.tpdo_muted:
                                self._tx(pdo.cob_id, self._pack_tpdo(pdo))
                            pdo.next_event = now + pdo.event_ms / 1000.0
                        nxt = min(nxt, pdo.next_event)
            # no SYNC for long: the fault reaction still ends (motor stopped)
            if self.state == State402.FAULT_REACTION_ACTIVE and self._last_sync_t is not None \
                    and now - self._last_sync_t > 0.05:
                self.velocity_mps = 0.0
                self._set_state(State402.FAULT)
            return min(nxt, now + 0.05)

    # ------------------------------------------------------------------ transmit

    def _tx(self, cob_id: int, data: bytes) -> None:
        if self._send is not None and not self.disconnected:
            self._send(cob_id, data)

    def _emcy(self, code: int, data: bytes = b'') -> None:
        """CiA 301 §7.2.7: EMCY frame = code (U16) + error register (U8) + 5 bytes."""
        if code:
            self._err_history.insert(0, code & 0xFFFF)
            del self._err_history[8:]
        reg = self._error_register()
        payload = struct.pack('<HB', code & 0xFFFF, reg) + bytes(data[:5]).ljust(5, b'\0')
        self.emcy_log.append((self._clock(), code, reg, payload))
        if self.nmt_state in (NmtState.PRE_OPERATIONAL, NmtState.OPERATIONAL):
            cob = self._store[(0x1014, 0)]
            if not cob & 0x80000000:
                self._tx(cob & 0x7FF, payload)

    def _error_register(self) -> int:
        reg = 0
        for code in self._faults:
            reg |= _ERR_REG_GENERIC | _error_register_bit(code)
        if self.master_heartbeat_lost:
            reg |= _ERR_REG_GENERIC | 0x10
        return reg

    # ------------------------------------------------------------------ NMT (CiA 301 §7.3.2)

    def _on_nmt(self, data: bytes) -> None:
        if len(data) < 2 or data[1] not in (0, self.node_id):
            return
        cs = data[0]
        if cs == 0x01 and self.nmt_state != NmtState.INITIALISING:
            self._set_nmt(NmtState.OPERATIONAL)
        elif cs == 0x02:
            self._set_nmt(NmtState.STOPPED)
        elif cs == 0x80:
            self._set_nmt(NmtState.PRE_OPERATIONAL)
        elif cs == 0x81:
            self._nmt_reset(application=True)
        elif cs == 0x82:
            self._nmt_reset(application=False)

    def _set_nmt(self, state: NmtState) -> None:
        if state == self.nmt_state:
            return
        self.nmt_state = state
        now = self._clock()
        for pdo in self._tpdo:
            pdo.sync_count = 0
            pdo.next_event = now
        for pdo in self._rpdo:
            pdo.pending = None

    def _nmt_reset(self, *, application: bool) -> None:
        """Reset node (application + communication) or reset communication, then boot-up."""
        self.nmt_state = NmtState.INITIALISING
        for (index, sub), var in self._defaults().items():
            if application or 0x1000 <= index <= 0x1FFF:
                self._store[(index, sub)] = var
        if application:
            self._reset_application()
        self._err_history.clear()
        self._rebuild_comm()
        self._tx(0x700 + self.node_id, b'\x00')          # boot-up
        self._set_nmt(NmtState.PRE_OPERATIONAL)
        now = self._clock()
        self._next_hb = now + self.hb_period_s if self.hb_period_s > 0 else math.inf

    def _defaults(self) -> dict[tuple[int, int], int]:
        out: dict[tuple[int, int], int] = {}
        for obj in self.od.values():
            subs = [obj] if isinstance(obj, odmod.ODVariable) else list(obj.values())
            for var in subs:
                val = var.value if var.value is not None else var.default
                if isinstance(val, (int, bool)):
                    out[(var.index, var.subindex)] = int(val)
                elif isinstance(val, (str, bytes)):
                    out[(var.index, var.subindex)] = val   # type: ignore[assignment]
        return out

    def _reset_application(self) -> None:
        """Power-up of the drive application: encoder counts restart at 0, not homed."""
        if not self._store:
            self._store.update(self._defaults())
        self._store.setdefault((0x6061, 0), 0)
        self._store[(0x6061, 0)] = self._store.get((0x6060, 0), 0)
        self._enc_zero = math.floor(self.length_m * self._cpm)
        self._home_shift = 0
        self.homed = False
        self._homing_attained = False
        self._homing_error = False
        self._faults.clear()
        self._controlword = 0
        self._cw_prev_fault_bit = False
        self._cw_prev_homing_bit = False
        self.velocity_mps = 0.0
        self._fe_time_s = 0.0
        self._target = self._true_position_counts()
        self.master_heartbeat_lost = False
        # NOT READY TO SWITCH ON -> SWITCH ON DISABLED (transition 1, automatic)
        self.state = State402.SWITCH_ON_DISABLED

    def _rebuild_comm(self) -> None:
        """Apply the communication objects of the store (after reset or SDO writes)."""
        s = self._store
        self.sync_cob_id = s.get((0x1005, 0), 0x80) & 0x7FF
        hb_ms = s.get((0x1017, 0), 0)
        self.hb_period_s = hb_ms / 1000.0
        cons = s.get((0x1016, 1), 0)
        self._hb_consumer_id = (cons >> 16) & 0x7F
        self._hb_consumer_s = (cons & 0xFFFF) / 1000.0
        if self._hb_consumer_s <= 0 or self._hb_consumer_id == 0:
            self._hb_deadline = math.inf
        for pdo in self._rpdo:
            self._compile_pdo(pdo, 0x1400, 0x1600)
        for pdo in self._tpdo:
            self._compile_pdo(pdo, 0x1800, 0x1A00)
        self._rpdo_by_cob = {p.cob_id: p for p in self._rpdo if p.valid}

    def _compile_pdo(self, pdo: _Pdo, com_base: int, map_base: int) -> None:
        s = self._store
        n = pdo.num - 1
        cob = s.get((com_base + n, 1), 0x80000000)
        pdo.cob_id = cob & 0x7FF
        pdo.valid = not cob & 0x80000000
        pdo.trans_type = s.get((com_base + n, 2), 255)
        pdo.event_ms = s.get((com_base + n, 5), 0)
        count = s.get((map_base + n, 0), 0)
        entries, fmt = [], '<'
        for i in range(1, count + 1):
            raw = s.get((map_base + n, i), 0)
            index, sub = raw >> 16, (raw >> 8) & 0xFF        # low byte: the bit length
            var = self._var(index, sub)
            entries.append((index, sub))
            fmt += _STRUCT_CODE[var.data_type]
        pdo.entries = entries
        pdo.codec = struct.Struct(fmt)
        pdo.pending = None

    def _var(self, index: int, sub: int) -> odmod.ODVariable:
        if index not in self.od:
            raise SdoAbortedError(0x06020000)
        obj = self.od[index]
        if isinstance(obj, odmod.ODVariable):
            if sub != 0:
                raise SdoAbortedError(0x06090011)
            return obj
        if sub not in obj:
            raise SdoAbortedError(0x06090011)
        return obj[sub]

    # ------------------------------------------------------------------ PDO codec

    def _pack_tpdo(self, pdo: _Pdo) -> bytes:
        return pdo.codec.pack(*[self._get(i, s) for i, s in pdo.entries])

    def _apply_rpdo(self, pdo: _Pdo, data: bytes) -> None:
        values = pdo.codec.unpack_from(data)
        for (index, sub), value in zip(pdo.entries, values):
            try:
                self._put(index, sub, value)
            except SdoAbortedError:
                pass  # an invalid value in a PDO is ignored (no SDO to abort)

    # ------------------------------------------------------------------ object access

    def _get(self, index: int, sub: int) -> int:
        """Current value of an object: process data live, parameters from the store."""
        if index == 0x6041:
            return self.statusword
        if index == 0x6064:
            return self.position_counts
        if index == 0x2401:
            return self.load_cell_counts
        if index == 0x606C:
            return round(self.velocity_mps * self._cpm)
        if index == 0x60F4:
            return self._fe_counts
        if index == 0x6077:
            return max(-32768, min(32767, round(1000.0 * self.force_n / self.limits.max_force)))
        if index == 0x1001:
            return self._error_register()
        if index == 0x603F:
            return self._error_code
        if index == 0x6040:
            return self._controlword
        if index == 0x607A:
            return self._target
        if index == 0x1003:
            if sub == 0:
                return len(self._err_history)
            return self._err_history[sub - 1] if sub <= len(self._err_history) else 0
        return self._store[(index, sub)]

    def _put(self, index: int, sub: int, value: int) -> None:
        """Write an object (SDO or RPDO) with its side effects; SdoAbortedError if refused."""
        if index == 0x6040:
            self._on_controlword(value)
            return
        if index == 0x607A:
            self._target = value
            return
        if index == 0x6060:
            if value not in (MODE_CSP, MODE_HOMING):
                raise SdoAbortedError(ABORT_VALUE_RANGE)
            self._store[(0x6060, 0)] = value
            if self._store[(0x6061, 0)] != value:
                self._store[(0x6061, 0)] = value
                self._homing_attained = False
                self._homing_error = False
                self._cw_prev_homing_bit = bool(self._controlword & 0x10)
            return
        if index == 0x1003:
            if sub == 0 and value == 0:
                self._err_history.clear()
                return
            raise SdoAbortedError(ABORT_VALUE_RANGE)
        if 0x1600 <= index <= 0x1603 or 0x1A00 <= index <= 0x1A03:
            self._check_mapping(index, sub, value)
        if index in (0x1400, 0x1401, 0x1402, 0x1403, 0x1800, 0x1801, 0x1802, 0x1803) and sub == 1:
            if value & 0x1FFFF800 and not value & 0x20000000:
                raise SdoAbortedError(ABORT_VALUE_RANGE)
        self._store[(index, sub)] = value
        if 0x1000 <= index <= 0x1FFF:
            self._rebuild_comm()
            if index == 0x1017:
                now = self._clock()
                self._next_hb = now + self.hb_period_s if self.hb_period_s > 0 else math.inf
            if index == 0x1016 and self._hb_consumer_s > 0:
                self._hb_deadline = math.inf   # restarts with the next heartbeat received
                self.master_heartbeat_lost = False

    def _check_mapping(self, index: int, sub: int, value: int) -> None:
        """CiA 301 §7.4.8.x: a mapping entry names a mappable object of its length; <= 64 bit."""
        if sub == 0:
            if value > 8:
                raise SdoAbortedError(ABORT_VALUE_HIGH)
            bits = 0
            for i in range(1, value + 1):
                bits += self._store.get((index, i), 0) & 0xFF
                self._check_entry(self._store.get((index, i), 0), rpdo=index < 0x1A00)
            if bits > 64:
                raise SdoAbortedError(ABORT_PDO_LENGTH)
        elif value:
            self._check_entry(value, rpdo=index < 0x1A00)

    def _check_entry(self, raw: int, *, rpdo: bool) -> None:
        idx, sub, bits = raw >> 16, (raw >> 8) & 0xFF, raw & 0xFF
        try:
            var = self._var(idx, sub)
        except SdoAbortedError:
            raise SdoAbortedError(ABORT_NOT_MAPPABLE) from None
        if not var.pdo_mappable or var.data_type not in _STRUCT_CODE or len(var) != bits \
                or (rpdo and not var.writable) or (not rpdo and not var.readable):
            raise SdoAbortedError(ABORT_NOT_MAPPABLE)

    # SdoServer's node interface (CiA 301 §7.2.4; bytes in, bytes out)
    def get_data(self, index: int, subindex: int, check_readable: bool = False) -> bytes:
        var = self._var(index, subindex)
        if check_readable and not var.readable:
            raise SdoAbortedError(0x06010001)
        return var.encode_raw(self._get(index, subindex))

    def set_data(self, index: int, subindex: int, data: bytes,
                 check_writable: bool = False) -> None:
        var = self._var(index, subindex)
        if check_writable and not var.writable:
            raise SdoAbortedError(0x06010002)
        if var.data_type in odmod.NUMBER_TYPES and 8 * len(data) != len(var):
            raise SdoAbortedError(0x06070010)
        value = var.decode_raw(bytes(data))
        if not isinstance(value, int):
            self._store[(index, subindex)] = value
            return
        if var.min is not None and value < var.min:
            raise SdoAbortedError(0x06090032)
        if var.max is not None and value > var.max:
            raise SdoAbortedError(ABORT_VALUE_HIGH)
        self._put(index, subindex, int(value))

    # ------------------------------------------------------------------ CiA 402 device control

    def _set_state(self, state: State402) -> None:
        if state == self.state:
            return
        entering_enabled = state == State402.OPERATION_ENABLED
        self.state = state
        if entering_enabled:
            self._fe_time_s = 0.0
        if state not in (State402.OPERATION_ENABLED, State402.QUICK_STOP_ACTIVE,
                         State402.FAULT_REACTION_ACTIVE):
            self.velocity_mps = 0.0     # motor disabled; the lead screw holds

    def _on_controlword(self, cw: int) -> None:
        """CiA 402 device control: the controlword command decoding (Table 'commands')."""
        cw &= 0xFFFF
        self._controlword = cw
        fault_edge = bool(cw & 0x80) and not self._cw_prev_fault_bit
        self._cw_prev_fault_bit = bool(cw & 0x80)
        st = self.state
        if st == State402.FAULT:
            if fault_edge and not self._active_fault_causes():
                self._faults.clear()
                self._fe_time_s = 0.0
                self._limit_active = False
                self._set_state(State402.SWITCH_ON_DISABLED)   # transition 15
                self._emcy(EmcyCode.NO_ERROR)
            return
        if st in (State402.FAULT_REACTION_ACTIVE, State402.NOT_READY_TO_SWITCH_ON):
            return
        if cw & 0x80:
            return      # fault reset bit set outside FAULT: no other command (CiA 402)
        disable_voltage = not cw & 0x02
        quick_stop = (cw & 0x06) == 0x02
        shutdown = (cw & 0x07) == 0x06
        switch_on = (cw & 0x0F) == 0x07
        enable_op = (cw & 0x0F) == 0x0F
        if st == State402.SWITCH_ON_DISABLED:
            if shutdown:
                self._set_state(State402.READY_TO_SWITCH_ON)                 # 2
        elif st == State402.READY_TO_SWITCH_ON:
            if disable_voltage or quick_stop:
                self._set_state(State402.SWITCH_ON_DISABLED)                 # 7
            elif switch_on:
                self._set_state(State402.SWITCHED_ON)                        # 3
            elif enable_op:
                self._set_state(State402.SWITCHED_ON)                        # 3 + 4
                self._enable_operation()
        elif st == State402.SWITCHED_ON:
            if disable_voltage or quick_stop:
                self._set_state(State402.SWITCH_ON_DISABLED)                 # 10
            elif shutdown:
                self._set_state(State402.READY_TO_SWITCH_ON)                 # 6
            elif enable_op:
                self._enable_operation()                                     # 4
        elif st == State402.OPERATION_ENABLED:
            if disable_voltage:
                self._set_state(State402.SWITCH_ON_DISABLED)                 # 9
            elif quick_stop:
                self._quick_stop()                                           # 11
            elif shutdown:
                self._set_state(State402.READY_TO_SWITCH_ON)                 # 8
            elif switch_on:
                self._set_state(State402.SWITCHED_ON)                        # 5
            else:
                self._homing_control(cw)
        elif st == State402.QUICK_STOP_ACTIVE:
            if disable_voltage:
                self._set_state(State402.SWITCH_ON_DISABLED)                 # 12
            elif enable_op and self._store[(0x605A, 0)] in (5, 6, 7, 8) \
                    and abs(self.velocity_mps) < 1e-9:
                self._enable_operation()                                     # 16

    def _enable_operation(self) -> None:
        self._set_state(State402.OPERATION_ENABLED)
        self._cw_prev_homing_bit = bool(self._controlword & 0x10)

    def _quick_stop(self) -> None:
        """605Ah: 0 disable drive; 1/2 ramp then SWITCH ON DISABLED; 5-8 ramp and stay."""
        option = self._store[(0x605A, 0)]
        if option == 0:
            self._set_state(State402.SWITCH_ON_DISABLED)
        else:
            self._set_state(State402.QUICK_STOP_ACTIVE)

    def _homing_control(self, cw: int) -> None:
        """Homing mode (6): rising edge of controlword bit 4 starts the method (6098h)."""
        start = bool(cw & 0x10)
        edge = start and not self._cw_prev_homing_bit
        self._cw_prev_homing_bit = start
        if self._store[(0x6061, 0)] != MODE_HOMING or not edge:
            return
        method = self._store[(0x6098, 0)]
        if method in (35, 37):
            raw = self._true_position_counts() - self._home_shift
            self._home_shift = self._store[(0x607C, 0)] - raw
            self.homed = True
            self._homing_attained = True
            self._homing_error = False
            self._target = self._true_position_counts()
        else:
            self._homing_attained = False
            self._homing_error = True

    def _active_fault_causes(self) -> set[int]:
        active: set[int] = set(self._injected_faults & self._faults)
        if EmcyCode.FOLLOWING_ERROR in self._faults:
            if self.stalled or abs(self._target - self._true_position_counts()) \
                    > self._store[(0x6065, 0)]:
                active.add(EmcyCode.FOLLOWING_ERROR)
        if EmcyCode.REFERENCE_LIMIT in self._faults and not self._target_in_limits():
            active.add(EmcyCode.REFERENCE_LIMIT)
        if EmcyCode.HEARTBEAT in self._faults and self.master_heartbeat_lost:
            active.add(EmcyCode.HEARTBEAT)
        return active

    def _enter_fault(self, code: int, data: bytes = b'') -> None:
        """Fault: FAULT REACTION ACTIVE (quick-stop ramp) -> FAULT, EMCY, 603Fh."""
        self._faults.add(code)
        self._error_code = code
        if self.state not in (State402.FAULT, State402.FAULT_REACTION_ACTIVE):
            if abs(self.velocity_mps) > 1e-9:
                self._set_state(State402.FAULT_REACTION_ACTIVE)
            else:
                self._set_state(State402.FAULT)
        self._emcy(code, data)

    def _on_master_heartbeat_lost(self) -> None:
        """CiA 301 heartbeat event + CiA 402 6007h abort connection option code."""
        self.master_heartbeat_lost = True
        option = self._store[(0x6007, 0)]
        if option == 1:
            self._enter_fault(EmcyCode.HEARTBEAT)
            return
        self._emcy(EmcyCode.HEARTBEAT)
        if self.state == State402.OPERATION_ENABLED:
            if option == 2:
                self._set_state(State402.SWITCH_ON_DISABLED)
            elif option == 3:
                self._quick_stop()

    # ------------------------------------------------------------------ motion (CSP)

    def _true_position_counts(self) -> int:
        return math.floor(self.length_m * self._cpm) - self._enc_zero + self._home_shift

    def _counts_to_length(self, counts: int) -> float:
        return (counts - self._home_shift + self._enc_zero + 0.5) / self._cpm

    def _target_in_limits(self) -> bool:
        lo, hi = self._store[(0x607D, 1)], self._store[(0x607D, 2)]
        if not self.homed or lo >= hi:
            return True
        return lo <= self._target <= hi

    def _motion_step(self, dt: float) -> None:
        """Advance the actuator by ``dt`` seconds with the setpoint latched at the last SYNC."""
        self._last_sync_t = self._clock()
        if dt <= 0.0:
            return
        lim = self.limits
        st = self.state
        v = self.velocity_mps
        amax = lim.max_acceleration
        if st == State402.OPERATION_ENABLED and self._store[(0x6061, 0)] == MODE_CSP:
            vmax = min(lim.max_velocity, self._store[(0x607F, 0)] / self._cpm)
            if not self._target_in_limits():
                self._limit_active = True
                self._enter_fault(EmcyCode.REFERENCE_LIMIT)
                self._motion_step(dt)
                return
            self._limit_active = False
            # inside the target's encoder count: hold (a quantised position loop)
            e = 0.0 if self._target == self._true_position_counts() else \
                self._counts_to_length(self._target) - self.length_m
            ae = abs(e)
            # the fastest speed that still stops at the target with |a| <= amax in steps of dt
            adt = amax * dt
            v_brake = adt * (math.sqrt(0.25 + 2.0 * ae / (adt * dt)) - 0.5)
            v_des = math.copysign(min(vmax, v_brake, ae / dt), e)
            v_new = min(max(v_des, v - amax * dt), v + amax * dt)
        elif st in (State402.QUICK_STOP_ACTIVE, State402.FAULT_REACTION_ACTIVE):
            decel = max(self._store[(0x6085, 0)] / self._cpm, 1e-6)
            if st == State402.QUICK_STOP_ACTIVE and self._store[(0x605A, 0)] in (1, 5):
                decel = max(self._store[(0x6084, 0)] / self._cpm, 1e-6)
            dv = decel * dt
            v_new = 0.0 if abs(v) <= dv else v - math.copysign(dv, v)
            if v_new == 0.0:
                if st == State402.FAULT_REACTION_ACTIVE:
                    self._set_state(State402.FAULT)
                elif self._store[(0x605A, 0)] in (1, 2):
                    self._set_state(State402.SWITCH_ON_DISABLED)
        else:
            v_new = 0.0
        if self.stalled:
            v_new = 0.0
        length = self.length_m + v_new * dt if not self.stalled else self.length_m
        self._at_hard_stop = False
        if length <= lim.stroke_min:
            length, v_new = lim.stroke_min, 0.0
            self._at_hard_stop = True
        elif length >= lim.stroke_max:
            length, v_new = lim.stroke_max, 0.0
            self._at_hard_stop = True
        self.length_m = length
        self.velocity_mps = v_new
        # following error (6065h window, 6066h time out), CSP in OPERATION ENABLED only
        if self.state == State402.OPERATION_ENABLED and self._store[(0x6061, 0)] == MODE_CSP:
            self._fe_counts = self._target - self._true_position_counts()
            if abs(self._fe_counts) > self._store[(0x6065, 0)]:
                self._fe_time_s += dt
                if self._fe_time_s * 1000.0 >= self._store[(0x6066, 0)]:
                    self._enter_fault(EmcyCode.FOLLOWING_ERROR)
            else:
                self._fe_time_s = 0.0
        else:
            self._fe_counts = 0
            if self.state not in (State402.FAULT, State402.FAULT_REACTION_ACTIVE):
                self._fe_time_s = 0.0
