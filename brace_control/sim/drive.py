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
* CSP as a servo drive does it (CiA 402-2 §"cyclic synchronous position mode"): the
  target 607Ah and the velocity offset 60B1h (counts/s, velocity feed-forward) latched
  at SYNC k are the end point of a segment that starts at the previous target (and
  offset) and is interpolated linearly over the interpolation period 60C2h
  (``value x 10^index`` s; the reference holds at the new target after one period if
  the next SYNC is late). A position loop on the encoder count (see
  :meth:`SimulatedDrive._csp_step`): ``v_cmd = v_ff + Kp (r - x)``, ``Kp = 2 pi
  bandwidth``, integrated in sub-steps with ``Kp h <= 0.2``; beyond
  ``e_lin = 0.9 a_max / Kp^2`` the feedback follows the braking curve
  ``sqrt(2 (0.9 a_max) (|e| - e_lin / 2))`` instead, so a large error (a step of the
  target) is closed without overshoot. The motor's speed and acceleration are clamped
  at the actuator's limits (``max_velocity`` and 607Fh, ``max_acceleration``). Entering
  CSP control (OPERATION ENABLED, or mode 8 while enabled) the reference, 607Ah and
  60B1h take the actual position and zero: no jump whatever 607Ah held before.
  Software limits 607Dh (checked once homed), hard end stops (the stroke), following
  error 6065h/6066h against the position demand 6062h, quick stop 605Ah/6085h (its own
  deceleration ramp, not the position loop), fault reaction.
* An incremental encoder: 6064h reads 0 at power-up (and after NMT reset node) until
  homed. Positions in counts inside, metres outside.

Faults and their EMCY codes (:class:`~brace_control.can.cia402.EmcyCode`, CiA 301 Table 21
/ CiA 402; the codes, states and statusword bits are those of :mod:`brace_control.can.cia402`,
shared with the master): following error 8611h,
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

import functools
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from canopen.sdo import SdoAbortedError

from ..can.cia402 import (STATE_STATUSWORD, EmcyCode, NmtState, OpMode, SdoAbortCode, State402,
                          Statusword)
from ..can.dictionary import STRUCT_CODES, ObjectRef
from ..can.pdo import LOAD_CELL_INPUT
from ..can.units import LoadInput
from .device import SimulatedDevice

__all__ = [
    'DriveLimits', 'SimulatedDrive', 'NmtState', 'State402', 'EmcyCode',
    'MODE_CSP', 'MODE_HOMING', 'DEFAULT_BANDWIDTH_HZ',
]

MODE_CSP = int(OpMode.CYCLIC_SYNC_POSITION)
MODE_HOMING = int(OpMode.HOMING)

#: Position-loop bandwidth (Hz) of the simulated drives unless told otherwise: position
#: loops of small servo drives close at tens of Hz (their velocity loops, not modelled
#: here, at hundreds); 30 Hz gives ``Kp = 2 pi 30 = 188 1/s``, well inside a 500 Hz SYNC
#: (``Kp T = 0.38``, two sub-steps), and rejects a disturbance within ``5 / Kp = 27 ms``.
DEFAULT_BANDWIDTH_HZ = 30.0
#: what a CiA 402 drive answers in its device type 1000h (CiA 301 7.5.2.1: profile 402 in
#: bits 0-15, 02h "servo drive" in bits 16-23) where its file leaves 1000h at 0 or unset:
#: a real drive reports its own, and some vendors' EDS (maxon's EPOS2, CiA's sample 402
#: device) say nothing
CIA402_DEVICE_TYPE = 0x00020192
# sub-steps of the position loop per SYNC: Kp h at most this (explicit Euler of the
# first-order loop is monotone for Kp h < 1)
_MAX_KP_H = 0.2
# share of the motor's acceleration limit the large-error braking curve uses (the
# remainder lets the acceleration-limited motor follow its own braking curve without
# overshoot in discrete time)
_BRAKING_SHARE = 0.9

_SW_VOLTAGE_ENABLED = int(Statusword.VOLTAGE_ENABLED)
_SW_WARNING = int(Statusword.WARNING)
_SW_REMOTE = int(Statusword.REMOTE)
_SW_TARGET_REACHED = int(Statusword.TARGET_REACHED)
_SW_INTERNAL_LIMIT = int(Statusword.INTERNAL_LIMIT)
_SW_OP_12 = int(Statusword.OP_SPECIFIC_12)     # CSP: follows the command; homing: attained
_SW_OP_13 = int(Statusword.OP_SPECIFIC_13)     # CSP: following error; homing: error

_POWERED = frozenset((State402.READY_TO_SWITCH_ON, State402.SWITCHED_ON,
                      State402.OPERATION_ENABLED, State402.QUICK_STOP_ACTIVE))
# the statusword bits a state alone sets: bits 0-3, 5, 6 of CiA 402-2 table 30, remote (9),
# voltage enabled (4) in the powered states
_STATE_BITS = {state: bits | _SW_REMOTE | (_SW_VOLTAGE_ENABLED if state in _POWERED else 0)
               for state, bits in STATE_STATUSWORD.items()}


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


class SimulatedDrive(SimulatedDevice):
    """A simulated CiA 402 drive with an incremental encoder and a load-cell input (2401h).

    :param node_id: CANopen node id 1..127.
    :param eds: the drive's EDS (``config/lumbar_drive.eds``); the object dictionary of
        the device, its access types and default values.
    :param limits: the actuator (SI).
    :param initial_length_m: the actuator's physical length at power-up (the parked brace).
    :param send: ``send(cob_id, data)`` puts a frame on the bus; ``None`` until a
        :class:`~brace_control.sim.host.SimBus` attaches the drive.
    :param clock: monotonic time source (s), for heartbeats and event timers.
    :param bandwidth_hz: position-loop bandwidth (Hz), ``Kp = 2 pi bandwidth_hz`` (1/s);
        see :meth:`_csp_step`.

    The drive is inert until :meth:`power_on` (boot-up message, PRE-OPERATIONAL).
    """

    def __init__(self, node_id: int, eds: str | Path, *, limits: DriveLimits | None = None,
                 initial_length_m: float | None = None,
                 send: Callable[[int, bytes], None] | None = None,
                 clock: Callable[[], float] = time.monotonic,
                 bandwidth_hz: float = DEFAULT_BANDWIDTH_HZ,
                 load_cell: tuple[int, int] = (LOAD_CELL_INPUT, 0), polarity: int = 1,
                 absolute_encoder: bool = False) -> None:
        if polarity not in (1, -1):
            raise ValueError(f'polarity must be +1 or -1, got {polarity!r}')
        #: +1, or -1: the encoder counts down as the actuator lengthens (its motor wired the
        #: other way round); the drive's position loop works on its own counts either way
        self.polarity = int(polarity)
        #: an absolute encoder: 6064h is the installed length in counts from power-up (no
        #: homing: ``can.homing_method: 0``); else incremental, 0 at power-up
        self.absolute_encoder = bool(absolute_encoder)
        if isinstance(bandwidth_hz, bool) or not isinstance(bandwidth_hz, (int, float)) \
                or not math.isfinite(bandwidth_hz) or bandwidth_hz <= 0.0:
            raise ValueError(f'position-loop bandwidth must be a positive number of Hz, '
                             f'got {bandwidth_hz!r}')
        #: position-loop bandwidth (Hz) and gain ``Kp = 2 pi bandwidth`` (1/s)
        self.bandwidth_hz = float(bandwidth_hz)
        self.kp = 2.0 * math.pi * self.bandwidth_hz
        self.limits = limits or DriveLimits()
        cpm = self.limits.counts_per_m
        self._cpm = cpm
        # ---- physical actuator (SI) ----
        mid = 0.5 * (self.limits.stroke_min + self.limits.stroke_max)
        self.length_m = float(mid if initial_length_m is None else initial_length_m)
        self.velocity_mps = 0.0
        #: the object the load cell is wired to (2401h, or a drive's analog input such as
        #: 3220h:1), and what that input can show (its data type from the dictionary)
        self.load_cell = (int(load_cell[0]), int(load_cell[1]))
        self.load_cell_counts: int | float = 0      # its reading, set by the physics each SYNC
        self.force_n = 0.0              # true actuator force (for 6077h)
        # ---- fault injection state ----
        self.stalled = False            # actuator mechanically blocked
        self.encoder_frozen_at: int | None = None   # 6064h frozen at this value
        self.encoder_jump_counts = 0    # added to 6064h
        self.injected_warning = False
        #: under local control (a panel, a setup tool): statusword bit 9 (remote) clear, the
        #: controlword from the bus ignored
        self.local_control = False
        self._injected_faults: set[int] = set()
        self._ff_mapped = True          # an RPDO carries 60B1h (else the demand's slope)
        self._sync_dt = 0.002           # the last SYNC interval (60C2h absent: the period)
        super().__init__(node_id, eds, send=send, clock=clock)
        var = self.dictionary.var(ObjectRef(*self.load_cell))
        self.load_input = LoadInput.of(STRUCT_CODES[var.data_type]) \
            if var is not None and var.data_type in STRUCT_CODES else LoadInput.INT16
        #: the modes of operation 6060h takes: 6502h's, else CSP and homing
        self.modes = frozenset(self.dictionary.supported_modes() or (MODE_CSP, MODE_HOMING))
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
        # CSP reference segment (m, m/s; SI of the actuator): from the previous target and
        # velocity offset to the ones latched at the last SYNC, over _seg_period_s
        self._seg_from_m = self.length_m
        self._seg_to_m = self.length_m
        self._vff_from = 0.0
        self._vff_to = 0.0
        self._seg_t = 0.0               # s since the segment started (its SYNC)
        self._seg_period_s = 0.002      # 60C2h at the segment's start
        self._demand_m = self.length_m  # position demand (6062h) after the last motion step
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
        # the state's bits 0-3, 5, 6 (bit 5 quick stop is active low: clear only in
        # QUICK STOP ACTIVE), CiA 402-2 table 30
        sw = _STATE_BITS[self.state]
        if self.local_control:
            sw &= ~_SW_REMOTE
        if (self.injected_warning or self.master_heartbeat_lost) and self.warning:
            sw |= _SW_WARNING
        if self._limit_active or self._at_hard_stop:
            sw |= _SW_INTERNAL_LIMIT
        mode = self._store[(0x6061, 0)]
        if mode == MODE_HOMING:
            if self._homing_attained:
                sw |= _SW_OP_12 | _SW_TARGET_REACHED
            if self._homing_error:
                sw |= _SW_OP_13
        elif mode == MODE_CSP:
            if self.state == State402.OPERATION_ENABLED:
                sw |= _SW_OP_12                # drive follows the command value
                if abs(self._fe_counts) <= self._store[(0x6065, 0)]:
                    sw |= _SW_TARGET_REACHED
            elif abs(self.velocity_mps) < 1e-9:
                sw |= _SW_TARGET_REACHED
            if self._fe_time_s > 0.0:
                sw |= _SW_OP_13                # following error
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

    def _firmware(self) -> dict[tuple[int, int], int]:
        """The drive's own settings of the CiA 402 parameters its dictionary does not show
        (they cannot be read or written, but the firmware has them): quick stop option 2
        (ramp, then SWITCH ON DISABLED), abort connection option 1 (fault), following-error
        monitoring off (6065h = FFFFFFFFh), no software limits, no home offset, the
        actuator's own speed and ramps."""
        acc = round(self.limits.max_acceleration * self._cpm)
        return {(0x6007, 0): 1, (0x605A, 0): 2, (0x6065, 0): 0xFFFFFFFF, (0x6066, 0): 0,
                (0x607F, 0): 0xFFFFFFFF, (0x6083, 0): acc, (0x6084, 0): acc, (0x6085, 0): acc,
                (0x607D, 1): 0, (0x607D, 2): 0, (0x607C, 0): 0, (0x6098, 0): 0, (0x60B1, 0): 0,
                (0x6060, 0): 0, (0x6061, 0): 0, (0x1014, 0): 0x80 + self.node_id}

    def _defaults(self) -> dict[tuple[int, int], int]:
        out = super()._defaults()
        if (0x1000, 0) in out and not out[(0x1000, 0)]:
            out[(0x1000, 0)] = CIA402_DEVICE_TYPE
        return out

    def _reset_application(self) -> None:
        """Power-up of the drive application: encoder counts restart at 0, not homed (an
        absolute encoder reads the length at once)."""
        if not self._store:
            self._store.update(self._defaults())
        for key, value in self._firmware().items():
            if self.dictionary.var(ObjectRef(*key)) is None:
                self._store.setdefault(key, value)
        self._store[(0x6061, 0)] = self._store.get((0x6060, 0), 0)
        self._enc_zero = 0 if self.absolute_encoder else math.floor(self.length_m * self._cpm)
        self._home_shift = 0
        self.homed = self.absolute_encoder
        self._homing_attained = False
        self._homing_error = False
        self._faults.clear()
        self._controlword = 0
        self._cw_prev_fault_bit = False
        self._cw_prev_homing_bit = False
        self.velocity_mps = 0.0
        self._fe_time_s = 0.0
        self._target = self._true_position_counts()
        self._seg_from_m = self._seg_to_m = self._demand_m = self.length_m
        self._vff_from = self._vff_to = 0.0
        self._seg_t = 0.0
        self.master_heartbeat_lost = False
        # NOT READY TO SWITCH ON -> SWITCH ON DISABLED (transition 1, automatic)
        self.state = State402.SWITCH_ON_DISABLED

    def _getter(self, index: int, sub: int) -> Callable[[], int]:
        """A zero-argument reader of a mapped object, equal to ``self._get(index, sub)`` at
        every call: the feedback TPDO's process data (statusword, position actual, load cell)
        read directly, every other object through :meth:`_get`."""
        cls = type(self)
        if index == 0x6041:
            return functools.partial(cls.statusword.fget, self)
        if index == 0x6064:
            return functools.partial(cls.position_counts.fget, self)
        if (index, sub) == self.load_cell:
            return functools.partial(getattr, self, 'load_cell_counts')
        return functools.partial(self._get, index, sub)

    def _rebuild_comm(self) -> None:
        super()._rebuild_comm()
        self._ff_mapped = self.mapped(0x60B1, 0)

    def _fault_codes(self) -> set[int]:
        return self._faults

    # ------------------------------------------------------------------ object access

    def _get(self, index: int, sub: int) -> int:
        """Current value of an object: process data live, parameters from the store."""
        if index == 0x6041:
            return self.statusword
        if index == 0x6064:
            return self.position_counts
        if (index, sub) == self.load_cell:
            return self.load_cell_counts
        if index == 0x6062:
            return self._length_to_counts(self._demand_m)
        if index == 0x606C:
            return round(self.polarity * self.velocity_mps * self._cpm)
        if index == 0x60F4:
            return self._fe_counts
        if index == 0x6077:
            return max(-32768, min(32767, round(self.polarity * 1000.0 * self.force_n / self.limits.max_force)))
        if index == 0x603F:
            return self._error_code
        if index == 0x6040:
            return self._controlword
        if index == 0x607A:
            return self._target
        return super()._get(index, sub)

    def _put(self, index: int, sub: int, value: int) -> None:
        """Write an object (SDO or RPDO) with its side effects; SdoAbortedError if refused."""
        if index == 0x6040:
            self._on_controlword(value)
            return
        if index == 0x607A:
            self._target = value
            return
        if index == 0x6060:
            if value not in self.modes:          # 6502h: the modes this drive has
                raise SdoAbortedError(SdoAbortCode.VALUE_RANGE)
            self._store[(0x6060, 0)] = value
            if self._store[(0x6061, 0)] != value:
                self._store[(0x6061, 0)] = value
                self._homing_attained = False
                self._homing_error = False
                self._cw_prev_homing_bit = bool(self._controlword & 0x10)
                if value == MODE_CSP and self.state == State402.OPERATION_ENABLED:
                    self._hold_actual_position()
            return
        super()._put(index, sub, value)

    def _after_sync(self) -> None:
        if self.state == State402.OPERATION_ENABLED and self._store[(0x6061, 0)] == MODE_CSP:
            self._start_segment()

    def _timer_step(self, now: float) -> float:
        # no SYNC for long: the fault reaction still ends (motor stopped)
        if self.state == State402.FAULT_REACTION_ACTIVE and self._last_sync_t is not None \
                and now - self._last_sync_t > 0.05:
            self.velocity_mps = 0.0
            self._set_state(State402.FAULT)
        return math.inf

    # ------------------------------------------------------------------ CiA 402 device control

    def _set_state(self, state: State402) -> None:
        if state == self.state:
            return
        entering_enabled = state == State402.OPERATION_ENABLED
        self.state = state
        if entering_enabled:
            self._fe_time_s = 0.0
            self._hold_actual_position()
        if state not in (State402.OPERATION_ENABLED, State402.QUICK_STOP_ACTIVE,
                         State402.FAULT_REACTION_ACTIVE):
            self.velocity_mps = 0.0     # motor disabled; the lead screw holds

    def _on_controlword(self, cw: int) -> None:
        """CiA 402 device control: the controlword command decoding (Table 'commands')."""
        cw &= 0xFFFF
        self._controlword = cw
        if self.local_control:
            return          # under local control (its panel, a setup tool): remote bit 9 clear
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

    def _length_to_counts(self, length_m: float) -> int:
        """The (homed) encoder count a length falls in."""
        return self.polarity * (math.floor(length_m * self._cpm) - self._enc_zero) + self._home_shift

    def _true_position_counts(self) -> int:
        return self._length_to_counts(self.length_m)

    def _counts_to_length(self, counts: int) -> float:
        """The length at the centre of an encoder count (what the drive's loop aims at)."""
        return (self.polarity * (counts - self._home_shift) + self._enc_zero + 0.5) / self._cpm

    def _target_in_limits(self) -> bool:
        lo, hi = self._store[(0x607D, 1)], self._store[(0x607D, 2)]
        if not self.homed or lo >= hi:
            return True
        return lo <= self._target <= hi

    def _hold_actual_position(self) -> None:
        """Entering CSP control: the reference, 607Ah and 60B1h take the actual position
        and zero velocity offset (no jump, whatever a stale 607Ah held)."""
        self._target = self._true_position_counts()
        here = self._counts_to_length(self._target)
        self._seg_from_m = self._seg_to_m = self._demand_m = here
        self._vff_from = self._vff_to = 0.0
        self._seg_t = 0.0
        self._store[(0x60B1, 0)] = 0

    def _start_segment(self) -> None:
        """SYNC in CSP: the reference runs from the previous target and velocity offset to
        the ones just latched (607Ah, 60B1h), linearly over the interpolation period 60C2h
        (``value x 10^index`` s; 0 s: the reference steps to the target; a drive without
        60C2h: the SYNC interval). A drive whose RPDOs do not carry 60B1h feeds its loop
        forward from the reference's own slope (servo drives' internal velocity feed-forward)."""
        self._seg_from_m = self._seg_to_m
        self._seg_to_m = self._counts_to_length(self._target)
        self._seg_t = 0.0
        if (0x60C2, 1) in self._store:
            self._seg_period_s = self._store[(0x60C2, 1)] * 10.0 ** self._store[(0x60C2, 2)]
        else:
            self._seg_period_s = self._sync_dt
        if self._ff_mapped:
            self._vff_from = self._vff_to
            self._vff_to = self.polarity * self._store[(0x60B1, 0)] / self._cpm
        else:
            period = self._seg_period_s
            slope = (self._seg_to_m - self._seg_from_m) / period if period > 0.0 else 0.0
            self._vff_from = self._vff_to = slope

    def _csp_step(self, dt: float) -> None:
        """Advance the actuator ``dt`` seconds under the CSP position loop.

        Reference over the segment (see :meth:`_start_segment`), ``s = min(1, t / T_ip)``:
        ``r(t) = r_prev + (r_new - r_prev) s``, ``v_ff(t) = v_prev + (v_new - v_prev) s``.
        Position loop on the encoder reading ``x_m`` (centre of its count), error
        ``e = r - x_m``::

            v_cmd = v_ff + Kp e                                   |e| <= e_lin
            v_cmd = v_ff + sign(e) sqrt(2 a_b (|e| - e_lin / 2))  |e| >  e_lin

        with ``Kp = 2 pi bandwidth``, ``a_b = 0.9 a_max``, ``e_lin = a_b / Kp^2`` (the two
        branches meet with equal value and slope; the square-root branch is the speed
        from which braking at ``a_b`` stops at ``e_lin / 2`` before the reference, so a
        step of the target is closed without overshoot). The motor: ``|v| <= min(
        max_velocity, 607Fh)``, ``|dv/dt| <= max_acceleration``; explicit Euler in ``n``
        sub-steps ``h = dt / n`` with ``Kp h <= 0.2``, the error at the sub-step's start and
        ``v_ff`` at its midpoint (so the linear loop ``x' = v_ff + Kp (r - x)`` tracks a ramp
        ``r = v t`` with the lag ``v / Kp`` of its continuous solution, and a parabola
        with feed-forward without the Euler lag ``a h / (2 Kp)`` of a start-point ``v_ff``).
        Plain floats: this runs for every drive at every SYNC. At rest on the reference (the
        drive holding, every SYNC while the brace is still) the error is exactly 0 in every
        sub-step, so the loop commands ``v = 0`` and leaves ``x`` where it is; only its clock
        advances: that case skips the loop (:meth:`_csp_loop`) with the very same result.
        """
        lim = self.limits
        cpm = self._cpm
        x = self.length_m
        r1 = self._seg_to_m
        if (self.velocity_mps == 0.0 and self._vff_from == 0.0 and self._vff_to == 0.0
                and self._seg_from_m == r1 and lim.stroke_min < x < lim.stroke_max
                and lim.max_acceleration >= 0.0 and (math.floor(x * cpm) + 0.5) / cpm == r1
                and min(lim.max_velocity, self._store[(0x607F, 0)] / cpm) >= 0.0):
            # e = r - x_m = 0: v_cmd = v_ff + Kp e = 0, within every clamp; x += 0 * h
            n = max(1, math.ceil(dt * self.kp / _MAX_KP_H))
            h = dt / n
            t = self._seg_t
            for _ in range(n):
                t += h
            self._seg_t = t
            self.length_m = x + 0.0          # the loop's x += 0.0 (only a -0.0 would change)
            self.velocity_mps = 0.0
            self._at_hard_stop = False
            period = self._seg_period_s
            r0 = self._seg_from_m
            self._demand_m = r1 if t >= period else r0 + (r1 - r0) * (t / period)
            return
        self._csp_loop(dt)

    def _csp_loop(self, dt: float) -> None:
        """The sub-steps of :meth:`_csp_step` (its docstring has the equations)."""
        lim = self.limits
        cpm = self._cpm
        kp = self.kp
        amax = lim.max_acceleration
        vmax = min(lim.max_velocity, self._store[(0x607F, 0)] / cpm)
        a_b = _BRAKING_SHARE * amax
        e_lin = a_b / (kp * kp)
        n = max(1, math.ceil(dt * kp / _MAX_KP_H))
        h = dt / n
        dv = amax * h
        period = self._seg_period_s
        t = self._seg_t
        r0, r1 = self._seg_from_m, self._seg_to_m
        g0, g1 = self._vff_from, self._vff_to
        dr, dg = r1 - r0, g1 - g0
        x, v = self.length_m, self.velocity_mps
        lo, hi = lim.stroke_min, lim.stroke_max
        stalled = self.stalled
        floor, sqrt = math.floor, math.sqrt
        hard = False
        for _ in range(n):
            # r exactly the target at the segment's end (no rounding residue at rest)
            e = (r1 if t >= period else r0 + dr * (t / period)) - (floor(x * cpm) + 0.5) / cpm
            if e > e_lin:
                vc = sqrt(2.0 * a_b * (e - 0.5 * e_lin))
            elif e < -e_lin:
                vc = -sqrt(2.0 * a_b * (-e - 0.5 * e_lin))
            else:
                vc = kp * e
            tm = t + 0.5 * h                 # feed-forward at the sub-step's midpoint
            vc += g1 if tm >= period else g0 + dg * (tm / period)
            if vc > vmax:
                vc = vmax
            elif vc < -vmax:
                vc = -vmax
            if vc > v + dv:
                vc = v + dv
            elif vc < v - dv:
                vc = v - dv
            v = 0.0 if stalled else vc
            x += v * h
            if x <= lo:
                x, v, hard = lo, 0.0, True
            elif x >= hi:
                x, v, hard = hi, 0.0, True
            t += h
        self._seg_t = t
        self.length_m = x
        self.velocity_mps = v
        self._at_hard_stop = hard
        self._demand_m = r1 if t >= period else r0 + dr * (t / period)

    def _motion_step(self, dt: float) -> None:
        """Advance the actuator by ``dt`` seconds: the CSP loop in OPERATION ENABLED, the
        quick-stop / fault-reaction ramp, else nothing (the lead screw holds)."""
        self._last_sync_t = self._clock()
        if dt <= 0.0:
            return
        self._sync_dt = dt
        st = self.state
        csp = st == State402.OPERATION_ENABLED and self._store[(0x6061, 0)] == MODE_CSP
        if csp:
            if not self._target_in_limits():
                self._limit_active = True
                self._enter_fault(EmcyCode.REFERENCE_LIMIT)
                self._motion_step(dt)
                return
            self._limit_active = False
            self._csp_step(dt)
        else:
            v = self.velocity_mps
            if st in (State402.QUICK_STOP_ACTIVE, State402.FAULT_REACTION_ACTIVE):
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
            lim = self.limits
            length = self.length_m + v_new * dt
            self._at_hard_stop = False
            if length <= lim.stroke_min:
                length, v_new = lim.stroke_min, 0.0
                self._at_hard_stop = True
            elif length >= lim.stroke_max:
                length, v_new = lim.stroke_max, 0.0
                self._at_hard_stop = True
            self.length_m = length
            self.velocity_mps = v_new
            self._demand_m = length
        # following error (6065h window, 6066h time out) of the position demand 6062h,
        # CSP in OPERATION ENABLED only
        if self.state == State402.OPERATION_ENABLED and self._store[(0x6061, 0)] == MODE_CSP:
            self._fe_counts = self._length_to_counts(self._demand_m) - self._true_position_counts()
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
