"""Receiving: TPDO1 samples and the SYNC they answer, heartbeats, EMCY, error frames.

Part of :class:`~.master.BraceMaster` (a mixin). The callbacks run in canopen's Notifier
thread, the only receive thread (ARCHITECTURE.md "CAN"). A TPDO1 is attributed to the SYNC
it answered (:meth:`ReceiveMixin._answered_sync`) so that positions taken two periods apart
never look simultaneous, and :meth:`ReceiveMixin.feedback` gives one consistent snapshot
(every drive's answer to the same SYNC).
"""
from __future__ import annotations

import math
import struct
import time
from collections.abc import Callable
from typing import Any

import can
import numpy as np

from .cia402 import NmtState, emcy_description
from .pdo import frame_bits
from .plan import PdoLayout
from .state import Feedback, _Drive, _Module, _Node
from .supervision import FaultKind, Sample, decode_error_frame

__all__ = ['ReceiveMixin', 'BusListener']

_EMCY = struct.Struct('<HB5s')


class ReceiveMixin:
    """The Notifier-thread callbacks and the measurement snapshot (see the module docstring)."""

    def _tpdo_callback(self, d: _Drive, layout: PdoLayout) -> Callable[[int, bytearray, float], None]:
        """The feedback TPDO of drive ``d``, decoded as planned (``layout``): statusword,
        position actual (in the master's counts: the drive's polarity and counts per revolution,
        the offset the master keeps), load cell (from its zero, its gain and offset; from the
        load-cell module when one carries it)."""
        codec = layout.codec
        unpack, size = codec.unpack_from, codec.size
        i_sw, i_pos, i_load = (layout.position_of('statusword'), layout.position_of('position'),
                               layout.position_of('load'))
        module = self._module
        period = self.config.period
        to_si, force_si = self.scaling.to_si, self.scaling.force_to_si
        bus_time = self._bus_time
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
            index, t = self._answered_sync(timestamp, None if prev is None else prev.sync_index)
            p = to_si(pos)
            d.sample = Sample(sw, p, (force_si(load) - d.load_offset) / d.load_gain, load, index, t)
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

    def _module_callback(self, m: _Module) -> Callable[[int, bytearray, float], None]:
        """The load-cell module's TPDO: one reading per actuator, kept for the drives' samples."""
        unpack, size = m.tpdo.codec.unpack_from, m.tpdo.codec.size

        def on_tpdo(can_id: int, data: bytearray, timestamp: float) -> None:
            if len(data) < size:
                return
            m.loads = unpack(data)
            self._bus_time(timestamp)
            if not m.heartbeat:
                m.nmt = NmtState.OPERATIONAL
            m.sync_index = self._answered_sync(timestamp)[0]
            m.rx_time = time.perf_counter()
            m.samples += 1
            m.rx_total = self._tpdo_total
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

    def _bus_time(self, timestamp: float) -> float:
        """The frame's bus timestamp on the wall clock (its receipt time where the
        interface's clock is another, or the frame is more than 0.5 s old); advances
        :attr:`_rx_wall`, the newest such time received."""
        wall = time.time()
        t = timestamp if abs(timestamp - wall) < 0.5 else wall
        if t > self._rx_wall:
            self._rx_wall = t
        return t

    def heartbeat_age(self, d: _Node) -> float:
        """s since drive ``d``'s last heartbeat, on the bus's clock (docs/safety.md §4).

        Judged on what was received, like :meth:`~.monitors.MonitorMixin._stale`: while the
        receive thread is behind by less than the consumer time, the age is the span of
        frames received since the heartbeat (other drives' TPDOs go on arriving when one
        drive falls silent), so frames still queued for a thread that did not get to run
        do not make a heartbeat look lost. When nothing at all has been received for longer
        than the consumer time or the all-silent bound (:attr:`all_silent_periods`, the
        drives' own consumer time of our heartbeat), whichever is longer (the bus, the
        wiring, or a host too starved to receive), it is the time since the heartbeat by
        the wall clock."""
        wall = time.time()
        newest = self._rx_wall
        if wall - newest <= max(self.limits.heartbeat_timeout, self.all_silent_periods * self.config.period):
            return newest - d.hb_wall
        return wall - d.hb_wall

    def _heartbeat_callback(self, d: _Node) -> Callable[[int, bytearray, float], None]:
        def on_heartbeat(can_id: int, data: bytearray, timestamp: float) -> None:
            if not data:
                return
            state = data[0] & 0x7F
            d.hb_time = time.monotonic()
            d.hb_wall = self._bus_time(timestamp)
            d.nmt = NmtState.PRE_OPERATIONAL if state == NmtState.BOOTUP else state
            if state == NmtState.BOOTUP and self._supervising:
                # a drive rebooted: configuration and homing are gone
                self.homed = False
                self.supervisor.report(
                    FaultKind.NMT_STATE, f'node {d.node_id} rebooted (boot-up message)',
                    drive=d.name, still_present=self._nmt_not_operational(d))
            d.booted.set()
        return on_heartbeat

    def _emcy_callback(self, d: _Node) -> Callable[[int, bytearray, float], None]:
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

    def _on_foreign_master(self, cob: int) -> None:
        """A SYNC, or a heartbeat with our node id, that this master did not send: another
        master drives the bus (a second bring-up, a PLC, a ros2_canopen master)."""
        now = time.monotonic()
        first = self._foreign_master is None
        self._foreign_master = (cob, now, self._foreign_master[2] + 1 if not first else 1)
        if self._supervising:
            what = 'SYNC (080h)' if cob == 0x80 else f'heartbeat of node {cob - 0x700} (ours)'
            self.supervisor.report(
                FaultKind.FOREIGN_MASTER,
                f'another CANopen master is on the bus: {what} frames this master did not send; two '
                'masters send SYNC and targets to the same drives: stop the other one',
                still_present=lambda: time.monotonic() - self._foreign_master[1] < 1.0)

    def foreign_master(self) -> str:
        """What another master on the bus was heard sending ('' if nothing)."""
        seen = self._foreign_master
        if seen is None:
            return ''
        cob, _, count = seen
        what = 'SYNC frames (COB-ID 080h)' if cob == 0x80 else \
            f'heartbeats of node {cob - 0x700}, the master node id can.master_node_id'
        return f'{count} {what} that this master did not send'

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

    def _update_rates(self, now: float) -> None:
        t0, f0, b0 = self._rate_mark
        frames = self._rx_frames + self._tx_frames
        bits = self._rx_bits + self._tx_bits
        if now > t0:
            self._rate = ((frames - f0) / (now - t0), (bits - b0) / (now - t0) / self.config.bitrate)
        self._rate_mark = (now, frames, bits)

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
        index = max((s.sync_index for s in samples if s), default=-1)
        wall = 0.0
        for w, _, i in reversed(tuple(self._sync_log)):      # a C-level copy
            if i == index:
                wall = w
                break
        return Feedback(pos, vel, force, tuple(d.state for d in drives), stamp, valid, wall)


class BusListener(can.Listener):
    """Counts frames for the bus load and hands error frames to the master (Notifier thread)."""

    def __init__(self, master: Any) -> None:
        self._m = master

    def on_message_received(self, msg: can.Message) -> None:
        m = self._m
        if msg.is_error_frame:
            m._on_error_frame(msg)
            return
        cob = msg.arbitration_id
        if (cob == 0x80 or cob == m._own_heartbeat_id) and msg.is_rx:
            m._on_foreign_master(cob)             # not our own frame: another master
        m._rx_frames += 1
        m._rx_bits += frame_bits(msg.dlc, extended=msg.is_extended_id)

    def stop(self) -> None:
        pass

