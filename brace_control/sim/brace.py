"""The simulated brace: one CiA 402 drive per actuator plus the physics of device and body.

:class:`SimulatedBrace` reads the device YAML (``mechanism``, ``actuator``, ``can``,
``sim`` sections), puts one :class:`~brace_control.sim.drive.SimulatedDrive` per node id
on the bus (:class:`~brace_control.sim.host.SimBus`) and, on every SYNC from the master:

1. advances each actuator by ``dt`` (the CSP position loop of
   :class:`~brace_control.sim.drive.SimulatedDrive` on the reference interpolated from the
   targets latched at the previous SYNCs, ``sim.drive_bandwidth_hz``; the actuator's
   speed/acceleration limits, end stops);
2. the physics (quasi-static, the thoracic ring massless):

   * the torso on the ring: ``W_body = sat(-K (pose - rest(t))) - D (pose_dot - rest_dot(t))``
     (``sim.stiffness``, ``sim.damping`` 3x3 row-major, ``sim.rest_pose``; the patient,
     see "The patient" below);
   * the pose of the thoracic ring: the equilibrium continuous with the previous pose
     (the branch ``mech.forward_nearest(q, pose)`` follows) of the ring between the legs
     and the torso, each leg = actuator length ``q_i`` in series with a stiffness
     ``sim.leg_stiffness`` (N/m, default ``actuator.stiffness``, else 1e6; see
     :meth:`SimulatedBrace._equilibrium`);
   * actuator forces from the equilibrium ``J^T f = -W_body`` (push positive); the wrench
     the brace applies to the body is ``J^T f``. (A rigid model has no bounded solution at
     the brace's singular poses, e.g. every theta = 0 pose incl. the home pose: the leg
     lines meet in one point; the series stiffness resolves it as the real straps do.)
   * load-cell reading (2401h) = ``f + noise + offset`` (``sim.load_cell_noise`` N std,
     seeded by ``sim.seed``; ``sim.load_cell_offset`` N), saturated at
     ``actuator.load_cell_rated_force``, quantised to ``actuator.load_cell_n_per_count``;

3. sends each drive's synchronous TPDOs, then applies the RPDOs received since the last
   SYNC (CiA 301: synchronous RPDO data take effect at the next SYNC).

Devices other than the planar 3-RPR (the neck braces, the four-bar trainer, the shoulder,
the continuum robot): rigid and quasi-static, any mechanism through its protocol
(:meth:`SimulatedBrace._rigid`): the pose from the actuator positions, ``W_body`` with
``sim.stiffness``/``sim.damping`` of size dof x dof, efforts from ``J^T f = -W_body`` by least
squares. The cable 4-RPR is compliant like the lumbar brace's legs, each cable pulling
only: a cable pushed (paid out longer than its anchors' distance) goes slack, reads zero,
and the platform settles on the taut ones (:meth:`SimulatedBrace._equilibrium`). Rotary
drives (``actuator.kind: rotary``): positions in rad, the effort is the joint torque in
6077h (per mille of ``rated_current x torque_constant x gear_ratio``). The device units
(counts per m or rad, N or N·m per count, full scale) are those of
:func:`brace_control.can.units.scaling_from_config`, the master's.

The actuators' physical lengths at power-up are ``mech.inverse(mech.home_pose)`` (the
parked brace); the incremental encoders read 0 until homed (method 35 with 607Ch = the
home length in counts, see docs/can.md).

The patient (the body's own motion and effort, docs/interaction.md):

* ``rest(t)`` is where the trunk would be without the brace: the base rest pose
  (``sim.rest_pose``, or the last ``/brace/sim/body_rest`` via :meth:`SimulatedBrace.
  set_rest_pose`) plus a scripted sway ``sim.sway_amplitude[i] sin(2 pi
  sim.sway_frequency_hz t + sim.sway_phase[i])`` per pose axis (m or rad; all zero, the
  default: no sway), ``t`` the simulated time since power-up. A stream of rest poses (one
  every :data:`REST_STREAM_GAP_S` or sooner) is a moving trunk: it goes through the samples
  in straight lines, each reached :data:`REST_STREAM_DELAY_S` after its stamp (a playout
  buffer: samples a DDS hop delivers bunched move it at the rate of their stamps; it never
  overshoots a sample), so a trunk streamed at 50 Hz moves smoothly, with its rate in the
  tissue damping, not in 20 ms steps; a rest pose after a longer silence is a step;
* the tissue between ring and trunk is the spring ``K`` and the damper ``D`` on the
  *relative* motion (pose - rest, pose_dot - rest_dot): a ring that moves with the trunk
  carries no load;
* ``K (rest - pose)`` is what the patient's muscles must produce to hold their trunk
  where they want it: it saturates per pose axis at ``sim.patient_max_wrench`` (N, N·m;
  0 = no limit). A brace that fights the patient's motion loads the patient up to that
  effort (the load cells show it) and no further: beyond it the patient yields and the
  brace moves the trunk; a patient cannot push the brace harder than that either.

Ground truth for tests: :meth:`SimulatedBrace.truth` (a consistent snapshot; ``body_pose``,
``body_rate``: ``rest(t)`` and its rate).
Fault injection: :attr:`SimulatedBrace.faults` (:class:`~brace_control.sim.faults.FaultInjector`).

Example::

    with SimulatedBrace('config/lumbar_brace.yaml', channel='test0') as sim:
        ...  # a master on can.Bus(interface='virtual', channel='test0')
        print(sim.truth().pose)
"""
from __future__ import annotations

import math
import operator
import threading
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..can.dictionary import ObjectRef, eds_files
from ..can.state import load_cell_source
from ..can.sync import stamped_after
from ..can.units import encoder_counts, per_actuator
from .device import SimulatedDevice
from ..can.units import actuator_kind, scaling_from_config
from ..config import ConfigError, DeviceConfig, config_dir, load_device_config
from ..mechanisms import mechanism_from_config
from ..mechanisms.planar_floats import PlanarRprFloats
from .drive import DriveLimits, SimulatedDrive
from .faults import FaultInjector
from .host import SimBus
from .module import SimulatedAnalogModule

__all__ = ['SimulatedBrace', 'BraceTruth']

#: SYNCs of load-cell noise drawn at once
NOISE_BLOCK = 500
#: SYNCs of ground truth kept for :meth:`SimulatedBrace.truth_at`
TRUTH_HISTORY = 64
#: s of ground truth kept at ``sim.truth_rate_hz`` for :meth:`SimulatedBrace.recorded_since`
#: (as long as the ground-truth topics keep it for a reader, ``topics.TRUTH_KEPT_S``)
TRUTH_RECORD_S = 5.0
#: s: rest poses closer than this are samples of one motion of the trunk (its rate is
#: their difference over the interval); farther apart, each is a step
REST_STREAM_GAP_S = 0.2
#: s: a streamed rest pose is reached this long after its stamp (the playout delay of
#: :meth:`SimulatedBrace.set_rest_pose`: DDS delivery jitter up to it does not show)
REST_STREAM_DELAY_S = 0.1
#: a stream whose stamps run ahead of the simulated clock (a loaded host skips SYNCs: the
#: simulated time runs slow, by 25 % on a loaded 2-core machine) is played at most this
#: much faster than its stamps while it is more than REST_STREAM_DELAY_S + 50 ms ahead ...
REST_STREAM_CATCH_UP = 1.25
#: s: ... and each sample reached at most this long after its arrival
REST_STREAM_MAX_LEAD_S = 2.0


@dataclass(frozen=True)
class BraceTruth:
    """Ground truth of the simulated brace after a SYNC (SI units).

    :ivar lengths: true actuator lengths q (m), shape (n,).
    :ivar velocities: true actuator rates q_dot (m/s).
    :ivar pose: thoracic ring pose (x m, y m, theta rad).
    :ivar pose_dot: its rate.
    :ivar body_wrench: ``W_body``, what the torso applies to the ring (Fx N, Fy N, M N·m).
    :ivar brace_wrench: ``J^T f``, what the brace applies to the body (= -W_body).
    :ivar forces: true actuator forces f (N, push positive).
    :ivar load_cell_counts: the readings put in 2401h.
    :ivar sync_count: SYNCs processed so far.
    :ivar time: simulated time (s), the sum of the SYNC steps.
    :ivar stamp: the bus timestamp (s, wall clock) of the SYNC this state follows: the instant
        the drives' TPDOs answering that SYNC describe, so measured and true states of the
        same SYNC carry the same time.
    :ivar body_pose: where the patient's trunk wants to be, ``rest(t)`` (the rest pose plus
        the sway; the ring is pulled towards it).
    :ivar body_rate: its rate ``rest_dot(t)``.
    """

    lengths: np.ndarray
    velocities: np.ndarray
    pose: np.ndarray
    pose_dot: np.ndarray
    body_wrench: np.ndarray
    brace_wrench: np.ndarray
    forces: np.ndarray
    load_cell_counts: np.ndarray
    sync_count: int
    time: float
    stamp: float = 0.0
    body_pose: np.ndarray | None = None
    body_rate: np.ndarray | None = None


def _solve3(a: list[list[float]], r: list[float]) -> tuple[float, float, float]:
    """``a^-1 r`` for a 3x3 ``a`` by Cramer's rule (plain floats; ``a`` positive definite here)."""
    (a00, a01, a02), (a10, a11, a12), (a20, a21, a22) = a
    c00 = a11 * a22 - a12 * a21
    c01 = a12 * a20 - a10 * a22
    c02 = a10 * a21 - a11 * a20
    det = a00 * c00 + a01 * c01 + a02 * c02
    r0, r1, r2 = r
    x0 = (r0 * c00 + r1 * (a02 * a21 - a01 * a22) + r2 * (a01 * a12 - a02 * a11)) / det
    x1 = (r0 * c01 + r1 * (a00 * a22 - a02 * a20) + r2 * (a02 * a10 - a00 * a12)) / det
    x2 = (r0 * c02 + r1 * (a01 * a20 - a00 * a21) + r2 * (a00 * a11 - a01 * a10)) / det
    return x0, x1, x2


def _matrix(value: Any, n: int, name: str) -> np.ndarray:
    arr = np.asarray(value, dtype=float)
    if arr.size != n * n or not np.all(np.isfinite(arr)):
        raise ConfigError(f'{name}: expected {n * n} finite numbers ({n}x{n} row-major, n = the '
                          f'mechanism\'s dof), got {value!r}')
    return arr.reshape(n, n)


def _matrix3(value: Any, name: str) -> np.ndarray:
    return _matrix(value, 3, name)


class SimulatedBrace:
    """The whole simulated device on one bus.

    :param config: the device YAML (path or device name) or an already loaded config.
    :param channel: python-can channel; default ``can.channel`` from the YAML. Tests pass a
        unique channel per test.
    :param interface: python-can interface; default ``can.interface`` (``virtual``).
    :param eds: the drives' EDS (one path, or one per drive); default ``can.eds`` relative to
        the YAML.
    :param seed: load-cell noise seed; default ``sim.seed``.
    :param dt_source: see :class:`~brace_control.sim.host.SimBus` (``'1006h'`` default).
    :param start: open the bus and boot the drives now (else call :meth:`start`).
    :param mechanism: the model of ``config``'s mechanism if the caller has built it (the CAN
        driver shares its own: the mechanism classes keep no per-call state); default: built
        from ``config``.
    """

    def __init__(self, config: DeviceConfig | Mapping[str, Any] | str | Path, *,
                 channel: str | None = None, interface: str | None = None,
                 eds: str | Path | None = None, seed: int | None = None,
                 dt_source: str = '1006h', start: bool = True, mechanism: Any = None) -> None:
        # a DeviceConfig is checked against brace_control.schema and has its defaults filled
        cfg = config if isinstance(config, DeviceConfig) else (
            DeviceConfig(config) if isinstance(config, Mapping) else load_device_config(config))
        self.config = cfg
        self.mechanism = mechanism if mechanism is not None else mechanism_from_config(cfg)
        can_cfg, act, sim = cfg.section('can'), cfg.section('actuator'), cfg.section('sim')
        believed = tuple(int(i) for i in cfg.get_path('can.node_ids'))
        n = self.mechanism.n_actuators
        if len(believed) != n:
            raise ConfigError(f'can.node_ids has {len(believed)} ids for {n} actuators')
        # the hardware as it really is (sim.*: docs/commissioning.md), by default as believed
        #: the node ids the drives really have, in actuator order (0: not on the bus)
        self.node_ids: tuple[int, ...] = tuple(int(i) for i in per_actuator(
            sim.get('node_ids') or list(believed), n, 'sim.node_ids'))
        real = [i for i in self.node_ids if i]
        if len(set(real)) != len(real):
            raise ConfigError(f'sim.node_ids = {list(self.node_ids)}: two drives with one node id')
        polarity = [int(p) for p in per_actuator(sim.get('polarity', 1), n, 'sim.polarity')]
        if any(p not in (1, -1) for p in polarity):
            raise ConfigError(f'sim.polarity = {polarity}: +1 or -1 per actuator')
        true_cpr = encoder_counts(cfg, 'sim.encoder_counts_per_rev' if sim.get('encoder_counts_per_rev')
                                  else 'actuator.encoder_counts_per_rev')
        believed_cpr = encoder_counts(cfg)[0]
        #: each load cell's gain and offset (reading = gain x force + offset + noise), N or N·m
        self.load_cell_gain = np.array(per_actuator(sim.get('load_cell_gain', 1.0), n, 'sim.load_cell_gain'), float)
        self.load_cell_offset = np.array(per_actuator(sim.get('load_cell_offset', 0.0), n, 'sim.load_cell_offset'), float)
        #: a known force on each load cell (N or N·m): the reference load of a calibration
        #: (brace-commission calibrate-load-cell), a weight hung along the leg
        self.reference_load = [0.0] * n
        self._gains, self._offsets = self.load_cell_gain.tolist(), self.load_cell_offset.tolist()
        # the drives' dictionaries, one per drive (can.eds: one file, or a list)
        if eds is None:
            eds_paths = list(eds_files(cfg, n))
        else:
            eds_paths = [Path(eds)] * n if isinstance(eds, (str, Path)) else [Path(e) for e in eds]
        # where the load cells are wired: a drive object each, or a CiA 401 module
        load_cell, module = load_cell_source(cfg)
        load_cell = load_cell or ObjectRef(0x2401)        # (the drives' own input is unused then)
        #: rotary drives (``actuator.kind: rotary``): positions in rad, the effort is the joint
        #: torque reported as 6077h torque actual; linear: m and the load cell 2401h
        self.rotary = actuator_kind(cfg) == 'rotary'
        scaling = scaling_from_config(cfg)          # the master's device units (can/units.py)
        self._scaling = scaling
        #: encoder counts per actuator unit (m, or rad for rotary drives)
        self.counts_per_m = scaling.counts_per_unit
        #: N (N·m) per count of 2401h (rotary: of 6077h, per mille of the rated torque)
        self.n_per_count = scaling.newton_per_count
        #: full scale of the force (torque) reading, N (N·m)
        self.rated_force = scaling.rated_force
        lo, hi = self.mechanism.actuator_limits
        dof = int(self.mechanism.dof)
        self.dof = dof
        # absent body stiffness / damping: none (a free body); absent rest pose: home
        self.stiffness = _matrix(sim.get('stiffness', [0.0] * dof * dof), dof, 'sim.stiffness')
        self.damping = _matrix(sim.get('damping', [0.0] * dof * dof), dof, 'sim.damping')
        self.rest_pose = np.asarray(sim.get('rest_pose', self.mechanism.home_pose), dtype=float)
        # streamed rest poses (set_rest_pose): the trunk's path, (simulated time, pose) points
        # it goes through in a straight line between them (the first: where it is, or was
        # last); _rest_offset maps a sample's stamp to its playout time on the simulated clock
        self._rest_track: deque[tuple[float, np.ndarray]] = deque([(-math.inf, self.rest_pose.copy())])
        self._rest_stamp: float | None = None
        self._rest_offset = 0.0
        self._init_patient(sim)
        self._body = self.body_at(0.0)
        self.noise_n = float(sim['load_cell_noise'])
        self._rng = np.random.default_rng(int(sim['seed'] if seed is None else seed))
        self._noise_block: list[list[float]] = []
        q0 = self.mechanism.inverse(self.mechanism.home_pose)
        #: series stiffness of each leg (N/m), see :meth:`_equilibrium`
        self.leg_stiffness = float(sim['leg_stiffness'])     # schema: absent -> actuator.stiffness
        #: |J^T f + W_body| below this (N, N·m) ends the equilibrium iteration
        self.equilibrium_tol = 1e-5
        self.equilibrium_failures = 0
        # the same mechanism with the stroke widened by 1 cm: inverse kinematics of the
        # rigid ring may leave the stroke by f / k at the end stops (physics only)
        mech_section = dict(cfg.section('mechanism'))
        #: a cable-driven mechanism (the 4-RPR neck brace): cables pull only, go slack
        self.cable = getattr(self.mechanism, 'actuation', None) == 'cable'
        #: the 3-RPR brace and cable mechanisms: legs / cables in series with a stiffness
        #: (see :meth:`_equilibrium`); any other mechanism: rigid (see :meth:`_rigid`)
        self.compliant = str(mech_section.get('type', '')) == 'rpr3' or self.cable
        if self.compliant:
            for key, widen in (('stroke_min', -0.01), ('stroke_max', 0.01)):
                widened = np.asarray(mech_section[key], dtype=float) + widen
                mech_section[key] = widened.tolist() if widened.ndim else float(widened)
            self._phys_mech = mechanism_from_config({'mechanism': mech_section})
        else:
            self._phys_mech = self.mechanism
        self._legs = self._fast_legs() if self.compliant else None
        #: seconds of physics per SYNC the rigid model aims at (see :meth:`_rigid_cost`)
        self.physics_budget = 1.5e-4
        self.physics_every = 1
        self._use_newton = False
        self._skipped = 0
        self._elapsed = 0.0
        if not self.compliant:
            self._rigid_cost(q0)
        #: names of the cables that are slack after the last SYNC (compliant cables)
        self.slack: tuple[str, ...] = ()
        self.drives: list[SimulatedDrive] = []
        #: position-loop bandwidth of the simulated drives (Hz), ``sim.drive_bandwidth_hz``
        self.drive_bandwidth_hz = float(sim['drive_bandwidth_hz'])   # range: the schema
        #: each drive's true encoder counts per actuator unit (sim.encoder_counts_per_rev)
        self.drive_counts_per_m = np.array([self.counts_per_m * c / believed_cpr for c in true_cpr])
        for i, node_id in enumerate(self.node_ids):
            limits = DriveLimits(
                counts_per_m=float(self.drive_counts_per_m[i]), max_velocity=float(act['max_velocity']),
                max_acceleration=float(act['max_acceleration']),
                stroke_min=float(lo[i]), stroke_max=float(hi[i]),
                # 6077h torque actual is in per mille of this (rotary: the rated torque)
                max_force=self.rated_force if self.rotary else float(act['max_force']))
            self.drives.append(SimulatedDrive(node_id or believed[i], eds_paths[i], limits=limits,
                                              initial_length_m=float(q0[i]),
                                              bandwidth_hz=self.drive_bandwidth_hz,
                                              load_cell=(load_cell.index, load_cell.subindex),
                                              polarity=polarity[i],
                                              absolute_encoder=not int(cfg.get_path('can.homing_method'))))
        #: the CiA 401 module carrying the load cells (``can.load_cell_node``), or None
        self.module: SimulatedAnalogModule | None = None
        if module is not None:
            self.module = SimulatedAnalogModule(module.node_id, module.eds, module.objects)
        #: where each load-cell reading goes: (device, index into its readings, input)
        self._load_sinks = ([(self.module, i, self.module.load_inputs[i]) for i in range(n)]
                            if self.module is not None else
                            [(d, None, d.load_input) for d in self.drives])
        self.host = SimBus(channel or str(can_cfg['channel']),
                           interface=interface or str(can_cfg['interface']),
                           sync_handler=self._on_sync, dt_source=dt_source)
        for d, node_id in zip(self.drives, self.node_ids):
            if node_id:                           # 0: the drive does not answer (not on the bus)
                self.host.add(d)
        if self.module is not None:
            self.host.add(self.module)
        #: foreign nodes on the bus (sim.extra_node_ids): CiA 401 I/O modules
        self.extra_nodes = [SimulatedDevice(int(i), config_dir() / 'analog_input_module.eds')
                            for i in (sim.get('extra_node_ids') or [])]
        for extra in self.extra_nodes:
            self.host.add(extra)
        self.lock = threading.Lock()
        self._pose = np.asarray(self.mechanism.home_pose, dtype=float).copy()
        self._f_unloaded = np.zeros(n)             # efforts holding the mechanism itself (see _rigid)
        self._q_last = q0.copy()
        self._q_last_list: list[float] = self._q_last.tolist()
        self._static: tuple[Any, ...] | None = None
        self._last_dynamic: tuple[np.ndarray, ...] | None = None
        self._time = 0.0
        self._sync_count = 0
        #: per-actuator load-cell override (N) for fault injection; None = physics
        self.load_cell_override: list[float | None] = [None] * n
        self._truth = self._physics(0.0)
        self._history: deque[BraceTruth] = deque([self._truth], maxlen=TRUTH_HISTORY)
        #: the truth at ``sim.truth_rate_hz`` (a SYNC at least a period after the last kept)
        self._record_period = 1.0 / float(sim['truth_rate_hz'])
        self._record: deque[BraceTruth] = deque(
            [self._truth], maxlen=math.ceil(TRUTH_RECORD_S / self._record_period) + 1)
        self.faults = FaultInjector(self)
        if start:
            self.start()

    # ------------------------------------------------------------------ lifecycle

    def start(self) -> 'SimulatedBrace':
        """Open the bus; every drive sends its boot-up message."""
        self.host.start()
        return self

    def shutdown(self) -> None:
        """Close the bus (idempotent)."""
        self.host.shutdown()

    def __enter__(self) -> 'SimulatedBrace':
        return self

    def __exit__(self, *exc: object) -> None:
        self.shutdown()

    @property
    def channel(self) -> str:
        return self.host.channel

    def drive(self, node_id: int) -> SimulatedDrive:
        """The simulated drive with this node id."""
        return self.host.drive(node_id)

    @property
    def cpu_seconds(self) -> float:
        """CPU seconds the simulated brace took so far, in whichever thread ran it
        (:attr:`SimBus.cpu_seconds <brace_control.sim.host.SimBus.cpu_seconds>`)."""
        return self.host.cpu_seconds

    @property
    def stalled_seconds(self) -> float:
        """Seconds the host process stood still so far, during which the simulated drives'
        clock stood still too (:mod:`brace_control.sim.host`, "Host stalls"): a drive's
        reaction is that much later in wall time than on its own clock."""
        return self.host.stalled_seconds

    # ------------------------------------------------------------------ ground truth

    def truth(self) -> BraceTruth:
        """The state after the last SYNC (a snapshot; arrays are copies)."""
        with self.lock:
            return self._truth

    def truth_at(self, stamp: float) -> BraceTruth:
        """The state after the SYNC whose bus timestamp is nearest ``stamp`` (wall clock, s),
        among the last :data:`TRUTH_HISTORY`: the truth of the same SYNC as a measurement."""
        # the stamps rise with the SYNCs, so the distance falls then rises: walk back from
        # the newest (the one asked for, mostly) while it does not rise; among equal
        # distances the older, as min() over the history would take. Under the lock, as
        # stamped_after walks the record: no copy of the history
        best, gap = None, math.inf
        with self.lock:
            for truth in reversed(self._history):
                d = abs(truth.stamp - stamp)
                if d > gap:
                    break
                best, gap = truth, d
            return self._truth if best is None else best

    def recorded_since(self, stamp: float) -> list[BraceTruth]:
        """The truths kept at ``sim.truth_rate_hz`` stamped after ``stamp`` (wall clock,
        s), oldest first, among the last :data:`TRUTH_RECORD_S`: what a reader that missed
        them for a while (the control cycle's process, its link to the node full) still
        has to send."""
        with self.lock:
            return stamped_after(self._record, stamp)

    def set_rest_pose(self, pose: np.ndarray, stamp: float | None = None) -> None:
        """Move the body's rest pose (the patient moves): the physics pulls the platform
        towards it. Thread safe.

        A stream of samples (stamps at most :data:`REST_STREAM_GAP_S` apart) is a moving
        trunk, played out like a jitter buffer: each sample is reached
        :data:`REST_STREAM_DELAY_S` after its stamp (on the simulated clock, from the
        stream's first sample), in a straight line from the previous one, so samples that a
        DDS hop delivers late or bunched still move the trunk at the rate of their stamps.
        A sample later than that: the trunk, held at the previous one, goes on from where it
        is over its stamped interval (the stream's delay grows by as much). A stream whose
        stamps run ahead of the simulated clock (SYNCs skipped: the simulated world stood
        still meanwhile, the trunk too) catches up at most :data:`REST_STREAM_CATCH_UP`
        times its stamps' rate, and each sample is reached at most
        :data:`REST_STREAM_MAX_LEAD_S` after its arrival. The first sample, or one after a
        longer silence, is a step.

        :param stamp: when the sample was taken (s, any clock; a message's header stamp);
            ``None``: its arrival on the simulated clock.
        :raises ValueError: not ``dof`` finite numbers.
        """
        arr = np.asarray(pose, dtype=float)
        if arr.shape != (self.dof,) or not np.all(np.isfinite(arr)):
            raise ValueError(f'body rest pose: expected {self.dof} finite numbers, got {pose!r}')
        with self.lock:
            now = self._time
            s = now if stamp is None else float(stamp)
            track = self._rest_track
            last = self._rest_stamp
            self._prune_rest(now)
            if last is not None and 0.0 < s - last <= REST_STREAM_GAP_S:   # the stream goes on
                play = s + self._rest_offset
                if play <= now:                    # later than the buffer: on from here
                    here = self._streamed_rest(now)[0]
                    track.clear()
                    track.append((now, here))
                    play = now + (s - last)
                elif play - now > REST_STREAM_DELAY_S + 0.05:    # the stream runs ahead
                    play = max(track[-1][0] + (s - last) / REST_STREAM_CATCH_UP, now + REST_STREAM_DELAY_S)
                play = min(play, now + REST_STREAM_MAX_LEAD_S)
                if play <= track[-1][0]:           # two samples at one instant: the newer
                    track[-1] = (track[-1][0], arr.copy())
                else:
                    track.append((play, arr.copy()))
                self._rest_offset = play - s
            else:                                  # a step: the first sample, or after a silence
                track.clear()
                track.append((now, arr.copy()))
                self._rest_offset = now + REST_STREAM_DELAY_S - s
            self._rest_stamp = s
            self.rest_pose = arr.copy()
            self._static = None            # the held state is no longer in equilibrium

    def _prune_rest(self, t: float) -> None:
        """Forget the trunk's path before the segment it is on at ``t``."""
        track = self._rest_track
        while len(track) > 1 and track[1][0] <= t:
            track.popleft()

    def _init_patient(self, sim: Mapping[str, Any]) -> None:
        """``sim.sway_amplitude``, ``sim.sway_frequency_hz``, ``sim.sway_phase``,
        ``sim.patient_max_wrench`` (module docstring, "The patient").

        :raises ConfigError: a value of the wrong length, negative or not finite.
        """
        dof = self.dof

        def per_axis(key: str, default: float) -> np.ndarray:
            raw = sim.get(key, [default])
            arr = np.atleast_1d(np.asarray(raw, dtype=float)).ravel()
            if arr.size == 1 and float(arr[0]) == default:
                arr = np.full(dof, default)
            if arr.shape != (dof,) or not np.all(np.isfinite(arr)):
                raise ConfigError(f'sim.{key}: expected {dof} finite numbers (one per pose axis), '
                                  f'got {raw!r}')
            return arr

        #: sway amplitude per pose axis (m, rad); all zero: no sway
        self.sway_amplitude = per_axis('sway_amplitude', 0.0)
        #: sway phase per pose axis (rad)
        self.sway_phase = per_axis('sway_phase', 0.0)
        freq = sim.get('sway_frequency_hz', 0.0)
        if isinstance(freq, bool) or not isinstance(freq, (int, float)) or not math.isfinite(freq) \
                or freq < 0.0:
            raise ConfigError(f'sim.sway_frequency_hz = {freq!r}: expected a number >= 0 (Hz)')
        #: sway frequency (Hz)
        self.sway_frequency_hz = float(freq)
        limit = per_axis('patient_max_wrench', 0.0)
        if np.any(limit < 0.0):
            raise ConfigError(f'sim.patient_max_wrench: expected numbers >= 0 (N, N·m per pose '
                              f'axis; 0 = no limit), got {limit.tolist()!r}')
        #: the patient's largest effort per pose axis (N, N·m); inf = no limit
        self.patient_max_wrench = np.where(limit > 0.0, limit, np.inf)
        self._swaying = bool(np.any(self.sway_amplitude != 0.0)) and self.sway_frequency_hz > 0.0

    def set_sway(self, amplitude: Any, frequency_hz: float, phase: Any = None) -> None:
        """Start (or change, or with zero amplitude end) the patient's sway now: from the next
        SYNC ``rest + A sin(2 pi f (t - t_now) + phi)``. Thread safe.

        :raises ValueError: not ``dof`` finite amplitudes / phases, or a negative frequency.
        """
        a = np.asarray(amplitude, dtype=float).ravel()
        ph = np.zeros(self.dof) if phase is None else np.asarray(phase, dtype=float).ravel()
        if a.shape != (self.dof,) or ph.shape != (self.dof,) or not np.all(np.isfinite(a)) \
                or not np.all(np.isfinite(ph)):
            raise ValueError(f'sway: expected {self.dof} finite amplitudes and phases, got '
                             f'{amplitude!r}, {phase!r}')
        if not math.isfinite(frequency_hz) or frequency_hz < 0.0:
            raise ValueError(f'sway frequency {frequency_hz!r}: expected a number >= 0 (Hz)')
        with self.lock:
            w = 2.0 * math.pi * float(frequency_hz)
            self.sway_amplitude, self.sway_frequency_hz = a.copy(), float(frequency_hz)
            self.sway_phase = ph - w * self._time          # t - t_now in the sine
            self._swaying = bool(np.any(a != 0.0)) and frequency_hz > 0.0
            self._static = None

    def _streamed_rest(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """The base rest pose at simulated time ``t`` and its rate: on the trunk's path of
        streamed samples (:meth:`set_rest_pose`), else the last sample.

        Read in the SYNC's thread while :meth:`set_rest_pose` appends in the stream's: the
        path is read from a copy (one C call under the interpreter lock, as the deque's own
        methods are), not iterated while another thread changes it ("deque mutated during
        iteration" stopped the physics of one SYNC in a full test run)."""
        track = tuple(self._rest_track)
        t1, p1 = track[-1]
        if t >= t1:
            return p1.copy(), np.zeros(self.dof)
        for (ta, pa), (tb, pb) in zip(track, track[1:]):
            if t < tb:
                if t < ta:
                    return pa.copy(), np.zeros(self.dof)
                rate = (pb - pa) / (tb - ta)
                return pa + rate * (t - ta), rate
        return p1.copy(), np.zeros(self.dof)

    def body_at(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Where the patient's trunk wants to be at simulated time ``t`` (s) and its rate:
        ``rest + A sin(w t + phi)``, ``A w cos(w t + phi)``, ``w = 2 pi sim.sway_frequency_hz``."""
        rest, rest_dot = self._streamed_rest(t)
        if not self._swaying:
            return rest, rest_dot
        w = 2.0 * math.pi * self.sway_frequency_hz
        arg = w * t + self.sway_phase
        return (rest + self.sway_amplitude * np.sin(arg),
                rest_dot + self.sway_amplitude * w * np.cos(arg))

    def _spring(self, pose: np.ndarray, rest: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The patient's spring ``-K (pose - rest)``, each pose axis saturated at
        ``sim.patient_max_wrench``, and its derivative ``d/dpose`` (rows of the saturated
        axes zero)."""
        w = -self.stiffness @ (pose - rest)
        lim = self.patient_max_wrench
        free = np.abs(w) <= lim
        if bool(np.all(free)):
            return w, self.stiffness
        return np.clip(w, -lim, lim), self.stiffness * free[:, None]

    def static_forces(self, q: np.ndarray, guess: np.ndarray | None = None
                      ) -> tuple[np.ndarray, np.ndarray]:
        """The quasi-static equilibrium of device and body for drive positions ``q`` (no
        damping, no noise): ``(pose, efforts)``, continuous with ``guess`` (default: the
        current pose). What the load cells read if the brace held still there: the static
        load a report compares measured forces with. Does not change the simulation."""
        saved = self._pose, self.slack
        if guess is not None:
            self._pose = np.asarray(guess, dtype=float).copy()
        try:
            q = np.asarray(q, dtype=float)
            pose, _, _, f = (self._equilibrium(q, 0.0) if self.compliant else self._rigid(q, 0.0))
        finally:
            self._pose, self.slack = saved
        return pose, f

    def lengths_to_counts(self, lengths_m: np.ndarray) -> np.ndarray:
        """Homed encoder counts of actuator lengths (counts = floor(length * counts/m), each
        drive's own counts per m)."""
        return np.floor(np.asarray(lengths_m, dtype=float) * self.drive_counts_per_m).astype(np.int64)

    # ------------------------------------------------------------------ SYNC

    def _on_sync(self, dt: float) -> None:
        for d in self.drives:
            d.on_sync(dt, phase='motion')
        truth = self._physics(dt)
        with self.lock:
            self._truth = truth
            self._history.append(truth)
            if truth.stamp - self._record[-1].stamp >= self._record_period - 0.5 * dt:
                self._record.append(truth)
        for d in self.drives:
            d.on_sync(dt, phase='comm')
        if self.module is not None:
            self.module.on_sync(dt, phase='comm')

    def _fast_legs(self) -> PlanarRprFloats | None:
        """The plain-float leg model (:class:`~brace_control.mechanisms.planar_floats.
        PlanarRprFloats`, ~10 us per evaluation instead of ~60 us) when the mechanism is a
        planar 3-RPR and it agrees with ``mech.inverse`` / ``mech.jacobian``."""
        mech = self.mechanism
        base = getattr(mech, 'base_anchors', None)
        plat = getattr(mech, 'platform_anchors', None)
        if mech.dof != 3 or mech.n_actuators != 3 or base is None or plat is None:
            return None
        try:
            legs = PlanarRprFloats(base, plat)
        except (ValueError, TypeError):
            return None
        home = mech.home_pose
        return legs if legs.agrees_with(mech, (home, home + np.array([0.004, -0.003, 0.05])),
                                        atol=1e-12, rtol=1e-5) else None

    def _kinematics(self, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Leg lengths L(pose) (stroke not checked) and J(pose)."""
        if self._legs is not None:
            return self._legs(pose)
        return self._phys_mech.inverse(pose), self._phys_mech.jacobian(pose)

    def _equilibrium(self, q: np.ndarray, dt: float) -> tuple[np.ndarray, ...]:
        """The platform's quasi-static equilibrium between the legs (or cables) and the body.

        Each leg is the actuator (length ``q_i``) in series with a stiffness ``k``
        (``sim.leg_stiffness``: load cell, straps, shells, or the cable and its drum):
        ``f = k (q - L(pose))``, push positive, ``L`` the leg lengths of the rigid
        platform (inverse kinematics). A cable only pulls: ``f = min(0, k (q - L))``; a
        cable whose paid-out length exceeds the distance between its anchors is slack
        (``f = 0``, listed in :attr:`slack`), and the platform settles where the taut
        ones and the body balance. Solve ``R(pose) = J^T f + W_body = 0``,
        ``W_body = -K (pose - rest) - D (pose - pose_prev) / dt`` by Newton from the
        previous pose (the branch continuous with it, as ``forward_nearest``), with
        ``dR/dpose ~ -(J_t^T k J_t + K + D/dt)``, ``J_t`` the rows of the taut legs. As
        ``k -> inf`` the pose tends to ``forward_nearest(q, pose_prev)``; a finite ``k``
        keeps the forces bounded near the singular poses of the brace (theta = 0), where a
        rigid model's ``J^T f = -W_body`` has no bounded solution.

        :returns: ``pose, J(pose), W_body, f`` with ``J^T f = -W_body`` to ``equilibrium_tol``.
        """
        if self._legs is not None:
            return self._equilibrium_floats(q, dt)
        k = self.leg_stiffness
        dof = self.dof
        c = self.damping / dt if dt > 0 else np.zeros((dof, dof))
        prev = self._pose
        pose = prev.copy()
        rest, rest_dot = self._body
        # the damper acts on the motion relative to the trunk: D (pose_dot - rest_dot)
        prev_rel = prev + rest_dot * dt
        for _ in range(30):
            lengths, J = self._kinematics(pose)
            J = np.asarray(J, dtype=float)
            f = k * (q - lengths)
            taut = np.ones(len(f), dtype=bool)
            if self.cable:
                taut = f < 0.0
                f = np.where(taut, f, 0.0)
            w_spring, dspring = self._spring(pose, rest)
            w_body = w_spring - c @ (pose - prev_rel)
            r = J.T @ f + w_body
            if float(np.max(np.abs(r))) <= self.equilibrium_tol:
                break
            Jt = J[taut]
            pose = pose + np.linalg.solve(k * (Jt.T @ Jt) + dspring + c, r)
        else:
            self.equilibrium_failures += 1
        if self.cable:
            self.slack = tuple(n for n, t in zip(self.mechanism.actuator_names, taut) if not t)
        return pose, J, w_body, f

    def _equilibrium_floats(self, q: np.ndarray, dt: float) -> tuple[np.ndarray, ...]:
        """:meth:`_equilibrium` for a planar 3-RPR in plain floats (the per-SYNC hot path)."""
        k = self.leg_stiffness
        legs = self._legs
        assert legs is not None
        K = self.stiffness.tolist()
        C = (self.damping / dt).tolist() if dt > 0 else [[0.0] * 3 for _ in range(3)]
        rest_arr, rest_dot = self._body
        rest = rest_arr.tolist()
        lim = self.patient_max_wrench.tolist()
        prev = (self._pose + rest_dot * dt).tolist()     # damper on the motion relative to the trunk
        pose = self._pose.tolist()
        qs = q.tolist()
        tol = self.equilibrium_tol
        rows: list[tuple[float, float, float]] = []
        f: list[float] = []
        w: list[float] = []
        for _ in range(20):
            x, y, th = pose
            cth, sth = math.cos(th), math.sin(th)
            rows, f = [], []
            for (ax, ay), (bx, by), qi in zip(legs.a, legs.b, qs):
                rx, ry = cth * bx - sth * by, sth * bx + cth * by
                dx, dy = x + rx - ax, y + ry - ay
                n = math.hypot(dx, dy)
                ux, uy = dx / n, dy / n
                rows.append((ux, uy, rx * uy - ry * ux))
                f.append(k * (qi - n))
            dp = [pose[j] - rest[j] for j in range(3)]
            dv = [pose[j] - prev[j] for j in range(3)]
            spring = [-(K[i][0] * dp[0] + K[i][1] * dp[1] + K[i][2] * dp[2]) for i in range(3)]
            free = [abs(spring[i]) <= lim[i] for i in range(3)]      # the patient's effort limit
            w = [(spring[i] if free[i] else math.copysign(lim[i], spring[i]))
                 - (C[i][0] * dv[0] + C[i][1] * dv[1] + C[i][2] * dv[2]) for i in range(3)]
            r = [rows[0][j] * f[0] + rows[1][j] * f[1] + rows[2][j] * f[2] + w[j] for j in range(3)]
            if max(abs(r[0]), abs(r[1]), abs(r[2])) <= tol:
                return np.array(pose), np.array(rows), np.array(w), np.array(f)
            a = [[(K[i][j] if free[i] else 0.0) + C[i][j]
                  + k * (rows[0][i] * rows[0][j] + rows[1][i] * rows[1][j]
                                  + rows[2][i] * rows[2][j]) for j in range(3)] for i in range(3)]
            d0, d1, d2 = _solve3(a, r)
            pose = [pose[0] + d0, pose[1] + d1, pose[2] + d2]
        self.equilibrium_failures += 1
        return np.array(pose), np.array(rows), np.array(w), np.array(f)

    def _rigid_cost(self, q0: np.ndarray) -> None:
        """Choose the rigid pose tracker and how often it runs while the device moves.

        The simulator shares the driver process (and its GIL) with the master and the
        nodes, so a SYNC's physics must stay near :attr:`physics_budget`. A square or
        redundant mechanism tracks its pose by one Gauss-Newton step on the IK residual
        per update (the actuators move little between SYNCs; at rest the steps converge
        within a few SYNCs before the state is frozen); an under-actuated one (the
        four-bar) uses ``forward_nearest``. When one update costs more than the budget,
        it runs every :attr:`physics_every` SYNCs while moving (every SYNC at rest).
        """
        import time as _time
        mech = self.mechanism
        home = np.asarray(mech.home_pose, dtype=float)
        self._use_newton = mech.n_actuators >= mech.dof
        t0 = _time.perf_counter()
        try:
            for _ in range(3):
                if self._use_newton:
                    mech.inverse(home)
                    mech.jacobian(home)
                else:
                    mech.forward_nearest(q0, home)
                    mech.jacobian(home)
        except ValueError:
            pass
        cost = (_time.perf_counter() - t0) / 3.0
        self.physics_every = max(1, math.ceil(cost / self.physics_budget))

    def _rigid_pose(self, q: np.ndarray, moving: bool) -> tuple[np.ndarray, np.ndarray | None]:
        """The rigid device's pose for actuator positions ``q``, continuous with the last
        one, and ``J`` at it when already computed."""
        mech = self.mechanism
        prev = self._pose
        if self._use_newton:
            # Gauss-Newton on the IK residual (least squares for a redundant device: its
            # lengths need not be exactly consistent while the drives track); one step per
            # SYNC while moving, to convergence at rest
            pose = prev.copy()
            for _ in range(1 if moving else 8):
                try:
                    r = q - mech.inverse(pose)
                    J = np.asarray(mech.jacobian(pose), dtype=float)
                    step = np.linalg.lstsq(J, r, rcond=None)[0]
                except ValueError:
                    break
                pose = pose + step
                if float(np.max(np.abs(step))) <= 1e-12:
                    return pose, J
            else:
                if moving:
                    return pose, None
            if float(np.max(np.abs(pose - prev))) < 0.05:
                return pose, None
        try:
            return np.asarray(mech.forward_nearest(q, prev), dtype=float), None
        except ValueError as exc:
            fit = getattr(exc, 'pose', None)        # 4-RPR: the best least-squares fit
            self.equilibrium_failures += 1
            return (np.asarray(fit, dtype=float) if fit is not None else prev.copy()), None

    def _rigid(self, q: np.ndarray, dt: float, moving: bool = False) -> tuple[np.ndarray, ...]:
        """Any mechanism, rigid and quasi-static: the pose from the actuator positions, the
        body's wrench ``W_body = -K (pose - rest) - D pose_dot`` (generalised forces
        conjugate to the pose coordinates, ``sim.stiffness``/``sim.damping`` dof x dof),
        the actuator efforts from ``J^T f = -W_body``: the least-squares (minimum-norm)
        solution, plus the mechanism's :meth:`unloaded_forces` (the continuum robot's
        bent bars push on the sliders with no load). (Cables are compliant, see
        :meth:`_equilibrium`.) An under-actuated device (the one-motor four-bar) balances
        only the part of ``W_body`` its motor can: the rest is taken by its joints.

        :returns: ``pose, J(pose), W_body, f``.
        """
        mech = self.mechanism
        pose, J = self._rigid_pose(q, moving)
        pose_dot = (pose - self._pose) / dt if dt > 0 else np.zeros(self.dof)
        rest, rest_dot = self._body
        w_body = self._spring(pose, rest)[0] - self.damping @ (pose_dot - rest_dot)
        if J is None:
            J = np.asarray(mech.jacobian(pose), dtype=float)
        f = np.linalg.lstsq(J.T, -w_body, rcond=None)[0]
        # plus what holds the mechanism's own elastic members (the continuum robot's bars);
        # a mechanism of the bare protocol (no MechanismBase) has none
        unloaded = getattr(mech, 'unloaded_forces', None)
        self._f_unloaded = np.zeros_like(f) if unloaded is None else np.asarray(unloaded(q), dtype=float)
        return pose, J, w_body, f + self._f_unloaded

    def _noise(self) -> list[float]:
        """One SYNC's load-cell noise, drawn from the seeded generator in blocks of
        :data:`NOISE_BLOCK` SYNCs (the same sequence as one draw per SYNC, without numpy's
        per-call cost on the SYNC path)."""
        if not self._noise_block:
            block = self._rng.normal(0.0, self.noise_n, (NOISE_BLOCK, len(self.drives)))
            self._noise_block = block.tolist()[::-1]
        return self._noise_block.pop()

    def _physics(self, dt: float) -> BraceTruth:
        """Pose from lengths, body wrench, actuator forces, load-cell counts (see module doc)."""
        lengths = [d.length_m for d in self.drives]
        rates = [d.velocity_mps for d in self.drives]
        moving_q = any(v != 0.0 for v in rates)              # as np.any: NaN counts as moving
        # the patient's trunk at the end of this step (a swaying trunk is never at rest)
        self._prune_rest(self._time)
        self._body = self.body_at(self._time + dt)
        if self._swaying or self._time < self._rest_track[-1][0] + dt:
            self._static = None           # the trunk moves (streamed rest poses): no held state
        self._elapsed += dt
        static = self._static
        if static is not None and dt > 0 and not moving_q \
                and all(map(operator.eq, lengths, self._q_last_list)):
            # at rest: only the noise changes (plain floats: this runs at every SYNC)
            pose, J, pose_dot, w_body, forces, forces_l, unloaded, brace_wrench = static
            if unloaded is not self._f_unloaded:             # static_forces() of a rigid model
                brace_wrench = J.T @ (forces - self._f_unloaded)
            brace_wrench = brace_wrench.copy()
            self._elapsed = 0.0
            q, q_dot = np.array(lengths), np.array(rates)
        else:
            q, q_dot = np.array(lengths), np.array(rates)
            if (not self.compliant and moving_q and self._skipped + 1 < self.physics_every
                    and self._last_dynamic is not None and dt > 0):
                # a costly rigid model runs every physics_every SYNCs while moving (GIL budget)
                self._skipped += 1
                pose, J, pose_dot, w_body, forces = self._last_dynamic
            else:
                self._skipped = 0
                dt_phys, self._elapsed = (dt if self.compliant else self._elapsed), 0.0
                pose, J, w_body, forces = (self._equilibrium(q, dt) if self.compliant
                                           else self._rigid(q, dt_phys, moving_q))
                pose_dot = (pose - self._pose) / dt_phys if dt > 0 else np.zeros(self.dof)
                self._last_dynamic = (pose, J, pose_dot, w_body, forces)
                self._pose, self._q_last, self._q_last_list = pose, q, lengths
                moving = bool(np.any(q_dot)) or float(np.max(np.abs(pose_dot))) > 1e-9
                # the held state, with what every SYNC at rest reuses: the forces as floats
                # and J^T (f - f_unloaded) for this f_unloaded
                self._static = None if moving else (
                    pose, J, np.zeros(self.dof), w_body, forces, forces.tolist(), self._f_unloaded,
                    J.T @ (forces - self._f_unloaded))
            forces_l = forces.tolist()
            brace_wrench = J.T @ (forces - self._f_unloaded)  # the bars' own push is not on the body
        noise = self._noise() if self.noise_n > 0.0 else [0.0] * len(self.drives)
        rated, to_counts = self.rated_force, self._scaling.force_to_counts
        counts_l = []
        gains, offsets, ref = self._gains, self._offsets, self.reference_load
        for i, (d, fi, (sink, k, load)) in enumerate(zip(self.drives, forces_l, self._load_sinks)):
            ov = self.load_cell_override[i]
            reading = gains[i] * (fi + ref[i]) + offsets[i] + noise[i] if ov is None else ov
            if self.rotary and d.polarity < 0:
                reading = -reading                   # the drive's torque, in its own sense
            reading = min(max(reading, -rated), rated)       # saturation at full scale
            # quantisation and the input's range (INTEGER16: 0 N at 0; UNSIGNED16: mid-scale)
            c = to_counts(reading, load)
            counts_l.append(c - load.zero)
            if k is None:
                sink.load_cell_counts = c
            else:
                sink.readings[k] = c
            # rotary drives report the measured joint torque in 6077h (per mille of rated)
            d.force_n = reading if self.rotary else fi
        counts = np.array(counts_l)
        self._time += dt
        self._sync_count += 1 if dt > 0 else 0
        return BraceTruth(q, q_dot, pose.copy(), pose_dot, w_body, brace_wrench, forces,
                          counts, self._sync_count, self._time, self.host.last_sync_stamp,
                          self._body[0], self._body[1])
