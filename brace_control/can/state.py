"""The CiA 402 master's state and configuration: what it holds, not what it does.

:class:`MasterConfig` (read from the device YAML), the master's :class:`MasterState`, the
snapshots it reports (:class:`DriveStatus`, :class:`BusStatus`, :class:`MasterStatus`,
:class:`Feedback`) and its per-drive bookkeeping (``_Drive``), shared by the parts the
master is made of (:mod:`.lifecycle`, :mod:`.boot`, :mod:`.receive`, :mod:`.monitors`,
:mod:`.cycle`, :mod:`.stream`).
"""
from __future__ import annotations

import enum
import math
import threading
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..config import ConfigError, DeviceConfig, as_device_config
from .cia402 import State402, decode_state
from .dictionary import ObjectRef, eds_files
from .pdo import LOAD_CELL_INPUT, TORQUE_ACTUAL
from .plan import PdoLayout, PdoSpec, pdo_specs
from .supervision import Fault, Limits, Sample
from .timing import TimingReport
from .units import (AxisScaling, actuator_kind, counts_ratios, encoder_counts, per_actuator,
                    scaling_from_config)

if TYPE_CHECKING:
    import canopen

__all__ = ['MasterState', 'MasterConfig', 'LoadCellModule', 'load_cell_source', 'DriveStatus', 'BusStatus', 'MasterStatus',
           'Feedback', 'interpolation_period']


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
    RELIEVING = 'relieving'      # a latched stop, the drives backing off the load (relieve())


@dataclass(frozen=True)
class LoadCellModule:
    """A CiA 401 analog-input module carrying the load cells (``can.load_cell_node``)."""

    node_id: int
    eds: Path
    objects: tuple[ObjectRef, ...]          # one per actuator, in actuator order
    tpdo: int = 1                           # the module's TPDO that carries them


@dataclass(frozen=True)
class MasterConfig:
    """Everything the master needs, read from the device YAML (SI units)."""

    interface: str
    channel: str
    bitrate: int
    node_ids: tuple[int, ...]
    names: tuple[str, ...]
    #: the EDS / DCF of each drive, in actuator order (``can.eds``: one file, or one per drive)
    eds: tuple[Path, ...]
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
    #: the object carrying each actuator's load cell (or joint torque) on its drive;
    #: ``None`` when :attr:`load_cell_module` carries them
    load_cell_object: ObjectRef | None = ObjectRef(LOAD_CELL_INPUT)
    load_cell_module: LoadCellModule | None = None
    #: ``can.rpdo`` / ``can.tpdo`` of the YAML (``None``: docs/can.md's default mapping)
    rpdo: dict[int, PdoSpec] | None = None
    tpdo: dict[int, PdoSpec] | None = None
    #: per drive: +1 / -1 (``actuator.polarity``: -1, the drive's counts grow as the actuator
    #: shortens), its counts per the first drive's (``actuator.encoder_counts_per_rev``), and
    #: its load cell's gain and offset (``actuator.load_cell_gain`` / ``_offset``: reading =
    #: gain x force + offset); ``()``: +1, 1.0, 1.0, 0.0 for every drive
    polarity: tuple[int, ...] = ()
    count_ratio: tuple[float, ...] = ()
    #: per drive: encoder counts per revolution (``actuator.encoder_counts_per_rev``), checked
    #: against the drive's own position unit (60A8h) at configure; ``()``: not checked
    counts_per_rev: tuple[int, ...] = ()
    load_gain: tuple[float, ...] = ()
    load_offset: tuple[float, ...] = ()
    sdo_timeout: float = 0.1          # s an SDO answer may take (``can.sdo_timeout``)
    sdo_retries: int = 1              # requests sent again after a time-out (``can.sdo_retries``)
    #: N/m (N·m/rad): each actuator's axial stiffness with its load path (``actuator.stiffness``);
    #: a relief's force gain comes from it
    stiffness: float = 1.0e6
    spin_s: float = 0.0              # busy-wait before each SYNC deadline (0: sleep only)
    send_timeout: float = 0.0005     # never block the cycle on a full TX queue
    transition_timeout: float = 1.0  # s for a 402 transition of all drives
    thread_priority: int = 0         # SCHED_FIFO priority of the SYNC thread (0: normal)
    #: the device's model (``None``: none in the file): the cycle's platform-wrench tiers
    #: (:mod:`brace_control.safety`) solve its statics
    mechanism: Any = None
    #: ``safety.max_wrench`` per wrench axis (``()``: no platform-wrench tiers)
    max_wrench: tuple[float, ...] = ()
    # a TPDO is attributed to the SYNC it answered from its bus timestamp (wall clock)

    @property
    def period(self) -> float:
        return 1.0 / self.sync_rate_hz

    @classmethod
    def from_device_config(cls, cfg: Mapping[str, Any], *, channel: str | None = None,
                           home_lengths: Sequence[float] | None = None,
                           mechanism: Any = None, **overrides: Any) -> MasterConfig:
        """Build from a :class:`~brace_control.config.DeviceConfig` (or nested mapping).

        ``home_lengths`` (m per actuator) default to IK(``mechanism.home_pose``) when the
        mechanism model can be built. ``channel`` and ``overrides`` replace YAML values.
        ``mechanism``: the model of ``cfg``'s mechanism, already built by the caller (the CAN
        driver builds one per process); default: built here from ``cfg``.

        :raises ConfigError: a missing or inconsistent parameter, named.
        """
        dc = as_device_config(cfg)      # checked against brace_control.schema, defaults filled
        scaling = scaling_from_config(dc)
        if mechanism is None and 'mechanism' in dc:
            from ..mechanisms import mechanism_from_config     # deferred: mechanisms is heavy
            mechanism = mechanism_from_config(dc)
        limits = Limits.from_config(dc, scaling, mechanism=mechanism)
        node_ids = tuple(int(i) for i in dc.get_path('can.node_ids'))
        names = tuple(str(n) for n in dc.get_path('mechanism.actuator_names',
                                                  [f'a{i + 1}' for i in range(len(node_ids))]))
        if len(names) != len(node_ids):
            raise ConfigError(f'parameter can.node_ids has {len(node_ids)} ids for '
                              f'{len(names)} actuators {list(names)}')
        if len(set(node_ids)) != len(node_ids) or not all(1 <= i <= 127 for i in node_ids):
            raise ConfigError(f'parameter can.node_ids = {list(node_ids)}: distinct ids 1..127 expected')
        master_id = int(dc.get_path('can.master_node_id'))
        if master_id in node_ids:
            raise ConfigError(f'parameter can.master_node_id = {master_id} collides with a drive id')
        eds = eds_files(dc, len(node_ids))
        polarity = tuple(int(p) for p in per_actuator(dc.get_path('actuator.polarity'), len(node_ids),
                                                       'actuator.polarity'))
        if any(p not in (1, -1) for p in polarity):
            raise ConfigError(f'parameter actuator.polarity = {list(polarity)}: expected +1 or -1 per actuator')
        cell, module = load_cell_source(dc)
        if module is not None and (module.node_id in node_ids or module.node_id == master_id):
            raise ConfigError(f'parameter can.load_cell_node.node_id = {module.node_id} is also a '
                              f"drive's or the master's node id ({list(node_ids)}, master {master_id})")
        try:
            rpdo = pdo_specs(dc.get_path('can.rpdo', None), 'rpdo')
            tpdo = pdo_specs(dc.get_path('can.tpdo', None), 'tpdo')
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
        if home_lengths is None and mechanism is not None:
            home_lengths = mechanism.inverse(mechanism.home_pose)
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
            homing_method=int(dc.get_path('can.homing_method')),
            frame_log=str(dc.get_path('can.frame_log') or ''),
            spin_s=float(dc.get_path('can.sync_spin_us')) * 1e-6,
            thread_priority=int(dc.get_path('can.sync_thread_priority')),
            following_error_window=float(dc.get_path('safety.following_error_window')),
            scaling=scaling, limits=limits,
            home_lengths=None if home_lengths is None else tuple(float(x) for x in home_lengths),
            # linear actuators carry a load cell (2401h by default); rotary drives report
            # 6077h torque actual by default
            load_cell_object=cell, load_cell_module=module, rpdo=rpdo, tpdo=tpdo,
            polarity=polarity, count_ratio=tuple(counts_ratios(dc)), counts_per_rev=tuple(encoder_counts(dc)),
            load_gain=tuple(float(g) for g in per_actuator(dc.get_path('actuator.load_cell_gain'),
                                                            len(node_ids), 'actuator.load_cell_gain')),
            load_offset=tuple(float(o) for o in per_actuator(dc.get_path('actuator.load_cell_offset'),
                                                              len(node_ids), 'actuator.load_cell_offset')),
            sdo_timeout=float(dc.get_path('can.sdo_timeout')),
            sdo_retries=int(dc.get_path('can.sdo_retries')),
            stiffness=float(dc.get_path('actuator.stiffness')),
            mechanism=mechanism,
            max_wrench=tuple(float(x) for x in dc.get_path('safety.max_wrench')),
        )
        values.update(overrides)
        return cls(**values)


def load_cell_source(cfg: DeviceConfig) -> tuple[ObjectRef | None, LoadCellModule | None]:
    """Where the load cells are wired (the YAML, read by the master and the simulator alike):
    ``(object on each drive, None)`` from ``can.load_cell_object`` (empty: 2401h:0, or 6077h:0
    torque actual on rotary drives), or ``(None, module)`` when ``can.load_cell_node.node_id``
    names a CiA 401 module.

    :raises ConfigError: an object reference that cannot be read, no module EDS, a wrong
        number of module objects (one per actuator), each named.
    """
    n = len(cfg.get_path('can.node_ids'))
    node_id = int(cfg.get_path('can.load_cell_node.node_id', 0) or 0)
    try:
        if not node_id:
            text = str(cfg.get_path('can.load_cell_object', '') or '')
            if text:
                return ObjectRef.parse(text, what='parameter can.load_cell_object'), None
            return ObjectRef(TORQUE_ACTUAL if actuator_kind(cfg) == 'rotary' else LOAD_CELL_INPUT), None
        eds_name = str(cfg.get_path('can.load_cell_node.eds', '') or '')
        if not eds_name:
            raise ConfigError("parameter can.load_cell_node.eds is empty: name the load-cell module's EDS")
        texts = cfg.get_path('can.load_cell_node.objects', None) or [f'0x6401:{i + 1}' for i in range(n)]
        if len(texts) != n:
            raise ConfigError(f'parameter can.load_cell_node.objects lists {len(texts)} objects for '
                              f'{n} actuators: one per actuator, in actuator order')
        objects = tuple(ObjectRef.parse(t, what='parameter can.load_cell_node.objects entry') for t in texts)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
    return None, LoadCellModule(node_id, cfg.resolve_file(eds_name, 'can.load_cell_node.eds'), objects,
                                int(cfg.get_path('can.load_cell_node.tpdo', 1)))


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
    accepted_setpoints: int = 0        # stream setpoints that passed the step limit
    rejected_setpoints: int = 0        # stream setpoints refused (stamps not increasing)
    execution: str = 'hold'            # the executor: hold | trajectory | stream
    trajectory: int | None = None      # tag (header stamp, ns) of the running trajectory


@dataclass(frozen=True)
class Feedback:
    """Latest measurements in SI, actuator order; ``stamp`` = perf_counter of the SYNC,
    ``wall`` = the wall clock (``time.time()``) when that SYNC was sent (0 if unknown): the
    instant the samples describe, on the clock of message stamps and of the bus."""

    position: np.ndarray
    velocity: np.ndarray
    force: np.ndarray
    states: tuple[State402, ...]
    stamp: float
    valid: bool              # every drive has answered at least one SYNC
    wall: float = 0.0


@dataclass
class _Setpoint:
    position: np.ndarray
    time: float              # perf_counter at reception
    seq: int
    stamp: float | None = None   # s, the sender's sample instant (header stamp), if any
    velocity: np.ndarray | None = None   # unit/s, the sender's rate (feed-forward), if any


def sender_rate(position: np.ndarray, previous: np.ndarray, interval: float, *, period: float,
                v_max: float) -> np.ndarray:
    """A setpoint stream's rate (unit/s) from two of its setpoints ``interval`` s apart (at
    least one period), scaled as a whole vector to at most ``v_max`` on every axis: the
    stream's feed-forward, so the command does not lag the stream by v / gain."""
    rate = (position - previous) / max(interval, period)
    over = float(np.max(np.abs(rate))) / v_max
    return rate / over if over > 1.0 else rate


@dataclass
class _Node:
    """What the master keeps of one CANopen node it supervises: heartbeat, NMT state, EMCY."""

    name: str
    node_id: int
    node: canopen.RemoteNode
    heartbeat: bool = True                 # it produces a heartbeat (1017h); else judged by TPDOs
    rx_time: float = -math.inf             # perf_counter of the last TPDO
    rx_total: int = 0                      # master's TPDO count at this node's last TPDO
    hb_time: float = -math.inf             # monotonic of the last heartbeat / boot-up
    hb_wall: float = -math.inf             # its bus timestamp (wall clock; see Receiver.bus_time)
    hb_stalled: float = 0.0                # Receiver.stalled_s when it was received
    nmt: int | None = None
    booted: threading.Event = field(default_factory=threading.Event)
    emcy: tuple[int, int, float] | None = None     # code, register, monotonic
    emcy_nonzero_time: float = -math.inf


@dataclass
class _Module(_Node):
    """The load-cell module (``can.load_cell_node``): its latest readings, one per actuator."""

    tpdo: PdoLayout | None = None
    loads: tuple = ()                      # raw readings of the last TPDO, actuator order
    zeros: tuple = ()                      # each channel's zero (counts), actuator order
    sync_index: int = -1                   # the SYNC they answer
    samples: int = 0


@dataclass
class _Drive(_Node):
    index: int = 0
    #: the RPDOs the master sends (planned against the drive's dictionary), and the bytes it
    #: last sent in each (an RPDO goes out when its content changes)
    rpdos: tuple[PdoLayout, ...] = ()
    rpdo_sent: list = field(default_factory=list)
    #: counts the master adds to the drive's 6064h (and takes from 607Ah): the home offset
    #: when the drive has no writable 607Ch
    count_offset: int = 0
    load_zero: int | float = 0             # the load-cell reading at zero force (counts)
    polarity: int = 1                      # actuator.polarity
    count_ratio: float = 1.0               # this drive's counts per the master's counts
    load_gain: float = 1.0                 # actuator.load_cell_gain
    load_offset: float = 0.0               # actuator.load_cell_offset (N or N·m)
    #: its RPDOs carry the velocity feed-forward 60B1h (else it lags by its position loop)
    feedforward: bool = True

    def to_wire(self, counts: float) -> int:
        """The master's counts (offset included) as this drive counts them."""
        return self.polarity * round((counts - self.count_offset) * self.count_ratio)

    def from_wire(self, raw: float) -> float:
        """This drive's counts as the master's (offset included)."""
        return self.polarity * raw / self.count_ratio + self.count_offset

    def rate_to_wire(self, counts_per_s: float) -> int:
        """A velocity (master counts/s) as this drive's."""
        return self.polarity * round(counts_per_s * self.count_ratio)
    sample: Sample | None = None
    checked: Sample | None = None          # last sample the monitors saw
    history: deque = field(default_factory=lambda: deque(maxlen=6))   # (t, pos, sync index)
    velocity: float = 0.0
    samples: int = 0
    target: int = 0                        # counts (the master's, offset included) of 607Ah
    velocity_offset: int = 0               # counts/s of 60B1h (the feed-forward, when mapped)
    recent: deque = field(default_factory=lambda: deque(maxlen=16))  # Samples, by SYNC
    sent: deque = field(default_factory=lambda: deque(maxlen=128))   # (SYNC index, target counts)
    reset_phase: bool = False
    flagged: bool = False                  # warning / internal-limit bit seen last sample
    remote_seen: bool = False              # statusword bit 9 (remote) seen set since the boot
    force_trend: deque = field(default_factory=lambda: deque(maxlen=10))   # |force| of recent samples

    @property
    def state(self) -> State402:
        return decode_state(self.sample.statusword) if self.sample is not None else State402.UNKNOWN



def interpolation_period(period: float) -> tuple[int, int]:
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



#: a relief stops this far (m or rad) from an actuator's stroke end
STROKE_MARGIN = 0.001


class Relief:
    """One relief in progress (:meth:`~.master.BraceMaster.relieve`), shared by the API thread
    that waits and the SYNC thread that moves (docs/safety.md §15)."""

    def __init__(self, *, release_force: float, speed: float, max_travel: float, deadline: float,
                 start: np.ndarray, forces: np.ndarray, relievable: frozenset,
                 lo: np.ndarray, hi: np.ndarray, names: tuple[str, ...],
                 confirm: int = 1, unit: str = 'm', force_limit: float = math.inf) -> None:
        self.release_force = release_force
        #: ``safety.force_limit``: a leg a relief loads beyond it (more than it started with,
        #: or the other way round) ends the relief: a relief never presses harder
        self.force_limit = float(force_limit)
        #: consecutive samples every force must stay below the release force (one noisy
        #: reading below it is not an unloaded leg)
        self.confirm = max(1, int(confirm))
        self._below = 0
        self.speed = speed
        self.max_travel = max_travel
        self.deadline = deadline
        self.start = np.asarray(start, dtype=float).copy()
        self.forces_before = np.asarray(forces, dtype=float).copy()
        self.forces = self.forces_before.copy()
        self.travel = 0.0
        self.relievable = relievable
        self.lo, self.hi, self.names = np.asarray(lo, float), np.asarray(hi, float), names
        #: the thousandth of the actuators' unit, for messages
        self.milli = 'mm' if unit == 'm' else f'm{unit}'
        self.outcome: str | None = None        # None while moving; '' unloaded; else why it stopped
        self.finished = threading.Event()

    def update(self, forces: np.ndarray, q: np.ndarray, t: float) -> None:
        """Judge the latest forces and travel: unloaded, or stopped short (and why)."""
        self.forces = np.asarray(forces, dtype=float).copy()
        self.travel = float(np.max(np.abs(np.asarray(q) - self.start)))
        self._below = self._below + 1 if np.all(np.abs(self.forces) < self.release_force) else 0
        f, f0 = np.abs(self.forces), np.abs(self.forces_before)
        # a leg the relief loads beyond the force limit: more than at its start, or the other
        # way round (a load cell that reads wrong steers the others into the body: a fault
        # sweep saw a2's true force reach 293 N against a 30 N limit while the hard limit,
        # latched already, stayed silent)
        worse = (f > self.force_limit) & ((f > f0 + 1.0) | (np.sign(self.forces) * np.sign(self.forces_before) < 0))
        if np.any(worse):
            i = int(np.argmax(worse))
            self.outcome = (f'{self.names[i]} at {self.forces[i]:.1f} (it started at '
                            f'{self.forces_before[i]:.1f}), beyond safety.force_limit = '
                            f'{self.force_limit:g}: a relief never presses harder')
        elif self._below >= self.confirm:
            self.outcome = ''
        elif np.any(np.asarray(q) <= self.lo + STROKE_MARGIN) or np.any(np.asarray(q) >= self.hi - STROKE_MARGIN):
            i = int(np.argmax((np.asarray(q) <= self.lo + STROKE_MARGIN) | (np.asarray(q) >= self.hi - STROKE_MARGIN)))
            self.outcome = (f'{self.names[i]} reached the end of its stroke with forces still '
                            f'{np.round(self.forces, 1).tolist()} N')
        elif self.travel > self.max_travel:
            self.outcome = (f'moved {self.travel * 1e3:.1f} {self.milli} (the most a relief may move) '
                            f'with forces still {np.round(self.forces, 1).tolist()} N')
        elif t > self.deadline:
            self.outcome = f'time out with forces still {np.round(self.forces, 1).tolist()} N'

    def check_faults(self, faults: tuple) -> None:
        """A new fault during the relief that it cannot back off from ends it."""
        other = [f for f in faults if f.kind not in self.relievable]
        if other and self.outcome is None:
            self.outcome = f'a new fault: {other[0].describe()}'
            # the cycle drops the relief at once: the caller waiting for it hears now (it
            # waited for the relief's time-out + 2 s, holding the API: a fault sweep)
            self.finished.set()


class TakeUp:
    """Slack taken up in pull-only legs (cables) in progress (:meth:`~.master.BraceMaster.take_up`),
    shared by the API thread that waits and the SYNC thread that moves.

    A cable reading less tension than ``below`` (thrust ``f > -below``: thrust is minus the
    tension) is slack: it shortens at ``speed`` until it reads ``below`` or more; a taut one
    holds. Done when every leg has read taut for ``confirm`` samples.
    """

    def __init__(self, *, below: float, speed: float, max_travel: float, deadline: float,
                 start: np.ndarray, forces: np.ndarray, lo: np.ndarray, names: tuple[str, ...],
                 confirm: int = 1, unit: str = 'm') -> None:
        self.below = float(below)
        self.speed = float(speed)
        self.max_travel = float(max_travel)
        self.deadline = deadline
        self.confirm = max(1, int(confirm))
        self._taut = 0
        self.start = np.asarray(start, dtype=float).copy()
        self.forces_before = np.asarray(forces, dtype=float).copy()
        self.forces = self.forces_before.copy()
        self.travel = np.zeros_like(self.start)
        self.lo, self.names = np.asarray(lo, float), names
        self.milli = 'mm' if unit == 'm' else f'm{unit}'
        self.outcome: str | None = None        # None while moving; '' taut; else why it stopped
        self.finished = threading.Event()

    def slack(self, forces: np.ndarray) -> np.ndarray:
        """Which legs read slack."""
        return np.asarray(forces, dtype=float) > -self.below

    def update(self, forces: np.ndarray, q: np.ndarray, t: float) -> None:
        """Judge the latest forces and travel: taut, or stopped short (and why)."""
        self.forces = np.asarray(forces, dtype=float).copy()
        q = np.asarray(q, dtype=float)
        self.travel = self.start - q
        slack = self.slack(self.forces)
        self._taut = 0 if np.any(slack) else self._taut + 1
        if self._taut >= self.confirm:
            self.outcome = ''
        elif np.any(slack & (q <= self.lo + STROKE_MARGIN)):
            i = int(np.argmax(slack & (q <= self.lo + STROKE_MARGIN)))
            self.outcome = (f'{self.names[i]} reached the end of its stroke still slack '
                            f'({-self.forces[i]:.1f} N of tension)')
        elif np.any(self.travel > self.max_travel):
            i = int(np.argmax(self.travel))
            self.outcome = (f'{self.names[i]} shortened {self.travel[i] * 1e3:.1f} {self.milli} (the '
                            f'most a take-up may) still slack ({-self.forces[i]:.1f} N of tension): '
                            'a broken or unhooked cable?')
        elif t > self.deadline:
            self.outcome = f'time out with tensions {np.round(-self.forces, 1).tolist()} N'
