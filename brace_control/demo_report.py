"""Read a recorded run (mcap) back and turn it into a plot and a summary that tell the truth.

Post-processing of a bag of the brace topics (:data:`brace_control.demo.RECORDED_TOPICS`)
with ``rosbags`` (its own CDR deserializer), the stack's message conventions
(:mod:`brace_control.nodes.msgs`, :mod:`brace_control.nodes.topics`) and matplotlib (Agg):

* :func:`read_run`: every topic as time series. Stamped messages are placed at their
  ``header.stamp`` (the SYNC a measurement answers, the instant a planned motion takes
  over), the rest at the time they were recorded; both as seconds from the bag's start.
* :func:`static_load`: for each joint-state sample, the load the body puts on the legs if
  the brace held still on the planned path there, and how far the measured forces are
  above it (internal force from lengths that left the planned motion).
* :func:`summarise`: goal outcomes from ``/brace/goal_status``, the estimate against the
  simulator's truth, the peak force above the static load, peak forces and wrench,
  protective stops, and the demo's three verdicts.
* :func:`plot_run`: ``run.png``.
"""
from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ['Series', 'Plan', 'GoalOutcome', 'RunData', 'read_run', 'LoadComparison', 'static_load',
           'Summary', 'summarise', 'plot_run', 'EXCESS_LIMIT_N', 'excess_limit', 'pose_error',
           'pair_stamps', 'STAMP_TOLERANCE_NS']

#: N: the peak load-cell force above the static load a demo run may show (linear actuators)
EXCESS_LIMIT_N = 10.0
#: the fraction of the actuator's rating that :data:`EXCESS_LIMIT_N` is of the lumbar brace's
#: 250 N: the limit for rotary drives (N·m), whose torques are an order of magnitude smaller
EXCESS_LIMIT_FRACTION = EXCESS_LIMIT_N / 250.0
#: ns: two stamps this close are the same SYNC (a quarter of the fastest SYNC period, 2 ms at
#: 500 Hz). The simulator's truth and the driver's measurement of one SYNC should carry the
#: identical stamp; they are read from two clocks microseconds apart (the bus frame's
#: timestamp, the master's log of its send), so pairing allows this much and says how much
#: it needed (:class:`Summary`).
STAMP_TOLERANCE_NS = 500_000
#: s between the samples of a planned motion rebuilt from its knots (plot, static load)
PLAN_STEP_S = 0.002
#: goal states that end a goal (trajectory_node: each goal ends in exactly one)
TERMINAL_STATES = ('succeeded', 'aborted', 'rejected', 'cancelled')

# pose coordinates per pose kind (brace_control.nodes.msgs.pose_kind): label, unit, scale from SI
_POSE_AXES = {
    'planar': (('x', 'mm', 1e3), ('y', 'mm', 1e3), ('theta', 'deg', 180.0 / math.pi)),
    'xy': (('x', 'mm', 1e3), ('y', 'mm', 1e3)),
    'path': (('s', 'mm', 1e3),),
    'spherical': (('abduction', 'deg', 180.0 / math.pi), ('flexion', 'deg', 180.0 / math.pi),
                  ('rotation', 'deg', 180.0 / math.pi)),
}
# the wrench components msgs.wrench_msg writes per pose kind: (force|torque, axis, label, unit)
_WRENCH_AXES = {
    'planar': (('force', 'x', 'Fx', 'N'), ('force', 'y', 'Fy', 'N'), ('torque', 'z', 'Mz', 'N·m')),
    'xy': (('force', 'x', 'Fx', 'N'), ('force', 'y', 'Fy', 'N')),
    'path': (('force', 'x', 'F', 'N'),),
    'spherical': (('torque', 'x', 'Mx', 'N·m'), ('torque', 'y', 'My', 'N·m'),
                  ('torque', 'z', 'Mz', 'N·m')),
}


@dataclass
class Series:
    """Samples of one topic.

    :ivar t: s from the bag's start: the header stamp where the message has a nonzero one,
        else the time it was recorded.
    :ivar v: (n, k) values in SI units.
    :ivar stamp: (n,) header stamps (ns, int64; 0 for messages without one): the key that
        pairs samples of the same instant across topics.
    :ivar raw: (n, 7) position x, y, z and orientation quaternion x, y, z, w of a pose
        topic (empty for other topics): device-independent pose errors.
    """

    t: np.ndarray
    v: np.ndarray
    stamp: np.ndarray
    raw: np.ndarray = field(default_factory=lambda: np.zeros((0, 7)))

    @classmethod
    def empty(cls, k: int) -> 'Series':
        return cls(np.zeros(0), np.zeros((0, k)), np.zeros(0, dtype=np.int64))

    def __len__(self) -> int:
        return int(self.t.size)


@dataclass
class Plan:
    """One planned motion as recorded: ``trajectory`` (knots, time from ``start_s``) or
    ``None`` for a stop (an empty trajectory: decelerate along the running path, hold)."""

    start_s: float
    stamp: int
    trajectory: Any


@dataclass(frozen=True)
class GoalOutcome:
    """One event of a goal on ``/brace/goal_status``; ``stamp`` = the goal message's stamp (ns)."""

    t: float
    goal_id: str
    state: str
    reason: str
    stamp: int
    target: str = ''


@dataclass
class RunData:
    """The brace topics of a run (see :func:`read_run`)."""

    kind: str                                   # pose kind: planar | xy | path | spherical
    goal: Series                                # /brace/pose_goal (recorded time)
    pose: Series                                # /brace/pose: the load-aware estimate
    truth_pose: Series                          # /brace/sim/pose: the simulator's truth
    plans: list[Plan]                           # /brace/pose_trajectory, by start
    actuator_plans: list[Plan]                  # /brace/actuator_trajectory, by start
    q: Series                                   # /brace/joint_states positions (m or rad)
    force: Series                               # /brace/joint_states efforts (N or N·m)
    q_true: Series                              # /brace/sim/joint_states positions
    force_true: Series                          # /brace/sim/joint_states efforts
    wrench: Series                              # /brace/wrench (platform frame)
    wrench_true: Series                         # /brace/sim/wrench
    names: list[str] = field(default_factory=list)
    goal_events: list[GoalOutcome] = field(default_factory=list)
    execution: list[tuple[float, str, dict[str, str]]] = field(default_factory=list)
    driver_states: list[tuple[float, int, str, dict[str, str]]] = field(default_factory=list)
    diagnostics: list[tuple[float, int, str, str, dict[str, str]]] = field(default_factory=list)
    effort_unit: str = 'N'
    duration_s: float = 0.0

    @property
    def pose_axes(self) -> tuple[tuple[str, str, float], ...]:
        return _POSE_AXES[self.kind]

    @property
    def wrench_axes(self) -> tuple[tuple[str, str, str, str], ...]:
        return _WRENCH_AXES[self.kind]


def _level(value: Any) -> int:
    return value if isinstance(value, int) else int.from_bytes(bytes(value), 'little')


def _device_config(config: Any) -> Any:
    """A :class:`~brace_control.config.DeviceConfig` from a path, a device name or a mapping."""
    from .config import DeviceConfig, load_device_config
    if isinstance(config, DeviceConfig):
        return config
    return DeviceConfig(config) if isinstance(config, Mapping) else load_device_config(config)


def _typestore():
    """The typestore :class:`brace_control.bag.Recorder` writes with (Kilted's definitions)."""
    from rosbags.typesys import Stores, get_typestore
    return get_typestore(Stores.ROS2_KILTED if hasattr(Stores, 'ROS2_KILTED') else Stores.LATEST)


def read_run(path: str | Path, *, config: Any = None) -> RunData:
    """Read the brace topics of a bag (directory, .mcap or .db3).

    :param config: the device (YAML path, name or loaded config): poses are decoded into
        its coordinates (:func:`~brace_control.nodes.msgs.pose_from_msg`), efforts get its
        unit. ``None``: a planar device with linear actuators.
    :raises MalformedMessage: a recorded message the device cannot hold (wrong kind of pose).
    """
    from rosbags.rosbag2 import Reader

    from .nodes import topics
    from .nodes.msgs import (joint_knots_from_msg, pose_from_msg, pose_kind, pose_knots_from_msg,
                             stamp_to_ns, status_values)
    from .trajectory import KnotTrajectory
    mech = None
    effort_unit = 'N'
    if config is not None:
        from .can.units import actuator_kind
        from .mechanisms import mechanism_from_config
        cfg = _device_config(config)
        mech = mechanism_from_config(cfg)
        effort_unit = 'N·m' if actuator_kind(cfg) == 'rotary' else 'N'
    kind = pose_kind(mech) if mech is not None else 'planar'
    store = _typestore()
    rows: dict[str, list] = {k: [] for k in ('goal', 'pose', 'truth_pose', 'q', 'force', 'q_true',
                                             'force_true', 'wrench', 'wrench_true')}
    pose_topics = {topics.POSE_GOAL: 'goal', topics.POSE: 'pose', topics.SIM_POSE: 'truth_pose'}
    wanted = set(pose_topics) | {
        topics.JOINT_STATES, topics.SIM_JOINT_STATES, topics.WRENCH, topics.SIM_WRENCH,
        topics.POSE_TRAJECTORY, topics.ACTUATOR_TRAJECTORY, topics.GOAL_STATUS,
        topics.EXECUTION_STATUS, topics.DRIVER_STATE, topics.DIAGNOSTICS}
    run = RunData(kind, *(Series.empty(1) for _ in range(3)), [], [],
                  *(Series.empty(1) for _ in range(6)), effort_unit=effort_unit)

    def rel(stamp_ns: int, t_ns: int) -> tuple[float, int]:
        return ((stamp_ns if stamp_ns else t_ns) - t0) * 1e-9, stamp_ns

    with Reader(Path(path)) as reader:
        t0 = reader.start_time
        run.duration_s = (reader.end_time - t0) * 1e-9
        for conn, t_ns, data in reader.messages():
            topic = conn.topic
            if topic not in wanted:
                continue
            m = store.deserialize_cdr(data, conn.msgtype)
            recorded = (t_ns - t0) * 1e-9
            if topic in pose_topics:
                # goals carry their exercise's own clock: placed where they were sent
                t, stamp = (recorded, stamp_to_ns(m.header.stamp)) if topic == topics.POSE_GOAL \
                    else rel(stamp_to_ns(m.header.stamp), t_ns)
                p, o = m.pose.position, m.pose.orientation
                rows[pose_topics[topic]].append(
                    (t, pose_from_msg(m, mechanism=mech, kind=kind), stamp,
                     [p.x, p.y, p.z, o.x, o.y, o.z, o.w]))
            elif topic in (topics.JOINT_STATES, topics.SIM_JOINT_STATES):
                t, stamp = rel(stamp_to_ns(m.header.stamp), t_ns)
                true = topic == topics.SIM_JOINT_STATES
                run.names = list(m.name)
                rows['q_true' if true else 'q'].append((t, list(m.position), stamp, None))
                if len(m.effort) == len(m.name):
                    rows['force_true' if true else 'force'].append((t, list(m.effort), stamp, None))
            elif topic in (topics.WRENCH, topics.SIM_WRENCH):
                t, stamp = rel(stamp_to_ns(m.header.stamp), t_ns)
                w = [getattr(getattr(m.wrench, part), axis) for part, axis, _, _ in _WRENCH_AXES[kind]]
                rows['wrench_true' if topic == topics.SIM_WRENCH else 'wrench'].append((t, w, stamp, None))
            elif topic == topics.POSE_TRAJECTORY:
                stamp, times, P, V, A = pose_knots_from_msg(m, frame_id=m.header.frame_id,
                                                            mechanism=mech, kind=kind)
                start = rel(stamp, t_ns)[0]
                run.plans.append(Plan(start, stamp, KnotTrajectory(times, P, V, A) if times.size else None))
            elif topic == topics.ACTUATOR_TRAJECTORY:
                stamp, times, Q, V, A = joint_knots_from_msg(m, list(m.joint_names))
                start = rel(stamp, t_ns)[0]
                run.actuator_plans.append(
                    Plan(start, stamp, KnotTrajectory(times, Q, V, A) if times.size else None))
            elif topic == topics.GOAL_STATUS:
                v = status_values(m)
                run.goal_events.append(GoalOutcome(
                    recorded, v.get('goal_id', m.name.rsplit('/', 1)[-1]), v.get('state', m.message),
                    v.get('reason', ''), int(v.get('stamp', '0') or 0), v.get('target', '')))
            elif topic == topics.EXECUTION_STATUS:
                run.execution.append((recorded, m.message, status_values(m)))
            elif topic == topics.DRIVER_STATE:
                run.driver_states.append((recorded, _level(m.level), m.message, status_values(m)))
            elif topic == topics.DIAGNOSTICS:
                for s in m.status:
                    run.diagnostics.append((recorded, _level(s.level), s.name, s.message,
                                            {kv.key: kv.value for kv in s.values}))

    def series(key: str) -> Series:
        r = rows[key]
        if not r:
            return Series.empty(1)
        order = np.argsort([x[0] for x in r], kind='stable')
        r = [r[i] for i in order]
        raw = np.array([x[3] for x in r], dtype=float) if r[0][3] is not None else np.zeros((0, 7))
        return Series(np.array([x[0] for x in r], dtype=float),
                      np.array([np.asarray(x[1], dtype=float) for x in r], dtype=float),
                      np.array([x[2] for x in r], dtype=np.int64), raw)

    for key in rows:
        setattr(run, key, series(key))
    run.plans.sort(key=lambda p: p.start_s)
    run.actuator_plans.sort(key=lambda p: p.start_s)
    return run


# ------------------------------------------------------------------------- static load

@dataclass
class LoadComparison:
    """Measured forces against the static load of the planned path (:func:`static_load`).

    :ivar t: s from the bag's start (the samples' stamps).
    :ivar q_plan: (n, m) the planned configuration nearest each sample in actuator space.
    :ivar static: (n, m) its quasi-static forces under the body (N or N·m).
    :ivar measured: (n, m) the load-cell forces (torques) of the same instants.
    :ivar source: the topic the configurations came from.
    """

    t: np.ndarray
    q_plan: np.ndarray
    static: np.ndarray
    measured: np.ndarray
    source: str

    @property
    def excess(self) -> np.ndarray:
        """``measured - static`` (n, m)."""
        return self.measured - self.static

    def peak(self) -> tuple[float, int, float]:
        """``(largest |measured - static|, actuator index, t)``; ``(0, -1, nan)`` when empty."""
        if self.t.size == 0:
            return 0.0, -1, math.nan
        e = np.abs(self.excess)
        i, j = np.unravel_index(int(np.argmax(e)), e.shape)
        return float(e[i, j]), int(j), float(self.t[i])


def _dense(trajectory: Any, step: float) -> np.ndarray:
    """Positions of a knot trajectory every ``step`` s over its knots, ends included."""
    t0, t1 = float(trajectory.times[0]), float(trajectory.times[-1])
    ts = np.append(np.arange(t0, t1, step), t1)
    return trajectory.sample_many(ts)[0]


def _nearest_on_polyline(points: np.ndarray, q: np.ndarray) -> np.ndarray:
    """The point of the polyline through ``points`` (k, m) nearest ``q`` (m,)."""
    if len(points) == 1:
        return points[0].copy()
    a, b = points[:-1], points[1:]
    d = b - a
    dd = np.einsum('ij,ij->i', d, d)
    s = np.where(dd > 0, np.einsum('ij,ij->i', q - a, d) / np.where(dd > 0, dd, 1.0), 0.0)
    c = a + np.clip(s, 0.0, 1.0)[:, None] * d
    return c[int(np.argmin(np.einsum('ij,ij->i', c - q, c - q)))]


def static_load(run: RunData, sim: Any, *, step: float = PLAN_STEP_S) -> LoadComparison:
    """The load-cell forces against the static load of the planned path, sample by sample.

    For every sample of ``/brace/sim/joint_states`` (the true drive positions; without the
    simulator's truth, ``/brace/joint_states``): the planned motion running then (the last
    actuator trajectory that took over at or before it; a stop continues the one it stops;
    before the first motion, its start), rebuilt from its knots every ``step`` s; on it, the
    configuration nearest the sample in actuator space; and that configuration's
    quasi-static forces under the body, ``sim.static_forces(q_plan, guess)`` (no damping, no
    noise), continuous with the true pose of the same stamp (else the previous result).
    The measured forces are the load cells of ``/brace/joint_states`` of the same SYNC
    (:func:`pair_stamps`; the sample's own efforts when there is none). With no planned motion at all, the
    sample's own configuration is the path.

    Lag along the path is not counted (the nearest configuration, not the one planned for
    that instant); what remains is the force of lengths that left the planned motion, e.g.
    internal force from legs that disagree, plus damping and noise.

    :param sim: a :class:`~brace_control.sim.SimulatedBrace` of the device (``start=False``).
    """
    from .nodes import topics
    src, forces, source = run.q_true, run.force_true, topics.SIM_JOINT_STATES
    if len(src) == 0:
        src, forces, source = run.q, run.force, topics.JOINT_STATES
    m = src.v.shape[1] if len(src) else 0
    empty = LoadComparison(np.zeros(0), np.zeros((0, m)), np.zeros((0, m)), np.zeros((0, m)), source)
    if len(src) == 0 or len(forces) == 0:
        return empty
    # configurations and efforts of the same message
    i_q, i_f = pair_stamps(src.stamp, forces.stamp, tol_ns=0)
    if i_q.size == 0:
        return empty
    effort = {int(i): forces.v[j] for i, j in zip(i_q, i_f)}
    # the load cells of the same SYNC, and the true pose of the same message
    i_s, i_m = pair_stamps(src.stamp, run.force.stamp) if source != topics.JOINT_STATES \
        else (i_q, i_f)
    measured = {int(i): run.force.v[j] for i, j in zip(i_s, i_m)} if source != topics.JOINT_STATES \
        else effort
    i_s, i_p = pair_stamps(src.stamp, run.truth_pose.stamp)
    truth = {int(i): run.truth_pose.v[j] for i, j in zip(i_s, i_p)}
    plans = [p for p in run.actuator_plans if p.trajectory is not None]
    starts = np.array([p.start_s for p in plans])
    polylines = [_dense(p.trajectory, step) for p in plans]
    t_out, q_out, f_static, f_meas = [], [], [], []
    guess = None
    for i in sorted(effort):
        t, q = float(src.t[i]), src.v[i]
        if plans:
            k = max(int(np.searchsorted(starts, t, side='right')) - 1, 0)
            q_plan = _nearest_on_polyline(polylines[k], q)
        else:
            q_plan = q.copy()
        guess = truth.get(i, guess)
        pose, f = sim.static_forces(q_plan, guess)
        guess = pose
        t_out.append(t)
        q_out.append(q_plan)
        f_static.append(np.asarray(f, dtype=float))
        f_meas.append(measured.get(i, effort[i]))
    return LoadComparison(np.array(t_out), np.array(q_out).reshape(-1, m),
                          np.array(f_static).reshape(-1, m), np.array(f_meas).reshape(-1, m), source)


def excess_limit(config: Any) -> tuple[float, str]:
    """The largest force above the static load a run may show, and its unit:
    :data:`EXCESS_LIMIT_N` for linear actuators, :data:`EXCESS_LIMIT_FRACTION` of
    ``actuator.max_force`` (N·m) for rotary drives."""
    from .can.units import actuator_kind
    cfg = _device_config(config)
    if actuator_kind(cfg) == 'rotary':
        return EXCESS_LIMIT_FRACTION * float(cfg.get_path('actuator.max_force')), 'N·m'
    return EXCESS_LIMIT_N, 'N'


# ------------------------------------------------------------------------------ summary

def pair_stamps(a: np.ndarray, b: np.ndarray, *, tol_ns: int = STAMP_TOLERANCE_NS
                ) -> tuple[np.ndarray, np.ndarray]:
    """Indices ``(ia, ib)`` of the samples of ``a`` and ``b`` (header stamps, ns) that are
    the same instant: for each nonzero stamp of ``a`` the nearest of ``b``, kept when they
    differ by at most ``tol_ns`` (0: identical stamps only). Each sample pairs at most once."""
    a = np.asarray(a, dtype=np.int64)
    b = np.asarray(b, dtype=np.int64)
    if a.size == 0 or b.size == 0:
        return np.zeros(0, dtype=int), np.zeros(0, dtype=int)
    order = np.argsort(b, kind='stable')
    bs = b[order]
    pos = np.searchsorted(bs, a)
    lo, hi = np.clip(pos - 1, 0, bs.size - 1), np.clip(pos, 0, bs.size - 1)
    near = np.where(np.abs(bs[lo] - a) <= np.abs(bs[hi] - a), lo, hi)
    ok = (np.abs(bs[near] - a) <= tol_ns) & (a != 0)
    ia, ib = np.flatnonzero(ok), order[near[ok]]
    _, first = np.unique(ib, return_index=True)           # a sample of b pairs once
    keep = np.sort(first)
    return ia[keep], ib[keep]


def pose_error(a: Series, b: Series, *, tol_ns: int = STAMP_TOLERANCE_NS
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(t, |position a - position b| m, rotation between a and b rad, stamp b - stamp a ns)``
    over the samples paired by :func:`pair_stamps`, from the raw poses (any device)."""
    ia, ib = pair_stamps(a.stamp, b.stamp, tol_ns=tol_ns)
    if ia.size == 0 or a.raw.size == 0 or b.raw.size == 0:
        return np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0, dtype=np.int64)
    ra, rb = a.raw[ia], b.raw[ib]
    dpos = np.linalg.norm(ra[:, :3] - rb[:, :3], axis=1)
    qa = ra[:, 3:] / np.linalg.norm(ra[:, 3:], axis=1, keepdims=True)
    qb = rb[:, 3:] / np.linalg.norm(rb[:, 3:], axis=1, keepdims=True)
    sign = np.where(np.einsum('ij,ij->i', qa, qb) < 0.0, -1.0, 1.0)[:, None]
    # 2 acos|qa.qb|, written so that small angles keep their precision
    angle = 4.0 * np.arctan2(np.linalg.norm(qa - sign * qb, axis=1),
                             np.linalg.norm(qa + sign * qb, axis=1))
    return a.t[ia], dpos, angle, b.stamp[ib] - a.stamp[ia]


@dataclass
class Summary:
    """What a run did (:func:`summarise`); :meth:`lines` prints it."""

    goals_expected: int
    outcomes: dict[str, int]                    # terminal state -> goals
    goals: list[GoalOutcome]                    # each goal's terminal event, in order
    anomalies: list[str]                        # goals without exactly one terminal state
    max_error_m: float                          # max |estimate - truth| (position)
    max_error_rad: float                        # max rotation between estimate and truth
    max_error_t: tuple[float, float]
    error_pairs: int                            # samples paired by stamp
    error_identical: int                        # of which with identical stamps
    error_stamp_gap_ns: int                     # largest stamp difference of a pair
    excess: float                               # largest |measured - static load|
    excess_actuator: str
    excess_t: float
    excess_samples: int
    excess_source: str
    excess_limit: float
    effort_unit: str
    peak_force: float
    peak_force_actuator: str
    wrench_axes: list[tuple[str, str]]          # (label, unit), e.g. ('Fx', 'N')
    peak_wrench: list[float]                    # max |component| of /brace/wrench
    peak_wrench_true: list[float]               # of /brace/sim/wrench
    diagnostics_errors: list[str]
    protective_stops: list[str]
    sync_cycle: dict[str, str] = field(default_factory=dict)   # the driver's last cycle status
    kind: str = 'planar'                        # pose kind: which errors are meaningful

    @property
    def goals_succeeded(self) -> int:
        return self.outcomes.get('succeeded', 0)

    @property
    def all_succeeded(self) -> bool:
        """Every expected goal ended, once, in ``succeeded``."""
        return (not self.anomalies and self.goals_succeeded == self.goals_expected
                and len(self.goals) == self.goals_expected)

    @property
    def no_protective_stop(self) -> bool:
        return not self.protective_stops

    @property
    def excess_ok(self) -> bool:
        """The peak above the static load is below the limit (and was measured at all)."""
        return self.excess_samples > 0 and self.excess < self.excess_limit

    @property
    def ok(self) -> bool:
        return self.all_succeeded and self.no_protective_stop and self.excess_ok

    def verdicts(self) -> list[tuple[str, bool]]:
        u = self.effort_unit
        return [
            (f'every goal succeeded ({self.goals_succeeded}/{self.goals_expected})', self.all_succeeded),
            ('no protective stop latched', self.no_protective_stop),
            (f'peak above the static load {self.excess:.2f} {u} < {self.excess_limit:g} {u}'
             if self.excess_samples else 'peak above the static load: no samples', self.excess_ok),
        ]

    def lines(self) -> list[str]:
        u = self.effort_unit
        others = ', '.join(f'{s} {self.outcomes.get(s, 0)}' for s in TERMINAL_STATES[1:])
        out = [f'goals: {self.goals_succeeded}/{self.goals_expected} succeeded ({others})']
        out += [f'  {a}' for a in self.anomalies]
        if self.error_pairs:
            how = ('identical stamps' if self.error_identical == self.error_pairs else
                   f'{self.error_identical} with identical stamps, the others up to '
                   f'{self.error_stamp_gap_ns / 1e3:.1f} us apart')
            parts = []
            if self.kind != 'spherical':
                parts.append(f'{self.max_error_m * 1e3:.3f} mm (t = {self.max_error_t[0]:.1f} s)')
            if self.kind in ('planar', 'spherical'):
                parts.append(f'{math.degrees(self.max_error_rad):.4f} deg (t = {self.max_error_t[1]:.1f} s)')
            out.append(f'estimate vs truth: max {", ".join(parts)} over {self.error_pairs} samples '
                       f'paired by stamp ({how})')
        else:
            out.append('estimate vs truth: no /brace/pose and /brace/sim/pose samples with the same stamp')
        if self.excess_samples:
            out.append(f'load cells above the static load: peak {self.excess:.2f} {u} '
                       f'({self.excess_actuator} at t = {self.excess_t:.2f} s) over '
                       f'{self.excess_samples} samples of {self.excess_source}')
        else:
            out.append('load cells above the static load: no samples')
        out.append(f'peak load-cell force: {self.peak_force:.1f} {u} ({self.peak_force_actuator})')
        if self.wrench_axes:
            out.append('peak wrench on the body: ' + ', '.join(
                f'|{label}| {w:.2f}' + ('' if math.isnan(wt) else f' (true {wt:.2f})') + f' {unit}'
                for (label, unit), w, wt in zip(self.wrench_axes, self.peak_wrench,
                                                self.peak_wrench_true)))
        if self.sync_cycle:
            c = self.sync_cycle
            cycles, overruns = int(c.get('cycles', 0) or 0), int(c.get('overruns', 0) or 0)
            out.append(f'SYNC cycle: {overruns} overruns in {cycles} cycles'
                       + (f' ({100.0 * overruns / cycles:.1f} %; a motion advances one period per '
                          'SYNC: missed SYNCs slow it down)' if cycles and overruns else '')
                       + f', period error p99 {c.get("period_error_p99_us", "?")} us, '
                         f'max {c.get("period_error_max_us", "?")} us')
        out.append(f'errors in /diagnostics: {len(self.diagnostics_errors)}'
                   + (f' (first: {self.diagnostics_errors[0]})' if self.diagnostics_errors else ''))
        out.append('protective stops: ' + ('; '.join(self.protective_stops) or 'none'))
        out += [f'verdict: {text}: {"yes" if ok else "NO"}' for text, ok in self.verdicts()]
        return out


def summarise(run: RunData, *, goals_expected: int | None = None,
              load: LoadComparison | None = None,
              limit: float = EXCESS_LIMIT_N) -> Summary:
    """The run in numbers (:class:`Summary`).

    * goals: each goal's terminal event on ``/brace/goal_status`` (succeeded, aborted,
      rejected, cancelled); a goal with none or with more than one is an anomaly.
      ``goals_expected`` defaults to the number of goals seen;
    * the largest distance and rotation between the estimate ``/brace/pose`` and the truth
      ``/brace/sim/pose`` over samples of the same stamp (:func:`pose_error`; how many
      stamps were identical and how far apart the others were);
    * the largest |measured - static load| of ``load`` (:func:`static_load`) against ``limit``;
    * the peak load-cell force, the peak |component| of the measured and true wrench;
    * ERROR statuses in ``/diagnostics``; protective stops (a driver state ``fault``, or a
      driver ``/safety`` diagnostic in ERROR); the driver's last SYNC cycle status (overruns:
      the executor advances a motion one period per SYNC, so missed SYNCs stretch it).
    """
    terminal: dict[str, list[GoalOutcome]] = {}
    seen: list[str] = []
    for ev in run.goal_events:
        if ev.goal_id not in seen:
            seen.append(ev.goal_id)
        if ev.state in TERMINAL_STATES:
            terminal.setdefault(ev.goal_id, []).append(ev)
    anomalies = []
    goals = []
    for gid in seen:
        ends = terminal.get(gid, [])
        if len(ends) != 1:
            anomalies.append(f'goal {gid}: {len(ends)} terminal states'
                             + (f' ({", ".join(e.state for e in ends)})' if ends else ''))
        if ends:
            goals.append(ends[0])
    expected = len(seen) if goals_expected is None else int(goals_expected)
    if len(seen) != expected:
        anomalies.append(f'{len(seen)} goals on /brace/goal_status, {expected} sent')
    outcomes = {s: sum(1 for g in goals if g.state == s) for s in TERMINAL_STATES}

    t_err, d_m, d_rad, gap = pose_error(run.pose, run.truth_pose)
    if t_err.size:
        i, j = int(np.argmax(d_m)), int(np.argmax(d_rad))
        e_m, e_rad, e_t = float(d_m[i]), float(d_rad[j]), (float(t_err[i]), float(t_err[j]))
    else:
        e_m, e_rad, e_t = math.nan, math.nan, (math.nan, math.nan)

    names = run.names or [f'#{k}' for k in range(run.force.v.shape[1])]
    if load is not None and load.t.size:
        ex, j, ex_t = load.peak()
        ex_name, ex_n, ex_src = names[j] if j < len(names) else f'#{j}', int(load.t.size), load.source
    else:
        ex, ex_name, ex_t, ex_n, ex_src = math.nan, '-', math.nan, 0, '-'
    if len(run.force):
        i, j = np.unravel_index(int(np.argmax(np.abs(run.force.v))), run.force.v.shape)
        peak_f, peak_name = float(abs(run.force.v[i, j])), names[j] if j < len(names) else f'#{j}'
    else:
        peak_f, peak_name = 0.0, '-'
    axes = [(label, unit) for _, _, label, unit in run.wrench_axes]

    def peaks(s: Series) -> list[float]:
        return [float(x) for x in np.max(np.abs(s.v), axis=0)] if len(s) else [math.nan] * len(axes)

    errors = [f'{name}: {msg}' for _, lvl, name, msg, _ in run.diagnostics if lvl >= 2]
    stops = []
    for _, _, message, values in run.driver_states:
        if values.get('state') == 'fault' and message not in stops:
            stops.append(message)
    for _, lvl, name, msg, _ in run.diagnostics:
        if lvl >= 2 and name.endswith('/safety') and not stops:
            stops.append(msg)
    return Summary(expected, outcomes, goals, anomalies, e_m, e_rad, e_t, int(t_err.size),
                   int(np.count_nonzero(gap == 0)), int(np.max(np.abs(gap))) if gap.size else 0,
                   ex, ex_name, ex_t, ex_n, ex_src, float(limit), run.effort_unit, peak_f, peak_name,
                   axes, peaks(run.wrench), peaks(run.wrench_true), errors, stops,
                   next((dict(v) for _, _, name, _, v in reversed(run.diagnostics)
                         if name.endswith('/cycle')), {}), run.kind)


# --------------------------------------------------------------------------------- plot

def _planned(plans: Sequence[Plan], t_end: float, step: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """The planned motion as one curve: each plan from its start to the next one's (a stop:
    a gap), rebuilt from its knots every ``step`` s; NaN rows between the pieces."""
    ts, vs = [], []
    for k, p in enumerate(plans):
        if p.trajectory is None:
            continue
        end = plans[k + 1].start_s if k + 1 < len(plans) else max(t_end, p.start_s + p.trajectory.duration)
        tau = np.append(np.arange(0.0, max(end - p.start_s, 0.0), step), max(end - p.start_s, 0.0))
        P = p.trajectory.sample_many(tau + float(p.trajectory.times[0]))[0]
        ts.append(np.append(p.start_s + tau, np.nan))
        vs.append(np.vstack([P, np.full((1, P.shape[1]), np.nan)]))
    if not ts:
        return np.zeros(0), np.zeros((0, 1))
    return np.concatenate(ts), np.vstack(vs)


def plot_run(run: RunData, out: str | Path, *, title: str = 'lumbar brace run',
             load: LoadComparison | None = None) -> Path:
    """``run.png``: one panel per pose coordinate (estimate, truth, plan, goals), the estimate's
    error against the truth, actuator positions measured vs true (from where they started),
    load cells measured vs the static load of ``load``, their difference, and the wrench on
    the body measured vs true. Agg backend."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    axes_p = run.pose_axes
    n_rows = max(len(axes_p) + 1, 4)
    fig, ax = plt.subplots(n_rows, 2, figsize=(15, 2.6 * n_rows + 0.8), sharex=True, squeeze=False)
    colors = plt.rcParams['axes.prop_cycle'].by_key()['color']
    t_end = max(run.duration_s, float(run.pose.t[-1]) if len(run.pose) else 0.0)
    plan_t, plan_v = _planned(run.plans, t_end)
    goal_v = run.goal.v if len(run.goal) else np.zeros((0, len(axes_p)))
    for i, (name, unit, scale) in enumerate(axes_p):
        a = ax[i, 0]
        if plan_t.size:
            a.plot(plan_t, plan_v[:, i] * scale, '-', color='0.55', lw=2.5, alpha=0.6, label='planned')
        if len(run.pose):
            a.plot(run.pose.t, run.pose.v[:, i] * scale, '-', color=colors[0], lw=0.8,
                   label='estimate (/brace/pose)')
        if len(run.truth_pose):
            a.plot(run.truth_pose.t, run.truth_pose.v[:, i] * scale, '-', color=colors[1], lw=1.4,
                   label='true (/brace/sim/pose)')
        if len(run.goal):
            a.plot(run.goal.t, goal_v[:, i] * scale, 'v', color='k', ms=6, label='goal sent')
        a.set_ylabel(f'{name} ({unit})')
        a.grid(alpha=0.3)
    ax[0, 0].legend(fontsize=8, loc='best', ncol=2)
    ax[0, 0].set_title(title)
    # estimate - truth
    a = ax[len(axes_p), 0]
    t_err, d_m, d_rad, gap = pose_error(run.pose, run.truth_pose)
    if t_err.size:
        if any(u == 'mm' for _, u, _ in axes_p):
            a.plot(t_err, d_m * 1e3, color=colors[2], lw=1, label='|position| (mm)')
        if any(u == 'deg' for _, u, _ in axes_p):
            a.plot(t_err, np.degrees(d_rad), color=colors[4], lw=1, label='rotation (deg)')
        a.legend(fontsize=8, loc='upper right')
    a.set_ylabel('|estimate - truth|')
    a.grid(alpha=0.3)
    for r in range(len(axes_p) + 1, n_rows):
        ax[r, 0].set_visible(False)
    names = run.names or [f'#{k}' for k in range(run.q.v.shape[1])]
    unit_q, scale_q = ('deg', 180.0 / math.pi) if run.effort_unit == 'N·m' else ('mm', 1e3)
    # actuator positions, from where each started (the strokes' offsets would hide the motion)
    a = ax[0, 1]
    ref = run.q_true if len(run.q_true) else run.q
    q0 = ref.v[0] if len(ref) else 0.0
    for k in range(run.q.v.shape[1] if len(run.q) else 0):
        a.plot(run.q.t, (run.q.v[:, k] - q0[k]) * scale_q, '-', color=colors[k % 10], lw=1.6,
               alpha=0.6, label=f'{names[k]} measured')
    for k in range(run.q_true.v.shape[1] if len(run.q_true) else 0):
        a.plot(run.q_true.t, (run.q_true.v[:, k] - q0[k]) * scale_q, ':', color='k', lw=1.0,
               label='true' if k == 0 else None)
    a.set_ylabel(f'actuator position\nfrom the start ({unit_q})')
    a.legend(fontsize=8, loc='best', ncol=2)
    a.grid(alpha=0.3)
    # load cells vs the static load
    u = run.effort_unit
    a = ax[1, 1]
    for k in range(run.force.v.shape[1] if len(run.force) else 0):
        a.plot(run.force.t, run.force.v[:, k], '-', color=colors[k % 10], lw=1.0, label=f'{names[k]} measured')
    if load is not None and load.t.size:
        for k in range(load.static.shape[1]):
            a.plot(load.t, load.static[:, k], '--', color='k', lw=0.9,
                   label='static load of the plan' if k == 0 else None)
    a.set_ylabel(f'load cell ({u})' if u == 'N' else f'joint torque ({u})')
    a.legend(fontsize=8, loc='best', ncol=2)
    a.grid(alpha=0.3)
    a = ax[2, 1]
    if load is not None and load.t.size:
        for k in range(load.excess.shape[1]):
            a.plot(load.t, load.excess[:, k], '-', color=colors[k % 10], lw=1.0, label=names[k])
        a.legend(fontsize=8, loc='best', ncol=3)
    a.set_ylabel(f'measured - static ({u})')
    a.grid(alpha=0.3)
    # wrench on the body
    a = ax[3, 1]
    for k, (_, _, label, wunit) in enumerate(run.wrench_axes):
        if len(run.wrench):
            a.plot(run.wrench.t, run.wrench.v[:, k], '-', color=colors[k % 10], lw=1.0,
                   label=f'{label} ({wunit}) measured')
        if len(run.wrench_true):
            a.plot(run.wrench_true.t, run.wrench_true.v[:, k], ':', color='k', lw=1.0,
                   label='true' if k == 0 else None)
    a.set_ylabel('wrench on the body\n(platform frame)')
    a.legend(fontsize=8, loc='best', ncol=2)
    a.grid(alpha=0.3)
    for r in range(4, n_rows):
        ax[r, 1].set_visible(False)
    for col in range(2):
        visible = [r for r in range(n_rows) if ax[r, col].get_visible()]
        ax[visible[-1], col].set_xlabel('time (s)')
        ax[visible[-1], col].xaxis.set_tick_params(labelbottom=True)
    fig.tight_layout()
    out = Path(out)
    fig.savefig(out, dpi=90)
    plt.close(fig)
    return out
