"""CPU at rest, per thread: the CAN driver process (simulated brace inside) and kinetics_node.

    ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST python bench/bench_rest_cpu.py [--seconds 10]
        [--config config/lumbar_brace.yaml] [--kinetics] [-p can.sync_spin_us:=0 ...]

**Driver**: a :class:`~brace_control.nodes.can_driver_node.CanDriverNode` with ``can.sim``
(the simulated brace in the same process, as ``brace-bringup --processes`` runs it), its
executor (``make_executor``: the events executor) spun in a thread of its own, homed,
enabled, then left at rest for 2 s. Over ``--seconds``: the CPU (user + system, from
``/proc/self/task``) of each thread in % of one core, and the process's. The threads:

* ``sim Notifier``: the simulated brace's receive thread; on each SYNC the drives' motion
  step, the physics, the TPDOs (python-can ``virtual`` sends);
* ``master Notifier``: canopen's receive thread (TPDO1 samples, heartbeats);
* ``SYNC``: the master's cycle (monitors, command, RPDOs when they change, SYNC);
* ``executor``: the node's callbacks (joint states 100 Hz with the wrench check, driver
  events 50 Hz, the simulator's truth 20 Hz, diagnostics 1 Hz);
* ``sim timer``: heartbeats.

**Kinetics** (``--kinetics``): a :class:`~brace_control.nodes.kinetics_node.KineticsNode` in
this process, fed by a driver process (this script, driver part only) publishing
``/brace/joint_states`` at 100 Hz: the process's CPU over ``--seconds``, and per joint state.

**Floor** (``--floor``): the same, with a node that only takes each joint state and
publishes a constant ``PoseStamped``, ``PoseWithCovarianceStamped`` and ``WrenchStamped``:
what receiving and publishing cost (rclpy, DDS), the part of kinetics_node's CPU that its
own computation cannot lower.

``-p name:=value`` overrides a parameter of the device file (both processes), e.g.
``can.sync_spin_us:=0 can.gil_switch_interval_us:=0``. Prints Markdown rows for
bench/RESULTS.md.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))
os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
os.environ.setdefault('ROS_DOMAIN_ID', str(150 + os.getpid() % 50))

from _timing import machine_line  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
TICK = os.sysconf('SC_CLK_TCK')


def thread_cpu() -> dict[int, float]:
    """CPU seconds (user + system) of each thread of this process, by native thread id."""
    out: dict[int, float] = {}
    for tid in os.listdir('/proc/self/task'):
        try:
            with open(f'/proc/self/task/{tid}/stat') as f:
                fields = f.read().rsplit(')', 1)[1].split()
        except OSError:
            continue                                  # the thread ended meanwhile
        out[int(tid)] = (int(fields[11]) + int(fields[12])) / TICK
    return out


def process_cpu() -> float:
    t = os.times()
    return t.user + t.system


def ros_args(config: str, params: list[str], channel: str) -> list[str]:
    # the per-thread view needs the master and the simulator in this process (with the
    # default can.cycle_process they run in a child: bench_stack.py splits that one)
    args = ['--ros-args', '--params-file', config, '-p', f'can.channel:={channel}',
            '-p', 'can.cycle_process:=false']
    for p in params:
        args += ['-p', p]
    return args


def spin_in_thread(node) -> tuple[threading.Event, threading.Thread]:
    from brace_control.nodes.runner import make_executor
    executor = make_executor(node.context)
    executor.add_node(node)
    stop = threading.Event()

    def spin() -> None:
        while not stop.is_set():
            executor.spin_once(timeout_sec=0.1)
    thread = threading.Thread(target=spin, name='executor', daemon=True)
    thread.start()
    return stop, thread


def driver(config: str, params: list[str], seconds: float, report: bool) -> None:
    """The driver at rest for ``seconds`` (after homing, enabling and 2 s to settle)."""
    import rclpy
    from brace_control.nodes.can_driver_node import CanDriverNode
    rclpy.init(args=['bench_rest_cpu'] + ros_args(config, params, f'restcpu{os.getpid()}'))
    node = CanDriverNode()
    node.autostart()                # lifecycle: configure + activate
    stop, thread = spin_in_thread(node)
    node.master.home()
    node.master.enable()
    time.sleep(2.0)
    names = {threading.get_native_id(): 'main (bench)', thread.native_id: 'executor'}
    for reader in node.sim.host._notifier._readers:
        names[reader.native_id] = 'sim Notifier'
    for reader in node.master.network.notifier._readers:
        names[reader.native_id] = 'master Notifier'
    for t in threading.enumerate():
        if t.name.startswith('sim-timer'):
            names[t.native_id] = 'sim timer'
        elif t.name == 'brace-can-sync':
            names[t.native_id] = 'SYNC'
    before, p0 = thread_cpu(), process_cpu()
    time.sleep(seconds)
    after, p1 = thread_cpu(), process_cpu()
    timing = node.master.status().timing
    if report:
        print(f'driver process: {100 * (p1 - p0) / seconds:.1f} % of one core over {seconds:g} s '
              f'({timing.cycles} SYNC cycles, {timing.overruns} overruns so far)')
        print('| thread | % of one core |\n|---|---|')
        shares: dict[str, float] = {}
        for t in after:                   # threads without a name here: rclpy's and DDS's
            name = names.get(t, 'other (rclpy, DDS)')
            shares[name] = shares.get(name, 0.0) + 100 * (after[t] - before.get(t, 0.0)) / seconds
        for name, share in sorted(shares.items(), key=lambda kv: -kv[1]):
            print(f'| {name} | {share:.1f} |')
        print(f'| **process** | **{100 * (p1 - p0) / seconds:.1f}** |')
    stop.set()
    thread.join()
    node.master.disable()
    node.shutdown()
    node.destroy_node()
    rclpy.shutdown()


def floor_node():
    """A node that takes /brace/joint_states and publishes three constant messages."""
    from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped, WrenchStamped
    from rclpy.node import Node
    from sensor_msgs.msg import JointState
    from brace_control.nodes import topics

    class Floor(Node):
        def __init__(self) -> None:
            super().__init__('kinetics_floor')
            self.received = 0
            self._pubs = [(self.create_publisher(t, topic, topics.STATE_QOS), t()) for t, topic in (
                (PoseStamped, topics.POSE), (PoseWithCovarianceStamped, topics.POSE_WITH_COVARIANCE),
                (WrenchStamped, topics.WRENCH))]
            self.create_subscription(JointState, topics.JOINT_STATES, self._on, topics.STATE_QOS)

        def _on(self, msg: JointState) -> None:
            self.received += 1
            for pub, out in self._pubs:
                pub.publish(out)
    return Floor()


def kinetics(config: str, params: list[str], seconds: float, *, floor: bool = False) -> None:
    """kinetics_node (or the floor node) here, fed by a driver process at rest."""
    feeder = subprocess.Popen(
        [sys.executable, __file__, '--driver-only', '--seconds', str(seconds + 10), '--config', config]
        + [a for p in params for a in ('-p', p)], stdout=subprocess.DEVNULL)
    import rclpy
    from brace_control.nodes.kinetics_node import KineticsNode
    rclpy.init(args=['bench_rest_cpu'] + ros_args(config, params, 'unused'))
    node = floor_node() if floor else KineticsNode()
    stop, thread = spin_in_thread(node)
    deadline = time.monotonic() + 60.0
    while node.received < 200 and time.monotonic() < deadline:
        time.sleep(0.1)
    if node.received < 200:
        raise SystemExit('kinetics: no joint states from the driver process within 60 s')
    time.sleep(1.0)
    r0, p0 = node.received, process_cpu()
    time.sleep(seconds)
    r1, p1 = node.received, process_cpu()
    n = max(1, r1 - r0)
    print(f'{"floor" if floor else "kinetics_node"} process: {100 * (p1 - p0) / seconds:.1f} % of one core over {seconds:g} s, '
          f'{n / seconds:.0f} joint states/s, {(p1 - p0) / n * 1e6:.0f} us of CPU per joint state')
    stop.set()
    thread.join()
    node.destroy_node()
    rclpy.shutdown()
    feeder.wait()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--seconds', type=float, default=10.0)
    ap.add_argument('--config', default=str(ROOT / 'config' / 'lumbar_brace.yaml'))
    ap.add_argument('--kinetics', action='store_true', help='also kinetics_node, fed by a driver process')
    ap.add_argument('--floor', action='store_true',
                    help='also a node that only receives the joint states and publishes constants')
    ap.add_argument('--driver-only', action='store_true', help=argparse.SUPPRESS)
    ap.add_argument('-p', dest='params', action='append', default=[], metavar='NAME:=VALUE')
    args = ap.parse_args()
    if args.driver_only:
        driver(args.config, args.params, args.seconds, report=False)
        return
    print(machine_line())
    print(f'parameters: {" ".join(args.params) or "the device file"}')
    driver(args.config, args.params, args.seconds, report=True)
    if args.kinetics:
        kinetics(args.config, args.params, args.seconds)
    if args.floor:
        kinetics(args.config, args.params, args.seconds, floor=True)


if __name__ == '__main__':
    main()
