"""Boot and configuration of the drives: bus, NMT, SDO set-up, PDO mapping, homing.

Part of :class:`~.master.BraceMaster` (a mixin: the state it uses is created in
``BraceMaster.__init__``). Boot (:meth:`BootMixin.boot`): wait for each drive's boot-up or
heartbeat (``can.boot_timeout``) -> NMT pre-operational -> SDO configuration (1017h,
1016h, 6007h, 605Ah, 6065h, 607Dh, 6060h, 60C2h, 1006h, 607Fh, 6083h-6085h, 6098h, 607Ch)
-> PDO mapping by SDO (RPDO1 6040h + 607Ah, RPDO2 60B1h, TPDO1 6041h + 6064h + 2401h or
6077h) -> NMT operational.
"""
from __future__ import annotations

import logging
import math
import struct
import threading
import time
from typing import Any

import can
import canopen

from .cia402 import NmtState, OpMode, State402, Statusword
from .errors import DriverInitializationError, DriverOperationError
from .pdo import SdoWrite, pdo_mapping_writes
from .receive import BusListener
from .state import MasterState, _Drive, interpolation_period
from .supervision import FaultKind

__all__ = ['BootMixin']

log = logging.getLogger('brace_control.can.master')


class BootMixin:
    """Opening the bus, booting and configuring the drives, homing (see the module docstring)."""

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
                    # virtual: frames keep the send time the master gives them (one clock
                    # read per SYNC for the master's log and for the simulated drives)
                    extra = {'preserve_timestamps': True} if cfg.interface == 'virtual' else {}
                    self._bus = can.Bus(interface=cfg.interface, channel=cfg.channel,
                                        bitrate=cfg.bitrate, receive_own_messages=bool(log_path),
                                        **extra)
                except (can.CanError, OSError, ValueError, ImportError) as exc:
                    raise DriverInitializationError(
                        f'cannot open CAN bus interface={cfg.interface!r} channel={cfg.channel!r} '
                        f'bitrate={cfg.bitrate}: {exc}') from exc
            self._count_tx = not log_path
            net = canopen.Network(self._bus)
            net.listeners.append(BusListener(self))
            if log_path:
                from .framelog import open_frame_log
                self._frame_log = open_frame_log(log_path)
                net.listeners.append(self._frame_log)
            for i, (name, node_id) in enumerate(zip(cfg.names, cfg.node_ids)):
                od: Any = str(cfg.eds) if cfg.eds is not None else canopen.ObjectDictionary()
                node = canopen.RemoteNode(node_id, od)
                net.add_node(node)
                d = _Drive(i, name, node_id, node, 0x200 + node_id, 0x300 + node_id)
                self._drives.append(d)
                net.subscribe(0x180 + node_id, self._tpdo_callback(d))
                net.subscribe(0x700 + node_id, self._heartbeat_callback(d))
                net.subscribe(0x80 + node_id, self._emcy_callback(d))
            net.connect()
            self.network = net
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, name='brace-can-sync', daemon=True)
            self._thread.start()
            self._set_state(MasterState.OPEN)

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
            self._set_state(MasterState.BOOTING)
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
                self._set_state(MasterState.FAULT)
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
            self._set_state(MasterState.FAULT if self.supervisor.latched else MasterState.DISABLED)
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
        ip_value, ip_index = interpolation_period(cfg.period)
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

    def home(self, *, timeout: float | None = None) -> None:
        """Home every drive with ``can.homing_method`` (6098h) and home offset 607Ch.

        Method 35 (37): the current position becomes the home offset, i.e. the actuator
        length at the home pose: park the brace there first. Only with the drives disabled:
        re-zeroing encoders under a held or moving command would leave a silent offset
        between where the drives are and where the command says they are.

        :raises DriverOperationError: the drives are not disabled (the message names the
            state), no home offset (no mechanism model), a homing error bit (6041h bit 13),
            or a protective stop latched.
        """
        with self._api_lock:
            self._require_ready()
            if self.state is not MasterState.DISABLED:
                raise DriverOperationError(
                    f'home refused: the drives are {self.state.value}; homing re-zeroes the '
                    'encoders and is only allowed with the drives disabled (call disable first)')
            if self.config.home_lengths is None:
                raise DriverOperationError('no home offset: the mechanism model (IK of home_pose) '
                                           'is unavailable; pass home_lengths to MasterConfig')
            self._tracking = False
            self._set_state(MasterState.HOMING)
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
                self._sdo_all(0x6060, 0, 'b', int(OpMode.CYCLIC_SYNC_POSITION))
                self.homed = True
            except BaseException:
                self._desired = State402.SWITCH_ON_DISABLED
                self._set_state(MasterState.FAULT if self.supervisor.latched else MasterState.DISABLED)
                raise
            self._desired = State402.SWITCH_ON_DISABLED
            self._wait(lambda: self._all_in(State402.SWITCH_ON_DISABLED), timeout=timeout,
                       what='SWITCH ON DISABLED after homing')
            self._set_state(MasterState.DISABLED)
            log.info('homed (method %d): %s', self.config.homing_method,
                     ', '.join(f'{n} {p:.4f} {self.limits.unit}' for n, p in zip(self.names, self.feedback().position)))

    def _sdo(self, d: _Drive, index: int, sub: int, fmt: str, value: int) -> None:
        try:
            d.node.sdo.download(index, sub, struct.pack('<' + fmt, value))
        except (canopen.SdoAbortedError, canopen.SdoCommunicationError) as exc:
            raise DriverOperationError(f'{d.name}: SDO {index:04X}h:{sub} = {value} failed: {exc}') from exc

    def _sdo_all(self, index: int, sub: int, fmt: str, value: int) -> None:
        for d in self._drives:
            self._sdo(d, index, sub, fmt, value)
