"""How long a reliable writer waits for one live reader's acknowledgement.

    ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST python bench/bench_acks.py [--samples 6]
        [--fast-dds-defaults]

A publisher on ``/brace/goal_status`` (``topics.GOAL_STATUS_QOS``) in this process, one
subscriber (``topics.STATUS_QOS``) in a child process spinning; after they matched, one sample
at a time: ``Publisher.wait_for_all_acked`` until it returns. With the package's Fast DDS
profile (``brace_control.nodes.dds``: writers' heartbeat every 0.1 s), or with Fast DDS's own
defaults (``--fast-dds-defaults``: a heartbeat every 3 s; the acknowledgement waits for it).
The trajectory node waits this way for its last statuses at shutdown.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
os.environ.setdefault('ROS_DOMAIN_ID', str(150 + os.getpid() % 50))

SUBSCRIBER = """
import sys, time, rclpy
from diagnostic_msgs.msg import DiagnosticStatus
from brace_control.nodes import topics
rclpy.init()
node = rclpy.create_node('bench_acks_reader')
node.create_subscription(DiagnosticStatus, topics.GOAL_STATUS, lambda m: None, topics.STATUS_QOS)
while rclpy.ok():
    rclpy.spin_once(node, timeout_sec=0.1)
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--samples', type=int, default=6)
    ap.add_argument('--fast-dds-defaults', action='store_true')
    args = ap.parse_args()
    from brace_control.nodes.dds import PROFILE_VARIABLES, use_discovery_profile
    if args.fast_dds_defaults:
        for name in PROFILE_VARIABLES:
            os.environ.pop(name, None)
        profile = 'none (Fast DDS defaults)'
    else:
        profile = use_discovery_profile() or 'the user\'s own'
    import rclpy
    from diagnostic_msgs.msg import DiagnosticStatus
    from rclpy.duration import Duration

    from brace_control.nodes import topics
    reader = subprocess.Popen([sys.executable, '-c', SUBSCRIBER], env=dict(os.environ))
    try:
        rclpy.init()
        node = rclpy.create_node('bench_acks_writer')
        pub = node.create_publisher(DiagnosticStatus, topics.GOAL_STATUS, topics.GOAL_STATUS_QOS)
        end = time.monotonic() + 30
        while pub.get_subscription_count() < 1 and time.monotonic() < end:
            time.sleep(0.05)
        time.sleep(1.0)                          # past the reader's first acknowledgements
        waits = []
        for k in range(args.samples):
            msg = DiagnosticStatus()
            msg.message = f'sample {k}'
            pub.publish(msg)
            t = time.monotonic()
            acked = pub.wait_for_all_acked(Duration(seconds=10.0))
            waits.append((time.monotonic() - t, acked))
            time.sleep(0.37)                     # not in phase with a heartbeat period
        print(f'profile: {profile}')
        print('waits (s): ' + ', '.join(f'{w:.3f}' + ('' if ok else ' (not acked)') for w, ok in waits))
        node.destroy_node()
        rclpy.shutdown()
    finally:
        reader.kill()
        reader.wait()


if __name__ == '__main__':
    main()
