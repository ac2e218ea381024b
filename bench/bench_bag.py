"""Burst replay: how many messages of a burst reach a live subscriber, and how fast (issue 13).

    python bench/bench_bag.py [--messages 5000] [--runs 3] [--pythonpath DIR]

A bag of ``--messages`` ``std_msgs/String`` stamped within one microsecond (written with
``rosbags``) is replayed by ``brace-bag replay BAG --wait-subscribers 1`` in a separate
process into this process's reliable subscriber, once per case:

* ``sub KEEP_ALL``: the subscriber keeps every message it has not taken yet;
* ``sub KEEP_LAST 100``: the subscriber's own history drops the oldest untaken ones;
* ``pub depth 10`` / ``pub depth 1``: KEEP_ALL subscriber, the replay's QoS overridden
  to a shallow publisher history (more acknowledgement round trips).

Reported per case: messages received (min / max over the runs), the replay's exit code,
the wall time of the ``replay`` process and the publish time it prints.
``--pythonpath DIR`` runs another checkout's ``brace_control`` (e.g. the code before
issue 13: ``git show <rev>:brace_control/bag.py``) in the replay process.
"""
from __future__ import annotations

import argparse
import os
import platform
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
os.environ.setdefault('ROS_DOMAIN_ID', str(1 + os.getpid() % 200))

import rclpy  # noqa: E402
from rclpy.context import Context  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from rosbags.rosbag2 import StoragePlugin, Writer  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402
from std_msgs.msg import String  # noqa: E402

REPO = Path(__file__).resolve().parent.parent
TOPIC = '/bench/burst'
CASES = {
    'sub KEEP_ALL': (QoSProfile(history=HistoryPolicy.KEEP_ALL,
                                reliability=ReliabilityPolicy.RELIABLE), None),
    'sub KEEP_LAST 100': (QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE), None),
    'pub depth 10': (QoSProfile(history=HistoryPolicy.KEEP_ALL,
                                reliability=ReliabilityPolicy.RELIABLE), 10),
    'pub depth 1': (QoSProfile(history=HistoryPolicy.KEEP_ALL,
                               reliability=ReliabilityPolicy.RELIABLE), 1),
}


def write_burst(path: Path, n: int) -> None:
    store = get_typestore(Stores.ROS2_HUMBLE)
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        c = w.add_connection(TOPIC, 'std_msgs/msg/String', typestore=store)
        for k in range(n):
            w.write(c, 10**18 + k * 1000 // n, bytes(store.serialize_cdr(
                store.types['std_msgs/msg/String'](data=f'b{k:05d}'), 'std_msgs/msg/String')))


def one_run(bag: Path, n: int, sub_qos: QoSProfile, pub_depth: int | None,
            pythonpath: str | None, tmp: Path) -> tuple[int, int, float, float]:
    ctx = Context()
    rclpy.init(context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    node = Node('bench_burst_listener', context=ctx)
    ex.add_node(node)
    got: list[bytes] = []
    node.create_subscription(String, TOPIC, got.append, sub_qos, raw=True)
    cmd = [sys.executable, '-m', 'brace_control.bag', 'replay', str(bag), '--wait-subscribers', '1']
    if pub_depth is not None:
        overrides = tmp / f'depth{pub_depth}.yaml'
        overrides.write_text(f'{TOPIC}: {{depth: {pub_depth}}}\n')
        cmd += ['--qos-profile-overrides-path', str(overrides)]
    env = dict(os.environ, PYTHONPATH=pythonpath or str(REPO))
    t0 = time.monotonic()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=env, cwd=pythonpath or str(REPO))
    while proc.poll() is None:
        ex.spin_once(timeout_sec=0.01)
    wall = time.monotonic() - t0
    deadline = time.monotonic() + 3.0            # stragglers after the process exited
    while len(got) < n and time.monotonic() < deadline:
        ex.spin_once(timeout_sec=0.01)
    _, err = proc.communicate()
    m = re.search(r'published \d+ messages in ([0-9.]+) s', err)
    ex.shutdown()
    node.destroy_node()
    rclpy.shutdown(context=ctx)
    return len(got), proc.returncode, wall, float(m.group(1)) if m else float('nan')


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--messages', type=int, default=5000)
    ap.add_argument('--runs', type=int, default=3)
    ap.add_argument('--pythonpath', default=None, help='checkout whose brace_control replays')
    ap.add_argument('--cases', nargs='+', default=list(CASES), choices=list(CASES))
    args = ap.parse_args()
    print(f'python {platform.python_version()}, {platform.machine()}, {os.cpu_count()} cpus, '
          f'load avg {os.getloadavg()[0]:.2f}; {args.messages} messages within 1 us; '
          f'replay code: {args.pythonpath or REPO}')
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        write_burst(tmp / 'burst', args.messages)
        print('| case | received (min / max of runs) | exit codes | replay process s '
              '(median) | publish + ack s (median) |')
        print('|---|---|---|---|---|')
        for name in args.cases:
            sub_qos, depth = CASES[name]
            runs = [one_run(tmp / 'burst', args.messages, sub_qos, depth, args.pythonpath, tmp)
                    for _ in range(args.runs)]
            got = [r[0] for r in runs]
            walls = sorted(r[2] for r in runs)
            pubs = sorted(r[3] for r in runs)
            print(f'| {name} | {min(got)} / {max(got)} of {args.messages} | '
                  f'{sorted({r[1] for r in runs})} | {walls[len(walls) // 2]:.2f} | '
                  f'{pubs[len(pubs) // 2]:.2f} |', flush=True)


if __name__ == '__main__':
    main()
