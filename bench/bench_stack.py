"""The whole stack as processes: CPU at rest and in motion, SYNC overruns, goal start latency.

    ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST python bench/bench_stack.py [--seconds 10]
        [--device lumbar_brace] [--goals 20]

The device comes up as ``brace-bringup --processes`` does it (each node its own process;
the master's control cycle and the simulated brace in the CAN driver's child process,
``can.cycle_process``; ``--in-driver-process``: both inside the driver's process), homed
and enabled. ``-p name:=value`` overrides a parameter (e.g. ``can.cycle_priority:=0``).
The driver's cycle process is measured on its own, and split into the simulated brace's
share (on hardware, the drives' firmware; its own count of its CPU, ``simulator_cpu_s`` in
the driver's ``/diagnostics``) and the master's (the rest). Then:

* **at rest**: each node process's CPU (user + system, from /proc) over ``--seconds``, in %
  of one core, and their sum;
* **in motion**: the same while goals alternate between two poses (each sent when the
  previous ended), plus the SYNC cycle's overruns from the driver's ``/diagnostics``
  (cycles, overruns) over that window;
* **start latency**: for each goal, from ``publish()`` of the pose goal to the SYNC whose
  targets are the first of its trajectory (the driver's ``started`` event carries that
  SYNC's time): planning, IK, two DDS hops and the wait for the takeover
  (``PLAN_LOOKAHEAD_S``, by design).

Prints a Markdown section for bench/RESULTS.md.
"""
from __future__ import annotations

import argparse
import math
import os
import platform
import sys
import tempfile
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
os.environ.setdefault('ROS_DOMAIN_ID', str(150 + os.getpid() % 50))

import rclpy  # noqa: E402
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus  # noqa: E402
from geometry_msgs.msg import PoseStamped  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402

from brace_control.bringup import ProcessBringUp, call_trigger, wait_for_links  # noqa: E402
from brace_control.demo import prepare_config  # noqa: E402
from brace_control.nodes import topics  # noqa: E402
from brace_control.nodes.msgs import pose_msg, status_values  # noqa: E402


def cpu_seconds(pid: int) -> float:
    """user + system CPU time of a process and its threads (s), from /proc/<pid>/stat."""
    fields = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')


def children(pid: int) -> list[int]:
    """The processes ``pid`` started (Linux: /proc/<pid>/task/*/children)."""
    out: list[int] = []
    for task in Path(f'/proc/{pid}/task').iterdir():
        try:
            out += [int(c) for c in (task / 'children').read_text().split()]
        except OSError:
            pass
    return out


def thread_cpu(pid: int) -> dict[str, float]:
    """CPU seconds per OS thread name of a process (the cycle process names its threads:
    master-sync, master-rx, sim-rx, sim-timer, cycle-push, cycle-commands)."""
    out: dict[str, float] = {}
    for task in Path(f'/proc/{pid}/task').iterdir():
        try:
            name = (task / 'comm').read_text().strip()
            fields = (task / 'stat').read_text().rsplit(')', 1)[1].split()
        except OSError:
            continue
        out[name] = out.get(name, 0.0) + (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')
    return out


def cpu_share(procs: dict, seconds: float, during=None) -> dict[str, float]:
    """% of one core per process over ``seconds`` (while ``during(seconds)`` runs)."""
    before = {n: cpu_seconds(p.pid) for n, p in procs.items()}
    t0 = time.monotonic()
    if during is None:
        time.sleep(seconds)
    else:
        during(seconds)
    dt = time.monotonic() - t0
    return {n: 100.0 * (cpu_seconds(p.pid) - before[n]) / dt for n, p in procs.items()}


def simulator_share(first: tuple, last: tuple) -> float:
    """% of one core the simulated brace took between two of the driver's ``/diagnostics``
    cycle statuses (``(cycles, overruns, simulator_cpu_s, stamp_s)``): its own count of its
    CPU, in whichever thread ran it (its drives take the master's frames in the master's
    thread: a split by thread names cannot see it)."""
    dt = last[3] - first[3]
    return 100.0 * (last[2] - first[2]) / dt if dt > 0 else math.nan


def home_and_enable(node, executor, timeout: float = 60.0) -> None:
    """``~/home`` then ``~/enable`` of can_driver_node, each asked again until it answers
    success (the driver may still be configuring) or ``timeout`` s pass."""
    for what in ('home', 'enable'):
        deadline = time.monotonic() + timeout
        ok, msg = False, ''
        while not ok and time.monotonic() < deadline:
            ok, msg = call_trigger(node, f'/can_driver_node/{what}', timeout=10, executor=executor)
            if not ok:
                time.sleep(0.3)
        assert ok, f'{what}: {msg}'


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--seconds', type=float, default=10.0)
    ap.add_argument('--device', default='lumbar_brace')
    ap.add_argument('--goals', type=int, default=20, help='goals for the start latency')
    ap.add_argument('--in-driver-process', action='store_true',
                    help='can.cycle_process false: the master and the simulator in the driver node')
    ap.add_argument('-p', dest='params', action='append', default=[], metavar='NAME:=VALUE')
    args = ap.parse_args(argv)

    tmp = Path(tempfile.mkdtemp(prefix='bench_stack_'))
    config, _ = prepare_config(args.device, tmp)
    extra = ['-p', 'can.channel:=bench_stack',
             '-p', f'can.cycle_process:={"false" if args.in_driver_process else "true"}']
    for param in args.params:
        extra += ['-p', param]
    group = ProcessBringUp(config, extra_args=extra).start()
    rclpy.init()
    node = rclpy.create_node('bench_stack')
    ex = SingleThreadedExecutor()
    ex.add_node(node)
    threading.Thread(target=ex.spin, daemon=True).start()
    lock = threading.Lock()
    ends: dict[str, str] = {}
    started: dict[int, int] = {}
    cycle: list[tuple[int, int, float, float]] = []   # cycles, overruns, simulator_cpu_s, stamp

    def on_status(m):
        v = status_values(m)
        if v['state'] != 'accepted':
            with lock:
                ends[v['goal_id']] = v['state']

    def on_exec(m):
        v = status_values(m)
        if v.get('kind') == 'started':
            with lock:
                started[int(v['stamp'])] = int(v['time'])

    def on_diag(m):
        for st in m.status:
            if st.name.endswith('/cycle'):
                v = status_values(st)
                stamp = m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec
                with lock:
                    cycle.append((int(v['cycles']), int(v['overruns']),
                                  float(v.get('simulator_cpu_s', 'nan')), stamp))

    node.create_subscription(DiagnosticStatus, topics.GOAL_STATUS, on_status, topics.STATUS_QOS)
    node.create_subscription(DiagnosticStatus, topics.EXECUTION_STATUS, on_exec, topics.STATUS_QOS)
    node.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, on_diag, 50)
    pub = node.create_publisher(PoseStamped, topics.POSE_GOAL, topics.GOAL_QOS)
    try:
        home_and_enable(node, ex)
        wait_for_links(node, timeout=30)
        time.sleep(2.0)
        procs = dict(group.procs)
        driver = procs.get('can_driver_node')
        cycle_pids = children(driver.pid) if driver is not None else []
        split = None
        if cycle_pids:          # can.cycle_process: the master and the simulator in a child
            split = 'cycle process (master + simulated brace)'
            procs[split] = SimpleNamespace(pid=cycle_pids[0])
        elif driver is not None:    # in the driver's process
            split = 'can_driver_node'
        with lock:
            c_rest0 = cycle[-1] if cycle else (0, 0, math.nan, 0.0)
        rest = cpu_share(procs, args.seconds)
        with lock:
            c_rest1 = cycle[-1] if cycle else (0, 0, math.nan, 0.0)

        from brace_control.config import load_device_config
        from brace_control.mechanisms import mechanism_from_config
        mech = mechanism_from_config(load_device_config(config))
        home = np.asarray(mech.home_pose)
        poses = [home + np.array([0.0, 0.015, math.radians(3.0)]), home]
        sent: dict[str, int] = {}
        count = [0]

        def goal(i: int) -> str:
            count[0] += 1
            gid = str(count[0])
            stamp = node.get_clock().now()
            sent[gid] = stamp.nanoseconds
            pub.publish(pose_msg(poses[i % 2], frame_id='brace_base', stamp=stamp.to_msg(),
                                 mechanism=mech))
            return gid

        def wait_end(gid: str, timeout: float = 15.0) -> None:
            deadline = time.monotonic() + timeout
            while time.monotonic() < deadline:
                with lock:
                    if gid in ends:
                        return
                time.sleep(0.01)
            raise RuntimeError(f'goal {gid} did not end')

        def motion(seconds: float) -> None:
            end = time.monotonic() + seconds
            i = 0
            while time.monotonic() < end:
                wait_end(goal(i))
                i += 1

        with lock:
            c0 = cycle[-1] if cycle else (0, 0, math.nan, 0.0)
        moving = cpu_share(procs, args.seconds, during=motion)
        time.sleep(1.2)
        with lock:
            c1 = cycle[-1]
        n_motion = count[0]
        for i in range(args.goals):
            wait_end(goal(i))
        time.sleep(0.5)
        # start latency: goal publish -> its first SYNC; the goal's trajectory is the one whose
        # stamp (its takeover time) follows the goal's publication first
        with lock:
            starts = sorted(started.items())
        lat = []
        for gid in [str(k) for k in range(n_motion + 1, count[0] + 1)]:
            t_pub = sent[gid]
            after = [t for stamp, t in starts if stamp > t_pub]
            if after:
                lat.append((after[0] - t_pub) * 1e-9)
        lat = np.asarray(lat)
        with lock:
            states = list(ends.values())
    finally:
        codes = group.stop()
        ex.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
    load = os.getloadavg()[0]
    cycles, overruns = c1[0] - c0[0], c1[1] - c0[1]
    print(f'## Stack as processes ({args.device}), bench/bench_stack.py\n')
    print('```\nROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST python bench/bench_stack.py '
          f'--seconds {args.seconds:g} --device {args.device} --goals {args.goals}'
          f'{" --in-driver-process" if args.in_driver_process else ""}'
          + ''.join(f' -p {p}' for p in args.params) + '\n```\n')
    print(f'Python {platform.python_version()}, {os.cpu_count()} CPUs, load average {load:.2f} '
          f'after the run; node exit codes {codes}; goals {states.count("succeeded")} succeeded of '
          f'{len(states)}.\n')
    print('| process | CPU at rest (% of a core) | CPU in motion |')
    print('|---|---:|---:|')
    for n in rest:
        print(f'| {n} | {rest[n]:.1f} | {moving[n]:.1f} |')
    print(f'| **all** | **{sum(rest.values()):.1f}** | **{sum(moving.values()):.1f}** |\n')
    if split is not None:
        sim_rest, sim_moving = simulator_share(c_rest0, c_rest1), simulator_share(c0, c1)
        print(f'{split} split: the simulated brace\'s own count of its CPU (``simulator_cpu_s``, '
              'driver /diagnostics, between the statuses nearest each window), the master the rest:\n')
        print('| part | CPU at rest | CPU in motion |')
        print('|---|---:|---:|')
        print(f'| master | {rest[split] - sim_rest:.1f} | {moving[split] - sim_moving:.1f} |')
        print(f'| simulated brace | {sim_rest:.1f} | {sim_moving:.1f} |')
        print()
    rc, ro = c_rest1[0] - c_rest0[0], c_rest1[1] - c_rest0[1]
    print(f'SYNC cycles at rest: {rc}, overruns {ro} ({100.0 * ro / max(rc, 1):.2f} %); '
          f'in motion: {cycles}, overruns {overruns} ({100.0 * overruns / max(cycles, 1):.2f} %).\n')
    if lat.size:
        print(f'Goal start latency (publish -> first SYNC of its trajectory), {lat.size} goals: '
              f'p50 {1e3 * np.percentile(lat, 50):.0f} ms, p99 {1e3 * np.percentile(lat, 99):.0f} ms, '
              f'max {1e3 * lat.max():.0f} ms (the takeover lookahead is 150 ms by design).')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
