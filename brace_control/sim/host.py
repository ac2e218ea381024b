"""Simulated drives on a python-can bus: one bus object, one timer thread.

:class:`SimBus` owns its own python-can bus object on the master's channel (python-can
``virtual`` buses on the same channel in one process see each other's frames) and
dispatches what it receives: SYNC to the SYNC handler (a
:class:`~brace_control.sim.brace.SimulatedBrace`, or each drive), everything else to
every drive's :meth:`~brace_control.sim.drive.SimulatedDrive.on_frame`. A single timer
thread runs the drives' heartbeats, heartbeat-consumer timeouts and TPDO event timers.

How it receives: on the ``virtual`` interface, in the sender's thread
(:meth:`brace_control.can.bus.VirtualBus.receive_inline`). A frame reaches the drives as it
is sent, as on a wire: the master's SYNC is answered (motion, physics, the TPDOs queued for
the master) before its ``send`` returns, with no thread of the simulator to wake and no
queue to wait in. That halves the thread hand-offs of a SYNC period (bench/RESULTS.md,
"The simulated drives take their frames in the sender's thread"). The master stamps a
SYNC before sending it (:meth:`brace_control.can.sync.SyncClock.stamp`), so its answers
arriving early is no problem. Where that cannot be (another interface; a second simulator
on the same channel already receiving so: two would call into each other holding their
own locks), a :class:`can.Notifier` thread receives.
:attr:`SimBus.cpu_seconds` counts the drives' CPU in whichever thread ran them.

Host stalls: the simulated drives run inside the host process. When that process does not
run at all for a while (a full pass of Python's garbage collector over a large heap, the OS
scheduler on a loaded machine), the timer thread wakes late, or its few microseconds of work
take that long; the drives' clock is taken to have stood still for that time
(:meth:`SimulatedDrive.host_stalled`), as the physics does (its step is clamped). Real drives
would not stand still: the master rides out its own stalls (``master.py``'s grace after a
stall; the heartbeat consumer time 1016h is twice the master's period), and the nodes freeze
their start-up heap out of the collector (:func:`brace_control.nodes.runner.freeze_start_up_heap`).
A master that stops while this process runs (its thread stuck, the heartbeat silenced) still
trips the drives on time.
With a receive thread, a frame the master sent that still waits in the simulator's receive
queue (that thread busy with the physics of earlier SYNCs) is not silence either: the drives'
heartbeat consumers judge silence only up to the oldest such frame's send time
(:meth:`SimBus._heard_until`; received in the sender's thread, nothing waits).
The other way round, the drives' own heartbeats (1017h) go out from whichever simulator
thread runs first, the timer or the SYNC handling: a real drive's producer does not wait
for a host thread, and the master must not see a drive vanish because the simulator's timer
thread waited for the GIL.

Bus-off of the simulated side (:attr:`SimBus.bus_off`): the drives neither send nor
receive (see :mod:`brace_control.sim.faults` for the master's side).
"""
from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any

import can

from ..can.bus import open_bus
from ..can.frame import Frame
from .device import SimulatedDevice
from .drive import SimulatedDrive

__all__ = ['SimBus', 'SyncHandler']

log = logging.getLogger(__name__)

#: the timer thread woke this much later than it asked (s): the host process did not run
HOST_STALL_S = 0.02

SyncHandler = Callable[[float], None]
"""``handler(dt)``: called on every SYNC with the time step in seconds."""


class SimBus:
    """Put :class:`SimulatedDrive` objects on a CAN bus.

    :param channel: python-can channel (the master's, e.g. ``'brace0'``).
    :param interface: python-can interface (``'virtual'``).
    :param sync_handler: called on SYNC with ``dt`` instead of ``drive.on_sync(dt)`` for
        each drive (the brace runs motion, physics, then the TPDOs).
    :param dt_source: ``'1006h'``: the SYNC period is the first drive's communication
        cycle period 1006h (deterministic physics; falls back to the measured interval
        when 1006h is 0); ``'measured'``: the time between SYNC frames (clamped to 0.1 s).
    :param bus_kwargs: passed to :class:`can.Bus` (:func:`~brace_control.can.bus.open_bus`).

    Use as a context manager, or :meth:`start` / :meth:`shutdown` (idempotent).
    """

    def __init__(self, channel: str, *, interface: str = 'virtual',
                 sync_handler: SyncHandler | None = None, dt_source: str = '1006h',
                 **bus_kwargs: Any) -> None:
        if dt_source not in ('1006h', 'measured'):
            raise ValueError(f"dt_source must be '1006h' or 'measured', got {dt_source!r}")
        self.channel = channel
        self.interface = interface
        self.drives: list[SimulatedDevice] = []         # every simulated node (drives, I/O modules)
        self.sync_handler = sync_handler
        self.dt_source = dt_source
        self._bus_kwargs = bus_kwargs
        #: on python-can's ``virtual`` interface, the drives take each frame in its sender's
        #: thread (:meth:`brace_control.can.bus.VirtualBus.receive_inline`, module docstring);
        #: ``False`` before :meth:`start`: a receive thread, as on any other interface
        self.inline = True
        #: CPU seconds the simulated drives took (their frames, their SYNCs, their timers),
        #: in whichever thread ran them: the simulator's share of its process's CPU
        self.cpu_seconds = 0.0
        self._cpu_lock = threading.Lock()     # the timer and the senders' threads add to it
        #: seconds the host stood still, by the timer thread's count: the drives' clock
        #: stood still with it (their timers are that much later in wall time)
        self.stalled_seconds = 0.0
        self.bus: can.BusABC | None = None
        self._notifier: can.Notifier | None = None
        self._timer: threading.Thread | None = None
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._woken_at = 0.0                  # monotonic: when the timer was last woken
        self.bus_off = False
        self.sync_count = 0
        self.last_sync_time: float | None = None   # monotonic
        self.error_frames_seen = 0
        self.send_errors = 0
        self._sync_ids: frozenset[int] = frozenset({0x80})
        #: the bus timestamp of the last SYNC frame (its sender's clock: python-can's
        #: ``virtual`` interface stamps a frame with ``time.time()`` when it is sent)
        self.last_sync_stamp = 0.0
        #: COB-ID -> the drives that take it (RPDOs, SDO requests, the master heartbeat);
        #: other frames (NMT, unknown) go to every drive. Rebuilt after NMT / SDO traffic.
        self._routes: dict[int, tuple[SimulatedDrive, ...]] = {}

    # ------------------------------------------------------------------ lifecycle

    def add(self, drive: SimulatedDrive) -> SimulatedDrive:
        """Attach a drive (before :meth:`start`, or it is powered on at once)."""
        drive.attach(self._send)
        self.drives.append(drive)
        self._refresh_routes()
        if self.bus is not None:
            drive.power_on()
            self._wake_timer()
        return drive

    def drive(self, node_id: int) -> SimulatedDrive:
        """The drive with this node id (KeyError if none)."""
        for d in self.drives:
            if d.node_id == node_id:
                return d
        raise KeyError(f'no simulated drive with node id {node_id}')

    def start(self) -> 'SimBus':
        """Open the bus, start receiving, power on every drive (boot-up messages)."""
        if self.bus is not None:
            return self
        self.bus = open_bus(self.interface, self.channel, **self._bus_kwargs)
        receive_inline = getattr(self.bus, 'receive_inline', None)
        if not (self.inline and receive_inline is not None and receive_inline(self._receive)):
            self._notifier = can.Notifier(self.bus, [self._receive], timeout=0.1)
        self._stop.clear()
        for d in self.drives:
            d.power_on()
        self._timer = threading.Thread(target=self._timer_loop, name=f'sim-timer-{self.channel}',
                                       daemon=True)
        self._timer.start()
        return self

    def shutdown(self) -> None:
        """Stop the timer and the Notifier, close the bus. Idempotent."""
        self._stop.set()
        self._wake.set()
        if self._timer is not None:
            self._timer.join(timeout=1.0)
            self._timer = None
        if self._notifier is not None:
            self._notifier.stop(timeout=1.0)
            self._notifier = None
        if self.bus is not None:
            self.bus.shutdown()
            self.bus = None

    def __enter__(self) -> 'SimBus':
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.shutdown()

    # ------------------------------------------------------------------ transmit

    def _send(self, cob_id: int, data: bytes) -> None:
        bus = self.bus
        if bus is None or self.bus_off:
            return
        try:
            bus.send(Frame(arbitration_id=cob_id, data=data, is_extended_id=False))
        except can.CanError as exc:    # a full queue or closed bus: the frame is lost
            self.send_errors += 1
            log.debug('sim send 0x%03X failed: %s', cob_id, exc)

    def send_raw(self, msg: can.Message) -> None:
        """Put any frame on the bus (error frames for fault injection); dropped in bus-off."""
        if self.bus is not None and not self.bus_off:
            self.bus.send(msg)

    # ------------------------------------------------------------------ receive

    def _receive(self, msg: can.Message) -> None:
        t = time.thread_time()
        try:
            self._on_message(msg)
        finally:
            self._count_cpu(t)

    def _count_cpu(self, since: float) -> None:
        spent = time.thread_time() - since
        with self._cpu_lock:
            self.cpu_seconds += spent

    def _on_message(self, msg: can.Message) -> None:
        if msg.is_error_frame:
            self.error_frames_seen += 1
            return
        if self.bus_off or msg.is_remote_frame or msg.is_extended_id:
            return
        cob = msg.arbitration_id
        if cob in self._sync_ids:
            self.last_sync_stamp = msg.timestamp
            self._on_sync()
            return
        data = bytes(msg.data)
        t = time.monotonic()
        for d in self._routes.get(cob, self.drives):
            d.on_frame(cob, data, t)
        if cob == 0 or 0x600 <= cob <= 0x67F:
            # NMT or SDO may have changed 1005h/1006h/1017h or a PDO mapping: refresh the
            # routes and wake the timer
            self._sync_ids = frozenset(d.sync_cob_id for d in self.drives) or frozenset({0x80})
            self._refresh_routes()
            self._wake_timer()

    def _refresh_routes(self) -> None:
        routes: dict[int, list[SimulatedDrive]] = {}
        for d in self.drives:
            for cob in d.listens_to():
                routes.setdefault(cob, []).append(d)
        self._routes = {cob: tuple(ds) for cob, ds in routes.items() if cob != 0}

    def _on_sync(self) -> None:
        now = time.monotonic()
        measured = 0.0 if self.last_sync_time is None else now - self.last_sync_time
        self.last_sync_time = now
        self.sync_count += 1
        dt = measured
        if self.dt_source == '1006h' and self.drives:
            period_us = self.drives[0]._store.get((0x1006, 0), 0)
            if period_us:
                dt = period_us * 1e-6
        dt = min(max(dt, 0.0), 0.1)
        try:
            if self.sync_handler is not None:
                self.sync_handler(dt)
            else:
                for d in self.drives:
                    d.on_sync(dt)
        except Exception:   # noqa: BLE001 - never into the sender (or the receive thread)
            log.exception('simulated SYNC handling failed')
        for d in self.drives:             # heartbeats also from here: see the module docstring
            d.heartbeat_due(now)

    # ------------------------------------------------------------------ timers

    def _heard_until(self, now: float) -> float:
        """Up to when (monotonic s) the drives have been handed every frame sent: ``now``, or
        the send time of the oldest frame still queued for the Notifier thread (python-can's
        ``virtual`` bus stamps a frame with ``time.time()`` when it is sent). A real drive
        receives a frame as it crosses the wire; here a busy receive thread may hold it for
        a while, and that is not the master falling silent (capped at 1 s)."""
        q = getattr(self.bus, 'queue', None)
        if q is None:
            return now
        if hasattr(q, 'oldest'):                   # brace_control.can.bus.RxQueue
            head = q.oldest()
        else:                                      # python-can's queue.Queue
            with q.mutex:
                head = q.queue[0] if q.queue else None
        if head is None:
            return now
        age = min(max(time.time() - head.timestamp, 0.0), 1.0)
        return now - age

    def _wake_timer(self) -> None:
        """Wake the timer thread now, noting when it was asked to run (:meth:`_timer_loop`)."""
        if not self._wake.is_set():
            self._woken_at = time.monotonic()
        self._wake.set()

    def _timer_loop(self) -> None:
        expected: float | None = None         # when this thread was due to run again
        while not self._stop.is_set():
            cpu = time.thread_time()
            now = time.monotonic()
            if expected is not None and now - expected > HOST_STALL_S:
                # the host process did not run (a garbage-collector pass, the OS scheduler):
                # the simulated drives live in it, so their clock stood still too
                self._host_stalled(now - expected)
            nxt = now + 0.05
            try:
                heard = self._heard_until(now)
            except Exception:   # noqa: BLE001 - never kill the timer thread (the consumers)
                log.exception('simulated bus: the receive queue could not be read')
                heard = now
            # also in bus-off: the drives' consumer timeouts expire (their sends are dropped)
            for d in self.drives:
                try:
                    nxt = min(nxt, d.tick(now, heard))
                except Exception:   # noqa: BLE001 - never kill the timer thread
                    log.exception('simulated drive %d timer failed', d.node_id)
            done = time.monotonic()
            if done - now > HOST_STALL_S:
                # the ticks take microseconds: the host stood still in the middle of them (the
                # deadlines were judged at ``now``, before it)
                self._host_stalled(done - now)
            deadline = max(nxt, done)
            self._count_cpu(cpu)
            woken = self._wake.wait(max(0.0, deadline - time.monotonic()))
            self._wake.clear()
            expected = min(self._woken_at, deadline) if woken else deadline

    def _host_stalled(self, seconds: float) -> None:
        self.stalled_seconds += seconds
        for d in self.drives:
            d.host_stalled(seconds)
