"""Garbage-collector pauses in the whole stack in one process (``BringUp``), with and
without :func:`~brace_control.nodes.runner.freeze_start_up_heap`.

    ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST python bench/bench_gc_pauses.py [--seconds 20]
        [--config config/lumbar_brace.yaml] [--no-freeze] [--keep-messages]

The four nodes and the simulated brace in this process, homed, enabled, at rest for
``--seconds``; every collection is timed with :data:`gc.callbacks` (start to stop: the GIL
is held all along, no other thread of the process runs). ``--keep-messages`` adds a
subscriber that keeps every ``/brace/joint_states``, ``/brace/pose`` and ``/brace/wrench``
message (as a test probe does): the heap grows by ~10^4 objects per second.

Why it matters: the drives quick-stop when the master's heartbeat is missing for 1016h =
2 x ``can.master_heartbeat_ms`` (200 ms for the lumbar brace); a pause that long in the
driver's process stops the brace. Prints Markdown rows for bench/RESULTS.md.
"""
from __future__ import annotations

import argparse
import gc
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))
os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
os.environ.setdefault('ROS_DOMAIN_ID', str(150 + os.getpid() % 50))

from _timing import machine_line  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--seconds', type=float, default=20.0)
    ap.add_argument('--config', default='lumbar_brace')
    ap.add_argument('--no-freeze', action='store_true', help='skip gc.freeze() at start-up')
    ap.add_argument('--keep-messages', action='store_true',
                    help='a probe keeps every joint state, pose and wrench message')
    args = ap.parse_args()

    import rclpy
    from geometry_msgs.msg import PoseStamped, WrenchStamped
    from rclpy.context import Context
    from sensor_msgs.msg import JointState

    import brace_control.nodes.runner as runner
    from brace_control.bringup import BringUp
    from brace_control.nodes import topics
    if args.no_freeze:
        runner.freeze_start_up_heap = lambda: None

    pauses: list[tuple[int, float]] = []
    started: list[float] = []

    def timed(phase: str, info: dict) -> None:
        if phase == 'start':
            started.append(time.perf_counter())
        elif started:
            pauses.append((info['generation'], time.perf_counter() - started.pop()))

    ctx = Context()
    rclpy.init(context=ctx)
    b = BringUp(args.config, context=ctx).start()
    kept: list = []
    if args.keep_messages:
        for typ, topic in ((JointState, topics.JOINT_STATES), (PoseStamped, topics.POSE),
                           (WrenchStamped, topics.WRENCH)):
            b.helper.create_subscription(typ, topic, kept.append, 50)
    try:
        for what in ('home', 'enable'):
            ok, msg = b.call(f'/can_driver_node/{what}', timeout=15)
            if not ok:
                print(f'{what} failed: {msg}', file=sys.stderr)
                return 1
        time.sleep(2.0)
        gc.callbacks.append(timed)
        tracked0 = len(gc.get_objects())
        time.sleep(args.seconds)
        gc.callbacks.remove(timed)
        tracked1 = len(gc.get_objects())
        faults = b.node('can_driver_node').master.supervisor.summary() \
            if b.node('can_driver_node').master.supervisor.latched else 'none'
    finally:
        b.shutdown()
        rclpy.shutdown(context=ctx)

    print(machine_line())
    print(f'freeze: {"no" if args.no_freeze else "yes"}, probe keeps messages: '
          f'{"yes" if args.keep_messages else "no"}, {args.seconds:g} s at rest; tracked objects '
          f'{tracked0} -> {tracked1}; protective stop: {faults}')
    print('| generation | collections | max pause ms | total ms |')
    print('|---|---|---|---|')
    for g in (0, 1, 2):
        d = [p for gen, p in pauses if gen == g]
        if d:
            print(f'| {g} | {len(d)} | {max(d) * 1e3:.1f} | {sum(d) * 1e3:.0f} |')
        else:
            print(f'| {g} | 0 | - | - |')
    return 0


if __name__ == '__main__':
    sys.exit(main())
