"""Boot and configuration of the drives: the plan, bus, NMT, SDO set-up, PDO mapping, homing.

A part of :class:`~.master.BraceMaster` with its own state: the plans, the bus and the
canopen Network it opened, the frame log. Before anything is sent, every drive's boot is
planned against its own object dictionary (:meth:`Boot.plan`, :mod:`.plan`): a drive that
lacks what the brace needs is refused with one message. Boot (:meth:`Boot.boot`): wait for each
drive's boot-up or heartbeat; a drive still silent gets an NMT reset-communication, then an
SDO probe, before it is declared missing (``can.boot_timeout``) -> NMT pre-operational -> the
planned SDO configuration and PDO mapping (``can.sdo_timeout``, ``can.sdo_retries``) -> NMT
operational. A CiA 401 load-cell module (``can.load_cell_node``) boots alongside.
"""
from __future__ import annotations

import dataclasses
import logging
import struct
import time
from collections.abc import Sequence
from typing import TYPE_CHECKING

import can
import canopen

from ..mechanisms.base import warm_up
from .bus import open_bus
from .cia402 import NmtState, OpMode, State402, Statusword
from .dictionary import Dictionary, DictionaryReadError, ObjectRef
from .errors import DriverInitializationError, DriverOperationError
from .frame import StampedNetwork
from .pdo import SdoWrite
from .plan import BootPlan, BootSettings, DictionaryError, ModulePlan, plan_drive, plan_module
from .receive import BusListener
from .state import MasterState, _Drive, _Module, _Node, interpolation_period
from .supervision import FaultKind
from .units import LoadInput

if TYPE_CHECKING:
    from .cycle import Cycle
    from .lifecycle import Lifecycle
    from .monitors import Monitors
    from .receive import BusTraffic, Receiver

__all__ = ['Boot', 'LISTEN_S']

log = logging.getLogger('brace_control.can.master')

#: s the boot listens for boot-ups and heartbeats before resetting the silent drives'
#: communication (a drive powered before the master listened, with no heartbeat yet)
LISTEN_S = 0.25
#: s an SDO probe (a read of 1000h) of a drive that sent no boot-up may take
PROBE_TIMEOUT_S = 0.1
#: s the boot listens at least for another master's SYNC (10 periods of a 500 Hz master)
MASTER_LISTEN_S = 0.02


class Boot:
    """Planning, opening the bus, booting and configuring the drives, homing (module docstring).

    The caller (the master's API) serialises the calls. ``bus``: an already open python-can
    bus to use instead of opening one (tests, replays); it is shut down on :meth:`close` only
    if this part opened it.
    """

    def __init__(self, life: Lifecycle, receiver: Receiver, traffic: BusTraffic, cycle: Cycle,
                 monitors: Monitors, *, bus: can.BusABC | None = None) -> None:
        self._life = life
        self._receiver = receiver
        self._traffic = traffic
        self._cycle = cycle
        self._monitors = monitors
        self._supervisor = life.supervisor
        self.config = life.config
        self.scaling = life.config.scaling
        self._own_bus = bus is None
        self.bus: can.BusABC | None = bus
        self.network: canopen.Network | None = None
        self._frame_log: can.Listener | None = None
        #: each drive's boot as planned against its dictionary (:meth:`plan`, at :meth:`open`)
        self.plans: list[BootPlan] = []
        self.module_plan: ModulePlan | None = None
        #: what the plans skipped and why, one line each (logged at configure)
        self.boot_report: list[str] = []

    # ------------------------------------------------------------------ the plan
    def plan(self) -> list[BootPlan]:
        """Plan every drive's boot against its dictionary (no bus needed); the load-cell
        module's plan goes to :attr:`module_plan`. Notes and warnings are logged once.

        :raises DictionaryError: what every drive lacks, drives with the same dictionary and
            the same gaps named together; nothing has been sent.
        """
        cfg = self.config
        plans: list[BootPlan] = []
        failures: dict[str, list[str]] = {}
        for i, (name, node_id) in enumerate(zip(cfg.names, cfg.node_ids)):
            try:
                d = Dictionary(cfg.eds[i], node_id)
                plans.append(plan_drive(d, self._boot_settings(i)))
            except DictionaryReadError as exc:
                failures.setdefault(f'can.eds: {exc}', []).append(f'{name} (node {node_id})')
            except DictionaryError as exc:
                # the same gaps in the same file: one entry naming every drive
                text = str(exc).split(' cannot drive the brace: ', 1)[-1]
                failures.setdefault(f'{d.product} cannot drive the brace: {text}', []).append(
                    f'{name} (node {node_id})')
        self.module_plan = None
        module = cfg.load_cell_module
        if module is not None:
            try:
                self.module_plan = plan_module(
                    Dictionary(module.eds, module.node_id), node_id=module.node_id,
                    objects=module.objects, tpdo=module.tpdo, master_node_id=cfg.master_node_id,
                    master_heartbeat_ms=cfg.master_heartbeat_ms, drive_heartbeat_ms=cfg.drive_heartbeat_ms)
            except (DictionaryError, DictionaryReadError) as exc:
                failures.setdefault(f'can.load_cell_node: {exc}', []).append(f'node {module.node_id}')
        if not failures:
            clash = self._cob_clashes(plans)
            if clash:
                failures[clash] = []
        if failures:
            raise DictionaryError('configure refused (nothing was sent to the bus): ' + ' | '.join(
                (', '.join(who) + ': ' if who else '') + why for why, who in failures.items()))
        self.boot_report = _report(plans, self.module_plan)
        for line in self.boot_report:
            (log.warning if line.startswith('warning') else log.info)('boot plan: %s', line)
        return plans

    def _cob_clashes(self, plans: Sequence[BootPlan]) -> str:
        """Two PDOs (or a PDO and a drive's heartbeat, EMCY or SDO) on one COB-ID."""
        used: dict[int, str] = {0x80: 'SYNC', 0x700 + self.config.master_node_id: "master's heartbeat"}
        nodes = list(self.config.node_ids) + ([self.module_plan.node_id] if self.module_plan else [])
        for n in nodes:
            for base, what in ((0x80, 'EMCY'), (0x580, 'SDO'), (0x600, 'SDO'), (0x700, 'heartbeat')):
                used[base + n] = f'node {n} {what}'
        layouts = [(p.name, lay) for p in plans for lay in (*p.rpdos, p.feedback)]
        if self.module_plan is not None:
            layouts.append((f'node {self.module_plan.node_id}', self.module_plan.tpdo))
        for who, lay in layouts:
            if lay.cob_id in used:
                return (f'{who} {lay.name} COB-ID {lay.cob_id:03X}h is also {used[lay.cob_id]}; '
                        'set a free can.{rpdo,tpdo}.<n>.cob_id')
            used[lay.cob_id] = f'{who} {lay.name}'
        return ''

    def _boot_settings(self, index: int) -> BootSettings:
        """What the master wants of drive ``index``, in its units (docs/can.md)."""
        cfg, sc = self.config, self.scaling
        lo, hi = self._life.limits.stroke_of(index)
        home = cfg.home_lengths[index] if cfg.home_lengths is not None else None
        # in the drive's own counts (its polarity and counts per revolution)
        p = cfg.polarity[index] if cfg.polarity else 1
        r = cfg.count_ratio[index] if cfg.count_ratio else 1.0

        def wire(counts: int) -> int:
            return p * round(counts * r)
        return BootSettings(
            node_id=cfg.node_ids[index], name=cfg.names[index], master_node_id=cfg.master_node_id,
            master_heartbeat_ms=cfg.master_heartbeat_ms, drive_heartbeat_ms=cfg.drive_heartbeat_ms,
            period_us=round(cfg.period * 1e6), interpolation=interpolation_period(cfg.period),
            homing_method=cfg.homing_method,
            following_error_counts=max(1, round(cfg.following_error_window * sc.counts_per_unit * r)),
            velocity_counts=round(sc.velocity_to_counts(self._life.limits.v_max) * r),
            acceleration_counts=round(sc.acceleration_to_counts(self._life.limits.a_max) * r),
            soft_limits_counts=(tuple(sorted((wire(sc.to_counts(lo)), wire(sc.to_counts(hi)))))
                                if lo > float('-inf') and hi < float('inf') else None),
            home_offset_counts=None if home is None else wire(sc.to_counts(home)),
            load_cell=cfg.load_cell_object, rpdo=cfg.rpdo, tpdo=cfg.tpdo,
            counts_per_rev=cfg.counts_per_rev[index] if cfg.counts_per_rev else None)

    def sdo_writes(self, index: int) -> list[SdoWrite]:
        """The configuration of drive ``index`` (actuator order) as planned, in write order."""
        plan = self.plans[index] if self.plans else self.plan()[index]
        return plan.writes + plan.mapping

    # ------------------------------------------------------------------ bus
    def open(self) -> None:
        """Plan the boot, open the bus and the canopen Network, start the SYNC thread
        (heartbeat only).

        :raises DictionaryError: a drive's dictionary lacks what the brace needs (nothing opened).
        :raises DriverInitializationError: the interface / channel cannot be opened.
        """
        life = self._life
        if life.state is not MasterState.CLOSED:
            return
        cfg = self.config
        self.plans = self.plan()
        log_path = cfg.frame_log
        if self.bus is None:
            try:
                # own frames back to the listener only when logging: the log then holds
                # both directions in bus order
                # virtual: frames keep the send time the master gives them (one clock
                # read per SYNC for the master's log and for the simulated drives)
                extra = {'preserve_timestamps': True} if cfg.interface == 'virtual' else {}
                self.bus = open_bus(cfg.interface, cfg.channel, bitrate=cfg.bitrate,
                                    receive_own_messages=bool(log_path), **extra)
            except (can.CanError, OSError, ValueError, ImportError) as exc:
                raise DriverInitializationError(
                    f'cannot open CAN bus interface={cfg.interface!r} channel={cfg.channel!r} '
                    f'bitrate={cfg.bitrate}: {exc}') from exc
        self._traffic.count_tx = not log_path
        net = StampedNetwork(self.bus)
        net.listeners.append(BusListener(self._receiver))
        if log_path:
            from .framelog import open_frame_log
            self._frame_log = open_frame_log(log_path)
            net.listeners.append(self._frame_log)
        life.module = None
        if self.module_plan is not None:
            mp = self.module_plan
            m = _Module('load-cell module', mp.node_id, self._remote(net, mp.node_id, mp.dictionary),
                        heartbeat=mp.heartbeat, tpdo=mp.tpdo,
                        zeros=tuple(LoadInput.of(e.code).zero for e in mp.tpdo.entries))
            life.module = m
            net.subscribe(mp.tpdo.cob_id, self._receiver.module_callback(m))
            self._subscribe_node(net, m)
        life.drives = []
        self._receiver.attach(life.drives, life.module)   # filled below, in place
        for i, (name, plan) in enumerate(zip(cfg.names, self.plans)):
            node = self._remote(net, plan.node_id, plan.dictionary)
            zero = 0
            if plan.load_type is not None and cfg.load_cell_object is not None:
                zero = LoadInput.of(plan.feedback.entries[plan.feedback.position_of('load')].code).zero
            d = _Drive(name, plan.node_id, node, heartbeat=plan.heartbeat, index=i,
                       rpdos=plan.rpdos, rpdo_sent=[None] * len(plan.rpdos), load_zero=zero,
                       polarity=cfg.polarity[i] if cfg.polarity else 1,
                       count_ratio=cfg.count_ratio[i] if cfg.count_ratio else 1.0,
                       load_gain=cfg.load_gain[i] if cfg.load_gain else 1.0,
                       load_offset=cfg.load_offset[i] if cfg.load_offset else 0.0,
                       feedforward=plan.feedforward)
            life.drives.append(d)
            net.subscribe(plan.feedback.cob_id, self._receiver.tpdo_callback(d, plan.feedback))
            self._subscribe_node(net, d)
        self._saturation_span()
        net.connect()
        self.network = net
        if self.config.mechanism is not None:
            warm_up(self.config.mechanism)     # its first-use imports here, not in the cycle
        # silent until the boot has listened for another master (our heartbeat would make a
        # running master stop)
        self._cycle.start(self.bus, net)
        life.set_state(MasterState.OPEN)

    def close(self) -> None:
        """Stop receiving and close the bus (if this part opened it); after the cycle stopped."""
        if self.network is not None:
            if self.network.notifier is not None:
                self.network.notifier.stop(1.0)
                self.network.notifier = None
            self.network = None
        self._frame_log = None            # the Notifier stopped (closed) it
        if self.bus is not None and self._own_bus:
            self.bus.shutdown()
        self.bus = None

    def _remote(self, net: canopen.Network, node_id: int, od_of: Dictionary) -> canopen.RemoteNode:
        node = canopen.RemoteNode(node_id, od_of.od)
        node.sdo.RESPONSE_TIMEOUT = self.config.sdo_timeout
        node.sdo.MAX_RETRIES = self.config.sdo_retries + 1      # canopen counts the first try
        net.add_node(node)
        return node

    def _subscribe_node(self, net: canopen.Network, n: _Node) -> None:
        net.subscribe(0x700 + n.node_id, self._receiver.heartbeat_callback(n))
        net.subscribe(0x80 + n.node_id, self._receiver.emcy_callback(n))

    def _saturation_span(self) -> None:
        """The saturation threshold within what every load-cell input can show."""
        spans = []
        for plan in self.plans:
            pos = plan.feedback.position_of('load')
            if pos is not None:
                spans.append(LoadInput.of(plan.feedback.entries[pos].code).span)
        if self.module_plan is not None:
            spans += [LoadInput.of(e.code).span for e in self.module_plan.tpdo.entries]
        if spans:
            sat = self.scaling.saturation_counts(self._life.limits.saturation_fraction, min(spans))
            self._life.limits = dataclasses.replace(self._life.limits, saturation_counts=sat)

    # ------------------------------------------------------------------ boot
    def boot(self, *, timeout: float | None = None) -> None:
        """Boot every drive to NMT OPERATIONAL with the planned configuration (docs/can.md).

        :raises DictionaryError: a drive's dictionary lacks what the brace needs (nothing sent).
        :raises DriverInitializationError: a drive did not boot within ``can.boot_timeout``
            (also latched as a BOOT_TIMEOUT fault) or rejected an SDO write (the object,
            value, abort code and drive named).
        """
        life = self._life
        if life.supervising:
            return                                       # booted already
        if life.state is MasterState.CLOSED:
            self.open()
        life.set_state(MasterState.BOOTING)
        limit = self.config.boot_timeout if timeout is None else timeout
        self._await_boot_up(limit)
        for d in life.drives:
            self.configure(d)
        if life.module is not None:
            self.configure_module(life.module)
        life.pdo_running = True
        for n in life.nodes:
            n.node.nmt.send_command(0x01)            # start remote node
        module = life.module
        life.wait(lambda: all(d.nmt == NmtState.OPERATIONAL and d.sample is not None
                              for d in life.drives)
                  and (module is None or (module.samples > 0
                                          and module.nmt == NmtState.OPERATIONAL)),
                  timeout=max(0.5, 4 * self.config.drive_heartbeat_ms * 1e-3),
                  what='drives OPERATIONAL with their feedback TPDO')
        for d in life.drives:
            d.target = life.actual_counts(d)
            d.checked = None
        life.supervising = True
        life.desired = State402.SWITCH_ON_DISABLED
        life.set_state(MasterState.FAULT if self._supervisor.latched else MasterState.DISABLED)
        log.info('CAN master: %d drives OPERATIONAL on %s', len(life.drives), self.config.channel)

    def _await_boot_up(self, limit: float) -> None:
        """Each node's boot-up or heartbeat; for the silent ones an NMT reset-communication (a
        drive that booted before we listened sends its boot-up again), then an SDO probe (a
        drive that sends none), before it is declared missing."""
        life = self._life
        deadline = time.monotonic() + limit
        nodes = life.nodes
        listen_end = time.monotonic() + min(LISTEN_S, 0.5 * limit)
        # at least a few SYNC periods of another master's, before any write
        heard_end = time.monotonic() + MASTER_LISTEN_S
        for n in nodes:
            n.booted.wait(max(0.0, listen_end - time.monotonic()))
        time.sleep(max(0.0, heard_end - time.monotonic()))
        other = self._receiver.foreign_master()
        if other:
            life.set_state(MasterState.OPEN)
            raise DriverInitializationError(
                f'another CANopen master is on {self.config.interface}:{self.config.channel}: '
                f'{other}. Two masters would send SYNC and targets to the same drives; stop the '
                'other master (another brace-bringup? ros2 node list) and configure again. '
                'Nothing was sent to the drives')
        self._cycle.heartbeat_on = True                  # the bus is ours: our heartbeat from now
        silent = [n for n in nodes if not n.booted.is_set()]
        for n in silent:
            log.info('node %d: no boot-up or heartbeat heard; NMT reset communication', n.node_id)
            n.node.nmt.send_command(0x82)                # reset communication: boot-up again
        reset_end = time.monotonic() + 0.5 * max(0.0, deadline - time.monotonic())
        for n in silent:
            n.booted.wait(max(0.0, reset_end - time.monotonic()))
        for n in [n for n in nodes if not n.booted.is_set()]:
            try:                                          # a drive that sends no boot-up at all
                sdo = n.node.sdo
                saved = sdo.RESPONSE_TIMEOUT, sdo.MAX_RETRIES
                sdo.RESPONSE_TIMEOUT, sdo.MAX_RETRIES = max(PROBE_TIMEOUT_S, self.config.sdo_timeout), 1
                try:
                    sdo.upload(0x1000, 0)
                finally:
                    sdo.RESPONSE_TIMEOUT, sdo.MAX_RETRIES = saved
            except (canopen.SdoAbortedError, canopen.SdoCommunicationError):
                continue
            log.warning('node %d sent no boot-up message (not even after an NMT reset); it '
                        'answers SDO: taken as present', n.node_id)
            n.nmt = NmtState.PRE_OPERATIONAL
            n.booted.set()
        for n in nodes:
            n.booted.wait(max(0.0, deadline - time.monotonic()))
        missing = [n for n in nodes if not n.booted.is_set()]
        for n in missing:
            self._supervisor.report(
                FaultKind.BOOT_TIMEOUT,
                f'no boot-up, heartbeat or SDO answer from node {n.node_id} within '
                f'{limit:g} s', drive=n.name,
                still_present=self._monitors.heartbeat_missing(n))
        if missing:
            life.set_state(MasterState.FAULT)
            raise DriverInitializationError(
                'drive(s) did not boot: ' + ', '.join(f'{n.name} (node {n.node_id})' for n in missing)
                + f' within can.boot_timeout = {limit:g} s (no boot-up message, no heartbeat, '
                'no answer to an NMT reset nor to an SDO read of 1000h); check power, wiring, '
                'node ids and bit rate')

    def _download(self, n: _Node, w: SdoWrite, source: str) -> None:
        try:
            n.node.sdo.download(w.index, w.subindex, w.data())
        except canopen.SdoAbortedError as exc:
            raise DriverInitializationError(
                f'{n.name} (node {n.node_id}) rejected {w.index:04X}h:{w.subindex} = {_shown(w.value)} '
                f'({w.what}): abort {exc} (dictionary {source})') from exc
        except canopen.SdoCommunicationError as exc:
            cfg = self.config
            raise DriverInitializationError(
                f'{n.name} (node {n.node_id}) did not answer the SDO write of {w.index:04X}h:'
                f'{w.subindex} = {_shown(w.value)} ({w.what}) within can.sdo_timeout = {cfg.sdo_timeout:g} s '
                f'({cfg.sdo_retries + 1} attempt(s)): {exc}; a slow drive needs a larger '
                'can.sdo_timeout') from exc

    def configure(self, d: _Drive) -> None:
        """NMT pre-operational, then the planned SDO writes, then the planned PDO mapping."""
        plan = self.plans[d.index]
        d.node.nmt.send_command(0x80)                    # enter pre-operational
        for w in plan.writes + plan.mapping:
            self._download(d, w, plan.dictionary.path.name)
        for w in plan.writes:
            if w.index == 0x60A9:
                self._verify_unit(d, w)
        try:
            raw = d.node.sdo.upload(0x1000, 0)
            device_type = struct.unpack('<I', raw[:4])[0]
            if device_type & 0xFFFF != 402:
                log.warning('%s: device type 1000h = %08Xh is not a CiA 402 drive',
                            d.name, device_type)
        except (canopen.SdoAbortedError, canopen.SdoCommunicationError, struct.error):
            pass

    def _verify_unit(self, d: _Drive, w: SdoWrite) -> None:
        """Read back a unit the boot set (60A9h): some firmware accepts the write and keeps only
        part of it (a drive whose velocity unit is always rpm, the power of ten aside). The
        feed-forward and the speed limits would then be read in another unit than the master
        writes them: the boot stops, naming what the drive kept."""
        try:
            raw = d.node.sdo.upload(w.index, w.subindex)
        except (canopen.SdoAbortedError, canopen.SdoCommunicationError) as exc:
            raise DriverInitializationError(
                f'{d.name} (node {d.node_id}): {w.index:04X}h:{w.subindex} ({w.what}) could not be read '
                f'back after the write: {exc}') from exc
        kept = int.from_bytes(bytes(raw[:4]), 'little')
        if kept != w.value & 0xFFFFFFFF:
            raise DriverInitializationError(
                f'{d.name} (node {d.node_id}) kept {w.index:04X}h:{w.subindex} = {kept:08X}h after '
                f'{w.value & 0xFFFFFFFF:08X}h was written ({w.what}): its velocity unit cannot be '
                'the position unit per second, and the master writes velocities (607Fh, 6083h..6085h, '
                'the 60B1h feed-forward) in it. Nothing moves; set the drive\'s units with its tool '
                '(docs/can.md, "Units")')

    def configure_module(self, m: _Module) -> None:
        plan: ModulePlan = self.module_plan
        m.node.nmt.send_command(0x80)
        for w in plan.writes + plan.mapping:
            self._download(m, w, plan.dictionary.path.name)

    # ------------------------------------------------------------------ homing
    def home(self, *, timeout: float | None = None) -> None:
        """Home every drive with ``can.homing_method`` (6098h) and home offset 607Ch; with
        ``can.homing_method: 0`` (absolute encoders) there is nothing to home and nothing is sent.

        Method 35 (37): the current position becomes the home offset, i.e. the actuator
        length at the home pose: park the brace there first. A drive without a writable 607Ch
        homes to its own offset and the master keeps the difference (positions on the bus
        are then the drive's counts plus that offset; 607Dh follows after homing). Only
        with the drives disabled: re-zeroing encoders under a held or moving command would
        leave a silent offset between where the drives are and where the command says they are.

        :raises DriverOperationError: the drives are not disabled (the message names the
            state), no home offset (no mechanism model), a homing error bit (6041h bit 13),
            or a protective stop latched.
        """
        life = self._life
        life.require_ready()
        if not self.config.homing_method:
            # can.homing_method 0: absolute encoders, the drives' positions are the lengths
            # already; nothing is sent (a drive without 6098h has no homing to ask for)
            life.homed = True
            log.info('home: can.homing_method = 0 (absolute encoders): nothing to home')
            return
        if life.state is not MasterState.DISABLED:
            raise DriverOperationError(
                f'home refused: the drives are {life.state.value}; homing re-zeroes the '
                'encoders and is only allowed with the drives disabled (call disable first)')
        if self.config.home_lengths is None:
            raise DriverOperationError('no home offset: the mechanism model (IK of home_pose) '
                                       'is unavailable; pass home_lengths to MasterConfig')
        life.tracking = False
        life.set_state(MasterState.HOMING)
        method = self.config.homing_method
        try:
            homes = [self.scaling.to_counts(self.config.home_lengths[d.index]) for d in life.drives]
            for d, home in zip(life.drives, homes):
                self._sdo(d, 0x6098, 0, method)
                if self.plans[d.index].home_offset_on_drive:
                    self._sdo(d, 0x607C, 0, d.to_wire(home))
            life.mode = int(OpMode.HOMING)
            self._sdo_all(0x6060, 0, life.mode)
            life.desired = State402.OPERATION_ENABLED
            life.wait(lambda: life.all_in(State402.OPERATION_ENABLED), timeout=timeout,
                      what='OPERATION ENABLED for homing')
            life.homing_start = True
            try:
                def done() -> bool:
                    for d in life.drives:
                        sw = d.sample.statusword if d.sample else 0
                        if sw & Statusword.OP_SPECIFIC_13:
                            raise DriverOperationError(
                                f'{d.name}: homing error (statusword {sw:04X}h), method {method}')
                        if not (sw & Statusword.OP_SPECIFIC_12 and sw & Statusword.TARGET_REACHED):
                            return False
                    return True
                life.wait(done, timeout=timeout or 2.0, what='homing attained')
            finally:
                life.homing_start = False
            life.wait_syncs(2)
            for d, home in zip(life.drives, homes):
                if not self.plans[d.index].home_offset_on_drive:
                    self._keep_home_offset(d, home)
                d.checked = None
                d.history.clear()
                d.target = life.actual_counts(d)
            life.mode = int(OpMode.CYCLIC_SYNC_POSITION)
            self._sdo_all(0x6060, 0, life.mode)
            life.homed = True
        except BaseException:
            # a homing cut short leaves the reference unknown (the drive may have set its
            # position already) and the drives in homing mode: not homed, and 6060h back to
            # cyclic synchronous position where the drives still answer (a fault sweep: a
            # failed re-homing kept `homed` and homing mode)
            life.homed = False
            life.mode = int(OpMode.CYCLIC_SYNC_POSITION)
            try:
                self._sdo_all(0x6060, 0, life.mode)
            except Exception as exc:  # noqa: BLE001 - the homing's own error is the one raised
                log.error('homing failed and 6060h could not be set back to cyclic synchronous '
                          'position (%s): recover and home again', exc)
            life.desired = State402.SWITCH_ON_DISABLED
            life.set_state(MasterState.FAULT if self._supervisor.latched else MasterState.DISABLED)
            raise
        life.desired = State402.SWITCH_ON_DISABLED
        life.wait(lambda: life.all_in(State402.SWITCH_ON_DISABLED), timeout=timeout,
                  what='SWITCH ON DISABLED after homing')
        life.set_state(MasterState.DISABLED)
        log.info('homed (method %d): %s', method,
                 ', '.join(f'{n} {p:.4f} {life.limits.unit}' for n, p in zip(self.config.names, self._receiver.feedback().position)))

    def _keep_home_offset(self, d: _Drive, home_counts: int) -> None:
        """The drive homed to its own offset (no writable 607Ch): from now on the master adds
        ``home - reading`` to its positions (and takes it from its targets); the drive's
        software limits 607Dh are written in its own counts."""
        raw = self.scaling.to_counts(d.sample.position) - d.count_offset
        shift = home_counts - raw - d.count_offset
        d.count_offset = home_counts - raw
        # the sample in hand in the new counts too: the cycle holds the drive where its latest
        # sample says, and a target from the old counts would be far outside 607Dh
        d.sample.position += self.scaling.to_si(shift)
        d.recent.clear()
        d.history.clear()
        plan = self.plans[d.index]
        lo, hi = self._life.limits.stroke_of(d.index)
        if plan.dictionary.writable(ObjectRef(0x607D, 1)) and plan.dictionary.writable(ObjectRef(0x607D, 2)) \
                and lo > float('-inf') and hi < float('inf'):
            try:
                low, high = sorted((d.to_wire(self.scaling.to_counts(lo)), d.to_wire(self.scaling.to_counts(hi))))
                self._sdo(d, 0x607D, 1, low)
                self._sdo(d, 0x607D, 2, high)
            except DriverOperationError as exc:
                log.warning('%s: software position limits not written after homing: %s', d.name, exc)
        log.info('%s: no writable 607Ch; the master keeps the home offset (%d counts)', d.name,
                 d.count_offset)

    def _sdo(self, d: _Drive, index: int, sub: int, value: int) -> None:
        """Write ``value`` in the object's own type (from the drive's dictionary)."""
        dic = self.plans[d.index].dictionary
        ref = ObjectRef(index, sub)
        try:
            data = dic.encode(ref, value)
        except ValueError as exc:
            raise DriverOperationError(f'{d.name}: {exc}') from exc
        try:
            d.node.sdo.download(index, sub, data)
        except (canopen.SdoAbortedError, canopen.SdoCommunicationError) as exc:
            raise DriverOperationError(f'{d.name}: SDO {index:04X}h:{sub} = {value} failed: {exc}') from exc

    def _sdo_all(self, index: int, sub: int, value: int) -> None:
        for d in self._life.drives:
            self._sdo(d, index, sub, value)


def _shown(value: int | float) -> str:
    """A value as a message shows it: hexadecimal when it is an id or a mapping entry."""
    return f'{value:08X}h' if isinstance(value, int) and value > 0xFFFF else f'{value}'


def _report(plans: Sequence[BootPlan], module: ModulePlan | None) -> list[str]:
    """The plans' notes and warnings, each once, with the drives it applies to."""
    lines: dict[str, list[str]] = {}
    for p in plans:
        for w in p.warnings:
            lines.setdefault(f'warning: {w}', []).append(p.name)
        for note in p.notes:
            lines.setdefault(note, []).append(p.name)
    if module is not None:
        for w in module.warnings:
            lines.setdefault(f'warning: {w}', []).append(f'load-cell module (node {module.node_id})')
        for note in module.notes:
            lines.setdefault(note, []).append(f'load-cell module (node {module.node_id})')
    out = []
    for text, who in lines.items():
        head, _, rest = text.partition('warning: ')
        out.append(f'warning: {", ".join(who)}: {rest}' if text.startswith('warning: ')
                   else f'{", ".join(who)}: {text}')
    return out
