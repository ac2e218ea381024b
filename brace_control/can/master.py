"""The CiA 402 master: boot, configure, enable, home and drive the brace's drives over CAN.

:class:`BraceMaster` opens a python-can bus from the device YAML (``can.interface``,
``can.channel``, ``can.bitrate``), puts a :class:`canopen.Network` on it (canopen's
Notifier is the only receive thread) and runs one cyclic thread that produces SYNC
(COB-ID 80h) at ``can.sync_rate_hz`` and the master heartbeat (700h + 127).

Per cycle (docs/can.md "PDO mapping"): monitor the TPDO1 samples that answered the
previous SYNC (statusword 6041h, position actual 6064h, load cell 2401h), compute the
targets (latest setpoint, step-limited; hold when stale or stopped), send each drive's
RPDO1 (controlword 6040h + target position 607Ah) as a raw frame, then SYNC.

Boot (:meth:`BraceMaster.boot`): wait for each drive's boot-up or heartbeat
(``can.boot_timeout``) → NMT pre-operational → SDO configuration (1017h, 1016h, 6007h,
605Ah, 6065h, 607Dh, 6060h, 60C2h, 1006h, 607Fh, 6083h–6085h, 6098h, 607Ch) → PDO mapping
by SDO → NMT operational.

Safety (SAFETY.md 1–9, 11; :mod:`.supervision`): any fault latches a protective stop
(quick stop 6040h = 0002h, 605Ah = 6 keeps the drives in QUICK STOP ACTIVE, holding)
until :meth:`BraceMaster.recover`, which resets drive faults and clears the latch only
when every cause is gone.

Typical use::

    with BraceMaster.from_device_config(load_device_config('lumbar_brace')) as m:
        m.boot(); m.home(); m.enable()
        m.set_targets([0.39, 0.39, 0.39])
        fb = m.feedback()          # SI: positions m, velocities m/s, forces N
"""
from __future__ import annotations

import enum
import logging
import math
import struct
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can
import canopen
import numpy as np

from ..config import ConfigError, DeviceConfig
from .cia402 import (Controlword, NmtState, OpMode, State402, Statusword, controlword_towards,
                     decode_state, describe_statusword, emcy_description)
from .errors import (DriverInitializationError, DriverOperationError, DriverTimeoutError,
                     FaultLatchedError)
from .pdo import (LOAD_CELL_INPUT, RPDO1, TORQUE_ACTUAL, TPDO1, SdoWrite, frame_bits,
                  pdo_mapping_writes)
from .supervision import (Fault, FaultKind, Limits, Sample, Supervisor, check_sample,
                          check_step, decode_error_frame)
from .timing import PeriodStats, TimingReport, run_periodic
from .units import AxisScaling, actuator_kind, scaling_from_config

__all__ = ['BraceMaster', 'MasterConfig', 'MasterState', 'DriveStatus', 'BusStatus',
           'MasterStatus', 'Feedback']

log = logging.getLogger(__name__)

_EMCY = struct.Struct('<HB5s')
# statusword bits as plain ints for the per-cycle path (IntFlag arithmetic is slow)
_SW_FAULT = int(Statusword.FAULT)
_SW_WARNING = int(Statusword.WARNING)
_SW_LIMIT = int(Statusword.INTERNAL_LIMIT)
_SYNC_ID = 0x80


class MasterState(enum.Enum):
    """Where the master is; ``FAULT`` = protective stop latched."""

    CLOSED = 'closed'
    OPEN = 'open'                # bus open, heartbeat produced, drives not configured
    BOOTING = 'booting'
    DISABLED = 'disabled'        # drives OPERATIONAL (NMT), 402 not enabled
    ENABLED = 'enabled'          # drives OPERATION ENABLED, following setpoints
    HALTED = 'halted'            # quick stop on request (not a fault)
    HOMING = 'homing'
    FAULT = 'fault'              # protective stop latched until recover()


@dataclass(frozen=True)
class MasterConfig:
    """Everything the master needs, read from the device YAML (SI units)."""

    interface: str
    channel: str
    bitrate: int
    node_ids: tuple[int, ...]
    names: tuple[str, ...]
    eds: Path | None
    sync_rate_hz: float
    boot_timeout: float
    drive_heartbeat_ms: int
    heartbeat_consumer_ms: int
    master_heartbeat_ms: int
    master_node_id: int
    homing_method: int
    frame_log: str
    following_error_window: float
    scaling: AxisScaling
    limits: Limits
    home_lengths: tuple[float, ...] | None = None
    force_object: int = LOAD_CELL_INPUT
    spin_s: float = 0.0003           # busy-wait before each SYNC deadline
    send_timeout: float = 0.0005     # never block the cycle on a full TX queue
    transition_timeout: float = 1.0  # s for a 402 transition of all drives
    thread_priority: int = 0         # SCHED_FIFO priority of the SYNC thread (0: normal)
    # a TPDO is attributed to the SYNC it answered from its bus timestamp (wall clock)

    @property
    def period(self) -> float:
        return 1.0 / self.sync_rate_hz

    @classmethod
    def from_device_config(cls, cfg: Mapping[str, Any], *, channel: str | None = None,
                           home_lengths: Sequence[float] | None = None,
                           **overrides: Any) -> MasterConfig:
        """Build from a :class:`~brace_control.config.DeviceConfig` (or nested mapping).

        ``home_lengths`` (m per actuator) default to IK(``mechanism.home_pose``) when the
        mechanism model can be built. ``channel`` and ``overrides`` replace YAML values.

        :raises ConfigError: a missing or inconsistent parameter, named.
        """
        dc = cfg if isinstance(cfg, DeviceConfig) else DeviceConfig(cfg)
        scaling = scaling_from_config(dc)
        limits = Limits.from_config(dc, scaling)
        node_ids = tuple(int(i) for i in dc.get_path('can.node_ids'))
        names = tuple(str(n) for n in dc.get_path('mechanism.actuator_names',
                                                  [f'a{i + 1}' for i in range(len(node_ids))]))
        if len(names) != len(node_ids):
            raise ConfigError(f'parameter can.node_ids has {len(node_ids)} ids for '
                              f'{len(names)} actuators {list(names)}')
        if len(set(node_ids)) != len(node_ids) or not all(1 <= i <= 127 for i in node_ids):
            raise ConfigError(f'parameter can.node_ids = {list(node_ids)}: distinct ids 1..127 expected')
        master_id = int(dc.get_path('can.master_node_id', 127))
        if master_id in node_ids:
            raise ConfigError(f'parameter can.master_node_id = {master_id} collides with a drive id')
        eds_name = str(dc.get_path('can.eds', '') or '')
        eds = dc.relative_file(eds_name) if eds_name else None
        if eds is not None and not eds.is_file():
            from ..config import config_dir
            alt = config_dir() / eds_name
            eds = alt if alt.is_file() else None
        if home_lengths is None:
            home_lengths = _home_lengths(dc)
        values: dict[str, Any] = dict(
            interface=str(dc.get_path('can.interface')),
            channel=channel or str(dc.get_path('can.channel')),
            bitrate=int(dc.get_path('can.bitrate')),
            node_ids=node_ids, names=names, eds=eds,
            sync_rate_hz=float(dc.get_path('can.sync_rate_hz')),
            boot_timeout=float(dc.get_path('can.boot_timeout')),
            drive_heartbeat_ms=int(dc.get_path('can.drive_heartbeat_ms')),
            heartbeat_consumer_ms=int(dc.get_path('can.heartbeat_consumer_ms')),
            master_heartbeat_ms=int(dc.get_path('can.master_heartbeat_ms')),
            master_node_id=master_id,
            homing_method=int(dc.get_path('can.homing_method', 35)),
            frame_log=str(dc.get_path('can.frame_log', '') or ''),
            spin_s=float(dc.get_path('can.sync_spin_us', 300)) * 1e-6,
            thread_priority=int(dc.get_path('can.sync_thread_priority', 0)),
            following_error_window=float(dc.get_path('safety.following_error_window')),
            scaling=scaling, limits=limits,
            home_lengths=None if home_lengths is None else tuple(float(x) for x in home_lengths),
            # linear actuators carry a load cell on 2401h; rotary drives report 6077h torque
            force_object=(LOAD_CELL_INPUT if actuator_kind(dc) == 'linear' else TORQUE_ACTUAL),
        )
        values.update(overrides)
        return cls(**values)


def _home_lengths(cfg: DeviceConfig) -> tuple[float, ...] | None:
    """IK(home_pose) of the device's mechanism, or ``None`` if the model is unavailable."""
    if 'mechanism' not in cfg:
        return None
    try:
        from ..mechanisms import mechanism_from_config
        mech = mechanism_from_config(cfg)
        return tuple(float(x) for x in mech.inverse(mech.home_pose))
    except ImportError:
        return None


@dataclass(frozen=True)
class DriveStatus:
    """One drive as the master sees it (diagnostics)."""

    name: str
    node_id: int
    nmt: str
    state: State402
    statusword: int
    position: float          # m
    velocity: float          # m/s
    force: float             # N
    target: float            # m, last target sent
    heartbeat_age: float     # s (inf: never heard)
    last_emcy: str           # '' if none
    samples: int


@dataclass(frozen=True)
class BusStatus:
    """Bus counters over the last ~second."""

    frames_per_s: float
    load: float              # fraction of the bit rate (worst-case stuffing)
    error_state: str         # 'active' | 'error passive' | 'bus off'
    error_frames: int
    send_failures: int


@dataclass(frozen=True)
class MasterStatus:
    state: MasterState
    drives: tuple[DriveStatus, ...]
    bus: BusStatus
    timing: TimingReport
    faults: tuple[Fault, ...]
    warnings: tuple[str, ...]
    stale_setpoint_holds: int
    homed: bool
    accepted_setpoints: int = 0        # setpoints passed the step limit and became goals


@dataclass(frozen=True)
class Feedback:
    """Latest measurements in SI, actuator order; ``stamp`` = perf_counter of the SYNC."""

    position: np.ndarray
    velocity: np.ndarray
    force: np.ndarray
    states: tuple[State402, ...]
    stamp: float
    valid: bool              # every drive has answered at least one SYNC


@dataclass
class _Setpoint:
    position: np.ndarray
    time: float              # perf_counter at reception
    seq: int
    stamp: float | None = None   # s, the sender's sample instant (header stamp), if any


@dataclass
class _Drive:
    index: int
    name: str
    node_id: int
    node: canopen.RemoteNode
    rpdo_id: int
    sample: Sample | None = None
    checked: Sample | None = None          # last sample the monitors saw
    history: deque = field(default_factory=lambda: deque(maxlen=6))   # (t, pos, sync index)
    velocity: float = 0.0
    samples: int = 0
    rx_time: float = -math.inf             # perf_counter of the last TPDO
    rx_total: int = 0                      # master's TPDO count at this drive's last TPDO
    hb_time: float = -math.inf             # monotonic of the last heartbeat / boot-up
    nmt: int | None = None
    booted: threading.Event = field(default_factory=threading.Event)
    emcy: tuple[int, int, float] | None = None     # code, register, monotonic
    emcy_nonzero_time: float = -math.inf
    target: int = 0                        # counts, sent in RPDO1
    goal: int | None = None                # counts of the last accepted setpoint (target ramps to it)
    recent: deque = field(default_factory=lambda: deque(maxlen=16))  # Samples, by SYNC
    sent: deque = field(default_factory=lambda: deque(maxlen=64))    # (SYNC index, target counts)
    target_f: float = 0.0                  # the ramp's target before rounding (counts)
    ramp_v: float = 0.0                    # the ramp's speed (counts per SYNC)
    goal_v: float = 0.0                    # the setpoint stream's speed (counts per SYNC)
    reset_phase: bool = False
    flagged: bool = False                  # warning / internal-limit bit seen last sample

    @property
    def state(self) -> State402:
        return decode_state(self.sample.statusword) if self.sample is not None else State402.UNKNOWN


class BraceMaster:
    """CiA 402 master of one device's drives (see the module docstring).

    :param config: :class:`MasterConfig` (``MasterConfig.from_device_config(cfg)``).
    :param bus: an already open python-can bus to use instead of opening one (tests,
        replays); the master shuts it down on :meth:`shutdown` only if it opened it.

    Thread model: canopen's Notifier thread runs the TPDO / heartbeat / EMCY / error
    frame callbacks; the SYNC thread runs the cycle; API calls (boot, enable, ...) come
    from any one caller thread at a time (serialised by a lock).
    """

    def __init__(self, config: MasterConfig, *, bus: can.BusABC | None = None) -> None:
        self.config = config
        self.scaling = config.scaling
        self.limits = config.limits
        # per-cycle bound on the RPDO target's change (counts): v_max for one SYNC period
        self._ramp_counts = max(1, math.ceil(self.limits.v_max * config.period * self.scaling.counts_per_unit))
        # ... and on its change: a_max for one SYNC period (counts per SYNC^2)
        self._ramp_acc = max(self.limits.a_max * config.period ** 2 * self.scaling.counts_per_unit, 1e-6)
        self.supervisor = Supervisor(on_fault=self._on_fault)
        self.stats = PeriodStats(config.period)
        self._own_bus = bus is None
        self._bus: can.BusABC | None = bus
        self.network: canopen.Network | None = None
        self._drives: list[_Drive] = []
        self._api_lock = threading.RLock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._frame_log: can.Listener | None = None
        self.state = MasterState.CLOSED
        # cycle inputs (written by API threads, read by the SYNC thread)
        self._pdo_running = False             # SYNC + RPDOs (else heartbeat only)
        self._supervising = False             # monitors armed (after boot)
        self._closing = False                 # shutdown: disable whatever the latch says
        self._desired = State402.SWITCH_ON_DISABLED
        self._reset_pulse = False
        self._homing_start = False
        self._tracking = False                 # targets follow setpoints
        self._setpoint: _Setpoint | None = None
        self._setpoint_seq = 0
        self._seq_at_enable = 0                # setpoint count and stale holds when enabled
        self._holds_at_enable = 0
        self._last_sp_seq = 0
        self._last_sp_time = -math.inf
        self._last_sp_stamp: float | None = None
        self._was_fresh = False
        self.stale_setpoint_holds = 0
        self.accepted_setpoints = 0
        self.homed = False
        self._recover_time = -math.inf
        # SYNC bookkeeping
        self._sync_index = 0
        self._sync_time = 0.0
        # (wall clock, perf_counter, index) of recent SYNCs: a TPDO is attributed to the
        # SYNC it answered by its bus timestamp, not by when our thread got to it
        self._sync_log: deque[tuple[float, float, int]] = deque(maxlen=128)
        #: the most SYNCs a TPDO1 may answer late and still be counted (see _answered_sync)
        self.attribution_window = 25
        self._tpdo_total = 0
        self._last_wake = 0.0
        self._grace_until = 0.0               # monotonic: after a host stall of this process
        self._hb_period = config.master_heartbeat_ms * 1e-3
        self._next_hb = 0.0
        #: all drives silent for this many SYNCs -> stale (one silent drive: stale_periods).
        #: From the master alone, "every drive silent" cannot be told from "this process
        #: did not get to receive", so the bound is the drives' own consumer time of our
        #: heartbeat (1016h = 2 x master_heartbeat_ms): by then they quick-stop themselves.
        self.all_silent_periods = max(config.limits.stale_periods,
                                      math.ceil(2 * config.master_heartbeat_ms * 1e-3 / config.period))
        self._hb_msg = can.Message(arbitration_id=0x700 + config.master_node_id,
                                   data=bytes([NmtState.OPERATIONAL]), is_extended_id=False)
        self._sync_msg = can.Message(arbitration_id=_SYNC_ID, data=b'', is_extended_id=False)
        # bus statistics
        self._rx_frames = 0
        self._rx_bits = 0
        self._tx_frames = 0
        self._tx_bits = 0
        self._rate = (0.0, 0.0)                # frames/s, load
        self._rate_mark = (time.perf_counter(), 0, 0)
        self._count_tx = True                 # False when own frames come back (frame log)
        self.error_frames = 0
        self.send_failures = 0
        self._last_send_failed = False
        self._bus_error_state = 'active'
        self._bus_off_time = -math.inf
        self._bus_restart_time = -math.inf

    # ------------------------------------------------------------------ construction

    @classmethod
    def from_device_config(cls, cfg: Mapping[str, Any], *, channel: str | None = None,
                           bus: can.BusABC | None = None, **overrides: Any) -> BraceMaster:
        """``BraceMaster(MasterConfig.from_device_config(cfg, channel=..., ...))``."""
        return cls(MasterConfig.from_device_config(cfg, channel=channel, **overrides), bus=bus)

    @property
    def names(self) -> tuple[str, ...]:
        return self.config.names

    @property
    def bus(self) -> can.BusABC | None:
        """The python-can bus (``None`` when closed)."""
        return self._bus

    def __enter__(self) -> BraceMaster:
        return self

    def __exit__(self, *exc: object) -> None:
        self.shutdown()

    # ------------------------------------------------------------------ bus

    def open(self) -> None:
        """Open the bus and the canopen Network, start the SYNC thread (heartbeat only).

        :raises DriverInitializationError: the interface / channel cannot be opened.
        """
        with self._api_lock:
            if self.state is not MasterState.CLOSED:
                return
            cfg = self.config
            log_path = cfg.frame_log
            if self._bus is None:
                try:
                    # own frames back to the listener only when logging: the log then holds
                    # both directions in bus order
                    self._bus = can.Bus(interface=cfg.interface, channel=cfg.channel,
                                        bitrate=cfg.bitrate, receive_own_messages=bool(log_path))
                except (can.CanError, OSError, ValueError, ImportError) as exc:
                    raise DriverInitializationError(
                        f'cannot open CAN bus interface={cfg.interface!r} channel={cfg.channel!r} '
                        f'bitrate={cfg.bitrate}: {exc}') from exc
            self._count_tx = not log_path
            net = canopen.Network(self._bus)
            net.listeners.append(_BusListener(self))
            if log_path:
                from .framelog import open_frame_log
                self._frame_log = open_frame_log(log_path)
                net.listeners.append(self._frame_log)
            for i, (name, node_id) in enumerate(zip(cfg.names, cfg.node_ids)):
                od: Any = str(cfg.eds) if cfg.eds is not None else canopen.ObjectDictionary()
                node = canopen.RemoteNode(node_id, od)
                net.add_node(node)
                d = _Drive(i, name, node_id, node, 0x200 + node_id)
                self._drives.append(d)
                net.subscribe(0x180 + node_id, self._tpdo_callback(d))
                net.subscribe(0x700 + node_id, self._heartbeat_callback(d))
                net.subscribe(0x80 + node_id, self._emcy_callback(d))
            net.connect()
            self.network = net
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, name='brace-can-sync', daemon=True)
            self._thread.start()
            self.state = MasterState.OPEN

    def boot(self, *, timeout: float | None = None) -> None:
        """Boot every drive to NMT OPERATIONAL with the configuration of docs/can.md.

        :raises DriverInitializationError: a drive did not boot within ``can.boot_timeout``
            (also latched as a BOOT_TIMEOUT fault) or rejected an SDO write.
        """
        with self._api_lock:
            if self._supervising:
                return                                   # booted already
            if self.state is MasterState.CLOSED:
                self.open()
            self.state = MasterState.BOOTING
            limit = self.config.boot_timeout if timeout is None else timeout
            deadline = time.monotonic() + limit
            for d in self._drives:
                d.booted.wait(max(0.0, deadline - 0.5 * limit - time.monotonic()))
            for d in self._drives:
                if not d.booted.is_set():
                    # booted before we listened, with no heartbeat (1017h = 0): NMT reset
                    # communication makes it send its boot-up message again
                    d.node.nmt.send_command(0x82)
            for d in self._drives:
                d.booted.wait(max(0.0, deadline - time.monotonic()))
            missing = [d for d in self._drives if not d.booted.is_set()]
            for d in missing:
                self.supervisor.report(
                    FaultKind.BOOT_TIMEOUT,
                    f'no boot-up or heartbeat from node {d.node_id} within '
                    f'{self.config.boot_timeout:g} s', drive=d.name,
                    still_present=self._heartbeat_missing(d))
            if missing:
                self.state = MasterState.FAULT
                raise DriverInitializationError(
                    'drive(s) did not boot: ' + ', '.join(
                        f'{d.name} (node {d.node_id})' for d in missing)
                    + f' within can.boot_timeout = {self.config.boot_timeout:g} s; '
                    'check power, wiring, node ids and bit rate')
            for d in self._drives:
                self._configure(d)
            self._pdo_running = True
            for d in self._drives:
                d.node.nmt.send_command(0x01)            # start remote node
            self._wait(lambda: all(d.nmt == NmtState.OPERATIONAL and d.sample is not None
                                   for d in self._drives),
                       timeout=max(0.5, 4 * self.config.drive_heartbeat_ms * 1e-3),
                       what='drives OPERATIONAL with TPDO1')
            for d in self._drives:
                d.target = self._actual_counts(d)
                d.checked = None
            self._supervising = True
            self._desired = State402.SWITCH_ON_DISABLED
            self.state = MasterState.FAULT if self.supervisor.latched else MasterState.DISABLED
            log.info('CAN master: %d drives OPERATIONAL on %s', len(self._drives), self.config.channel)

    def _configure(self, d: _Drive) -> None:
        """NMT pre-operational, then the SDO writes of docs/can.md, then the PDO mapping."""
        d.node.nmt.send_command(0x80)                    # enter pre-operational
        for w in self.sdo_writes(d.index):
            try:
                d.node.sdo.download(w.index, w.subindex, w.data())
            except (canopen.SdoAbortedError, canopen.SdoCommunicationError) as exc:
                raise DriverInitializationError(
                    f'{d.name} (node {d.node_id}) rejected {w.index:04X}h:{w.subindex} = '
                    f'{w.value} ({w.what}): {exc}') from exc
        try:
            raw = d.node.sdo.upload(0x1000, 0)
            device_type = struct.unpack('<I', raw[:4])[0]
            if device_type & 0xFFFF != 402:
                log.warning('%s: device type 1000h = %08Xh is not a CiA 402 drive',
                            d.name, device_type)
        except (canopen.SdoAbortedError, canopen.SdoCommunicationError, struct.error):
            pass

    def sdo_writes(self, index: int) -> list[SdoWrite]:
        """The configuration of drive ``index`` (actuator order), in write order."""
        cfg, sc = self.config, self.scaling
        node_id = cfg.node_ids[index]
        period_us = round(cfg.period * 1e6)
        ip_value, ip_index = _interpolation_period(cfg.period)
        lo, hi = self.limits.stroke_of(index)
        writes = [
            SdoWrite(0x1017, 0, 'H', cfg.drive_heartbeat_ms, 'producer heartbeat time (ms)'),
            SdoWrite(0x1016, 1, 'I', (cfg.master_node_id << 16) | (2 * cfg.master_heartbeat_ms),
                     "consumer heartbeat time of the master's heartbeat"),
            SdoWrite(0x6007, 0, 'h', 3, 'abort connection option: quick stop'),
            SdoWrite(0x605A, 0, 'h', 6, 'quick stop option: ramp, stay in QUICK STOP ACTIVE'),
            SdoWrite(0x6065, 0, 'I', max(1, round(cfg.following_error_window * sc.counts_per_unit)),
                     'following error window (counts)'),
            SdoWrite(0x6060, 0, 'b', int(OpMode.CYCLIC_SYNC_POSITION), 'mode: cyclic synchronous position'),
            SdoWrite(0x60C2, 1, 'B', ip_value, 'interpolation time period value'),
            SdoWrite(0x60C2, 2, 'b', ip_index, 'interpolation time index (10^index s)'),
            SdoWrite(0x1006, 0, 'I', period_us, 'communication cycle period (us)'),
            SdoWrite(0x607F, 0, 'I', sc.velocity_to_counts(self.limits.v_max), 'max profile velocity'),
            SdoWrite(0x6083, 0, 'I', sc.acceleration_to_counts(self.limits.a_max), 'profile acceleration'),
            SdoWrite(0x6084, 0, 'I', sc.acceleration_to_counts(self.limits.a_max), 'profile deceleration'),
            SdoWrite(0x6085, 0, 'I', sc.acceleration_to_counts(self.limits.a_max), 'quick stop deceleration'),
            SdoWrite(0x6098, 0, 'b', cfg.homing_method, 'homing method'),
        ]
        if math.isfinite(lo) and math.isfinite(hi):
            writes += [SdoWrite(0x607D, 1, 'i', sc.to_counts(lo), 'software position limit min'),
                       SdoWrite(0x607D, 2, 'i', sc.to_counts(hi), 'software position limit max')]
        if cfg.home_lengths is not None:
            writes.append(SdoWrite(0x607C, 0, 'i', sc.to_counts(cfg.home_lengths[index]),
                                   'home offset = IK(home_pose) length'))
        return writes + pdo_mapping_writes(node_id, force_object=cfg.force_object)

    # ------------------------------------------------------------------ callbacks (Notifier thread)

    def _tpdo_callback(self, d: _Drive) -> Callable[[int, bytearray, float], None]:
        unpack = TPDO1.unpack_from
        period = self.config.period
        to_si, force_si = self.scaling.to_si, self.scaling.force_to_si

        def on_tpdo(can_id: int, data: bytearray, timestamp: float) -> None:
            if len(data) < TPDO1.size:
                return
            sw, pos, load = unpack(data)
            prev = d.sample
            index, t = self._answered_sync(timestamp, None if prev is None else prev.sync_index)
            p = to_si(pos)
            d.sample = Sample(sw, p, force_si(load), load, index, t)
            d.recent.append(d.sample)
            d.rx_time = time.perf_counter()
            d.samples += 1
            self._tpdo_total += 1
            d.rx_total = self._tpdo_total
            h = d.history
            h.append((t, p, index))
            # speed over the last few SYNCs, timed by the later of the SYNCs' send times and
            # their count x period: a TPDO matched to a SYNC sent late or early (host
            # stalls) must not turn into a speed the drive never had
            dt = max(h[-1][0] - h[0][0], (h[-1][2] - h[0][2]) * period)
            if len(h) >= 2 and dt > 0:
                d.velocity = (h[-1][1] - h[0][1]) / dt
        return on_tpdo

    def _answered_sync(self, timestamp: float, previous: int | None = None) -> tuple[int, float]:
        """(index, perf_counter) of the SYNC a drive's TPDO1 answers.

        The bus timestamp bounds it from above: the last SYNC sent before the frame. A
        drive answers every SYNC once and in order (transmission type 1), so the answer
        after the one to SYNC ``previous`` is to ``previous + 1`` unless that bound is
        lower. Counting matters when answers come late in a burst (a simulator or a
        receive thread that did not run for a few periods): by timestamp alone, answers to
        SYNCs n, n+1, n+2 sent together after SYNC n+2 would all be n+2, and positions
        two periods apart would look simultaneous (a false overspeed). After a silence of
        more than :attr:`attribution_window` SYNCs (a lost frame, a restart) the
        timestamp alone decides again.

        Falls back to the latest SYNC when the interface's timestamps are not on the
        wall clock (hardware clocks).
        """
        if not self._sync_log or abs(timestamp - time.time()) > 0.5:
            return self._sync_index, self._sync_time
        log_ = tuple(self._sync_log)      # a C-level copy: the SYNC thread appends meanwhile
        bound = None
        for wall, perf, index in reversed(log_):
            if wall <= timestamp:
                bound = index, perf
                break
        if bound is None:
            return log_[0][2], log_[0][1]
        if previous is None or not 0 <= bound[0] - previous - 1 <= self.attribution_window:
            return bound
        index = previous + 1
        first = log_[0][2]
        return (index, log_[index - first][1]) if 0 <= index - first < len(log_) else bound

    def _heartbeat_callback(self, d: _Drive) -> Callable[[int, bytearray, float], None]:
        def on_heartbeat(can_id: int, data: bytearray, timestamp: float) -> None:
            if not data:
                return
            state = data[0] & 0x7F
            d.hb_time = time.monotonic()
            d.nmt = NmtState.PRE_OPERATIONAL if state == NmtState.BOOTUP else state
            if state == NmtState.BOOTUP and self._supervising:
                # a drive rebooted: configuration and homing are gone
                self.homed = False
                self.supervisor.report(
                    FaultKind.NMT_STATE, f'node {d.node_id} rebooted (boot-up message)',
                    drive=d.name, still_present=self._nmt_not_operational(d))
            d.booted.set()
        return on_heartbeat

    def _emcy_callback(self, d: _Drive) -> Callable[[int, bytearray, float], None]:
        def on_emcy(can_id: int, data: bytearray, timestamp: float) -> None:
            if len(data) < 8:
                data = bytes(data) + bytes(8 - len(data))
            code, register, _ = _EMCY.unpack_from(data)
            now = time.monotonic()
            d.emcy = (code, register, now)
            if code == 0:
                return          # error reset / no error
            d.emcy_nonzero_time = now
            if self._supervising:
                self.supervisor.report(
                    FaultKind.EMCY, f'EMCY {code:04X}h {emcy_description(code)} '
                    f'(error register {register:02X}h)', drive=d.name, code=code,
                    still_present=self._emcy_present(d))
        return on_emcy

    def _on_error_frame(self, msg: can.Message) -> None:
        self.error_frames += 1
        info = decode_error_frame(msg)
        now = time.monotonic()
        if info.bus_off:
            self._bus_off_time = now
            self._bus_error_state = 'bus off'
            self.supervisor.report(FaultKind.BUS_OFF,
                                   f'error frame: {info.description}; the controller must restart '
                                   '(SocketCAN: restart-ms, or ip link set <channel> type can restart)',
                                   still_present=lambda: self._bus_restart_time < self._bus_off_time)
        elif info.restarted or info.back_to_active:
            self._bus_restart_time = now
            self._bus_error_state = 'active'
            self.supervisor.unwarn('bus')
        elif info.error_passive:
            self._bus_error_state = 'error passive'
            self.supervisor.warn('bus', f'CAN controller error passive ({info.description}): '
                                 'frames may be delayed; check termination and wiring')
        else:
            self.supervisor.warn('bus', f'CAN error frame: {info.description}')

    def _on_fault(self, fault: Fault) -> None:
        """First reaction to a newly latched fault: protective stop on the next cycle."""
        log.error('protective stop: %s', fault.describe())
        self._tracking = False
        if self.state not in (MasterState.CLOSED, MasterState.OPEN, MasterState.BOOTING):
            self.state = MasterState.FAULT

    # ------------------------------------------------------------------ "cause still present" predicates

    def _heartbeat_missing(self, d: _Drive) -> Callable[[], bool]:
        return lambda: time.monotonic() - d.hb_time > self.limits.heartbeat_timeout

    def _nmt_not_operational(self, d: _Drive) -> Callable[[], bool]:
        return lambda: d.nmt != NmtState.OPERATIONAL

    def _emcy_present(self, d: _Drive) -> Callable[[], bool]:
        return lambda: (d.state in (State402.FAULT, State402.FAULT_REACTION_ACTIVE)
                        or d.emcy_nonzero_time > self._recover_time)

    def _drive_faulted(self, d: _Drive) -> Callable[[], bool]:
        return lambda: d.state in (State402.FAULT, State402.FAULT_REACTION_ACTIVE)

    def _stale(self, d: _Drive, *, timed: bool = True) -> bool:
        """No TPDO1 from ``d`` for ``stale_periods`` SYNCs (SAFETY 9).

        Judged on what was received, in bus order, so a receive thread (or a simulator)
        that runs late does not make a drive look silent: ``d`` is stale when the other
        drives have sent ``stale_periods`` TPDO1 each since its last one, or when every
        drive has been silent for :attr:`all_silent_periods` SYNCs (bus, wiring, or a
        host too loaded to receive: heartbeat and error-frame supervision cover those too).
        """
        s = d.sample
        if s is None:
            return True
        n = self.limits.stale_periods
        others = len(self._drives) - 1
        if others and self._tpdo_total - d.rx_total >= n * others:
            return True
        return timed and (self._sync_index - s.sync_index >= self.all_silent_periods
                and time.perf_counter() - d.rx_time > self.all_silent_periods * self.config.period)

    def _sample_condition(self, d: _Drive, kind: FaultKind) -> Callable[[], bool]:
        def present() -> bool:
            s = d.sample
            if s is None or self._stale(d):
                return True
            found = check_sample(None, s, self.limits, commanded=self.scaling.to_si(d.target))
            return any(k is kind for k, _ in found)
        return present

    def _step_condition(self) -> bool:
        sp = self._setpoint
        if sp is None or time.perf_counter() - sp.time > self.limits.command_timeout:
            return False
        for d in self._drives:
            if d.sample is not None and check_step(d.name, d.sample.position, float(sp.position[d.index]),
                                                   self.limits.command_timeout, self.limits, d.index):
                return True
        return False

    # ------------------------------------------------------------------ the cycle (SYNC thread)

    def _run(self) -> None:
        set_thread_priority(self.config.thread_priority)
        try:
            run_periodic(self.config.period, self._cycle, self._stop, stats=self.stats,
                         spin_s=self.config.spin_s)
        except Exception as exc:  # noqa: BLE001 - report, the drives stop on heartbeat loss
            log.exception('SYNC thread died')
            self.supervisor.report(FaultKind.CYCLE_STOPPED,
                                   f'SYNC thread died: {exc!r}; restart the driver',
                                   still_present=lambda: True)

    def _send(self, msg: can.Message) -> bool:
        bus = self._bus
        if bus is None:
            return False
        try:
            with self.network.send_lock:       # type: ignore[union-attr]
                bus.send(msg, timeout=self.config.send_timeout)
        except (can.CanError, OSError) as exc:
            self.send_failures += 1
            self._last_send_failed = True
            self.supervisor.report(
                FaultKind.SEND_FAILED, f'frame {msg.arbitration_id:03X}h not sent: {exc}',
                still_present=lambda: self._last_send_failed)
            return False
        self._last_send_failed = False
        if self._count_tx:
            self._tx_frames += 1
            self._tx_bits += frame_bits(msg.dlc)
        return True

    def _cycle(self, k: int, t_wake: float) -> None:
        if t_wake >= self._next_hb:          # by time: overruns skip cycles, not heartbeats
            self._next_hb += self._hb_period
            if self._next_hb <= t_wake:
                self._next_hb = t_wake + self._hb_period
            self._send(self._hb_msg)
        if k % 256 == 0:
            self._update_rates(t_wake)
        if not self._pdo_running:
            self._last_wake = t_wake
            return
        if t_wake - self._last_wake > 3 * self.config.period and self._last_wake:
            # this process did not run for a while: frames queued meanwhile are not yet
            # received; give the receive thread a moment before judging silence by time
            self._grace_until = time.monotonic() + max(0.02, 10 * self.config.period)
        self._last_wake = t_wake
        if self._supervising:
            self._monitor()
        stopped = self.supervisor.latched
        if not stopped and self._tracking:
            self._apply_setpoint(t_wake)
            stopped = self.supervisor.latched
        for d in self._drives:
            s = d.sample
            if s is None:
                continue
            state = decode_state(s.statusword)
            cw = self._controlword(d, state, stopped)
            if not (self._tracking and not stopped and state is State402.OPERATION_ENABLED):
                d.target = self._actual_counts(d)     # hold where it is; enable without a jump
                d.goal = None
            msg = can.Message(arbitration_id=d.rpdo_id, data=RPDO1.pack(cw, d.target),
                              is_extended_id=False)
            self._send(msg)
            d.sent.append((self._sync_index + 1, d.target))     # for the SYNC sent next
        # the TPDOs answering this SYNC may arrive before send() returns: stamp first
        self._sync_time = time.perf_counter()
        self._sync_index += 1
        self._sync_log.append((time.time(), self._sync_time, self._sync_index))
        self._send(self._sync_msg)

    def _controlword(self, d: _Drive, state: State402, stopped: bool) -> int:
        if self._closing:
            return int(Controlword.DISABLE_VOLTAGE)
        if self._reset_pulse:
            if state in (State402.FAULT, State402.FAULT_REACTION_ACTIVE):
                d.reset_phase = not d.reset_phase          # 0000h, 0080h, 0000h, ... edges
                return int(Controlword.FAULT_RESET) if d.reset_phase else 0
            return int(Controlword.DISABLE_VOLTAGE)
        if stopped:
            return int(Controlword.QUICK_STOP)
        if self._homing_start and state is State402.OPERATION_ENABLED:
            return int(Controlword.START_HOMING)
        cw = controlword_towards(state, self._desired)
        return int(Controlword.DISABLE_VOLTAGE) if cw is None else cw

    def _monitor(self) -> None:
        """Per-cycle monitors on each drive's latest TPDO1 and heartbeat (SAFETY 2, 4, 8, 9, 11)."""
        limits = self.limits
        now = time.monotonic()
        tracking = self._tracking and self.state is MasterState.ENABLED
        in_grace = now < self._grace_until
        for d in self._drives:
            name = d.name
            if now - d.hb_time > limits.heartbeat_timeout and not in_grace:
                age = now - d.hb_time
                self.supervisor.report(
                    FaultKind.HEARTBEAT_LOST,
                    f'no heartbeat from node {d.node_id} for {age * 1e3:.0f} ms '
                    f'(consumer time {limits.heartbeat_timeout * 1e3:.0f} ms)',
                    drive=name, still_present=self._heartbeat_missing(d))
            elif d.nmt is not None and d.nmt != NmtState.OPERATIONAL:
                self.supervisor.report(
                    FaultKind.NMT_STATE, f'node {d.node_id} reports NMT state '
                    f'{NmtState(d.nmt).name if d.nmt in NmtState._value2member_map_ else d.nmt}',
                    drive=name, still_present=self._nmt_not_operational(d))
            s = d.sample
            if s is None:
                continue
            if self._stale(d, timed=not in_grace):
                self.supervisor.report(
                    FaultKind.STALE_FEEDBACK,
                    f'no TPDO1 (position, load cell) from node {d.node_id} for '
                    f'{self._sync_index - s.sync_index} SYNC periods (the other drives answered)'
                    if self._tpdo_total - d.rx_total >= self.limits.stale_periods * max(1, len(self._drives) - 1)
                    else f'no TPDO1 from any drive for {self._sync_index - s.sync_index} SYNC periods',
                    drive=name,
                    still_present=lambda d=d: self._stale(d))
            if s is d.checked:
                continue
            sw = s.statusword
            if sw & _SW_FAULT:
                code = d.emcy[0] if d.emcy and d.emcy[0] else None
                why = f' (last EMCY {code:04X}h {emcy_description(code)})' if code else ''
                self.supervisor.report(FaultKind.DRIVE_FAULT,
                                       f'statusword {sw:04X}h: {describe_statusword(sw)}{why}',
                                       drive=name, code=code, still_present=self._drive_faulted(d))
            if sw & (_SW_WARNING | _SW_LIMIT) or d.flagged:
                d.flagged = bool(sw & (_SW_WARNING | _SW_LIMIT))
                if sw & _SW_WARNING:
                    self.supervisor.warn(f'{name}.warning', f'{name}: statusword warning bit set ({sw:04X}h)')
                else:
                    self.supervisor.unwarn(f'{name}.warning')
                if sw & _SW_LIMIT:
                    self.supervisor.warn(f'{name}.limit', f'{name}: internal limit active ({sw:04X}h)')
                else:
                    self.supervisor.unwarn(f'{name}.limit')
            commanded = (self.scaling.to_si(self._commanded_for(d, s))
                         if tracking and decode_state(sw) is State402.OPERATION_ENABLED else None)
            for kind, cause in check_sample(d.checked, s, limits, commanded=commanded):
                self.supervisor.report(kind, cause, drive=name,
                                       still_present=(None if kind is FaultKind.POSITION_JUMP
                                                      else self._sample_condition(d, kind)))
                if kind is FaultKind.POSITION_JUMP:
                    self.homed = False         # the encoder reference is suspect
            if commanded is not None and abs(d.velocity) > limits.speed_factor * limits.v_max:
                self.supervisor.report(
                    FaultKind.OVERSPEED, f'measured speed {d.velocity * 1e3:.1f} mm/s exceeds '
                    f'{limits.speed_factor:g} x {limits.v_max * 1e3:.1f} mm/s', drive=name,
                    still_present=lambda d=d: abs(d.velocity) > self.limits.speed_factor * self.limits.v_max)
            d.checked = s

    def _commanded_for(self, d: _Drive, s: Sample) -> int:
        """The target (counts) a sample is judged against: of the targets sent from two SYNCs
        before the one it answers up to now, the one nearest to its position.

        A drive answers SYNC k with where it was after following the targets up to SYNC
        k - 1; an answer that arrives late (a loaded host, a simulator in the same process)
        must not be judged against targets sent after it was sampled: with a fast actuator
        one SYNC of the target ramp (v_max x period) can exceed the path tolerance.
        Without a record (before the first SYNC of tracking) the current target.
        """
        pos = self.scaling.to_counts(s.position)
        best = None
        for index, target in reversed(tuple(d.sent)):     # a C-level copy: the SYNC thread appends
            if index < s.sync_index - 2:
                break
            if best is None or abs(target - pos) < abs(best - pos):
                best = target
        return d.target if best is None else best

    def _apply_setpoint(self, t_wake: float) -> None:
        """Latest setpoint → goals, step-limited (SAFETY 7); stale → hold and report (SAFETY 1).

        Staleness is by arrival: no setpoint received for ``command_timeout`` (the stream
        stopped), not by the age of its stamp (that is transport latency, not staleness).
        The step limit compares a setpoint with the previous accepted one over the time
        between their stamps (the sender's sample instants), so bunched or delayed
        deliveries do not look like fast motion; unstamped setpoints use the time between
        arrivals. Each cycle then moves the RPDO target towards the goal (:meth:`_ramp`).
        """
        sp = self._setpoint
        limits = self.limits
        if sp is None or t_wake - sp.time > limits.command_timeout:
            if self._was_fresh:
                self._was_fresh = False
                self.stale_setpoint_holds += 1
                self.supervisor.warn('setpoint', 'setpoints stale (none for safety.command_timeout '
                                     f'= {limits.command_timeout * 1e3:.0f} ms): holding position')
            for d in self._drives:
                d.goal_v = 0.0                 # brake to the last setpoint and hold it there
        elif sp.seq != self._last_sp_seq:
            self._accept_setpoint(sp)
            if self.supervisor.latched:
                return
        self._ramp()

    def _ramp(self) -> None:
        """Move each RPDO target towards its goal within ``v_max`` and ``a_max`` per SYNC.

        The target follows the setpoint stream's speed (``goal_v``) plus a correction that
        can still brake onto the goal (``v <= sqrt(2 a e)`` in discrete steps), with its
        speed changing by at most ``a_max · period`` per SYNC: a CSP drive sees neither a
        position nor a speed step, also when the stream resumes after a gap or stops.
        """
        a, vmax = self._ramp_acc, float(self._ramp_counts)
        for d in self._drives:
            if d.goal is None:
                d.ramp_v, d.target_f = 0.0, float(d.target)
                continue
            tf = d.target_f if abs(d.target_f - d.target) < 1.0 else float(d.target)
            e = d.goal - tf
            if abs(e) < 0.5 and abs(d.ramp_v - d.goal_v) <= a:
                tf, v = float(d.goal), d.goal_v
            else:
                brake = a * (math.sqrt(0.25 + 2.0 * abs(e) / a) - 0.5)
                v_des = max(-vmax, min(vmax, d.goal_v + math.copysign(min(brake, abs(e)), e)))
                v = max(d.ramp_v - a, min(d.ramp_v + a, v_des))
                tf += v
            d.ramp_v, d.target_f, d.target = v, tf, round(tf)

    def _accept_setpoint(self, sp: _Setpoint) -> None:
        limits = self.limits
        if sp.stamp is not None and self._last_sp_stamp is not None:
            dt = sp.stamp - self._last_sp_stamp
            if dt <= 0.0:                     # out of order or repeated: not a newer command
                self._last_sp_seq = sp.seq
                return
            dt = max(dt, self.config.period)
            basis = 'between stamps'
        else:
            dt = min(max(sp.time - self._last_sp_time, self.config.period), limits.command_timeout)
            if self._last_sp_stamp is not None or sp.stamp is None:
                basis = 'since the last setpoint\'s arrival'
            else:
                # what came before tells a late stream from a starved cycle
                basis = (f'the first stamped setpoint since enable, from the position held; '
                         f'{sp.seq - self._seq_at_enable - 1} setpoints had arrived since enable '
                         f'without being fresh at a SYNC, {self.stale_setpoint_holds - self._holds_at_enable} '
                         f'stale holds')
        if not self._was_fresh:
            self.supervisor.unwarn('setpoint')
            self._was_fresh = True
        for d in self._drives:
            current = d.goal if d.goal is not None else d.target
            cause = check_step(d.name, self.scaling.to_si(current), float(sp.position[d.index]),
                               dt, limits, d.index)
            if cause:
                self.supervisor.report(FaultKind.STEP_LIMIT, f'setpoint rejected: {cause}; time {basis}',
                                       drive=d.name, still_present=self._step_condition)
                return
        steps = max(dt / self.config.period, 1.0)
        vmax = float(self._ramp_counts)
        for d in self._drives:
            goal = self.scaling.to_counts(float(sp.position[d.index]))
            d.goal_v = 0.0 if d.goal is None else max(-vmax, min(vmax, (goal - d.goal) / steps))
            d.goal = goal
        self._last_sp_seq = sp.seq
        self._last_sp_time = sp.time
        self._last_sp_stamp = sp.stamp
        self.accepted_setpoints += 1

    def _update_rates(self, now: float) -> None:
        t0, f0, b0 = self._rate_mark
        frames = self._rx_frames + self._tx_frames
        bits = self._rx_bits + self._tx_bits
        if now > t0:
            self._rate = ((frames - f0) / (now - t0), (bits - b0) / (now - t0) / self.config.bitrate)
        self._rate_mark = (now, frames, bits)

    # ------------------------------------------------------------------ API

    def set_targets(self, positions: Sequence[float], *, stamp: float | None = None) -> None:
        """The latest setpoint (m per actuator, actuator order); applied on the next SYNC.

        ``stamp`` (s, any clock the sender keeps) is the setpoint's sample instant, e.g. its
        message header stamp: the step limit then uses the time between stamps.

        Held only while fresh (``safety.command_timeout``); the cycle rejects it, latching
        a STEP_LIMIT fault, if it steps further than ``v_max·dt + margin`` (SAFETY 7).

        :raises ValueError: wrong length, non-finite, or outside the stroke (SAFETY 5, 6);
            nothing is sent.
        """
        arr = np.asarray(positions, dtype=float)
        n = len(self._drives) or len(self.config.node_ids)
        if arr.shape != (n,):
            raise ValueError(f'expected {n} target positions ({", ".join(self.names)}), got shape {arr.shape}')
        u = self.limits.unit
        for i, v in enumerate(arr):
            if not math.isfinite(v):
                raise ValueError(f'target of {self.names[i]} is not finite: {v}')
            lo, hi = self.limits.stroke_of(i)
            if not lo <= v <= hi:
                raise ValueError(f'target of {self.names[i]} = {v:.5f} {u} is outside the '
                                 f'{"stroke" if u == "m" else "joint range"} {lo:.3f}–{hi:.3f} {u}')
        self._setpoint_seq += 1
        self._setpoint = _Setpoint(arr.copy(), time.perf_counter(), self._setpoint_seq,
                                   None if stamp is None else float(stamp))

    def feedback(self) -> Feedback:
        """Positions (m), velocities (m/s), load-cell forces (N) in actuator order.

        One consistent snapshot: every drive's TPDO answering the same SYNC (the newest
        SYNC all drives answered), so a pose computed from it mixes no two instants (near
        a singularity a few um between cycles are mm of pose). Falls back to each drive's
        latest sample when no common SYNC is held (a drive silent: supervision reports it).
        """
        drives = self._drives
        recent = [tuple(d.recent) for d in drives]       # C-level copies: the rx thread appends
        samples = [d.sample for d in drives]
        common = set.intersection(*({s.sync_index for s in r} for r in recent)) if recent and all(recent) else set()
        if common:
            k = max(common)
            samples = [next(s for s in reversed(r) if s.sync_index == k) for r in recent]
        valid = bool(samples) and all(s is not None for s in samples)
        pos = np.array([s.position if s else math.nan for s in samples])
        force = np.array([s.force if s else math.nan for s in samples])
        vel = np.array([d.velocity for d in drives])
        stamp = max((s.time for s in samples if s), default=0.0)
        return Feedback(pos, vel, force, tuple(d.state for d in drives), stamp, valid)

    def enable(self, *, timeout: float | None = None) -> None:
        """All drives to OPERATION ENABLED in CSP, targets = actual positions first (no jump).

        :raises FaultLatchedError: a protective stop is latched (call :meth:`recover`).
        :raises DriverOperationError: not booted, or not homed (call :meth:`home`).
        :raises DriverTimeoutError: a drive did not reach OPERATION ENABLED.
        """
        with self._api_lock:
            self._require_ready()
            if not self.homed and self.config.homing_method:
                raise DriverOperationError(
                    'not homed: park the brace at the home pose and call home() first '
                    '(incremental encoders read 0 at power-up)')
            if self.state is MasterState.ENABLED and self._all_in(State402.OPERATION_ENABLED):
                return
            self._setpoint = None
            self._last_sp_stamp = None
            self._was_fresh = False
            self._desired = State402.OPERATION_ENABLED
            self._wait(lambda: self._all_in(State402.OPERATION_ENABLED), timeout=timeout,
                       what='OPERATION ENABLED')
            self._last_sp_seq = self._seq_at_enable = self._setpoint_seq
            self._holds_at_enable = self.stale_setpoint_holds
            self._tracking = True
            self.state = MasterState.ENABLED

    def disable(self, *, timeout: float | None = None) -> None:
        """All drives to SWITCH ON DISABLED (power stage off); allowed in any state."""
        with self._api_lock:
            self._require_open()
            self._tracking = False
            self._desired = State402.SWITCH_ON_DISABLED
            if self.supervisor.latched:
                return          # the protective stop already holds; recover() disables
            self._wait(lambda: all(d.state in (State402.SWITCH_ON_DISABLED, State402.FAULT)
                                   for d in self._drives), timeout=timeout, what='SWITCH ON DISABLED')
            self.state = MasterState.DISABLED

    def halt(self, *, timeout: float | None = None) -> None:
        """Quick stop (6040h = 0002h): ramp down, hold in QUICK STOP ACTIVE (605Ah = 6).

        Not a fault: :meth:`enable` resumes. Drives not enabled are disabled.
        """
        with self._api_lock:
            self._require_open()
            self._tracking = False
            self._desired = State402.QUICK_STOP_ACTIVE
            if self.supervisor.latched:
                return
            self._wait(lambda: all(d.state in (State402.QUICK_STOP_ACTIVE, State402.SWITCH_ON_DISABLED)
                                   for d in self._drives), timeout=timeout, what='QUICK STOP ACTIVE')
            self.state = MasterState.HALTED

    def recover(self, *, timeout: float | None = None) -> list[Fault]:
        """Fault reset (6040h bit 7 edge) and clear the latch — only if every cause is gone.

        Drives that left OPERATIONAL are re-configured and started. On success the
        drives are in SWITCH ON DISABLED; call :meth:`enable` to move again.

        :returns: the faults whose cause is still present (empty list: recovered).
        """
        with self._api_lock:
            self._require_open()
            if not self.supervisor.latched and not any(
                    d.state in (State402.FAULT, State402.FAULT_REACTION_ACTIVE) for d in self._drives):
                return []
            self._tracking = False
            self._recover_time = time.monotonic()
            restarted = []
            for d in self._drives:
                if d.nmt is not None and d.nmt != NmtState.OPERATIONAL and \
                        not self._heartbeat_missing(d)():
                    try:
                        self._configure(d)
                        d.node.nmt.send_command(0x01)
                        restarted.append(d)
                        d.checked = None
                        d.history.clear()
                    except DriverInitializationError as exc:
                        log.error('recover: %s', exc)
            if restarted:
                start = self._tpdo_total
                self._wait(lambda: all(d.nmt == NmtState.OPERATIONAL and d.rx_total > start
                                       for d in restarted),
                           timeout=max(0.5, 4 * self.config.drive_heartbeat_ms * 1e-3),
                           what='restarted drives OPERATIONAL', raise_=False)
            self._desired = State402.SWITCH_ON_DISABLED
            self._reset_pulse = True
            try:
                self._wait(lambda: self._all_in(State402.SWITCH_ON_DISABLED),
                           timeout=min(0.5, timeout or 0.5), what='SWITCH ON DISABLED', raise_=False)
                # one more monitor pass on fresh samples before judging the causes
                self._wait_syncs(2)
            finally:
                self._reset_pulse = False
            blocking = self.supervisor.try_clear()
            if blocking:
                self.state = MasterState.FAULT
                return blocking
            self.supervisor.unwarn('setpoint')
            self.state = MasterState.DISABLED
            return []

    def home(self, *, timeout: float | None = None) -> None:
        """Home every drive with ``can.homing_method`` (6098h) and home offset 607Ch.

        Method 35 (37): the current position becomes the home offset, i.e. the actuator
        length at the home pose: park the brace there first. Leaves the drives in the
        state they were in (enabled drives are re-enabled in CSP with targets = actual).

        :raises DriverOperationError: no home offset (no mechanism model), a homing error
            bit (6041h bit 13), or a protective stop latched.
        """
        with self._api_lock:
            self._require_ready()
            if self.config.home_lengths is None:
                raise DriverOperationError('no home offset: the mechanism model (IK of home_pose) '
                                           'is unavailable; pass home_lengths to MasterConfig')
            was_enabled = self._desired is State402.OPERATION_ENABLED
            self._tracking = False
            self.state = MasterState.HOMING
            try:
                self._sdo_all(0x6098, 0, 'b', self.config.homing_method)
                for d in self._drives:
                    self._sdo(d, 0x607C, 0, 'i', self.scaling.to_counts(self.config.home_lengths[d.index]))
                self._sdo_all(0x6060, 0, 'b', int(OpMode.HOMING))
                self._desired = State402.OPERATION_ENABLED
                self._wait(lambda: self._all_in(State402.OPERATION_ENABLED), timeout=timeout,
                           what='OPERATION ENABLED for homing')
                self._homing_start = True
                try:
                    def done() -> bool:
                        for d in self._drives:
                            sw = d.sample.statusword if d.sample else 0
                            if sw & Statusword.OP_SPECIFIC_13:
                                raise DriverOperationError(
                                    f'{d.name}: homing error (statusword {sw:04X}h), method '
                                    f'{self.config.homing_method}')
                            if not (sw & Statusword.OP_SPECIFIC_12 and sw & Statusword.TARGET_REACHED):
                                return False
                        return True
                    self._wait(done, timeout=timeout or 2.0, what='homing attained')
                finally:
                    self._homing_start = False
                self._wait_syncs(2)
                for d in self._drives:
                    d.checked = None
                    d.history.clear()
                    d.target = self._actual_counts(d)
                    d.goal = None
                self._sdo_all(0x6060, 0, 'b', int(OpMode.CYCLIC_SYNC_POSITION))
                self.homed = True
            except BaseException:
                self._desired = State402.SWITCH_ON_DISABLED
                self.state = MasterState.FAULT if self.supervisor.latched else MasterState.DISABLED
                raise
            if was_enabled:
                self._last_sp_seq = self._setpoint_seq
                self._tracking = True
                self.state = MasterState.ENABLED
            else:
                self._desired = State402.SWITCH_ON_DISABLED
                self._wait(lambda: self._all_in(State402.SWITCH_ON_DISABLED), timeout=timeout,
                           what='SWITCH ON DISABLED after homing')
                self.state = MasterState.DISABLED
            log.info('homed (method %d): %s', self.config.homing_method,
                     ', '.join(f'{n} {p:.4f} {self.limits.unit}' for n, p in zip(self.names, self.feedback().position)))

    def protective_stop(self, kind: FaultKind, cause: str, *, drive: str | None = None,
                        still_present: Callable[[], bool] | None = None) -> Fault | None:
        """Latch a fault found outside the master (e.g. the node's wrench monitor)."""
        return self.supervisor.report(kind, cause, drive=drive, still_present=still_present)

    def status(self) -> MasterStatus:
        """Snapshot for diagnostics."""
        now = time.monotonic()
        drives = []
        for d in self._drives:
            s = d.sample
            nmt = ('-' if d.nmt is None else
                   NmtState(d.nmt).name if d.nmt in NmtState._value2member_map_ else str(d.nmt))
            emcy = ''
            if d.emcy is not None:
                code, reg, t = d.emcy
                emcy = f'{code:04X}h {emcy_description(code)} ({now - t:.1f} s ago)'
            drives.append(DriveStatus(
                d.name, d.node_id, nmt, d.state, s.statusword if s else 0,
                s.position if s else math.nan, d.velocity, s.force if s else math.nan,
                self.scaling.to_si(d.target), now - d.hb_time, emcy, d.samples))
        frames, load = self._rate
        bus = BusStatus(frames, load, self._bus_error_state, self.error_frames, self.send_failures)
        return MasterStatus(self.state, tuple(drives), bus, self.stats.report(),
                            self.supervisor.faults, tuple(w.message for w in self.supervisor.warnings),
                            self.stale_setpoint_holds, self.homed, self.accepted_setpoints)

    def shutdown(self, *, timeout: float = 0.5) -> None:
        """Disable the drives, NMT pre-operational, stop SYNC, close the bus. Idempotent."""
        with self._api_lock:
            if self.state is MasterState.CLOSED:
                return
            if self._pdo_running and self._bus is not None:
                self._tracking = False
                self._supervising = False     # the drives will miss our heartbeat: expected
                self._closing = True
                self._desired = State402.SWITCH_ON_DISABLED
                try:
                    self._wait(lambda: all(d.state in (State402.SWITCH_ON_DISABLED, State402.FAULT,
                                                       State402.UNKNOWN) for d in self._drives),
                               timeout=timeout, what='SWITCH ON DISABLED', raise_=False)
                except Exception:  # noqa: BLE001 - closing anyway
                    pass
            self._pdo_running = False
            self._supervising = False
            if self.network is not None and self._drives:
                for d in self._drives:
                    try:
                        d.node.nmt.send_command(0x80)     # pre-operational: PDOs off, SDO kept
                    except Exception:  # noqa: BLE001 - bus may be gone already
                        pass
            self._stop.set()
            if self._thread is not None and self._thread is not threading.current_thread():
                self._thread.join(timeout=2.0)
            self._thread = None
            if self.network is not None:
                if self.network.notifier is not None:
                    self.network.notifier.stop(1.0)
                    self.network.notifier = None
                self.network = None
            self._frame_log = None            # the Notifier stopped (closed) it
            if self._bus is not None and self._own_bus:
                self._bus.shutdown()
            self._bus = None
            self.state = MasterState.CLOSED

    # ------------------------------------------------------------------ helpers

    def _require_open(self) -> None:
        if self.state in (MasterState.CLOSED, MasterState.OPEN, MasterState.BOOTING):
            raise DriverOperationError(f'master is {self.state.value}: boot() first')

    def _require_ready(self) -> None:
        self._require_open()
        if self.supervisor.latched:
            raise FaultLatchedError(f'protective stop latched: {self.supervisor.summary()}; '
                                    'call recover() once the cause is gone')

    def _all_in(self, state: State402) -> bool:
        return all(d.state is state for d in self._drives)

    def _actual_counts(self, d: _Drive) -> int:
        return self.scaling.to_counts(d.sample.position) if d.sample is not None else d.target

    def _sdo(self, d: _Drive, index: int, sub: int, fmt: str, value: int) -> None:
        try:
            d.node.sdo.download(index, sub, struct.pack('<' + fmt, value))
        except (canopen.SdoAbortedError, canopen.SdoCommunicationError) as exc:
            raise DriverOperationError(f'{d.name}: SDO {index:04X}h:{sub} = {value} failed: {exc}') from exc

    def _sdo_all(self, index: int, sub: int, fmt: str, value: int) -> None:
        for d in self._drives:
            self._sdo(d, index, sub, fmt, value)

    def _wait_syncs(self, n: int, timeout: float = 1.0) -> None:
        target = self._sync_index + n
        end = time.monotonic() + timeout
        while self._sync_index < target and time.monotonic() < end:
            time.sleep(self.config.period / 2)
        time.sleep(self.config.period)       # the answer to that SYNC

    def _wait(self, cond: Callable[[], bool], *, timeout: float | None, what: str,
              raise_: bool = True) -> bool:
        """Poll ``cond`` each half period; raise on a latched fault or the time limit."""
        limit = self.config.transition_timeout if timeout is None else timeout
        end = time.monotonic() + limit
        while True:
            if cond():
                return True
            if raise_ and self.supervisor.latched:
                raise FaultLatchedError(f'waiting for {what}: protective stop: {self.supervisor.summary()}')
            if time.monotonic() > end:
                if not raise_:
                    return False
                states = ', '.join(f'{d.name}: {describe_statusword(d.sample.statusword) if d.sample else "no TPDO"}'
                                   f' (NMT {d.nmt})' for d in self._drives)
                raise DriverTimeoutError(f'{what} not reached within {limit:g} s ({states})')
            time.sleep(self.config.period / 2)


class _BusListener(can.Listener):
    """Counts frames for the bus load and hands error frames to the master (Notifier thread)."""

    def __init__(self, master: BraceMaster) -> None:
        self._m = master

    def on_message_received(self, msg: can.Message) -> None:
        m = self._m
        if msg.is_error_frame:
            m._on_error_frame(msg)
            return
        m._rx_frames += 1
        m._rx_bits += frame_bits(msg.dlc, extended=msg.is_extended_id)

    def stop(self) -> None:
        pass


def set_thread_priority(priority: int) -> bool:
    """SCHED_FIFO ``priority`` for the calling thread (Linux; needs CAP_SYS_NICE).

    Returns whether it took effect; 0 leaves the thread as it is.
    """
    if priority <= 0:
        return False
    import os
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        return True
    except (AttributeError, OSError) as exc:
        log.warning('SYNC thread keeps normal scheduling: SCHED_FIFO %d refused (%s)', priority, exc)
        return False


def _interpolation_period(period: float) -> tuple[int, int]:
    """60C2h value and index (value·10^index s) of the SYNC period, value ≤ 255."""
    for index in (-3, -4, -5, -6, -2, -1, 0):
        value = period / 10.0 ** index
        if 1 <= round(value) <= 255 and abs(round(value) - value) < 1e-6 * max(1.0, value):
            return round(value), index
    for index in (-3, -4, -5, -6):
        value = round(period / 10.0 ** index)
        if 1 <= value <= 255:
            return value, index
    return 255, 0
