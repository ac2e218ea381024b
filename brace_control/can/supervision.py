"""Fault model of the CAN layer: what counts as a fault, how it latches, when it may clear.

docs/safety.md §1–§9 and §11. Any fault puts the master into a protective stop (quick
stop 6040h = 0x0002, targets held) and stays latched until an explicit ``recover()``;
``recover()`` clears the latch only when every fault's cause is gone (each
:class:`Fault` carries a ``still_present`` predicate the master evaluates then).
Warnings (error-passive bus, stale setpoints) are reported, never latched.

Pure logic, no bus: :class:`Supervisor` latches, :class:`Limits` holds the thresholds
from the device YAML, :func:`check_sample` / :func:`check_step` are the per-cycle
monitors, :func:`decode_error_frame` reads SocketCAN-style error frames. The monitors'
rules are :mod:`brace_control.safety`'s (:mod:`~brace_control.safety.stroke`,
:mod:`~brace_control.safety.force`, :mod:`~brace_control.safety.tracking`); here they are
given the thresholds of :class:`Limits` and their verdicts become fault kinds.

Fault matrix (reaction: quick stop of every drive on the next SYNC cycle, targets held;
bounds at 500 Hz, tested in test/test_can_master.py with 50 ms of scheduling slack):

=====================  ==========================================  =====================  ==========================================
kind                   detected when                               bound                  cause gone (``recover`` may clear) when
=====================  ==========================================  =====================  ==========================================
BOOT_TIMEOUT           no boot-up / heartbeat within boot_timeout   boot_timeout           heartbeat received
HEARTBEAT_LOST         heartbeat age > heartbeat_consumer_ms        150 ms                 heartbeats again
NMT_STATE              boot-up message / NMT state not OPERATIONAL  next heartbeat         OPERATIONAL (recover re-configures it)
BUS_OFF                bus-off error frame                          1 frame                RESTARTED / back-to-active error frame
SEND_FAILED            ``bus.send`` raises (ENOBUFS, TX full)       1 period               the next send succeeds
EMCY                   EMCY with code ≠ 0                           1 frame                drive out of FAULT after the reset and no
                                                                                           new EMCY since
DRIVE_FAULT            statusword bit 3                             1 period               drive out of FAULT after the fault reset
STEP_LIMIT             |Δtarget| > v·dt + margin, v ramped near     1 period               no fresh setpoint that still violates it
                       the stroke ends
OVERSPEED              measured speed > 1.5·v_max                   6 samples              speed back below
FORCE_LIMIT            |load cell| > force_limit                    1 period               force back below
WRENCH_LIMIT           platform wrench > max_wrench (any axis)      1 period               wrench back below
STALE_FEEDBACK         no TPDO1 while the other drives sent         3 periods (100 ms if   TPDO1 again
                       stale_periods each (all silent: 2 x master   all drives silent)
                       heartbeat = the drives' own consumer time)
POSITION_JUMP          |Δposition| > 4·v_max·Δt + margin            1 period               at once (momentary); re-homing required
LOAD_CELL_SATURATED    |counts| ≥ saturation_fraction·full scale    1 period               reading back below
FOLLOWING_ERROR        |target − actual| > path_tolerance           tolerance / speed      error back within the tolerance
=====================  ==========================================  =====================  ==========================================
"""
from __future__ import annotations

import enum
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from ..config import ConfigError, as_device_config
from ..safety.force import force_limit as _force_limit
from ..safety.force import saturation as _saturation
from ..safety.stroke import max_step as _max_step
from ..safety.stroke import step_limit as _step_limit
from ..safety.stroke import stroke as _stroke
from ..safety.tracking import following_error as _following_error
from ..safety.tracking import position_jump as _position_jump
from ..safety.verdict import OK as _OK
from ..schema import release_force, soft_force_limit
from .units import AxisScaling

if TYPE_CHECKING:
    import can

__all__ = [
    'FaultKind', 'Fault', 'Warning_', 'Supervisor', 'Limits', 'Sample',
    'check_sample', 'check_step', 'ErrorFrame', 'decode_error_frame',
]


class FaultKind(enum.Enum):
    """Why the master stopped; ``value`` is the short text used in reports."""

    BOOT_TIMEOUT = 'boot timeout'                  # docs/safety.md §2
    HEARTBEAT_LOST = 'heartbeat lost'              # docs/safety.md §2
    NMT_STATE = 'drive left OPERATIONAL'           # docs/safety.md §2 (reboot, NMT stop)
    BUS_OFF = 'bus off'                            # docs/safety.md §3
    SEND_FAILED = 'send failed'                    # docs/safety.md §3
    EMCY = 'emergency'                             # docs/safety.md §4
    DRIVE_FAULT = 'drive fault'                    # docs/safety.md §4 (statusword bit 3)
    STEP_LIMIT = 'step limit'                      # docs/safety.md §5, §7
    OVERSPEED = 'overspeed'                        # docs/safety.md §8
    FORCE_LIMIT = 'force limit'                    # docs/safety.md §8
    WRENCH_LIMIT = 'wrench limit'                  # docs/safety.md §8 (brace_control.safety)
    STALE_FEEDBACK = 'stale feedback'              # docs/safety.md §9
    POSITION_JUMP = 'impossible position jump'     # docs/safety.md §9
    LOAD_CELL_SATURATED = 'load cell saturated'    # docs/safety.md §9
    FOLLOWING_ERROR = 'following error'            # docs/safety.md §11
    CYCLE_STOPPED = 'SYNC thread stopped'          # the master's own cycle died
    FOREIGN_MASTER = 'another master on the bus'   # SYNC / our heartbeat id from someone else
    EXTERNAL = 'external stop'                     # reported by a caller


@dataclass(frozen=True)
class Fault:
    """One latched fault.

    :param still_present: evaluated at ``recover()``; ``True`` keeps the latch. ``None``:
        a momentary event whose cause is gone once it has been reported.
    """

    kind: FaultKind
    cause: str
    drive: str | None = None
    code: int | None = None
    time: float = field(default_factory=time.monotonic)
    still_present: Callable[[], bool] | None = field(default=None, compare=False, repr=False)

    def describe(self) -> str:
        who = f'{self.drive}: ' if self.drive else ''
        return f'{who}{self.kind.value}: {self.cause}'


@dataclass(frozen=True)
class Warning_:
    """A reported, non-latching condition (error-passive bus, stale setpoints)."""

    key: str
    message: str
    time: float = field(default_factory=time.monotonic)


class Supervisor:
    """Latches faults (thread-safe); the first fault is the one a report leads with.

    :param on_fault: called (outside the lock) once per newly latched fault; the master
        uses it to start the protective stop at once.
    """

    def __init__(self, *, on_fault: Callable[[Fault], None] | None = None,
                 history: int = 200) -> None:
        self._lock = threading.Lock()
        self._faults: dict[tuple[FaultKind, str | None], Fault] = {}
        self._warnings: dict[str, Warning_] = {}
        self.history: deque[Fault] = deque(maxlen=history)
        self._on_fault = on_fault

    # -- faults ----------------------------------------------------------------------
    def report(self, kind: FaultKind, cause: str, *, drive: str | None = None,
               code: int | None = None,
               still_present: Callable[[], bool] | None = None) -> Fault | None:
        """Latch a fault; returns it, or ``None`` if the same kind is already latched for ``drive``."""
        fault = Fault(kind, cause, drive, code, time.monotonic(), still_present)
        with self._lock:
            if (kind, drive) in self._faults:
                return None
            self._faults[(kind, drive)] = fault
            self.history.append(fault)
        if self._on_fault is not None:
            self._on_fault(fault)
        return fault

    @property
    def latched(self) -> bool:
        return bool(self._faults)

    @property
    def faults(self) -> tuple[Fault, ...]:
        """Latched faults, oldest first."""
        with self._lock:
            return tuple(sorted(self._faults.values(), key=lambda f: f.time))

    @property
    def first(self) -> Fault | None:
        faults = self.faults
        return faults[0] if faults else None

    def has(self, kind: FaultKind, drive: str | None = ...) -> bool:  # type: ignore[assignment]
        with self._lock:
            return any(k == kind and (drive is ... or d == drive) for k, d in self._faults)

    def blocking(self) -> list[Fault]:
        """Latched faults whose cause is still present."""
        out = []
        for f in self.faults:
            try:
                present = f.still_present() if f.still_present is not None else False
            except Exception:  # noqa: BLE001 - a predicate that cannot tell keeps the latch
                present = True
            if present:
                out.append(f)
        return out

    def try_clear(self) -> list[Fault]:
        """Clear the latch if no cause is present; returns the faults that block it."""
        blocking = self.blocking()
        if not blocking:
            with self._lock:
                self._faults.clear()
        return blocking

    def summary(self) -> str:
        faults = self.faults
        if not faults:
            return 'no fault'
        return '; '.join(f.describe() for f in faults)

    # -- warnings ----------------------------------------------------------------------
    def warn(self, key: str, message: str) -> None:
        with self._lock:
            self._warnings[key] = Warning_(key, message)

    def unwarn(self, key: str) -> None:
        with self._lock:
            self._warnings.pop(key, None)

    @property
    def warnings(self) -> tuple[Warning_, ...]:
        with self._lock:
            return tuple(self._warnings.values())


@dataclass(frozen=True)
class Limits:
    """Thresholds of the monitors, SI, from the device YAML (``actuator.*``, ``safety.*``, ``can.*``)."""

    period: float                  # s, SYNC period
    v_max: float                   # m/s (rad/s)
    a_max: float                   # m/s²
    stroke: tuple[float, float]    # m
    step_margin: float             # m
    path_tolerance: float          # m
    force_limit: float             # N
    saturation_counts: float       # |load-cell counts from its zero| at or above -> saturated
    stale_periods: int
    heartbeat_timeout: float       # s
    boot_timeout: float            # s
    command_timeout: float         # s
    soft_force_limit: float = math.inf   # N: above it a motion decelerates and holds (no latch)
    release_force: float = 0.0     # N: a relief ends once every force is below it
    jump_factor: float = 4.0       # a step above jump_factor·v_max·Δt + margin is impossible
    speed_factor: float = 1.5      # measured speed above speed_factor·v_max -> overspeed
    #: per-actuator (lo, hi) range (m or rad) from ``mechanism.actuator_limits``; ``None``:
    #: every actuator has :attr:`stroke`
    strokes: tuple[tuple[float, float], ...] | None = None
    unit: str = 'm'                # 'm' (linear) or 'rad' (rotary), for messages
    saturation_fraction: float = 0.95   # of the load cell's full scale (safety.saturation_fraction)

    @property
    def force_unit(self) -> str:
        """The unit of the load cells' readings: N on linear actuators, N·m on rotary joints."""
        return 'N' if self.unit == 'm' else 'N·m'

    def stroke_of(self, index: int | None) -> tuple[float, float]:
        """The range of actuator ``index`` (the common :attr:`stroke` if not per actuator)."""
        if index is None or self.strokes is None:
            return self.stroke
        return self.strokes[index]

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any], scaling: AxisScaling, *,
                    mechanism: Any = None) -> Limits:
        """Read the thresholds; :class:`ConfigError` names a missing, unknown or out-of-range
        parameter (a dict is checked against :mod:`brace_control.schema` like a file).
        ``mechanism``: the model of ``cfg``'s mechanism if the caller has built it (else
        built here)."""
        cfg = as_device_config(cfg)
        get = cfg.get_path
        mech = cfg.get('mechanism', {}) if isinstance(cfg.get('mechanism'), Mapping) else {}
        strokes = _actuator_limits(cfg, mechanism)
        if strokes is not None:
            lo, hi = min(s[0] for s in strokes), max(s[1] for s in strokes)
        else:
            lo = float(mech.get('stroke_min', -math.inf))
            hi = float(mech.get('stroke_max', math.inf))
        if lo >= hi:
            raise ConfigError(f'mechanism.stroke_min {lo} must be below mechanism.stroke_max {hi}')
        from .units import actuator_kind
        consumer = float(get('can.heartbeat_consumer_ms'))
        producer = float(get('can.drive_heartbeat_ms'))
        if consumer <= producer:
            raise ConfigError(
                f'parameter can.heartbeat_consumer_ms = {consumer:g} must exceed '
                f'can.drive_heartbeat_ms = {producer:g} (docs/safety.md §2)')
        force_limit = float(get('safety.force_limit'))
        soft, release = soft_force_limit(cfg), release_force(cfg)
        if not 0.0 < soft <= force_limit:
            raise ConfigError(f'parameter safety.soft_force_limit = {soft:g} must be in (0, '
                              f'safety.force_limit = {force_limit:g}] (docs/safety.md §14)')
        if not 0.0 < release < soft:
            raise ConfigError(f'parameter safety.release_force = {release:g} must be in (0, '
                              f'safety.soft_force_limit = {soft:g}) (docs/safety.md §15)')
        return cls(
            period=1.0 / float(get('can.sync_rate_hz')),
            v_max=float(get('actuator.max_velocity')),
            a_max=float(get('actuator.max_acceleration')),
            stroke=(lo, hi),
            step_margin=float(get('safety.step_margin')),
            path_tolerance=float(get('safety.path_tolerance')),
            force_limit=force_limit,
            soft_force_limit=soft,
            release_force=release,
            saturation_counts=scaling.saturation_counts(float(get('safety.saturation_fraction'))),
            saturation_fraction=float(get('safety.saturation_fraction')),
            stale_periods=int(get('safety.stale_periods')),
            heartbeat_timeout=consumer / 1000.0,
            boot_timeout=float(get('can.boot_timeout')),
            command_timeout=float(get('safety.command_timeout')),
            strokes=strokes,
            unit='rad' if actuator_kind(cfg) == 'rotary' else 'm',
        )

    def max_step(self, current: float, new: float, dt: float, index: int | None = None) -> float:
        """Largest allowed |new − current| over ``dt``: ``v·dt + margin`` (docs/safety.md §7).

        ``v`` is ``v_max``, ramped down near the stroke end being approached
        (``v ≤ √(2·a_max·d)``, ``d`` the distance from ``new`` to that end; docs/safety.md §5):
        :func:`brace_control.safety.stroke.max_step` with these limits.
        """
        lo, hi = self.stroke_of(index)
        return _max_step(current, new, dt, lo=lo, hi=hi, v_max=self.v_max, a_max=self.a_max,
                         margin=self.step_margin)


@dataclass
class Sample:
    """One TPDO1 of one drive, SI (position m, force N) plus the raw load-cell counts."""

    statusword: int
    position: float
    force: float
    load_counts: int
    sync_index: int               # SYNC this sample answers
    time: float                   # perf_counter of that SYNC


def check_step(drive: str, current: float, new: float, dt: float, limits: Limits,
               index: int | None = None) -> str | None:
    """Cause text if a new target violates the stroke or the per-command step limit, else None.

    ``index``: the actuator's index, for per-actuator ranges (:attr:`Limits.strokes`).

    The rules are :mod:`brace_control.safety`'s: :func:`~brace_control.safety.stroke.stroke`
    (docs/safety.md §5), then :func:`~brace_control.safety.stroke.step_limit` (§7, with the
    ramp of §5); the reason of the first that is not *ok*.
    """
    lo, hi = limits.stroke_of(index)
    u = limits.unit
    verdict = _stroke(new, lo, hi, u)
    if verdict is _OK:
        verdict = _step_limit(current, new, dt, lo=lo, hi=hi, v_max=limits.v_max, a_max=limits.a_max,
                              margin=limits.step_margin, unit=u)
        if verdict is _OK:
            return None
    return verdict.reason


def _actuator_limits(cfg: Mapping[str, Any], mechanism: Any = None
                     ) -> tuple[tuple[float, float], ...] | None:
    """Per-actuator ranges from the mechanism model (``mechanism.actuator_limits``; the given
    model, else one built from ``cfg``), or ``None`` when the config holds no buildable
    mechanism (then ``stroke_min/max`` apply)."""
    if mechanism is not None:
        lo, hi = mechanism.actuator_limits
        return tuple((float(a), float(b)) for a, b in zip(lo, hi))
    if not isinstance(cfg.get('mechanism'), Mapping) or 'type' not in cfg['mechanism']:
        return None
    from ..mechanisms import mechanism_from_config
    try:
        lo, hi = mechanism_from_config(cfg).actuator_limits
    except (ValueError, KeyError, TypeError):      # not a buildable mechanism section
        return None
    return tuple((float(a), float(b)) for a, b in zip(lo, hi))


def check_sample(prev: Sample | None, cur: Sample, limits: Limits, *,
                 commanded: float | None, jump: bool = False) -> list[tuple[FaultKind, str]]:
    """Per-sample monitors of one drive: saturation, force, jump, following error.

    ``commanded`` is the target the drive should track (``None``: not tracking, e.g.
    disabled or homing: no following-error check). ``jump``: judge a position jump while not
    tracking as well (a disabled or halted drive whose encoder jumps: not while homing,
    which moves the reference on purpose).

    The rules are :mod:`brace_control.safety`'s: :func:`~brace_control.safety.force.saturation`
    (docs/safety.md §9), else :func:`~brace_control.safety.force.force_limit` (§8), then while
    tracking :func:`~brace_control.safety.tracking.position_jump` (§9) and
    :func:`~brace_control.safety.tracking.following_error` (§11); each verdict that is not
    *ok* becomes ``(kind, reason)``, in that order.
    """
    out: list[tuple[FaultKind, str]] = []
    verdict = _saturation(cur.load_counts, cur.force, limits.saturation_counts, limits.force_unit)
    if verdict is not _OK:
        out.append((FaultKind.LOAD_CELL_SATURATED, verdict.reason))
    else:
        verdict = _force_limit(cur.force, limits.force_limit, limits.force_unit)
        if verdict is not _OK:
            out.append((FaultKind.FORCE_LIMIT, verdict.reason))
    if (commanded is not None or jump) and prev is not None and cur.sync_index > prev.sync_index:
        verdict = _position_jump(prev.position, cur.position,
                                 (cur.sync_index - prev.sync_index) * limits.period,
                                 v_max=limits.v_max, jump_factor=limits.jump_factor,
                                 margin=limits.step_margin, unit=limits.unit)
        if verdict is not _OK:
            out.append((FaultKind.POSITION_JUMP, verdict.reason))
    if commanded is not None:
        verdict = _following_error(cur.position, commanded, limits.path_tolerance, limits.unit)
        if verdict is not _OK:
            out.append((FaultKind.FOLLOWING_ERROR, verdict.reason))
    return out


# ---------------------------------------------------------------------- error frames

# SocketCAN linux/can/error.h: error class bits in the identifier, controller status in data[1]
CAN_ERR_TX_TIMEOUT = 0x001
CAN_ERR_LOSTARB = 0x002
CAN_ERR_CRTL = 0x004
CAN_ERR_PROT = 0x008
CAN_ERR_TRX = 0x010
CAN_ERR_ACK = 0x020
CAN_ERR_BUSOFF = 0x040
CAN_ERR_BUSERROR = 0x080
CAN_ERR_RESTARTED = 0x100
CAN_ERR_CRTL_RX_WARNING = 0x04
CAN_ERR_CRTL_TX_WARNING = 0x08
CAN_ERR_CRTL_RX_PASSIVE = 0x10
CAN_ERR_CRTL_TX_PASSIVE = 0x20
CAN_ERR_CRTL_ACTIVE = 0x40


@dataclass(frozen=True)
class ErrorFrame:
    """A decoded error frame (SocketCAN layout, which python-can passes through)."""

    bus_off: bool
    error_passive: bool
    error_warning: bool
    back_to_active: bool
    restarted: bool
    description: str


def decode_error_frame(msg: can.Message) -> ErrorFrame:
    """Decode ``msg.is_error_frame`` messages: class bits in the id, controller status in data[1]."""
    cls = msg.arbitration_id
    ctrl = msg.data[1] if (cls & CAN_ERR_CRTL) and len(msg.data) > 1 else 0
    parts = []
    names = ((CAN_ERR_TX_TIMEOUT, 'TX timeout'), (CAN_ERR_LOSTARB, 'lost arbitration'),
             (CAN_ERR_PROT, 'protocol violation'), (CAN_ERR_TRX, 'transceiver'),
             (CAN_ERR_ACK, 'no ACK'), (CAN_ERR_BUSOFF, 'bus off'), (CAN_ERR_BUSERROR, 'bus error'),
             (CAN_ERR_RESTARTED, 'controller restarted'))
    parts += [text for bit, text in names if cls & bit]
    cnames = ((CAN_ERR_CRTL_RX_WARNING, 'RX warning'), (CAN_ERR_CRTL_TX_WARNING, 'TX warning'),
              (CAN_ERR_CRTL_RX_PASSIVE, 'RX error passive'), (CAN_ERR_CRTL_TX_PASSIVE, 'TX error passive'),
              (CAN_ERR_CRTL_ACTIVE, 'back to error active'))
    parts += [text for bit, text in cnames if ctrl & bit]
    return ErrorFrame(
        bus_off=bool(cls & CAN_ERR_BUSOFF),
        error_passive=bool(ctrl & (CAN_ERR_CRTL_RX_PASSIVE | CAN_ERR_CRTL_TX_PASSIVE)),
        error_warning=bool(ctrl & (CAN_ERR_CRTL_RX_WARNING | CAN_ERR_CRTL_TX_WARNING)),
        back_to_active=bool(ctrl & CAN_ERR_CRTL_ACTIVE),
        restarted=bool(cls & CAN_ERR_RESTARTED),
        description=', '.join(parts) or f'error frame 0x{cls:03X}',
    )
