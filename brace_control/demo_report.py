"""Read a recorded run (mcap) back and turn it into a plot and a summary.

Pure post-processing with ``rosbags`` (its own CDR deserializer) and matplotlib (Agg):
usable on any recorded bag of the brace topics, with or without ROS.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ['RunData', 'read_run', 'Summary', 'summarise', 'plot_run']


@dataclass
class Series:
    t: np.ndarray                  # s since the start of the bag
    v: np.ndarray                  # (n, k)

    @classmethod
    def empty(cls, k: int) -> 'Series':
        return cls(np.zeros(0), np.zeros((0, k)))


@dataclass
class RunData:
    """The brace topics of a run as time series (bag receive time, s from the start)."""

    goal: Series
    setpoint: Series               # /brace/pose_setpoint (x, y, theta)
    pose: Series                   # /brace/pose (measured)
    q_cmd: Series                  # /brace/actuator_setpoint positions
    q: Series                      # /brace/joint_states positions
    force: Series                  # /brace/joint_states efforts (load cells, N)
    wrench: Series                 # /brace/wrench (Fx, Fy, Mz)
    names: list[str] = field(default_factory=list)
    diagnostics: list[tuple[float, int, str, str]] = field(default_factory=list)


def _yaw(q: Any) -> float:
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


def read_run(path: str | Path) -> RunData:
    """Read the brace topics of a bag (directory, .mcap or .db3)."""
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore
    store = get_typestore(Stores.ROS2_HUMBLE)
    rows: dict[str, list] = {k: [] for k in ('goal', 'setpoint', 'pose', 'q_cmd', 'q', 'force', 'wrench')}
    diags: list[tuple[float, int, str, str]] = []
    names: list[str] = []
    with Reader(Path(path)) as reader:
        t0 = reader.start_time
        for conn, t_ns, data in reader.messages():
            t = (t_ns - t0) * 1e-9
            topic = conn.topic
            if topic in ('/brace/pose_goal', '/brace/pose_setpoint', '/brace/pose'):
                m = store.deserialize_cdr(data, conn.msgtype)
                p = m.pose
                key = {'/brace/pose_goal': 'goal', '/brace/pose_setpoint': 'setpoint',
                       '/brace/pose': 'pose'}[topic]
                rows[key].append((t, [p.position.x, p.position.y, _yaw(p.orientation)]))
            elif topic == '/brace/actuator_setpoint':
                m = store.deserialize_cdr(data, conn.msgtype)
                rows['q_cmd'].append((t, list(m.position)))
            elif topic == '/brace/joint_states':
                m = store.deserialize_cdr(data, conn.msgtype)
                names = list(m.name)
                rows['q'].append((t, list(m.position)))
                if len(m.effort) == len(m.name):
                    rows['force'].append((t, list(m.effort)))
            elif topic == '/brace/wrench':
                m = store.deserialize_cdr(data, conn.msgtype)
                w = m.wrench
                rows['wrench'].append((t, [w.force.x, w.force.y, w.torque.z]))
            elif topic == '/diagnostics':
                m = store.deserialize_cdr(data, conn.msgtype)
                for s in m.status:
                    lvl = s.level if isinstance(s.level, int) else int.from_bytes(bytes(s.level), 'little')
                    diags.append((t, int(lvl), s.name, s.message))

    def series(key: str, k: int) -> Series:
        r = rows[key]
        if not r:
            return Series.empty(k)
        return Series(np.array([x[0] for x in r]), np.array([x[1] for x in r], dtype=float))

    return RunData(series('goal', 3), series('setpoint', 3), series('pose', 3), series('q_cmd', 3),
                   series('q', 3), series('force', 3), series('wrench', 3), names, diags)


@dataclass
class Summary:
    goals: int
    goals_reached: int
    max_tracking_error_m: float         # |setpoint - measured| (x, y) while moving
    max_tracking_error_rad: float
    final_error: list[float]            # last goal - last measured pose
    peak_force_n: float
    peak_force_actuator: str
    peak_wrench: list[float]            # max |Fx|, |Fy|, |Mz|
    diagnostics_errors: list[str]

    def lines(self) -> list[str]:
        return [
            f'goals reached: {self.goals_reached}/{self.goals}',
            f'max tracking error: {self.max_tracking_error_m * 1e3:.2f} mm, '
            f'{math.degrees(self.max_tracking_error_rad):.3f} deg',
            f'peak load-cell force: {self.peak_force_n:.1f} N ({self.peak_force_actuator})',
            f'peak wrench on the body: |Fx| {self.peak_wrench[0]:.1f} N, |Fy| {self.peak_wrench[1]:.1f} N, '
            f'|Mz| {self.peak_wrench[2]:.2f} N·m',
        ] + ([f'errors in /diagnostics: {len(self.diagnostics_errors)} '
              f'(first: {self.diagnostics_errors[0]})'] if self.diagnostics_errors else [])


def _interp(src: Any, t: np.ndarray) -> np.ndarray:
    return np.column_stack([np.interp(t, src.t, src.v[:, i]) for i in range(src.v.shape[1])])


def summarise(run: RunData, goals: Sequence[Sequence[float]], *, tol_m: float = 0.002,
              tol_rad: float = math.radians(0.2)) -> Summary:
    """Goals reached (the measured pose came within tolerance of the goal before the next
    goal was sent, or by the end), the largest |setpoint - measured pose|, peak forces."""
    reached = 0
    gt = list(run.goal.t) + [math.inf]
    for k, g in enumerate(goals):
        if run.pose.t.size == 0:
            break
        t_from = gt[k] if k < len(run.goal.t) else math.inf
        sel = (run.pose.t >= t_from) & (run.pose.t < gt[k + 1] if k + 1 < len(gt) else True)
        if not np.any(sel):
            continue
        err = run.pose.v[sel] - np.asarray(g, dtype=float)
        ok = (np.hypot(err[:, 0], err[:, 1]) <= tol_m) & (np.abs(err[:, 2]) <= tol_rad)
        reached += bool(np.any(ok))
    e_m = e_rad = 0.0
    if run.setpoint.t.size and run.pose.t.size:
        sel = (run.pose.t >= run.setpoint.t[0]) & (run.pose.t <= run.setpoint.t[-1])
        if np.any(sel):
            sp = _interp(run.setpoint, run.pose.t[sel])
            d = run.pose.v[sel] - sp
            e_m = float(np.max(np.hypot(d[:, 0], d[:, 1])))
            e_rad = float(np.max(np.abs(d[:, 2])))
    final = (list(np.asarray(goals[-1]) - run.pose.v[-1]) if goals and run.pose.t.size else [])
    if run.force.t.size:
        i, j = np.unravel_index(int(np.argmax(np.abs(run.force.v))), run.force.v.shape)
        peak_f = float(abs(run.force.v[i, j]))
        peak_name = run.names[j] if j < len(run.names) else f'#{j}'
    else:
        peak_f, peak_name = 0.0, '-'
    peak_w = list(np.max(np.abs(run.wrench.v), axis=0)) if run.wrench.t.size else [0.0] * 3
    errors = [f'{name}: {msg}' for _, lvl, name, msg in run.diagnostics if lvl >= 2]
    return Summary(len(goals), reached, e_m, e_rad, [float(x) for x in final], peak_f, peak_name,
                   [float(x) for x in peak_w], errors)


def plot_run(run: RunData, out: str | Path, *, title: str = 'lumbar brace run') -> Path:
    """Four panels over time: commanded vs measured pose, actuator lengths, load-cell
    forces, wrench on the body. Written with the Agg backend."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(4, 1, figsize=(11, 13), sharex=True)
    labels = ['x (mm)', 'y - y0 (mm)', 'theta (deg)']
    colors = ['tab:blue', 'tab:orange', 'tab:green']
    y0 = run.pose.v[0, 1] if run.pose.t.size else 0.0

    def conv(v: np.ndarray) -> np.ndarray:
        return np.column_stack([v[:, 0] * 1e3, (v[:, 1] - y0) * 1e3, np.degrees(v[:, 2])])

    a = ax[0]
    if run.setpoint.t.size:
        sp = conv(run.setpoint.v)
        for i in range(3):
            a.plot(run.setpoint.t, sp[:, i], '--', color=colors[i], lw=1, label=f'{labels[i]} commanded')
    if run.pose.t.size:
        ps = conv(run.pose.v)
        for i in range(3):
            a.plot(run.pose.t, ps[:, i], '-', color=colors[i], lw=1.6, alpha=0.7, label=f'{labels[i]} measured')
    if run.goal.t.size:
        for t in run.goal.t:
            a.axvline(t, color='0.8', lw=0.8, zorder=0)
    a.set_ylabel('pose')
    a.legend(ncol=2, fontsize=8, loc='upper right')
    a.set_title(title)
    a = ax[1]
    names = run.names or ['a1', 'a2', 'a3']
    for i in range(run.q.v.shape[1] if run.q.t.size else 0):
        a.plot(run.q.t, run.q.v[:, i] * 1e3, lw=1.6, color=colors[i % 3], label=f'{names[i]} measured')
    for i in range(run.q_cmd.v.shape[1] if run.q_cmd.t.size else 0):
        a.plot(run.q_cmd.t, run.q_cmd.v[:, i] * 1e3, '--', lw=1, color=colors[i % 3], label=f'{names[i]} setpoint')
    a.set_ylabel('actuator length (mm)')
    a.legend(ncol=2, fontsize=8, loc='upper right')
    a = ax[2]
    for i in range(run.force.v.shape[1] if run.force.t.size else 0):
        a.plot(run.force.t, run.force.v[:, i], lw=1, color=colors[i % 3], label=names[i])
    a.set_ylabel('load-cell force (N)')
    a.legend(fontsize=8, loc='upper right')
    a = ax[3]
    if run.wrench.t.size:
        a.plot(run.wrench.t, run.wrench.v[:, 0], lw=1, label='Fx (N)')
        a.plot(run.wrench.t, run.wrench.v[:, 1], lw=1, label='Fy (N)')
        a.plot(run.wrench.t, run.wrench.v[:, 2] * 10, lw=1, label='Mz (N·m) x10')
    a.set_ylabel('wrench on the body\n(platform frame)')
    a.set_xlabel('time (s)')
    a.legend(fontsize=8, loc='upper right')
    for a in ax:
        a.grid(alpha=0.3)
    fig.tight_layout()
    out = Path(out)
    fig.savefig(out, dpi=90)
    plt.close(fig)
    return out
