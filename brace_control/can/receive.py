"""Receiving: TPDO1 samples and the SYNC they answer, heartbeats, EMCY, error frames.

A part of :class:`~.master.BraceMaster` with its own state: :class:`Receiver` holds what was
received (each drive's samples, the newest bus time, the TPDO count, another master heard),
:class:`BusTraffic` the frame and bit counts both ways and the controller's error state. The
callbacks run in canopen's Notifier thread, the only receive thread (ARCHITECTURE.md "CAN").
A TPDO1 is attributed to the SYNC it answered (:meth:`~.sync.SyncClock.answered`) so that
positions taken two periods apart never look simultaneous, and :meth:`Receiver.feedback`
gives one consistent snapshot (every drive's answer to the same SYNC).

The receiver reports faults to the master's :class:`~.supervision.Supervisor`; what it needs
of the rest of the master comes in as callables: whether supervision is armed, what a reboot
means (the homing is gone), and the monitors' "cause still present" predicates.
"""
from __future__ import annotations

import math
import struct
import time
from collections.abc import Callable

import can
import numpy as np

from .cia402 import NmtState, emcy_description
from .pdo import frame_bits
from .plan import PdoLayout
from .state import Feedback, MasterConfig, _Drive, _Module, _Node
from .supervision import FaultKind, Sample, Supervisor, decode_error_frame
from .sync import SyncClock
from ..safety.liveness import heartbeat_age

__all__ = ['Receiver', 'BusTraffic', 'BusListener']

#: ``predicate(node) -> still_present()``: a "cause still present" check of the monitors
Predicate = Callable[[_Node], Callable[[], bool]]

_EMCY = struct.Struct('<HB5s')


class BusTraffic:
    """Frames and bits on the bus both ways, the bus load, and the CAN controller's error
    state (error frames, bus-off and its restart)."""

    def __init__(self, bitrate: int) -> None:
        self.bitrate = bitrate
        self.rx_frames = 0
        self.rx_bits = 0
        self.tx_frames = 0
        self.tx_bits = 0
        #: count the frames sent here (``False`` when the bus hands our own frames back to the
        #: receive side, which counts them: the frame log)
        self.count_tx = True
        self.rate = (0.0, 0.0)                 # frames/s, load
        self._mark = (time.perf_counter(), 0, 0)
        self.error_frames = 0
        self.error_state = 'active'
        self.bus_off_time = -math.inf
        self.restart_time = -math.inf

    def sent(self, dlc: int) -> None:
        if self.count_tx:
            self.tx_frames += 1
            self.tx_bits += frame_bits(dlc)

    def received(self, msg: can.Message) -> None:
        self.rx_frames += 1
        self.rx_bits += frame_bits(msg.dlc, extended=msg.is_extended_id)

    def update_rates(self, now: float) -> None:
        t0, f0, b0 = self._mark
        frames = self.rx_frames + self.tx_frames
        bits = self.rx_bits + self.tx_bits
        if now > t0:
            self.rate = ((frames - f0) / (now - t0), (bits - b0) / (now - t0) / self.bitrate)
        self._mark = (now, frames, bits)


class Receiver:
    """The Notifier-thread callbacks and the measurement snapshot (see the module docstring).

    :param config: the master's configuration (scaling, period, heartbeat timeout).
    :param clock: the SYNCs sent (the cycle stamps them).
    :param traffic: the bus counters (error frames are counted here).
    :param supervisor: where faults are reported.
    :param supervising: whether supervision is armed (after the boot).
    :param rebooted: called when a supervised drive sends a boot-up (its homing is gone).
    :param nmt_not_operational: the monitors' predicate for an NMT-state fault.
    :param emcy_present: the monitors' predicate for an EMCY fault.
    """

    def __init__(self, config: MasterConfig, clock: SyncClock, traffic: BusTraffic,
                 supervisor: Supervisor, *, supervising: Callable[[], bool],
                 rebooted: Callable[[], None], nmt_not_operational: Predicate,
                 emcy_present: Predicate) -> None:
        self.config = config
        self.scaling = config.scaling
        self.clock = clock
        self.traffic = traffic
        self.supervisor = supervisor
        self._supervising = supervising
        self._rebooted = rebooted
        self._nmt_not_operational = nmt_not_operational
        self._emcy_present = emcy_present
        self.heartbeat_timeout = config.limits.heartbeat_timeout
        #: the drives (actuator order) and the load-cell module, set at the master's open
        self.drives: list[_Drive] = []
        self.module: _Module | None = None
        #: TPDO1 frames received from all drives (a drive's ``rx_total`` is this count at its last)
        self.tpdo_total = 0
        #: bus timestamp (wall clock) of the newest frame received from a drive
        self.rx_wall = -math.inf
        #: s this process did not run, summed over the stalls its SYNC thread saw
        #: (:meth:`host_stalled`): no heartbeat age counts them. On python-can's virtual bus
        #: only: its drives (the simulated brace) stand still with this process; on a real
        #: bus the frames of meanwhile wait in the socket with the kernel's timestamps, and
        #: the span of frames received already tells a drive's silence from this process's
        self.stalled_s = 0.0
        self._stalls_stop_the_bus = config.interface == 'virtual'
        #: all drives silent for this many SYNCs -> stale (one silent drive: stale_periods).
        #: From the master alone, "every drive silent" cannot be told from "this process
        #: did not get to receive", so the bound is the drives' own consumer time of our
        #: heartbeat (1016h = 2 x master_heartbeat_ms): by then they quick-stop themselves.
        self.all_silent_periods = max(config.limits.stale_periods,
                                      math.ceil(2 * config.master_heartbeat_ms * 1e-3 / config.period))
        #: (COB-ID, monotonic, count) of the last SYNC or master heartbeat another node sent
        self.foreign: tuple[int, float, int] | None = None
        self.own_heartbeat_id = 0x700 + config.master_node_id

    def attach(self, drives: list[_Drive], module: _Module | None) -> None:
        """The nodes the master opened (before the bus connects)."""
        self.drives = drives
        self.module = module

    def tpdo_callback(self, d: _Drive, layout: PdoLayout) -> Callable[[int, bytearray, float], None]:
        """The feedback TPDO of drive ``d``, decoded as planned (``layout``): statusword,
        position actual (in the master's counts: the drive's polarity and counts per revolution,
        the offset the master keeps), load cell (from its zero, its gain and offset; from the
        load-cell module when one carries it)."""
        codec = layout.codec
        unpack, size = codec.unpack_from, codec.size
        i_sw, i_pos, i_load = (layout.position_of('statusword'), layout.position_of('position'),
                               layout.position_of('load'))
        module = self.module
        period = self.config.period
        to_si, force_si = self.scaling.to_si, self.scaling.force_to_si
        bus_time = self.bus_time
        answered = self.clock.answered
        operational = NmtState.OPERATIONAL

        def on_tpdo(can_id: int, data: bytearray, timestamp: float) -> None:
            if len(data) < size:
                return
            values = unpack(data)
            sw, pos = values[i_sw], d.from_wire(values[i_pos])
            if i_load is not None:
                load = values[i_load] - d.load_zero
            elif module is not None and module.loads:
                load = module.loads[d.index] - module.zeros[d.index]
            else:
                load = 0
            bus_time(timestamp)
            if not d.heartbeat:
                d.nmt = operational               # a TPDO is sent only in OPERATIONAL
            prev = d.sample
            index, t = answered(timestamp, None if prev is None else prev.sync_index)
            p = to_si(pos)
            d.sample = Sample(sw, p, (force_si(load) - d.load_offset) / d.load_gain, load, index, t)
            d.recent.append(d.sample)
            d.rx_time = time.perf_counter()
            d.samples += 1
            self.tpdo_total += 1
            d.rx_total = self.tpdo_total
            h = d.history
            h.append((t, p, index))
            # speed over the last few SYNCs, timed by the later of the SYNCs' send times and
            # their count x period: a TPDO matched to a SYNC sent late or early (host
            # stalls) must not turn into a speed the drive never had
            dt = max(h[-1][0] - h[0][0], (h[-1][2] - h[0][2]) * period)
            if len(h) >= 2 and dt > 0:
                d.velocity = (h[-1][1] - h[0][1]) / dt
        return on_tpdo

    def module_callback(self, m: _Module) -> Callable[[int, bytearray, float], None]:
        """The load-cell module's TPDO: one reading per actuator, kept for the drives' samples."""
        unpack, size = m.tpdo.codec.unpack_from, m.tpdo.codec.size

        def on_tpdo(can_id: int, data: bytearray, timestamp: float) -> None:
            if len(data) < size:
                return
            m.loads = unpack(data)
            self.bus_time(timestamp)
            if not m.heartbeat:
                m.nmt = NmtState.OPERATIONAL
            m.sync_index = self.clock.answered(timestamp)[0]
            m.rx_time = time.perf_counter()
            m.samples += 1
            m.rx_total = self.tpdo_total
        return on_tpdo

    def bus_time(self, timestamp: float) -> float:
        """The frame's bus timestamp on the wall clock (its receipt time where the
        interface's clock is another, or the frame is more than 0.5 s old); advances
        :attr:`rx_wall`, the newest such time received."""
        wall = time.time()
        t = timestamp if abs(timestamp - wall) < 0.5 else wall
        if t > self.rx_wall:
            self.rx_wall = t
        return t

    def heartbeat_age(self, d: _Node) -> float:
        """s since drive ``d``'s last heartbeat, on the bus's clock (docs/safety.md §4).

        Judged on what was received, like the monitors' stale check (:mod:`.monitors`): while the
        receive thread is behind by less than the consumer time, the age is the span of
        frames received since the heartbeat (other drives' TPDOs go on arriving when one
        drive falls silent), so frames still queued for a thread that did not get to run
        do not make a heartbeat look lost. When nothing at all has been received for longer
        than the consumer time or the all-silent bound (:attr:`all_silent_periods`, the
        drives' own consumer time of our heartbeat), whichever is longer (the bus, the
        wiring, or a host too starved to receive), it is the time since the heartbeat by
        the wall clock.

        On the virtual bus the time this process did not run since that heartbeat
        (:meth:`host_stalled`) does not count: the simulated drives stood still with it. A
        1.5 s stop of the control cycle's process read as a drive's heartbeat lost for 1.5 s,
        once the first TPDO after it arrived before that drive's next heartbeat (fresh-clone
        run 1402). On a real bus the heartbeats of meanwhile arrive afterwards with their own
        timestamps."""
        age = heartbeat_age(d.hb_wall, self.rx_wall, time.time(), consumer_time=self.heartbeat_timeout,
                            all_silent=self.all_silent_periods * self.config.period)
        return max(0.0, age - (self.stalled_s - d.hb_stalled))

    def host_stalled(self, seconds: float) -> None:
        """This process did not run for ``seconds`` (its SYNC thread woke that late): on the
        virtual bus, whose drives stood still with it, no heartbeat heard before counts them
        (:meth:`heartbeat_age`)."""
        if seconds > 0.0 and self._stalls_stop_the_bus:
            self.stalled_s += seconds

    def heartbeat_callback(self, d: _Node) -> Callable[[int, bytearray, float], None]:
        def on_heartbeat(can_id: int, data: bytearray, timestamp: float) -> None:
            if not data:
                return
            state = data[0] & 0x7F
            d.hb_time = time.monotonic()
            d.hb_wall = self.bus_time(timestamp)
            d.hb_stalled = self.stalled_s
            d.nmt = NmtState.PRE_OPERATIONAL if state == NmtState.BOOTUP else state
            if state == NmtState.BOOTUP and self._supervising():
                # a drive rebooted: configuration and homing are gone
                self._rebooted()
                self.supervisor.report(
                    FaultKind.NMT_STATE, f'node {d.node_id} rebooted (boot-up message)',
                    drive=d.name, still_present=self._nmt_not_operational(d))
            d.booted.set()
        return on_heartbeat

    def emcy_callback(self, d: _Node) -> Callable[[int, bytearray, float], None]:
        def on_emcy(can_id: int, data: bytearray, timestamp: float) -> None:
            if len(data) < 8:
                data = bytes(data) + bytes(8 - len(data))
            code, register, _ = _EMCY.unpack_from(data)
            now = time.monotonic()
            d.emcy = (code, register, now)
            if code == 0:
                return          # error reset / no error
            d.emcy_nonzero_time = now
            if self._supervising():
                self.supervisor.report(
                    FaultKind.EMCY, f'EMCY {code:04X}h {emcy_description(code)} '
                    f'(error register {register:02X}h)', drive=d.name, code=code,
                    still_present=self._emcy_present(d))
        return on_emcy

    def on_foreign_master(self, cob: int) -> None:
        """A SYNC, or a heartbeat with our node id, that this master did not send: another
        master drives the bus (a second bring-up, a PLC, a ros2_canopen master)."""
        now = time.monotonic()
        first = self.foreign is None
        self.foreign = (cob, now, self.foreign[2] + 1 if not first else 1)
        if self._supervising():
            what = 'SYNC (080h)' if cob == 0x80 else f'heartbeat of node {cob - 0x700} (ours)'
            self.supervisor.report(
                FaultKind.FOREIGN_MASTER,
                f'another CANopen master is on the bus: {what} frames this master did not send; two '
                'masters send SYNC and targets to the same drives: stop the other one',
                still_present=lambda: time.monotonic() - self.foreign[1] < 1.0)

    def foreign_master(self) -> str:
        """What another master on the bus was heard sending ('' if nothing)."""
        seen = self.foreign
        if seen is None:
            return ''
        cob, _, count = seen
        what = 'SYNC frames (COB-ID 080h)' if cob == 0x80 else \
            f'heartbeats of node {cob - 0x700}, the master node id can.master_node_id'
        return f'{count} {what} that this master did not send'

    def on_error_frame(self, msg: can.Message) -> None:
        traffic = self.traffic
        traffic.error_frames += 1
        info = decode_error_frame(msg)
        now = time.monotonic()
        if info.bus_off:
            traffic.bus_off_time = now
            traffic.error_state = 'bus off'
            self.supervisor.report(FaultKind.BUS_OFF,
                                   f'error frame: {info.description}; the controller must restart '
                                   '(SocketCAN: restart-ms, or ip link set <channel> type can restart)',
                                   still_present=lambda: traffic.restart_time < traffic.bus_off_time)
        elif info.restarted or info.back_to_active:
            traffic.restart_time = now
            traffic.error_state = 'active'
            self.supervisor.unwarn('bus')
        elif info.error_passive:
            traffic.error_state = 'error passive'
            self.supervisor.warn('bus', f'CAN controller error passive ({info.description}): '
                                 'frames may be delayed; check termination and wiring')
        else:
            self.supervisor.warn('bus', f'CAN error frame: {info.description}')

    def feedback(self) -> Feedback:
        """Positions (m), velocities (m/s), load-cell forces (N) in actuator order.

        One consistent snapshot: every drive's TPDO answering the same SYNC (the newest
        SYNC all drives answered), so a pose computed from it mixes no two instants (near
        a singularity a few um between cycles are mm of pose). Falls back to each drive's
        latest sample when no common SYNC is held (a drive silent: supervision reports it).
        """
        drives = self.drives
        recent = [tuple(d.recent) for d in drives]       # C-level copies: the rx thread appends
        samples = [d.sample for d in drives]
        if recent and all(recent):
            common = _newest_common(recent)
            if common is not None:
                samples = common
        valid = bool(samples) and all(s is not None for s in samples)
        pos = np.array([s.position if s else math.nan for s in samples])
        force = np.array([s.force if s else math.nan for s in samples])
        vel = np.array([d.velocity for d in drives])
        stamp = max((s.time for s in samples if s), default=0.0)
        index = max((s.sync_index for s in samples if s), default=-1)
        wall = self.clock.wall_of(index)
        return Feedback(pos, vel, force, tuple(d.state for d in drives), stamp, valid, wall)


def _newest_common(recent: list[tuple[Sample, ...]]) -> list[Sample] | None:
    """Of each drive's recent samples (oldest first), the ones answering the newest SYNC they
    all answered; ``None`` when they answered none in common. That SYNC is at most the
    oldest of their newest; when every drive answered that one (a drive that misses none:
    nearly always) it is found from the end of each, else by intersecting the whole sets."""
    k = min(r[-1].sync_index for r in recent)
    found = []
    for r in recent:
        for s in reversed(r):
            if s.sync_index <= k:
                if s.sync_index == k:
                    found.append(s)
                break
        else:
            break
    if len(found) == len(recent):
        return found
    common = set.intersection(*({s.sync_index for s in r} for r in recent))
    if not common:
        return None
    k = max(common)
    return [next(s for s in reversed(r) if s.sync_index == k) for r in recent]


class BusListener(can.Listener):
    """Counts frames for the bus load and hands error frames and another master's frames to
    the receiver (Notifier thread)."""

    def __init__(self, receiver: Receiver) -> None:
        self._r = receiver

    def on_message_received(self, msg: can.Message) -> None:
        r = self._r
        if msg.is_error_frame:
            r.on_error_frame(msg)
            return
        cob = msg.arbitration_id
        if (cob == 0x80 or cob == r.own_heartbeat_id) and msg.is_rx:
            r.on_foreign_master(cob)              # not our own frame: another master
        r.traffic.received(msg)

    def stop(self) -> None:
        pass
