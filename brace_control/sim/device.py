"""A simulated CANopen device (CiA 301), answering as its object dictionary describes it.

:class:`SimulatedDevice` is the communication side every simulated node shares: the
CiA 402 drives (:class:`~brace_control.sim.drive.SimulatedDrive`) and the CiA 401 analog-input
module (:class:`~brace_control.sim.module.SimulatedAnalogModule`). It is independent of any
transport: frames come in through :meth:`SimulatedDevice.on_frame` and
:meth:`SimulatedDevice.on_sync`, go out through the ``send(cob_id, data)`` callable it is given.

The device is the one its EDS / DCF describes (``canopen.import_od``): the objects that exist,
their data types, access and LowLimit / HighLimit, which PDOs it has and what may be mapped
come from the file, and the SDO server answers with the CiA 301 abort code a real device
gives (:class:`~brace_control.can.cia402.SdoAbortCode`):

* an object or sub-index the file does not list: 06020000 / 06090011;
* a write to a read-only object: 06010002; a read of a write-only one: 06010001;
* a value outside the data type or the file's limits: 06090031 / 06090032; of the wrong
  size: 06070010;
* a mapping entry that is absent, not ``PDOMapping=1``, of another length, not writable
  (RPDO) or readable (TPDO): 06040041; more than 64 bits: 06040042; more entries than the
  mapping object has: 06090031;
* a PDO the device does not have: its communication / mapping objects are absent (06020000).

What it implements: CiA 301 §7.3.2 NMT slave (INITIALISING -> boot-up ``0x700+id: 00`` ->
PRE-OPERATIONAL; start, stop, enter pre-operational, reset node, reset communication, for
this id or all), §7.2.8 heartbeat producer (1017h) and consumer of the master (1016h sub1,
monitored from the first heartbeat received), §7.2.4 SDO server (canopen's ``SdoServer``
on this device's dictionary: expedited and segmented), §7.2.2 PDOs (synchronous RPDOs
latched and applied at the next SYNC, event-driven ones at once; synchronous TPDOs every
n-th SYNC in OPERATIONAL, event-driven ones on their event timer), §7.2.7 EMCY (1014h),
1001h error register, 1003h error history.

Field quirks a test can give it (:class:`~brace_control.sim.faults.FaultInjector`):
:attr:`sdo_delay` (SDO answers that late), :attr:`silent_boot` (no boot-up message at
power-on, only after an NMT reset), and the transport faults (:attr:`disconnected`,
:attr:`heartbeat_silenced`, :attr:`tpdo_muted`).

Thread safety: every entry point takes the device's lock (the bus receive thread and the
timer thread both call in).
"""
from __future__ import annotations

import functools
import math
import struct
import threading
import time
from collections.abc import Callable
from pathlib import Path

from canopen import objectdictionary as odmod
from canopen.sdo import SdoAbortedError, SdoServer

from ..can.cia402 import ErrorRegister, NmtState, SdoAbortCode, error_register_bits
from ..can.dictionary import STRUCT_CODES, Dictionary, lookup

__all__ = ['SimulatedDevice', 'NmtState']


class _Pdo:
    """One PDO's communication + mapping, compiled for the hot path."""

    __slots__ = ('num', 'cob_id', 'valid', 'trans_type', 'entries', 'codec', 'getters',
                 'sync_count', 'event_ms', 'next_event', 'pending')

    def __init__(self, num: int) -> None:
        self.num = num
        self.cob_id = 0
        self.valid = False
        self.trans_type = 255
        self.entries: list[tuple[int, int]] = []
        self.codec = struct.Struct('<')
        #: one zero-argument reader per mapped entry, ``getter() == device._get(index, sub)``
        self.getters: tuple[Callable[[], int], ...] = ()
        self.sync_count = 0
        self.event_ms = 0
        self.next_event = 0.0
        self.pending: bytes | None = None


class _Network:
    """The shim canopen's SdoServer sends through (with the injected SDO answer delay)."""

    def __init__(self, device: 'SimulatedDevice') -> None:
        self._device = device

    def send_message(self, can_id: int, data: bytes | bytearray) -> None:
        dev = self._device
        if dev.sdo_delay > 0.0:
            timer = threading.Timer(dev.sdo_delay, dev._tx, (can_id, bytes(data)))
            timer.daemon = True
            timer.start()
        else:
            dev._tx(can_id, bytes(data))


class SimulatedDevice:
    """A CANopen device (CiA 301) whose objects are those of its EDS (module docstring).

    :param node_id: CANopen node id 1..127.
    :param eds: the device's EDS or DCF.
    :param send: ``send(cob_id, data)`` puts a frame on the bus; ``None`` until a
        :class:`~brace_control.sim.host.SimBus` attaches the device.
    :param clock: monotonic time source (s), for heartbeats and event timers.

    The device is inert until :meth:`power_on` (boot-up message, PRE-OPERATIONAL).
    """

    def __init__(self, node_id: int, eds: str | Path, *,
                 send: Callable[[int, bytes], None] | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        if not 1 <= node_id <= 127:
            raise ValueError(f'node id must be 1..127, got {node_id}')
        self.node_id = node_id
        self.eds = str(eds)
        self.dictionary = Dictionary(eds, node_id)
        self.od = self.dictionary.od
        self.object_dictionary = self.od     # the name canopen's SdoServer reads
        self._send = send
        self._clock = clock
        self.lock = threading.RLock()
        # ---- fault injection state ----
        self.heartbeat_silenced = False
        self.disconnected = False       # no TX, no RX (cable pulled)
        self.tpdo_muted = False         # TPDOs not sent (stale data at the master)
        #: s every SDO answer is held back (a slow drive during configuration)
        self.sdo_delay = 0.0
        #: no boot-up message: '' normal, 'power_on' none at power-on (one after an NMT reset:
        #: a drive powered before the master listened), 'always' none ever (SDO still answers)
        self.silent_boot = ''
        # ---- CANopen state ----
        self.nmt_state = NmtState.INITIALISING
        self._store: dict[tuple[int, int], int] = {}
        self._rpdo = [_Pdo(n) for n in self.dictionary.pdo_numbers('rpdo')]
        self._tpdo = [_Pdo(n) for n in self.dictionary.pdo_numbers('tpdo')]
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

    # ------------------------------------------------------------------ public API

    def attach(self, send: Callable[[int, bytes], None]) -> None:
        """Give the device its transmit function (a bus)."""
        self._send = send

    def power_on(self) -> None:
        """CiA 301 initialisation: reset application + communication, boot-up, PRE-OPERATIONAL."""
        with self.lock:
            self._nmt_reset(application=True, boot_up=not self.silent_boot)
            if self.silent_boot == 'power_on':
                self.silent_boot = ''

    def read_od(self, index: int, subindex: int = 0) -> int:
        """The current value of an object (as the SDO server would return it)."""
        with self.lock:
            return self._get(index, subindex)

    def mapped(self, index: int, subindex: int = 0, *, direction: str = 'rpdo') -> bool:
        """Whether a valid PDO of ``direction`` carries the object now."""
        pdos = self._rpdo if direction == 'rpdo' else self._tpdo
        return any(p.valid and (index, subindex) in p.entries for p in pdos)

    # ------------------------------------------------------------------ bus entry points

    def listens_to(self) -> set[int]:
        """COB-IDs of the frames this device acts on besides NMT and SYNC: its valid RPDOs,
        its SDO requests and the heartbeat it consumes (a bus may route by them)."""
        with self.lock:
            cobs = set(self._rpdo_by_cob) | {0x600 + self.node_id}
            if self._hb_consumer_id:
                cobs.add(0x700 + self._hb_consumer_id)
            return cobs

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
        """SYNC (CiA 301 §7.2.5): ``'comm'`` sends the synchronous TPDOs and applies the
        RPDOs latched since the previous SYNC; ``'motion'`` is the application's step over
        ``dt`` (:meth:`_motion_step`); ``'all'`` both."""
        if self.disconnected:
            return
        with self.lock:
            if phase in ('motion', 'all'):
                self._motion_step(dt)
            if phase in ('comm', 'all'):
                if self.nmt_state == NmtState.OPERATIONAL:
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
                self._after_sync()

    def _motion_step(self, dt: float) -> None:
        """The application's step over ``dt`` at a SYNC (a drive: its actuator)."""

    def _after_sync(self) -> None:
        """After the SYNC's TPDOs and RPDOs (a drive: the next reference segment)."""

    def heartbeat_due(self, now: float) -> None:
        """Send the heartbeat (1017h) if it is due: from the timer, and on every SYNC (a real
        device's producer does not wait for a host thread; see :mod:`brace_control.sim.host`)."""
        if self.disconnected or now < self._next_hb:
            return
        with self.lock:
            self._produce_heartbeat(now)

    def _produce_heartbeat(self, now: float) -> None:
        if now >= self._next_hb:
            if not self.heartbeat_silenced:
                self._tx(0x700 + self.node_id, bytes((int(self.nmt_state),)))
            if self.hb_period_s > 0:
                nxt_hb = self._next_hb + self.hb_period_s
                self._next_hb = nxt_hb if nxt_hb > now else now + self.hb_period_s
            else:
                self._next_hb = math.inf

    def tick(self, now: float, heard_until: float | None = None) -> float:
        """Timers: heartbeat producer, heartbeat consumer, TPDO event timers.

        :param heard_until: the consumer judges silence up to this instant (monotonic s;
            default ``now``): frames sent before it have been handed to this device (a
            frame still queued for the simulator's receive thread is not silence).
        :returns: the next time (monotonic s) this device needs a tick.
        """
        if self.disconnected:
            return now + 0.05
        heard = now if heard_until is None else min(now, heard_until)
        with self.lock:
            self._produce_heartbeat(now)
            if heard >= self._hb_deadline:
                self._hb_deadline = math.inf
                self._on_master_heartbeat_lost()
            # a deadline passed by the clock but not by the frames received: look again soon
            nxt = min(self._next_hb, self._hb_deadline if self._hb_deadline > now else now + 0.005)
            if self.nmt_state == NmtState.OPERATIONAL:
                for pdo in self._tpdo:
                    if pdo.valid and pdo.trans_type >= 254 and pdo.event_ms > 0:
                        if now >= pdo.next_event:
                            if not self.tpdo_muted:
                                self._tx(pdo.cob_id, self._pack_tpdo(pdo))
                            pdo.next_event = now + pdo.event_ms / 1000.0
                        nxt = min(nxt, pdo.next_event)
            nxt = min(nxt, self._timer_step(now))
            return min(nxt, now + 0.05)

    def _timer_step(self, now: float) -> float:
        """The application's timer work; returns when it next needs a tick."""
        return math.inf

    def host_stalled(self, seconds: float) -> None:
        """The host process did not run for ``seconds``: this device's clock stood still, so
        its heartbeat-consumer deadline (1016h) moves by as much (:mod:`brace_control.sim.host`)."""
        with self.lock:
            if self._hb_deadline != math.inf:
                self._hb_deadline += seconds

    def _on_master_heartbeat_lost(self) -> None:
        """CiA 301 heartbeat event: EMCY 8130h (a drive adds its 6007h reaction)."""
        from ..can.cia402 import EmcyCode
        self.master_heartbeat_lost = True
        self._emcy(EmcyCode.HEARTBEAT)

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
            cob = self._store.get((0x1014, 0), 0x80 + self.node_id)
            if not cob & 0x80000000:
                self._tx(cob & 0x7FF, payload)

    def _fault_codes(self) -> set[int]:
        """EMCY codes of the faults the application holds (for 1001h)."""
        return set()

    def _error_register(self) -> int:
        reg = ErrorRegister(0)
        for code in self._fault_codes():
            reg |= error_register_bits(code)
        if self.master_heartbeat_lost:
            reg |= ErrorRegister.GENERIC | ErrorRegister.COMMUNICATION
        return int(reg)

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

    def _nmt_reset(self, *, application: bool, boot_up: bool = True) -> None:
        """Reset node (application + communication) or reset communication, then boot-up."""
        self.nmt_state = NmtState.INITIALISING
        for (index, sub), var in self._defaults().items():
            if application or 0x1000 <= index <= 0x1FFF:
                self._store[(index, sub)] = var
        if application:
            self._reset_application()
        self._err_history.clear()
        self._rebuild_comm()
        if boot_up and self.silent_boot != 'always':
            self._tx(0x700 + self.node_id, b'\x00')      # boot-up
        self._set_nmt(NmtState.PRE_OPERATIONAL)
        now = self._clock()
        self._next_hb = now + self.hb_period_s if self.hb_period_s > 0 else math.inf

    def _defaults(self) -> dict[tuple[int, int], int]:
        """Every object's start value from the file (DCF ParameterValue, else DefaultValue)."""
        out: dict[tuple[int, int], int] = {}
        for obj in self.od.values():
            subs = [obj] if isinstance(obj, odmod.ODVariable) else list(obj.values())
            for var in subs:
                val = var.value if var.value is not None else var.default
                if val is None and var.data_type in odmod.NUMBER_TYPES:
                    val = 0                               # a number the file leaves unset
                if isinstance(val, (int, bool, float)):
                    out[(var.index, var.subindex)] = val if isinstance(val, float) else int(val)
                elif isinstance(val, (str, bytes)):
                    out[(var.index, var.subindex)] = val   # type: ignore[assignment]
        # the identity (1018h) a real device answers: the file's [DeviceInfo] where its 1018h
        # defaults say nothing, and a serial number of its own
        info = self.od.device_information
        for sub, value in ((1, info.vendor_number), (2, info.product_number), (3, info.revision_number),
                           (4, 0x5E000000 + self.node_id)):
            if (0x1018, sub) in out and not out[(0x1018, sub)] and value:
                out[(0x1018, sub)] = int(value)
        return out

    def _reset_application(self) -> None:
        """Power-up of the application: every object back to the file's value."""
        self.master_heartbeat_lost = False

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
            try:
                var = self._var(index, sub)
            except SdoAbortedError:
                pdo.valid = False                            # a file's default the device lacks
                continue
            if var.data_type not in STRUCT_CODES:
                pdo.valid = False
                continue
            entries.append((index, sub))
            fmt += STRUCT_CODES[var.data_type]
        pdo.entries = entries
        pdo.codec = struct.Struct(fmt)
        pdo.getters = tuple(self._getter(index, sub) for index, sub in entries)
        pdo.pending = None

    def _getter(self, index: int, sub: int) -> Callable[[], int]:
        """A zero-argument reader of a mapped object, equal to ``self._get(index, sub)`` at
        every call (an application reads its process data directly)."""
        return functools.partial(self._get, index, sub)

    def _var(self, index: int, sub: int) -> odmod.ODVariable:
        var = lookup(self.od, index, sub)
        if var is None:
            raise SdoAbortedError(SdoAbortCode.NO_OBJECT if index not in self.od
                                  else SdoAbortCode.NO_SUBINDEX)
        return var

    # ------------------------------------------------------------------ PDO codec

    def _pack_tpdo(self, pdo: _Pdo) -> bytes:
        return pdo.codec.pack(*[get() for get in pdo.getters])

    def _apply_rpdo(self, pdo: _Pdo, data: bytes) -> None:
        values = pdo.codec.unpack_from(data)
        for (index, sub), value in zip(pdo.entries, values):
            try:
                self._put(index, sub, value)
            except SdoAbortedError:
                pass  # an invalid value in a PDO is ignored (no SDO to abort)

    # ------------------------------------------------------------------ object access

    def _get(self, index: int, sub: int) -> int:
        """Current value of an object: the application's process data, else the store."""
        if index == 0x1001:
            return self._error_register()
        if index == 0x1003:
            if sub == 0:
                return len(self._err_history)
            return self._err_history[sub - 1] if sub <= len(self._err_history) else 0
        return self._store[(index, sub)]

    def _put(self, index: int, sub: int, value: int) -> None:
        """Write an object (SDO or RPDO) with its side effects; SdoAbortedError if refused."""
        if index == 0x1003:
            if sub == 0 and value == 0:
                self._err_history.clear()
                return
            raise SdoAbortedError(SdoAbortCode.VALUE_RANGE)
        if 0x1600 <= index <= 0x17FF or 0x1A00 <= index <= 0x1BFF:
            self._check_mapping(index, sub, value)
        if (0x1400 <= index <= 0x15FF or 0x1800 <= index <= 0x19FF) and sub == 1:
            if value & 0x1FFFF800 and not value & 0x20000000:
                raise SdoAbortedError(SdoAbortCode.VALUE_RANGE)
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
        """CiA 301 §7.4.8.x: a mapping entry names a mappable object of its length; <= 64 bit,
        at most the entries the mapping object has."""
        rpdo = index < 0x1A00
        if sub == 0:
            capacity = self.dictionary.mapping_capacity('rpdo' if rpdo else 'tpdo',
                                                       (index & 0x1FF) + 1)
            if value > capacity:
                raise SdoAbortedError(SdoAbortCode.VALUE_HIGH)
            bits = 0
            for i in range(1, value + 1):
                bits += self._store.get((index, i), 0) & 0xFF
                self._check_entry(self._store.get((index, i), 0), rpdo=rpdo)
            if bits > 64:
                raise SdoAbortedError(SdoAbortCode.PDO_LENGTH)
        elif value:
            self._check_entry(value, rpdo=rpdo)

    def _check_entry(self, raw: int, *, rpdo: bool) -> None:
        idx, sub, bits = raw >> 16, (raw >> 8) & 0xFF, raw & 0xFF
        try:
            var = self._var(idx, sub)
        except SdoAbortedError:
            raise SdoAbortedError(SdoAbortCode.NOT_MAPPABLE) from None
        if not var.pdo_mappable or var.data_type not in STRUCT_CODES or len(var) != bits \
                or (rpdo and not var.writable) or (not rpdo and not var.readable):
            raise SdoAbortedError(SdoAbortCode.NOT_MAPPABLE)

    # SdoServer's node interface (CiA 301 §7.2.4; bytes in, bytes out)
    def get_data(self, index: int, subindex: int, check_readable: bool = False) -> bytes:
        var = self._var(index, subindex)
        if check_readable and not var.readable:
            raise SdoAbortedError(SdoAbortCode.READ_WRITE_ONLY)
        return var.encode_raw(self._get(index, subindex))

    def set_data(self, index: int, subindex: int, data: bytes,
                 check_writable: bool = False) -> None:
        var = self._var(index, subindex)
        if check_writable and not var.writable:
            raise SdoAbortedError(SdoAbortCode.WRITE_READ_ONLY)
        if var.data_type in odmod.NUMBER_TYPES and 8 * len(data) != len(var):
            raise SdoAbortedError(SdoAbortCode.LENGTH_MISMATCH)
        value = var.decode_raw(bytes(data))
        if not isinstance(value, int):
            self._store[(index, subindex)] = value
            return
        if var.min is not None and value < var.min:
            raise SdoAbortedError(SdoAbortCode.VALUE_LOW)
        if var.max is not None and value > var.max:
            raise SdoAbortedError(SdoAbortCode.VALUE_HIGH)
        self._put(index, subindex, int(value))
