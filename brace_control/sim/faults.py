"""Fault injection for tests: what can go wrong on a real brace's bus, on demand.

:class:`FaultInjector` is reached as ``SimulatedBrace.faults``; every method takes the
actuator's node id. Each injection stays until undone (call it again with ``False`` /
``None``, or :meth:`FaultInjector.clear_all`).

Error frames follow the SocketCAN error-frame layout (linux/can/error.h), the one
python-can's socketcan interface delivers: ``is_error_frame=True``, the error class in
``arbitration_id`` (:class:`ErrorClass`), controller status in ``data[1]``
(:class:`CtrlStatus`), TX/RX error counters in ``data[6]``/``data[7]``.

Bus-off (how it is simulated, see docs/can.md "Simulated bus faults"):
:meth:`FaultInjector.bus_off` (1) sends a bus-off error frame (``ErrorClass.BUS_OFF``)
that the master's bus receives, (2) silences the simulated side (the drives neither send
nor receive), and (3) when given the master's python-can bus object, makes its ``send``
raise :class:`can.CanOperationError` (``error_code = errno.ENOBUFS``, "No buffer space
available") as SocketCAN does when the controller is bus-off. :meth:`FaultInjector.bus_on`
undoes all three and sends a ``RESTARTED`` error frame.
"""
from __future__ import annotations

import errno
from enum import IntFlag
from typing import Any, Protocol

import can

from ..can.cia402 import EmcyCode
from .device import SimulatedDevice
from .drive import SimulatedDrive
from .host import SimBus

__all__ = ['FaultInjector', 'FaultTarget', 'ErrorClass', 'CtrlStatus', 'error_frame']


class FaultTarget(Protocol):
    """What :class:`FaultInjector` needs of a simulated brace (``SimulatedBrace`` is one):
    its drives by node id, its bus host, and the load-cell overrides. A protocol, so that
    this module does not import ``sim/brace.py``, which imports it."""

    host: SimBus
    node_ids: tuple[int, ...]
    load_cell_override: list[float | None]
    rated_force: float

    def drive(self, node_id: int) -> SimulatedDrive: ...


class ErrorClass(IntFlag):
    """SocketCAN error classes (``can_id`` of an error frame, linux/can/error.h)."""

    TX_TIMEOUT = 0x001
    LOSTARB = 0x002
    CRTL = 0x004        # controller problems, details in data[1]
    PROT = 0x008        # protocol violations
    TRX = 0x010
    ACK = 0x020         # no ACK on transmission
    BUS_OFF = 0x040
    BUS_ERROR = 0x080
    RESTARTED = 0x100   # controller restarted (after bus-off)
    CNT = 0x200         # TX/RX error counters in data[6]/data[7]


class CtrlStatus(IntFlag):
    """SocketCAN controller status (``data[1]`` of a ``CRTL`` error frame)."""

    RX_OVERFLOW = 0x01
    TX_OVERFLOW = 0x02
    RX_WARNING = 0x04
    TX_WARNING = 0x08
    RX_PASSIVE = 0x10
    TX_PASSIVE = 0x20
    ACTIVE = 0x40       # back to error active


_KINDS: dict[str, tuple[int, int, int]] = {
    # kind: (error class, data[1], error counter)
    'bus_error': (ErrorClass.BUS_ERROR | ErrorClass.PROT | ErrorClass.CNT, 0, 8),
    'warning': (ErrorClass.CRTL | ErrorClass.CNT, CtrlStatus.TX_WARNING | CtrlStatus.RX_WARNING, 96),
    'passive': (ErrorClass.CRTL | ErrorClass.CNT, CtrlStatus.TX_PASSIVE | CtrlStatus.RX_PASSIVE, 128),
    'active': (ErrorClass.CRTL | ErrorClass.CNT, CtrlStatus.ACTIVE, 0),
    'bus_off': (ErrorClass.BUS_OFF | ErrorClass.CNT, 0, 255),
    'restarted': (ErrorClass.RESTARTED | ErrorClass.CNT, 0, 0),
    'no_ack': (ErrorClass.ACK | ErrorClass.CNT, 0, 8),
}


def error_frame(kind: str) -> can.Message:
    """A SocketCAN-style error frame: ``kind`` in ``bus_error, warning, passive, active,
    bus_off, restarted, no_ack``."""
    if kind not in _KINDS:
        raise ValueError(f'error frame kind {kind!r} unknown; expected one of {sorted(_KINDS)}')
    cls, ctrl, counter = _KINDS[kind]
    data = bytearray(8)
    data[1] = int(ctrl)
    data[6] = data[7] = min(counter, 255)
    return can.Message(arbitration_id=int(cls), is_error_frame=True, is_extended_id=False,
                       data=bytes(data), dlc=8)


class FaultInjector:
    """Inject faults into a simulated brace (:class:`FaultTarget`, e.g.
    :class:`~brace_control.sim.brace.SimulatedBrace`)."""

    def __init__(self, brace: FaultTarget) -> None:
        self._brace = brace
        self._patched_bus: Any = None

    def _d(self, node_id: int) -> SimulatedDrive:
        return self._brace.drive(node_id)

    # ---- heartbeat / node loss
    def silence_heartbeat(self, node_id: int, silenced: bool = True) -> None:
        """Stop (or resume) this drive's heartbeat; everything else keeps working."""
        self._d(node_id).heartbeat_silenced = silenced

    def disconnect(self, node_id: int, disconnected: bool = True) -> None:
        """Pull this drive's cable: no frame in or out (no heartbeat, no TPDO, no SDO)."""
        d = self._d(node_id)
        d.disconnected = disconnected

    def mute_tpdo(self, node_id: int, muted: bool = True) -> None:
        """Stop this drive's TPDOs (stale position and load cell at the master)."""
        self._d(node_id).tpdo_muted = muted

    # ---- field quirks of real drives (boot)
    def delay_sdo(self, node_id: int, seconds: float) -> None:
        """Every SDO answer of this node comes ``seconds`` late (a drive busy while it is
        configured: ros2_canopen#194); 0 undoes."""
        self._device(node_id).sdo_delay = max(0.0, float(seconds))

    def silent_boot(self, node_id: int, when: str = 'power_on') -> None:
        """This node sends no boot-up message: ``'power_on'`` only at power-on (it answers an
        NMT reset with one: ros2_canopen#199), ``'always'`` never (it still answers SDO),
        ``''`` undoes. Set before the brace starts (``SimulatedBrace(..., start=False)``)."""
        if when not in ('', 'power_on', 'always'):
            raise ValueError(f"silent_boot when = {when!r}: expected '', 'power_on' or 'always'")
        self._device(node_id).silent_boot = when

    def _device(self, node_id: int) -> SimulatedDevice:
        for d in self._brace.host.drives:
            if d.node_id == node_id:
                return d
        raise KeyError(f'no simulated node with id {node_id}')

    # ---- EMCY / drive faults
    def send_emcy(self, node_id: int, code: int = EmcyCode.GENERIC, data: bytes = b'', *,
                  fault: bool = False) -> None:
        """Send an EMCY from the drive; with ``fault`` the drive also goes to FAULT with this
        cause, which a fault reset clears only after :meth:`clear_emcy_fault`."""
        self._d(node_id).send_emcy(code, data, fault=fault)

    def clear_emcy_fault(self, node_id: int, code: int | None = None) -> None:
        """Remove the cause of an injected fault (the master still has to reset it)."""
        self._d(node_id).clear_injected_fault(code)

    def warning(self, node_id: int, on: bool = True) -> None:
        """Set (clear) the statusword warning bit 7."""
        self._d(node_id).injected_warning = on

    def local_control(self, node_id: int, on: bool = True) -> None:
        """The drive under local control (its panel, a vendor's setup tool): statusword bit 9
        (remote) clear, the controlword from the bus ignored."""
        self._d(node_id).local_control = on

    # ---- sensors / actuator
    def freeze_encoder(self, node_id: int, frozen: bool = True) -> None:
        """6064h stops changing at its current value (the drive's own loop is unaffected:
        a failed output encoder on a dual-loop drive)."""
        d = self._d(node_id)
        with d.lock:
            d.encoder_frozen_at = d.position_counts if frozen else None

    def jump_encoder(self, node_id: int, delta_m: float) -> None:
        """Add ``delta_m`` (m, as counts) to the reported 6064h from now on (0 undoes all)."""
        d = self._d(node_id)
        with d.lock:
            d.encoder_jump_counts = 0 if delta_m == 0 else \
                d.encoder_jump_counts + round(delta_m * d.limits.counts_per_m)

    def saturate_load_cell(self, node_id: int, sign: int | None = 1) -> None:
        """Load cell reads full scale (``sign`` +1 / -1); ``None`` back to the physics."""
        i = self._brace.node_ids.index(node_id)
        self._brace.load_cell_override[i] = None if sign is None else \
            (1.0 if sign >= 0 else -1.0) * self._brace.rated_force

    def set_load_cell(self, node_id: int, force_n: float | None) -> None:
        """Load cell reads ``force_n`` (N) whatever the physics; ``None`` undoes."""
        i = self._brace.node_ids.index(node_id)
        self._brace.load_cell_override[i] = force_n

    def stall_actuator(self, node_id: int, stalled: bool = True) -> None:
        """Block the actuator mechanically: it stops where it is; a moving target then
        ends in a following-error fault (8611h), not reset while stalled."""
        self._d(node_id).stalled = stalled

    # ---- bus
    def error_frame(self, kind: str = 'bus_error') -> None:
        """Put one SocketCAN-style error frame on the bus (see :func:`error_frame`)."""
        self._brace.host.send_raw(error_frame(kind))

    def bus_off(self, master_bus: can.BusABC | None = None) -> None:
        """Bus-off: error frame, the simulated side goes silent, and ``master_bus.send``
        raises :class:`can.CanOperationError` (ENOBUFS) until :meth:`bus_on`."""
        host = self._brace.host
        host.send_raw(error_frame('bus_off'))
        host.bus_off = True
        if master_bus is not None:
            def _send(msg: can.Message, timeout: float | None = None) -> None:
                raise can.CanOperationError('simulated bus-off: No buffer space available',
                                            error_code=errno.ENOBUFS)
            master_bus.send = _send      # type: ignore[method-assign]
            self._patched_bus = master_bus

    def bus_on(self) -> None:
        """End bus-off: restore the master's send, the drives talk again, RESTARTED frame."""
        if self._patched_bus is not None:
            try:
                del self._patched_bus.send
            except AttributeError:
                pass
            self._patched_bus = None
        host = self._brace.host
        host.bus_off = False
        host.send_raw(error_frame('restarted'))

    @property
    def is_bus_off(self) -> bool:
        return self._brace.host.bus_off

    def clear_all(self) -> None:
        """Undo every injection (faults latched in the drives stay until reset)."""
        if self.is_bus_off:
            self.bus_on()
        for node_id in self._brace.node_ids:
            d = self._d(node_id)
            with d.lock:
                d.heartbeat_silenced = d.disconnected = d.tpdo_muted = False
                d.stalled = d.injected_warning = d.local_control = False
                d.encoder_frozen_at = None
                d.encoder_jump_counts = 0
            d.clear_injected_fault()
        for dev in self._brace.host.drives:
            dev.sdo_delay = 0.0
        self._brace.load_cell_override[:] = [None] * len(self._brace.node_ids)
