"""End-to-end latency and CPU of the bring-up (issue 5).

    ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST python bench/bench_e2e.py [--seconds 10] [--executor per-node]

The lumbar brace comes up in this process (:class:`brace_control.bringup.BringUp`: the
four nodes + the simulated drives on a python-can virtual bus), homed and enabled. A
bench thread publishes ``/brace/pose_setpoint`` at 200 Hz (a slow sway around the parked
pose, well inside the step limit) and, interleaved, one bare ``PoseStamped`` on
``/bench/hop`` to a subscriber on its own executor thread. A python-can listener on the
same virtual channel time-stamps every RPDO1 of drive 1.

* setpoint -> RPDO: from ``publish()`` of setpoint k to the first RPDO1 (0x201) whose
  target position 607Ah equals round(IK_a1(pose_k) x counts/m) (±1 count). The path:
  DDS hop to ik_node, IK, DDS hop to can_driver_node, master's next SYNC cycle (500 Hz:
  up to 2 ms of waiting by design).
* bare hop: ``publish()`` -> subscription callback, same process, same run.
* CPU: user + system time of this process (all nodes, simulator, bench threads) over
  the measurement window, in % of one core; the machine's load average alongside.
"""
from __future__ import annotations

import argparse
import math
import os
import platform
import resource
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')

import can  # noqa: E402
import rclpy  # noqa: E402
from geometry_msgs.msg import PoseStamped  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402

from brace_control.bringup import BringUp  # noqa: E402
from brace_control.config import load_device_config  # noqa: E402
from brace_control.demo import prepare_config  # noqa: E402
from brace_control.mechanisms import mechanism_from_config  # noqa: E402
from brace_control.nodes.msgs import pose_msg  # noqa: E402

#: an RPDO later than this after its setpoint is not matched (a sway revisits its counts)
MATCH_WINDOW_S = 0.25
QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)


def pct(a, q):
    return float(np.percentile(np.asarray(a), q)) if len(a) else float('nan')


def run(seconds: float, executor: str, rate_hz: float = 200.0,
        command_timeout: float | None = None) -> dict:
    tmp = Path(tempfile.mkdtemp(prefix='bench_e2e_'))
    cfg_path, _ = prepare_config('lumbar_brace', tmp)
    cfg = load_device_config(cfg_path)
    mech = mechanism_from_config(cfg)
    counts_per_m = cfg['actuator']['encoder_counts_per_rev'] / cfg['actuator']['screw_lead']
    channel = f'bench{os.getpid()}'
    rclpy.init()
    extra = ['-p', f'can.channel:={channel}']
    if command_timeout is not None:
        extra += ['-p', f'safety.command_timeout:={command_timeout}']
    b = BringUp(cfg_path, executor=executor, extra_args=extra).start()
    rpdo: list[tuple[float, int]] = []
    bus = can.Bus(interface='virtual', channel=channel, receive_own_messages=False)

    class Listener(can.Listener):
        def on_message_received(self, msg: can.Message) -> None:
            if msg.arbitration_id == 0x201 and len(msg.data) >= 6:
                rpdo.append((time.perf_counter(), int.from_bytes(msg.data[2:6], 'little', signed=True)))

    notifier = can.Notifier(bus, [Listener()])
    for what in ('home', 'enable'):
        ok, msg = b.call(f'/can_driver_node/{what}', timeout=15)
        if not ok:
            raise SystemExit(f'{what} failed: {msg}')
    # bare hop: subscriber on its own node + executor thread
    hop_node = rclpy.create_node('bench_hop_sub')
    hop_times: list[float] = []
    hop_sent: dict[int, float] = {}
    hop_node.create_subscription(
        PoseStamped, '/bench/hop',
        lambda m: hop_times.append(time.perf_counter() - hop_sent.get(m.header.stamp.nanosec, math.nan)),
        QOS)
    hop_exec = SingleThreadedExecutor()
    hop_exec.add_node(hop_node)
    threading.Thread(target=hop_exec.spin, daemon=True).start()
    pub_node = rclpy.create_node('bench_pub')
    sp_pub = pub_node.create_publisher(PoseStamped, '/brace/pose_setpoint', QOS)
    hop_pub = pub_node.create_publisher(PoseStamped, '/bench/hop', QOS)
    while sp_pub.get_subscription_count() < 1 or hop_pub.get_subscription_count() < 1:
        time.sleep(0.01)
    home = np.asarray(mech.home_pose, float)
    frame = cfg['base_frame']
    sent: list[tuple[float, int]] = []
    period = 1.0 / rate_hz
    load0 = os.getloadavg()[0]
    r0 = resource.getrusage(resource.RUSAGE_SELF)
    t0 = time.perf_counter()
    n = int(seconds * rate_hz)
    for k in range(n):
        s = k * period
        pose = home + np.array([0.004 * math.sin(2 * math.pi * 0.25 * s),
                                0.003 * math.sin(2 * math.pi * 0.2 * s), 0.0])
        q1 = mech.inverse(pose)[0]
        msg = pose_msg(pose, frame_id=frame, stamp=b.helper.get_clock().now().to_msg())
        now = time.perf_counter()
        sp_pub.publish(msg)
        sent.append((now, round(q1 * counts_per_m)))
        hop = PoseStamped()
        hop.header.stamp.nanosec = k
        hop_sent[k] = time.perf_counter()
        hop_pub.publish(hop)
        delay = t0 + (k + 1) * period - time.perf_counter()
        if delay > 0:
            time.sleep(delay)
    t1 = time.perf_counter()
    r1 = resource.getrusage(resource.RUSAGE_SELF)
    load1 = os.getloadavg()[0]
    time.sleep(0.2)
    cpu = 100 * ((r1.ru_utime + r1.ru_stime) - (r0.ru_utime + r0.ru_stime)) / (t1 - t0)
    driver = b.node('can_driver_node')
    sync = driver.master.status().timing
    rejected = driver.rejected
    # match setpoints to RPDOs
    rp_t = np.array([t for t, _ in rpdo])
    rp_c = np.array([c for _, c in rpdo])
    lat = []
    for ts, c in sent[20:]:
        i0 = np.searchsorted(rp_t, ts)
        i1 = np.searchsorted(rp_t, ts + MATCH_WINDOW_S)
        hits = np.nonzero(np.abs(rp_c[i0:i1] - c) <= 1)[0]
        if hits.size:
            lat.append(rp_t[i0 + hits[0]] - ts)
    notifier.stop()
    bus.shutdown()
    hop_exec.shutdown()
    b.shutdown()
    rclpy.try_shutdown()
    hop = [h for h in hop_times[20:] if h == h]
    return {
        'executor': executor, 'setpoints': n, 'matched': len(lat),
        'lat_p50_ms': pct(lat, 50) * 1e3, 'lat_p99_ms': pct(lat, 99) * 1e3,
        'lat_max_ms': (max(lat) * 1e3 if lat else math.nan),
        'over_15ms': 100 * float(np.mean(np.asarray(lat) > 0.015)) if lat else math.nan,
        'hop_p50_ms': pct(hop, 50) * 1e3, 'hop_p99_ms': pct(hop, 99) * 1e3, 'hops': len(hop),
        'cpu_pct': cpu, 'load': (load0, load1), 'sync_p99_us': sync.p99 * 1e6,
        'sync_overruns': sync.overruns, 'sync_cycles': sync.cycles, 'rejected': rejected,
    }


def _proc_cpu_s(pid: int) -> float:
    fields = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')


def run_processes(seconds: float, rate_hz: float = 200.0, command_timeout: float | None = None) -> dict:
    """CPU of each node process (``--processes``) while this process streams setpoints."""
    from brace_control.bringup import ProcessBringUp, call_trigger
    tmp = Path(tempfile.mkdtemp(prefix='bench_e2e_'))
    cfg_path, _ = prepare_config('lumbar_brace', tmp)
    cfg = load_device_config(cfg_path)
    mech = mechanism_from_config(cfg)
    extra = [] if command_timeout is None else ['-p', f'safety.command_timeout:={command_timeout}']
    group = ProcessBringUp(cfg_path, extra_args=extra).start()
    rclpy.init()
    node = rclpy.create_node('bench_processes')
    ex = SingleThreadedExecutor()
    ex.add_node(node)
    threading.Thread(target=ex.spin, daemon=True).start()
    try:
        for what in ('home', 'enable'):
            deadline = time.monotonic() + 30
            while True:
                ok, msg = call_trigger(node, f'/can_driver_node/{what}', timeout=10, executor=ex)
                if ok or time.monotonic() > deadline:
                    break
                time.sleep(0.2)
            if not ok:
                raise SystemExit(f'{what} failed: {msg}')
        pub = node.create_publisher(PoseStamped, '/brace/pose_setpoint', QOS)
        while pub.get_subscription_count() < 1:
            time.sleep(0.01)
        home = np.asarray(mech.home_pose, float)
        c0 = {n: _proc_cpu_s(p.pid) for n, p in group.procs.items()}
        load0 = os.getloadavg()[0]
        t0 = time.perf_counter()
        period = 1.0 / rate_hz
        for k in range(int(seconds * rate_hz)):
            s = k * period
            pose = home + np.array([0.004 * math.sin(2 * math.pi * 0.25 * s),
                                    0.003 * math.sin(2 * math.pi * 0.2 * s), 0.0])
            pub.publish(pose_msg(pose, frame_id=cfg['base_frame'], stamp=node.get_clock().now().to_msg()))
            delay = t0 + (k + 1) * period - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
        t1 = time.perf_counter()
        c1 = {n: _proc_cpu_s(p.pid) for n, p in group.procs.items()}
        return {'cpu': {n: 100 * (c1[n] - c0[n]) / (t1 - t0) for n in c0},
                'load': (load0, os.getloadavg()[0]), 'failed': group.failed()}
    finally:
        group.stop()
        ex.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--seconds', type=float, default=10.0)
    ap.add_argument('--executor', choices=('per-node', 'multi', 'processes'), default='per-node',
                    help='one process (executor per node, or one MultiThreadedExecutor), or '
                         '--processes (CPU per node process only: the bus is inside the driver)')
    ap.add_argument('--command-timeout', type=float, default=1.0,
                    help='safety.command_timeout for the run (s; default 1.0 so that every '
                         'setpoint reaches the bus and its latency is measured; the YAML has 0.015)')
    args = ap.parse_args()
    if args.executor == 'processes':
        r = run_processes(args.seconds, command_timeout=args.command_timeout)
        total = sum(r['cpu'].values())
        print(f'--processes, load average {r["load"][0]:.2f} -> {r["load"][1]:.2f}: CPU '
              + ', '.join(f'{n} {c:.0f} %' for n, c in r['cpu'].items())
              + f'; total {total:.0f} % of one core' + (f'; ended: {r["failed"]}' if r['failed'] else ''))
        return 0
    r = run(args.seconds, args.executor, command_timeout=args.command_timeout)
    print(f'CPython {platform.python_version()}, {os.cpu_count()} CPUs, load average '
          f'{r["load"][0]:.2f} -> {r["load"][1]:.2f}, executor {r["executor"]}, '
          f'{time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}')
    print(f'| setpoint -> RPDO1 on the bus | {r["lat_p50_ms"]:.2f} | {r["lat_p99_ms"]:.2f} | '
          f'{r["lat_max_ms"]:.2f} | {r["matched"]}/{r["setpoints"] - 20} matched, '
          f'{r["over_15ms"]:.1f} % over 15 ms |')
    print(f'| bare rclpy publish -> subscribe hop | {r["hop_p50_ms"]:.2f} | {r["hop_p99_ms"]:.2f} | '
          f'- | {r["hops"]} |')
    print(f'CPU of the bring-up process: {r["cpu_pct"]:.0f} % of one core; SYNC period error p99 '
          f'{r["sync_p99_us"]:.0f} us, overruns {r["sync_overruns"]}/{r["sync_cycles"]}; '
          f'setpoints rejected by the driver: {r["rejected"]}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
