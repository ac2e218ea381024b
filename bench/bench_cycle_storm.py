"""The SYNC cycle under an rclpy storm: a subscriber flood to the CAN driver's node.

    ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST python bench/bench_cycle_storm.py
        [--rate 5000] [--seconds 10] [--config config/lumbar_brace.yaml]

``can_driver_node`` runs as ``ros2 run`` runs it (its own process, the simulated brace on a
``virtual`` bus), homed and enabled, at rest, once with the control cycle in its own process
(``can.cycle_process: true``, the default) and once in the node's process (``false``). For
each: ``--seconds`` quiet, then ``--seconds`` while a flooder process publishes ``--rate``
``JointState`` messages per second on ``/brace/actuator_setpoint`` whose joint names are
not the brace's. The node deserialises and rejects every one in its executor (rclpy work
that holds the node's interpreter lock; nothing reaches the drives). The SYNC cycle's
overruns and period error p99 per window come from the driver's ``/diagnostics`` (cumulative
``cycles`` and ``overruns``); the flood's delivered rate from its ``setpoints_rejected``
count. Prints a Markdown table for bench/RESULTS.md.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))
os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
os.environ.setdefault('ROS_DOMAIN_ID', str(100 + os.getpid() % 50))

from _timing import machine_line  # noqa: E402

FLOODER = '''
import sys, time, rclpy
from sensor_msgs.msg import JointState
from brace_control.nodes import topics
rate, seconds = float(sys.argv[1]), float(sys.argv[2])
rclpy.init()
node = rclpy.create_node('storm_flooder')
pub = node.create_publisher(JointState, topics.ACTUATOR_SETPOINT, topics.SETPOINT_QOS)
while pub.get_subscription_count() == 0:
    time.sleep(0.05)
msg = JointState(name=['not_a_leg'], position=[0.0])
period, t = 1.0 / rate, time.perf_counter()
end, n = t + seconds, 0
while t < end:
    pub.publish(msg)
    n += 1
    t += period
    delay = t - time.perf_counter()
    if delay > 0:
        time.sleep(delay)
print(n, flush=True)
node.destroy_node()
rclpy.shutdown()
'''


def run(config: str, cycle_process: bool, rate: float, seconds: float) -> dict:
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.executors import SingleThreadedExecutor

    from bench_stack import home_and_enable

    from brace_control.nodes import topics
    from brace_control.nodes.msgs import status_values

    channel = f'storm{os.getpid()}{int(cycle_process)}'
    driver = subprocess.Popen(
        [sys.executable, '-m', 'brace_control.nodes.can_driver_node', '--ros-args', '--params-file',
         config, '-p', f'can.channel:={channel}', '-p', f'can.cycle_process:={str(cycle_process).lower()}'],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    node = rclpy.create_node(f'storm_bench_{int(cycle_process)}')
    ex = SingleThreadedExecutor()
    ex.add_node(node)
    lock = threading.Lock()
    latest: dict[str, dict] = {}

    def on_diag(m) -> None:
        for st in m.status:
            for part in ('cycle', 'safety'):
                if st.name.endswith(f'/{part}'):
                    with lock:
                        latest[part] = status_values(st)
    node.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, on_diag, 50)
    stop = threading.Event()
    spinner = threading.Thread(target=lambda: [ex.spin_once(timeout_sec=0.05) for _ in iter(stop.is_set, True)],
                               daemon=True)
    spinner.start()

    def sample() -> tuple[int, int, int, float]:
        with lock:
            n0 = latest.get('cycle', {}).get('cycles')
        deadline = time.monotonic() + 3.0       # the next diagnostics (1 Hz): a fresh count
        while time.monotonic() < deadline:
            with lock:
                c = latest.get('cycle', {})
                if c.get('cycles') != n0:
                    s = latest.get('safety', {})
                    return (int(c['cycles']), int(c['overruns']), int(s.get('setpoints_rejected', 0)),
                            float(c['period_error_p99_us']))
            time.sleep(0.01)
        raise RuntimeError('no /diagnostics from can_driver_node')

    try:
        home_and_enable(node, ex)
        time.sleep(2.0)
        a = sample()
        time.sleep(seconds)
        b = sample()
        flooder = subprocess.Popen([sys.executable, '-c', FLOODER, str(rate), str(seconds)],
                                   stdout=subprocess.PIPE, text=True)
        sent = int(flooder.communicate(timeout=seconds + 60)[0].split()[-1])
        c = sample()
    finally:
        stop.set()
        spinner.join()
        driver.send_signal(2)
        try:
            driver.wait(15)
        except subprocess.TimeoutExpired:
            driver.kill()
        node.destroy_node()
    quiet = (b[0] - a[0], b[1] - a[1], b[3])
    storm = (c[0] - b[0], c[1] - b[1], c[3])
    return {'quiet': quiet, 'storm': storm, 'sent': sent, 'handled': c[2] - b[2]}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--rate', type=float, default=5000.0, help='messages per second')
    ap.add_argument('--seconds', type=float, default=10.0)
    ap.add_argument('--config', default=str(ROOT / 'config' / 'lumbar_brace.yaml'))
    args = ap.parse_args()
    import rclpy
    rclpy.init()
    try:
        rows = [(mode, run(args.config, mode, args.rate, args.seconds)) for mode in (True, False)]
    finally:
        rclpy.try_shutdown()
    print(machine_line())
    print(f'load average after: {os.getloadavg()[0]:.2f}\n')
    print('| control cycle | window | SYNC cycles | overruns | p99 period error (us, last 5000 SYNCs) '
          '| flood sent / handled by the node |')
    print('|---|---|---:|---:|---:|---|')
    for mode, r in rows:
        where = 'own process' if mode else "in the node's process"
        for window in ('quiet', 'storm'):
            cycles, overruns, p99 = r[window]
            flood = f'{r["sent"]} / {r["handled"]}' if window == 'storm' else '-'
            print(f'| {where} | {window} {args.seconds:g} s | {cycles} | {overruns} '
                  f'({100.0 * overruns / max(cycles, 1):.2f} %) | {p99:.0f} | {flood} |')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
