"""brace-commission: from an unknown bus to a device YAML that is right (docs/commissioning.md).

A lab's first day with a brace: which node id is which actuator, whether each drive counts
the way the YAML says (polarity, counts per revolution), where each load cell's zero and gain
are, and whether the nodes on the bus are the drives the EDS describes::

    brace-commission CONFIG plan
    brace-commission CONFIG scan
    brace-commission CONFIG check [--axis NAME] [--yes] [--write OUT.yaml]
    brace-commission CONFIG calibrate-load-cell --axis NAME --known-force N [--yes] [--write OUT.yaml]

Exit status: 0 the hardware matches the YAML, 1 corrections were found (and written with
``--write``), 2 an error that stops commissioning (one message says which).

It works on the YAML's CAN interface, with or without ROS running; with ``can.sim: true`` the
simulated brace runs in this process, built from the ``sim.*`` keys (how the hardware really
is) while ``can.*`` / ``actuator.*`` say what the user believes.

``check`` jogs one axis at a time (the others holding) a small distance out and back, at
most 10 % of the actuator's speed and acceleration, inside the stroke, and no further than
the model says keeps every leg below a fifth of ``safety.force_limit``. The encoders cannot
tell a swapped, inverted or mis-scaled drive: a drive follows its own counts whatever they
mean. What can is the load the jog puts on the body (or the test fixture the YAML's
``sim.stiffness`` describes) and so on every leg: the load cells. The tool predicts, from the
mechanism and the body, the change of every load cell for each actuator moving (the
columns of ``M = df/dq``), and finds the assignment of node ids to actuators, the sign and
the scale of each drive that explain the measured changes of all jogs together (least
squares over every permutation). The tare comes from the load cells at rest. The result is
a YAML patch naming each key it changes.
"""
from __future__ import annotations

import argparse
import copy
import itertools
import math
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .config import ConfigError, DeviceConfig, load_device_config, read_yaml

__all__ = ['main', 'scan', 'plan_report', 'NodeInfo', 'ScanResult', 'CheckResult', 'identify',
           'scale_is_wrong', 'EXIT_MATCH', 'EXIT_CORRECTED', 'EXIT_ERROR']

EXIT_MATCH, EXIT_CORRECTED, EXIT_ERROR = 0, 1, 2
#: s an SDO probe of a node id may take (the scan's answer window after all requests)
PROBE_WINDOW_S = 0.15
#: a drive's scale counts as wrong beyond this relative deviation (a wrong counts per
#: revolution is a factor: x4 evaluation forgotten, another encoder)
SCALE_TOLERANCE = 0.1
#: ... and beyond this many of its standard errors: a jog that barely loads the load cells
#: (the trainer's crank: 0.01 N) measures its scale too loosely to correct anything
SCALE_SIGMAS = 4.0
#: the scales a drive may have (travel over commanded travel): a wrong counts per revolution
SCALE_RANGE = (0.2, 5.0)
#: a load cell's gain counts as wrong beyond this
GAIN_TOLERANCE = 0.01
#: a jog's effect must stand this many standard errors above the load cells' noise
SIGNIFICANCE = 6.0
#: share of safety.force_limit the model may predict for a jog
JOG_FORCE_SHARE = 0.2
#: samples averaged for each reading (at rest)
SAMPLES = 150


class CommissionError(Exception):
    """What stops commissioning (exit 2), said in one message."""


# ------------------------------------------------------------------ scan

@dataclass
class NodeInfo:
    """One node that answered on the bus."""

    node_id: int
    device_type: int | None = None
    vendor: int | None = None
    product: int | None = None
    revision: int | None = None
    serial: int | None = None
    name: str = ''
    heard: str = ''                 # 'boot-up' / 'heartbeat <state>' seen while listening

    @property
    def profile(self) -> str:
        if self.device_type is None:
            return '-'
        return f'CiA {self.device_type & 0xFFFF}'

    def row(self) -> str:
        def h(v: int | None) -> str:
            return '-' if v is None else f'{v:08X}h'
        dt = '-' if self.device_type is None else f'{self.device_type:08X}h ({self.profile})'
        return (f'{self.node_id:>4}  {dt:<22} vendor {h(self.vendor)}  product {h(self.product)}  '
                f'rev {h(self.revision)}  serial {h(self.serial)}  {self.name!r}')


@dataclass
class ScanResult:
    nodes: list[NodeInfo]
    differences: list[str] = field(default_factory=list)
    #: the node ids the drives really have, in actuator order, when the scan can tell
    node_ids: list[int] | None = None
    seconds: float = 0.0


def scan(bus: Any, *, ids: Sequence[int] = range(1, 128), listen: float = 0.25,
         sdo_timeout: float = 0.1) -> tuple[list[NodeInfo], float]:
    """Every node on ``bus``: boot-ups and heartbeats heard for ``listen`` s, then an SDO
    read of 1000h sent to every id at once (the answers come within :data:`PROBE_WINDOW_S`),
    then each answering node's 1008h, 1009h, 100Ah and 1018h read one by one. Returns the
    nodes (id order) and the seconds it took."""
    import can
    import canopen
    t0 = time.monotonic()
    heard: dict[int, str] = {}
    answered: dict[int, int | None] = {}
    lock = threading.Lock()

    class _Listener(can.Listener):
        def on_message_received(self, msg: can.Message) -> None:
            cob, data = msg.arbitration_id, bytes(msg.data)
            if msg.is_error_frame or msg.is_remote_frame:
                return
            with lock:
                if 0x701 <= cob <= 0x77F and data:
                    heard[cob - 0x700] = 'boot-up' if data[0] == 0 else f'heartbeat {data[0]:02X}h'
                elif 0x581 <= cob <= 0x5FF and len(data) >= 8 and data[1:4] == b'\x00\x10\x00':
                    node = cob - 0x580
                    if data[0] & 0xE0 == 0x40:           # upload response
                        answered[node] = int.from_bytes(data[4:8], 'little')
                    elif data[0] == 0x80:                  # an abort is an answer too
                        answered.setdefault(node, None)

    listener = _Listener()
    notifier = can.Notifier(bus, [listener], timeout=0.02)
    try:
        time.sleep(listen)
        for node in ids:
            bus.send(can.Message(arbitration_id=0x600 + node, is_extended_id=False,
                                 data=bytes([0x40, 0x00, 0x10, 0x00, 0, 0, 0, 0])))
        time.sleep(PROBE_WINDOW_S)
    finally:
        notifier.stop()
    with lock:
        present = sorted(set(answered) | set(heard))
    net = canopen.Network(bus)
    net.connect()                              # the bus is open already: only its notifier
    infos: list[NodeInfo] = []
    try:
        for node_id in present:
            node = canopen.RemoteNode(node_id, canopen.ObjectDictionary())
            node.sdo.RESPONSE_TIMEOUT = sdo_timeout
            net.add_node(node)
            info = NodeInfo(node_id, answered.get(node_id), heard=heard.get(node_id, ''))
            for index, sub, attr in ((0x1018, 1, 'vendor'), (0x1018, 2, 'product'), (0x1018, 3, 'revision'),
                                     (0x1018, 4, 'serial')):
                setattr(info, attr, _read_int(node, index, sub))
            if info.device_type is None:
                info.device_type = _read_int(node, 0x1000, 0)
            info.name = _read_text(node, 0x1008)
            infos.append(info)
    finally:
        net.notifier.stop()
    return infos, time.monotonic() - t0


def _read_int(node: Any, index: int, sub: int) -> int | None:
    import canopen
    try:
        raw = node.sdo.upload(index, sub)
    except (canopen.SdoAbortedError, canopen.SdoCommunicationError):
        return None
    return int.from_bytes(raw[:4], 'little') if raw else None


def _read_text(node: Any, index: int) -> str:
    import canopen
    try:
        raw = node.sdo.upload(index, 0)
    except (canopen.SdoAbortedError, canopen.SdoCommunicationError):
        return ''
    return raw.decode('latin-1', errors='replace').rstrip('\x00').strip()


def compare(cfg: DeviceConfig, nodes: Sequence[NodeInfo]) -> ScanResult:
    """What the scan found against the YAML's ``can.node_ids`` (and load-cell module) and the
    EDS's identity ([DeviceInfo] VendorNumber / ProductNumber, or 1018h's defaults)."""
    from .can.dictionary import Dictionary, eds_files
    from .can.state import load_cell_source
    names = list(cfg.get_path('mechanism.actuator_names'))
    expected = [int(i) for i in cfg.get_path('can.node_ids')]
    files = eds_files(cfg, len(expected))
    identities = [_identity(Dictionary(f, n)) for f, n in zip(files, expected)]
    _, module = load_cell_source(cfg)
    by_id = {n.node_id: n for n in nodes}
    diffs: list[str] = []
    node_ids = list(expected)
    spare = [n for n in nodes if n.node_id not in expected and (module is None or n.node_id != module.node_id)]
    for i, (name, node_id, ident) in enumerate(zip(names, expected, identities)):
        found = by_id.get(node_id)
        if found is None:
            match = [n for n in spare if _matches(n, ident)]
            if len(match) == 1:
                node_ids[i] = match[0].node_id
                spare.remove(match[0])
                diffs.append(f'{name}: node {node_id} (can.node_ids) does not answer; node '
                             f'{match[0].node_id} answers with the identity of its EDS '
                             f'({_ident_text(ident)}): can.node_ids[{i}] = {match[0].node_id}?')
            else:
                diffs.append(f'{name}: node {node_id} (can.node_ids) does not answer on the bus '
                             '(power, wiring, node id switches, bit rate)')
            continue
        if not _matches(found, ident):
            diffs.append(f'{name}: node {node_id} is {_node_ident(found)}, its EDS describes '
                         f'{_ident_text(ident)}')
        if found.device_type is not None and found.device_type & 0xFFFF != 402:
            diffs.append(f'{name}: node {node_id} device type {found.device_type:08X}h is not a CiA 402 drive')
    if module is not None and module.node_id not in by_id:
        diffs.append(f'load-cell module: node {module.node_id} (can.load_cell_node.node_id) does not answer')
    for n in spare:
        diffs.append(f'node {n.node_id} ({_node_ident(n)}{", " + repr(n.name) if n.name else ""}) is on the bus '
                     'and not in the YAML: a foreign node (mind its traffic and node id)')
    return ScanResult(list(nodes), diffs, node_ids if node_ids != expected else None)


def _identity(d: Any) -> tuple[int | None, int | None]:
    from .can.dictionary import ObjectRef
    vendor = d.vendor_number if d.vendor_number is not None else d.default(ObjectRef(0x1018, 1))
    product = d.product_number if d.product_number is not None else d.default(ObjectRef(0x1018, 2))
    return vendor, product


def _matches(n: NodeInfo, ident: tuple[int | None, int | None]) -> bool:
    vendor, product = ident
    return (vendor is None or n.vendor is None or n.vendor == vendor) and \
        (product is None or n.product is None or n.product == product)


def _ident_text(ident: tuple[int | None, int | None]) -> str:
    vendor, product = ident
    return f'vendor {"?" if vendor is None else f"{vendor:08X}h"}, product {"?" if product is None else f"{product:08X}h"}'


def _node_ident(n: NodeInfo) -> str:
    return _ident_text((n.vendor, n.product))


# ------------------------------------------------------------------ identification

@dataclass
class AxisFinding:
    """What one jog showed: the physical actuator it moved, the sign and the scale."""

    axis: int                        # the jogged axis (as the YAML believes: node can.node_ids[axis])
    actuator: int                    # the actuator it really moved
    sign: int
    scale: float                     # physical travel / commanded travel
    stderr: float                    # standard error of sign * scale
    significant: bool
    following_error: float = 0.0     # m or rad, the largest of the jog


def model_response(cfg: DeviceConfig, sim_model: Any, pose: np.ndarray, step: float) -> np.ndarray:
    """``M[k, j]``: the change of load cell ``k`` per unit of actuator ``j`` moving (the others
    holding), from the YAML's mechanism and body (central differences of the static model)."""
    mech = sim_model.mechanism
    q0 = np.asarray(mech.inverse(pose), float)
    n = len(q0)
    M = np.zeros((n, n))
    _, f_base = sim_model.static_forces(q0, pose)
    for j in range(n):
        plus, minus = q0.copy(), q0.copy()
        plus[j] += step
        minus[j] -= step
        _, fp = sim_model.static_forces(plus, pose)
        _, fm = sim_model.static_forces(minus, pose)
        # the steeper side (a cable goes slack one way and tightens the other)
        up, down = (fp - f_base) / step, (f_base - fm) / step
        M[:, j] = up if np.max(np.abs(up)) >= np.max(np.abs(down)) else down
    return M


def identify(F: dict[tuple[int, int, int], np.ndarray], jogs: dict[int, tuple[float, np.ndarray]],
             noise: np.ndarray) -> tuple[tuple[int, ...], list[AxisFinding], float]:
    """The assignment of the jogged nodes to actuators, and each drive's sign and scale, that
    explain the load-cell changes of all the jogs together.

    :param F: ``F[i, j, s]``: the model's change of every load cell (actuator order) when the
        jog of axis ``i`` moves actuator ``j`` the commanded way (``s = +1``) or the other way
        (``s = -1``), the others holding (secants at the jog's own amplitude: the model need
        not be linear over it, a cable pulls only one way).
    :param jogs: axis ``i`` (the node believed to drive actuator ``i``) -> (commanded travel,
        the measured change of the load cells, read node by node in axis order).
    :param noise: standard deviation of each measured change.
    :returns: ``perm`` (``perm[i]``: the actuator node ``i`` drives), one finding per jog, and
        the margin: the next best assignment's misfit minus the best's (in units of the
        noise variance; small: the load cells cannot tell them apart).
    """
    n = len(noise)
    w = 1.0 / np.maximum(noise, 1e-12) ** 2

    def fit(i: int, j: int, sign: int, perm: Sequence[int], df: np.ndarray) -> tuple[float, float, float]:
        # the scale a drive can really have is a factor near 1 (a wrong counts per revolution:
        # x4, x2, 1/2 ...): within SCALE_RANGE; "it did not move" is not an explanation (the
        # encoder says it moved)
        col = F[i, j, sign][list(perm)]     # the reading of node k is the load cell of actuator perm[k]
        denom = float(np.sum(w * col * col))
        if denom < 1.0:                      # the model predicts no change (a cable going slack)
            return float(np.sum(w * df * df)), 1.0, 0.0
        x = min(max(float(np.sum(w * col * df)) / denom, SCALE_RANGE[0]), SCALE_RANGE[1])
        return float(np.sum(w * (df - x * col) ** 2)), x, denom

    scores = []
    for perm in itertools.permutations(range(n)):
        total = 0.0
        for i, (_, df) in jogs.items():
            total += min(fit(i, perm[i], s, perm, df)[0] for s in (1, -1))
        scores.append((total, perm))
    scores.sort(key=lambda item: item[0])
    best_score, perm = scores[0]
    margin = (scores[1][0] - best_score) if len(scores) > 1 else math.inf
    findings = []
    for i, (_, df) in jogs.items():
        (res_p, x_p, den_p), (res_m, x_m, den_m) = (fit(i, perm[i], s, perm, df) for s in (1, -1))
        sign, x, denom = (1, x_p, den_p) if res_p <= res_m else (-1, x_m, den_m)
        stderr = 1.0 / math.sqrt(denom) if denom > 0 else math.inf
        # significant: one sign explains the change far better than the other
        findings.append(AxisFinding(i, perm[i], sign, x, stderr, abs(res_p - res_m) > 25.0))
    return perm, findings, margin


#: how close (relative) a measured counts per revolution must be to the believed one times a
#: power of two to be taken for it, before any other encoder resolution: the load cells measure
#: the jog's scale to about a percent (a soft body's creep, a busy host's late reading), and
#: 4000 and 4096 counts are 2.4 % apart
FAMILY_WINDOW = 0.03


#: usual encoder resolutions (counts per motor turn; each also x4, quadrature)
USUAL_CPR = (250, 256, 360, 500, 512, 1000, 1024, 2000, 2048, 2500, 4000, 4096, 5000, 8192,
             10000, 16384, 20000, 32768, 65536, 131072, 262144, 1 << 20, 1 << 23)


def scale_is_wrong(scale: float, stderr: float) -> bool:
    """A jog's measured scale (travel over commanded travel) says the counts per revolution
    are wrong: off 1 by more than :data:`SCALE_TOLERANCE` and by more than
    :data:`SCALE_SIGMAS` standard errors. A fresh-clone run beside two busy loops measured the
    healthy trainer's crank at 1.101 +- 0.075 and proposed 4000 counts for its 4096."""
    off = abs(scale - 1.0)
    return off > SCALE_TOLERANCE and off > SCALE_SIGMAS * stderr


def _snap_cpr(value: float, believed: int) -> tuple[int, list[int]]:
    """The counts per revolution a measured ``value`` is, and the other usual resolutions as
    close to it (within :data:`FAMILY_WINDOW`: the measurement cannot tell them apart).

    The believed one times a power of two (a quadrature factor, another interpolation) within
    :data:`FAMILY_WINDOW` comes first; else the nearest usual resolution within 8 %; else
    ``value`` rounded."""
    family = {believed * 2 ** e for e in range(-4, 5)}
    usual = set(family) | {c for base in USUAL_CPR for c in (base, base * 4)}
    near = min(family, key=lambda c: abs(c - value))
    if abs(near - value) <= FAMILY_WINDOW * value:
        chosen = int(near)
    else:
        best = min(usual, key=lambda c: abs(c - value))
        chosen = int(best) if abs(best - value) <= 0.08 * value else int(round(value))
    others = sorted(int(c) for c in usual if c != chosen and abs(c - value) <= FAMILY_WINDOW * value)
    return chosen, others


# ------------------------------------------------------------------ the session

class Session:
    """The bus, the simulated brace (``can.sim``) and the master of one commissioning run."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.cfg = load_device_config(self.path)
        from .checks import check_device
        self.mech = check_device(self.cfg)
        self.sim = None
        self.names = list(self.cfg.get_path('mechanism.actuator_names'))
        self.n = len(self.names)
        self.rotary = str(self.cfg.get_path('actuator.kind')) == 'rotary'
        self.unit = 'rad' if self.rotary else 'm'
        self._bus = None

    def __enter__(self) -> 'Session':
        if self.cfg.get_path('can.sim'):
            from .sim import SimulatedBrace
            self.sim = SimulatedBrace(self.cfg, mechanism=None)
        return self

    def __exit__(self, *exc: object) -> None:
        if self._bus is not None:
            self._bus.shutdown()
            self._bus = None
        if self.sim is not None:
            self.sim.shutdown()

    def bus(self) -> Any:
        import can
        if self._bus is None:
            iface, channel = str(self.cfg.get_path('can.interface')), str(self.cfg.get_path('can.channel'))
            try:
                self._bus = can.Bus(interface=iface, channel=channel,
                                    bitrate=int(self.cfg.get_path('can.bitrate')))
            except (can.CanError, OSError, ValueError, ImportError) as exc:
                raise CommissionError(f'cannot open CAN bus interface={iface!r} channel={channel!r}: {exc}') from exc
        return self._bus

    def close_bus(self) -> None:
        if self._bus is not None:
            self._bus.shutdown()
            self._bus = None

    def scan(self) -> ScanResult:
        nodes, seconds = scan(self.bus(), sdo_timeout=float(self.cfg.get_path('can.sdo_timeout')))
        result = compare(self.cfg, nodes)
        result.seconds = seconds
        self.close_bus()
        return result

    def master(self, node_ids: Sequence[int] | None = None) -> Any:
        """A booted master (the scan's node ids, if it found the real ones)."""
        from .can import BraceMaster, DriverError, MasterConfig
        cfg = self.cfg
        if node_ids is not None:
            params = copy.deepcopy(dict(cfg))
            params['can']['node_ids'] = list(node_ids)
            cfg = DeviceConfig(params, cfg.path, source=cfg.source)
        m = BraceMaster(MasterConfig.from_device_config(cfg, mechanism=self.mech))
        try:
            m.boot()
        except DriverError as exc:
            m.shutdown()
            raise CommissionError(f'the drives did not boot: {exc}') from exc
        return m


def _settled_forces(master: Any, samples: int = SAMPLES, timeout: float = 10.0,
                    skip: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """Mean and standard error of each load cell over ``samples`` SYNCs (one per SYNC), after
    ``skip`` SYNCs (answers already on their way when the load changed)."""
    seen: list[np.ndarray] = []
    last = None
    samples += skip
    end = time.monotonic() + timeout
    while len(seen) < samples and time.monotonic() < end:
        fb = master.feedback()
        if fb.valid and fb.stamp != last:
            seen.append(np.asarray(fb.force, float))
            last = fb.stamp
        time.sleep(master.config.period * 0.5)
    if len(seen) < samples // 2:
        raise CommissionError('the load cells did not answer (no feedback)')
    arr = np.array(seen[skip:])
    return arr.mean(axis=0), arr.std(axis=0, ddof=1) / math.sqrt(len(arr))


def _jog(master: Any, axis: int, delta: float, limits: Any, log: list) -> float:
    """Axis ``axis`` out by ``delta`` and hold (the others holding): min-jerk at most 10 % of
    the actuator's speed and acceleration. Returns the largest following error (m or rad)."""
    from .can import ActuatorTrajectory
    q0 = np.asarray(master.feedback().position, float)
    v = 0.1 * limits.v_max
    a = 0.1 * limits.a_max
    duration = max(1.875 * abs(delta) / v, math.sqrt(5.78 * abs(delta) / a), 0.3)
    t = np.linspace(0.0, duration, 41)
    s = t / duration
    p = 10 * s ** 3 - 15 * s ** 4 + 6 * s ** 5
    pd = (30 * s ** 2 - 60 * s ** 3 + 30 * s ** 4) / duration
    pdd = (60 * s - 180 * s ** 2 + 120 * s ** 3) / duration ** 2
    e = np.zeros(len(q0))
    e[axis] = delta
    start = time.perf_counter() + 0.05
    tag = int(time.time_ns() & 0x7FFFFFFF)
    reason = master.execute(ActuatorTrajectory(t, q0 + np.outer(p, e), np.outer(pd, e), np.outer(pdd, e)),
                            start=start, tag=tag)
    if reason:
        raise CommissionError(f'the jog of axis {axis} was refused: {reason}')
    worst = 0.0
    end = start + duration + 5.0
    while time.perf_counter() < end:
        now = time.perf_counter()
        fb = master.feedback()
        u = min(max((now - start) / duration, 0.0), 1.0)
        cmd = q0[axis] + delta * (10 * u ** 3 - 15 * u ** 4 + 6 * u ** 5)
        log.append((now - start, cmd, float(fb.position[axis])))
        if master.supervisor.latched:
            raise CommissionError(f'protective stop during the jog: {master.supervisor.summary()}')
        if u >= 1.0 and not master.moving:
            break
        time.sleep(master.config.period)
    for ts, c, m in log:
        if 0.0 <= ts <= duration + 0.2:
            worst = max(worst, abs(c - m))
    return worst


@dataclass
class CheckResult:
    corrections: dict[str, Any]
    lines: list[str]
    findings: list[AxisFinding]
    traces: dict[int, list] = field(default_factory=dict)


def run_check(session: Session, *, axes: Sequence[int] | None = None, jog: float | None = None,
              node_ids: Sequence[int] | None = None) -> CheckResult:
    """Tare, then jog each axis and identify (module docstring). The brace must rest at its
    home pose (where it is homed)."""
    from .sim import SimulatedBrace
    cfg, n = session.cfg, session.n
    names = session.names
    model = SimulatedBrace(cfg, channel=f'commission-model-{id(session)}', start=False,
                           mechanism=session.mech)
    home = np.asarray(session.mech.home_pose, float)
    step = 1e-5 if not session.rotary else math.radians(0.005)
    M = model_response(cfg, model, home, step)          # for the jogs' size
    q_home = np.asarray(session.mech.inverse(home), float)
    _, f_home = model.static_forces(q_home, home)
    jog = jog if jog is not None else (math.radians(0.5) if session.rotary else 0.0005)
    master = session.master(node_ids)
    lines: list[str] = []
    corrections: dict[str, Any] = {}
    traces: dict[int, list] = {}
    try:
        master.home()
        master.enable()
        rest, rest_err = _settled_forces(master)
        believed_offset = _per_axis(cfg.get_path('actuator.load_cell_offset', 0.0), n)
        believed_gain = _per_axis(cfg.get_path('actuator.load_cell_gain', 1.0), n)
        raw_rest = rest * believed_gain + believed_offset       # what the cells read, in N
        offsets = raw_rest - believed_gain * f_home
        noise = float(cfg.get_path('kinetics.load_cell_noise', 0.05)) or 0.05
        lines.append('tare (axes at rest at the home pose): load cells read '
                     f'{np.round(raw_rest, 3).tolist()} N, the model {np.round(f_home, 3).tolist()} N')
        limits = master.limits
        force_limit = limits.force_limit
        jogs: dict[int, tuple[float, np.ndarray]] = {}
        following: dict[int, float] = {}
        for i in (range(n) if axes is None else axes):
            lo, hi = limits.stroke_of(i)
            q = float(master.feedback().position[i])
            peak = float(np.max(np.abs(M[:, i]))) or 1e-12
            amplitude = min(jog, JOG_FORCE_SHARE * force_limit / peak)
            # a cable pulls only: jog the way that tightens it (where the model responds)
            sign = 1.0
            if getattr(session.mech, 'actuation', None) == 'cable':
                sign = -1.0
            room = (hi - q) if sign > 0 else (q - lo)
            amplitude = min(amplitude, 0.5 * max(room - 1e-4, 0.0))
            if amplitude <= 0:
                lines.append(f'{names[i]}: no room to jog inside the stroke; not checked')
                continue
            delta = sign * amplitude
            trace: list = []
            following[i] = _jog(master, i, delta, limits, trace)
            out, out_err = _settled_forces(master)
            back: list = []
            _jog(master, i, -delta, limits, back)
            traces[i] = trace + [(t + trace[-1][0], c, m) for t, c, m in back] if trace else back
            df = (out - rest) * believed_gain
            jogs[i] = (delta, df)
            lines.append(f'{names[i]} (node {master.config.node_ids[i]}): jogged {delta * (1e3 if not session.rotary else 180 / math.pi):+.3f} '
                         f'{"mm" if not session.rotary else "deg"}, load cells changed by {np.round(df, 3).tolist()} N')
        F = {}
        for i, (delta, _) in jogs.items():
            for j in range(n):
                for sgn in (1, -1):
                    q = q_home.copy()
                    q[j] += sgn * delta
                    F[i, j, sgn] = model.static_forces(q, home)[1] - f_home
        sigma = np.full(n, noise * math.sqrt(2.0 / SAMPLES)) + 1e-4
        perm, findings, margin = identify(F, jogs, sigma)
    finally:
        try:
            master.disable()
        finally:
            master.shutdown()
    for f in findings:
        f.following_error = following.get(f.axis, 0.0)
    believed_ids = list(master.config.node_ids)
    polarity = _per_axis(cfg.get_path('actuator.polarity', 1), n).astype(int)
    cpr = _per_axis(cfg.get_path('actuator.encoder_counts_per_rev'), n)
    new_ids, new_pol, new_cpr = list(believed_ids), polarity.copy(), cpr.copy()
    ambiguous = len(jogs) == n and n > 1 and margin < 25.0
    all_jogged = len(jogs) == n
    if all_jogged and not ambiguous and list(perm) != list(range(n)):
        for i, j in enumerate(perm):
            new_ids[j] = believed_ids[i]
        lines.append('node ids: ' + ', '.join(f'node {believed_ids[i]} drives {names[j]}'
                                              for i, j in enumerate(perm)))
    elif ambiguous:
        lines.append(f'node ids: the load cells cannot tell the assignment apart at this pose '
                     f'(misfit margin {margin:.1f}); confirm by eye which actuator each node moves')
    for f in findings:
        phys = f.actuator if (all_jogged and not ambiguous) else f.axis
        if not f.significant:
            lines.append(f'{names[f.axis]}: the jog\'s effect ({f.scale:.3g} +- {f.stderr:.2g} of the '
                         'commanded travel) is within the load cells\' noise: sign and scale not verified')
            continue
        if f.sign < 0:
            new_pol[phys] = -polarity[phys]
        others: list[int] = []
        if scale_is_wrong(f.scale, f.stderr):
            new_cpr[phys], others = _snap_cpr(cpr[phys] / f.scale, int(cpr[phys]))
        elif abs(f.scale - 1.0) > SCALE_TOLERANCE:
            lines.append(f'{names[f.actuator]}: scale {f.scale:.3f} +- {f.stderr:.3f}, within '
                         f'{SCALE_SIGMAS:g} standard errors of 1: the jog loads the load cells too '
                         'little to verify the counts per revolution; check the encoder\'s data sheet')
        lines.append(f'{names[f.axis]}: moved {names[f.actuator]}, sign {f.sign:+d}, scale {f.scale:.3f} '
                     f'(+- {f.stderr:.3f}), following error {f.following_error * (1e3 if not session.rotary else 180 / math.pi):.3f} '
                     f'{"mm" if not session.rotary else "deg"}')
        if others:
            lines.append(f'{names[f.actuator]}: {int(new_cpr[phys])} counts per revolution proposed '
                         f'({cpr[phys] / f.scale:.0f} measured); {", ".join(map(str, others))} would fit '
                         'as well: check the encoder\'s data sheet')
    # per physical actuator: the load cells (read through the node that drives it)
    gains = _per_axis(cfg.get_path('actuator.load_cell_gain', 1.0), n)
    new_offsets = _per_axis(cfg.get_path('actuator.load_cell_offset', 0.0), n).copy()
    new_gains = gains.copy()
    inv = {f.actuator if (all_jogged and not ambiguous) else f.axis: f.axis for f in findings}
    for phys in range(n):
        node_axis = inv.get(phys, phys)
        if abs(offsets[node_axis] - believed_offset[phys]) > max(5 * rest_err[node_axis], 2 * noise / math.sqrt(SAMPLES), 0.02):
            new_offsets[phys] = float(offsets[node_axis])
    if all_jogged and not ambiguous:
        g = _row_gains(F, jogs, perm, findings, new_cpr, cpr, sigma)
        for phys in range(n):
            node_axis = inv.get(phys, phys)
            # g: the cell's own gain (raw reading over force), the believed one undone in df
            if g[node_axis] is not None and abs(g[node_axis] - gains[phys]) > GAIN_TOLERANCE * gains[phys]:
                new_gains[phys] = round(float(g[node_axis]), 4)
    if new_ids != believed_ids:
        corrections['can.node_ids'] = new_ids
    if not np.array_equal(new_pol, polarity):
        corrections['actuator.polarity'] = [int(p) for p in new_pol]
    if not np.array_equal(new_cpr, cpr):
        corrections['actuator.encoder_counts_per_rev'] = [int(c) for c in new_cpr]
    if not np.allclose(new_offsets, _per_axis(cfg.get_path('actuator.load_cell_offset', 0.0), n)):
        corrections['actuator.load_cell_offset'] = [round(float(o), 3) for o in new_offsets]
    if not np.allclose(new_gains, gains):
        corrections['actuator.load_cell_gain'] = [float(g) for g in new_gains]
    return CheckResult(corrections, lines, findings, traces)


def _row_gains(F: dict, jogs: dict, perm: Sequence[int], findings: Sequence[AxisFinding],
               new_cpr: np.ndarray, cpr: np.ndarray, sigma: np.ndarray) -> list[float | None]:
    """Each node's load-cell gain: its reading's change over the model's, with every drive's
    sign and (corrected) scale known, over all jogs; ``None`` where the jogs do not load that
    cell enough to tell a gain off by :data:`GAIN_TOLERANCE` from the noise."""
    n = len(perm)
    num, den = np.zeros(n), np.zeros(n)
    by_axis = {f.axis: f for f in findings}
    for i, (_, df) in jogs.items():
        f = by_axis[i]
        if not f.significant:
            continue
        scale = cpr[f.actuator] / new_cpr[f.actuator]
        pred = F[i, perm[i], f.sign][list(perm)] * scale
        num += pred * df
        den += pred * pred
    out: list[float | None] = []
    for k in range(n):
        if den[k] <= 1e-12 or sigma[k] / math.sqrt(den[k]) * SIGNIFICANCE > GAIN_TOLERANCE:
            out.append(None)
        else:
            out.append(float(num[k] / den[k]))
    return out


def _per_axis(value: Any, n: int) -> np.ndarray:
    arr = np.atleast_1d(np.asarray(value, dtype=float))
    return np.full(n, float(arr[0])) if arr.size == 1 else arr.astype(float)


def run_calibration(session: Session, axis: int, known_force: float, *, yes: bool) -> tuple[dict, list[str]]:
    """Two-point calibration of one load cell: its reading at rest (tare) and with
    ``known_force`` applied to it (a weight; with ``can.sim`` the simulator's reference load)."""
    cfg, n = session.cfg, session.n
    master = session.master()
    lines: list[str] = []
    try:
        gains = _per_axis(cfg.get_path('actuator.load_cell_gain', 1.0), n)
        offsets = _per_axis(cfg.get_path('actuator.load_cell_offset', 0.0), n)
        r0, e0 = _settled_forces(master)
        raw0 = r0[axis] * gains[axis] + offsets[axis]
        if session.sim is not None:
            session.sim.reference_load[axis] = known_force
        elif not yes:
            input(f'apply {known_force:g} N to the load cell of {session.names[axis]} (a weight along '
                  'the leg), then press Enter: ')
        else:
            raise CommissionError('calibrate-load-cell on real hardware asks for the load to be applied: '
                                  'run it without --yes')
        r1, e1 = _settled_forces(master)
        raw1 = r1[axis] * gains[axis] + offsets[axis]
        if session.sim is not None:
            session.sim.reference_load[axis] = 0.0
    finally:
        master.shutdown()
    gain = (raw1 - raw0) / known_force
    if not gain > 0:
        raise CommissionError(f'{session.names[axis]}: the reading fell ({raw0:.3f} -> {raw1:.3f} N) under '
                              f'{known_force:g} N: is the load on the right leg, pushing?')
    offset = raw0                      # the brace unloaded at rest: the cell's zero
    lines.append(f'{session.names[axis]}: reads {raw0:.3f} N unloaded and {raw1:.3f} N with {known_force:g} N: '
                 f'gain {gain:.4f}, offset {offset:.3f} N')
    corrections: dict[str, Any] = {}
    g_new, o_new = gains.copy(), offsets.copy()
    g_new[axis], o_new[axis] = round(gain, 4), round(offset, 3)
    if abs(gain - gains[axis]) > 1e-3 * max(1.0, abs(gains[axis])):
        corrections['actuator.load_cell_gain'] = [float(g) for g in g_new]
    if abs(offset - offsets[axis]) > max(0.02, 5 * e0[axis]):
        corrections['actuator.load_cell_offset'] = [float(o) for o in o_new]
    return corrections, lines


# ------------------------------------------------------------------ output

def write_corrected(src: Path, out: Path, corrections: dict[str, Any]) -> None:
    """The whole parameter file with ``corrections`` applied, to ``out`` (never ``src``);
    files it names are made absolute when ``out`` is in another directory."""
    out = Path(out)
    if out.resolve() == Path(src).resolve():
        raise CommissionError(f'--write {out}: that is the parameter file itself; write a copy')
    doc = read_yaml(src)
    params = doc['/**']['ros__parameters'] if '/**' in doc else next(
        (v['ros__parameters'] for v in doc.values() if isinstance(v, dict) and 'ros__parameters' in v), doc)
    for key, value in corrections.items():
        node = params
        parts = key.split('.')
        for p in parts[:-1]:
            node = node.setdefault(p, {})
        node[parts[-1]] = value
    if out.resolve().parent != Path(src).resolve().parent:
        cfg = load_device_config(src)
        from .can.dictionary import eds_files
        can = params.setdefault('can', {})
        if 'eds' in can and can['eds']:
            files = [str(p) for p in eds_files(cfg, len(cfg.get_path('can.node_ids')))]
            can['eds'] = files[0] if isinstance(can['eds'], str) else files
        node = can.get('load_cell_node') or {}
        if node.get('eds'):
            node['eds'] = str(cfg.resolve_file(node['eds'], 'can.load_cell_node.eds'))
    import yaml
    header = f'# {src} with the corrections of brace-commission ({", ".join(corrections) or "none"})\n'
    out.write_text(header + yaml.safe_dump(doc, sort_keys=False))
    load_device_config(out)            # it reads back


def plot_jogs(traces: dict[int, list], names: Sequence[str], unit: str, out_dir: Path) -> list[Path]:
    """A PNG per jog: commanded against measured position over time."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    out_dir.mkdir(parents=True, exist_ok=True)
    scale, label = (1e3, 'mm') if unit == 'm' else (180 / math.pi, 'deg')
    paths = []
    for i, trace in traces.items():
        if not trace:
            continue
        t = np.array([r[0] for r in trace])
        c = np.array([r[1] for r in trace]) * scale
        m = np.array([r[2] for r in trace]) * scale
        fig, ax = plt.subplots(figsize=(6, 3.2))
        ax.plot(t, c - c[0], label='commanded')
        ax.plot(t, m - c[0], '--', label='measured (encoder)')
        ax.set_xlabel('s')
        ax.set_ylabel(f'{names[i]} travel ({label})')
        ax.set_title(f'jog of {names[i]}')
        ax.legend()
        fig.tight_layout()
        path = out_dir / f'jog_{names[i]}.png'
        fig.savefig(path, dpi=90)
        plt.close(fig)
        paths.append(path)
    return paths


# ------------------------------------------------------------------ CLI

def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog='brace-commission', description=__doc__.split('\n\n')[0])
    ap.add_argument('config', help='device YAML')
    sub = ap.add_subparsers(dest='command', required=True)
    sub.add_parser('plan', help='without a bus: the boot planned against each drive\'s EDS/DCF (every '
                                'SDO write, what is skipped and why), or why the drives cannot drive '
                                'the brace')
    sub.add_parser('scan', help='find the nodes on the bus and compare them with the YAML and the EDS')
    check = sub.add_parser('check', help='jog each axis: node ids, polarity, scale, following error, tare')
    check.add_argument('--axis', default=None, help='only this actuator (a name of mechanism.actuator_names)')
    check.add_argument('--yes', action='store_true', help='do not ask before moving the brace')
    check.add_argument('--write', default=None, metavar='OUT.yaml', help='write the corrected parameter file')
    check.add_argument('--jog', type=float, default=None, help='jog distance (m or rad; default 0.5 mm or 0.5 deg)')
    check.add_argument('--report', default=None, metavar='DIR', help='report and plots (default commission_report/)')
    cal = sub.add_parser('calibrate-load-cell', help='two-point gain and offset of one load cell')
    cal.add_argument('--axis', required=True)
    cal.add_argument('--known-force', type=float, required=True, metavar='N')
    cal.add_argument('--yes', action='store_true')
    cal.add_argument('--write', default=None, metavar='OUT.yaml')
    return ap


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(list(sys.argv[1:] if argv is None else argv))
    try:
        return _main(args)
    except (CommissionError, ConfigError) as exc:
        print(f'brace-commission: {exc}', file=sys.stderr)
        return EXIT_ERROR
    except KeyboardInterrupt:
        print('brace-commission: interrupted', file=sys.stderr)
        return EXIT_ERROR


def _axis(session: Session, name: str | None) -> int | None:
    if name is None:
        return None
    if name not in session.names:
        raise CommissionError(f'--axis {name!r}: the actuators are {session.names}')
    return session.names.index(name)


def plan_report(cfg: DeviceConfig) -> tuple[bool, list[str]]:
    """The boot of ``cfg``'s drives planned against their dictionaries, without a bus:
    (planned, lines). The lines name every SDO write per drive and what the plan skipped and
    why (the boot report); when the dictionaries cannot serve, the one message that says why
    (:class:`~brace_control.can.plan.DictionaryError`)."""
    from .can import BraceMaster, MasterConfig
    from .can.errors import DriverInitializationError
    master = BraceMaster(MasterConfig.from_device_config(cfg))
    try:
        plans = master.plan()
    except DriverInitializationError as exc:
        return False, [str(exc)]
    mp = master.module_plan
    nodes = [(f'{p.name} (node {p.node_id}', p) for p in plans]
    nodes += [] if mp is None else [(f'load-cell module (node {mp.node_id}', mp)]
    lines = []
    for who, p in nodes:
        writes = p.writes + p.mapping
        lines.append(f'{who}, {p.dictionary.product}): {len(writes)} SDO writes')
        lines += [f'  {w.index:04X}h:{w.subindex} = {w.value:#x}  {w.what}' for w in writes]
    lines += master.boot_report
    return True, lines


def _main(args: argparse.Namespace) -> int:
    path = Path(args.config)
    if not path.is_file():
        from .config import resolve_device_file
        path = resolve_device_file(args.config)
    if args.command == 'plan':
        planned, lines = plan_report(load_device_config(path))
        print('\n'.join(lines))
        return EXIT_MATCH if planned else EXIT_ERROR
    with Session(path) as session:
        found = session.scan()
        print(f'scan of {session.cfg.get_path("can.interface")}:{session.cfg.get_path("can.channel")} '
              f'(node ids 1-127) in {found.seconds:.2f} s: {len(found.nodes)} node(s)')
        for node in found.nodes:
            print('  ' + node.row())
        for d in found.differences:
            print(f'  differs: {d}')
        if args.command == 'scan':
            if found.node_ids is not None:
                print('corrections (YAML patch):')
                print(f'  can.node_ids: {found.node_ids}')
            return EXIT_CORRECTED if found.differences else EXIT_MATCH
        corrections: dict[str, Any] = {}
        if found.node_ids is not None:
            corrections['can.node_ids'] = found.node_ids
        missing = [d for d in found.differences if 'does not answer' in d and '?' not in d]
        if missing:
            raise CommissionError('cannot move the brace with a drive missing: ' + '; '.join(missing))
        if args.command == 'check':
            if not args.yes:
                if not sys.stdin.isatty():
                    raise CommissionError('check moves the brace: confirm with --yes (no terminal to ask)')
                answer = input(f'check jogs each axis of {path.name} a little out and back: the brace must '
                               'be parked at its home pose, nobody in it. Go on? [yes/no] ')
                if answer.strip().lower() not in ('y', 'yes'):
                    raise CommissionError('not confirmed')
            axis = _axis(session, args.axis)
            result = run_check(session, axes=None if axis is None else [axis], jog=args.jog,
                               node_ids=found.node_ids)
            for line in result.lines:
                print(f'  {line}')
            merged = {**corrections, **result.corrections}
            if 'can.node_ids' in corrections and 'can.node_ids' in result.corrections:
                merged['can.node_ids'] = result.corrections['can.node_ids']
            corrections = merged
            report = Path(args.report or 'commission_report')
            plots = plot_jogs(result.traces, session.names, session.unit, report)
            (report / 'report.txt').write_text('\n'.join(result.lines + [f'{k}: {v}' for k, v in corrections.items()]) + '\n')
            print(f'  report: {report / "report.txt"}, plots: {", ".join(str(p) for p in plots)}')
        else:
            axis = _axis(session, args.axis)
            cal, lines = run_calibration(session, axis, args.known_force, yes=args.yes)
            for line in lines:
                print(f'  {line}')
            corrections.update(cal)
    if corrections:
        print('corrections (YAML patch):')
        for key, value in corrections.items():
            print(f'  {key}: {value}')
        if getattr(args, 'write', None):
            write_corrected(path, Path(args.write), corrections)
            print(f'wrote {args.write}')
        return EXIT_CORRECTED
    print('the hardware matches the YAML')
    return EXIT_MATCH


if __name__ == '__main__':
    raise SystemExit(main())
