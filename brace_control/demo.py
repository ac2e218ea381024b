"""``make demo``: the lumbar brace on the simulated CAN bus, end to end, told truthfully.

    python -m brace_control.demo --device lumbar_brace --out demo_output

(``--mode interaction``, ``make demo MODE=interaction``: a zero-torque and wrench-goal
session instead, :mod:`brace_control.demo_interaction`.)

1. builds the bundled exercise (:mod:`brace_control.exercise`) into ``OUT/exercise``;
2. brings the four nodes up with the simulated brace on the virtual bus, each node as
   its own process (:class:`brace_control.bringup.ProcessBringUp`; ``--in-process``: all
   in this process, :class:`~brace_control.bringup.BringUp`; either takes the CAN driver,
   a lifecycle node, through configure and activate), homes and enables the drives (the
   CAN driver's ``home`` / ``enable`` services);
3. records every brace topic a run publishes (:data:`RECORDED_TOPICS`: goals, planned
   pose and actuator trajectories, joint states, the estimate, wrench, goal, execution and
   driver status, ``/diagnostics`` and the simulator's truth ``/brace/sim/*``) to
   ``OUT/run.mcap`` while it replays the exercise onto ``/brace/pose_goal`` (a progress
   line on the terminal); a replay that did not deliver every goal fails the demo;
4. disables the drives, shuts down, and writes ``OUT/run.png`` and a summary
   (:mod:`brace_control.demo_report`): the estimated pose against the true one and the
   plan, actuator positions measured vs true, load cells against the static load of the
   planned path, the wrench measured vs true; goal outcomes from ``/brace/goal_status``,
   the largest estimate error, the peak load-cell force above the static load.

Exit code 0 only when every goal succeeded, no protective stop latched and the peak force
above the static load is below 10 N (rotary drives: 4 % of ``actuator.max_force``); the
three verdicts are printed. 1 otherwise, or on a failure on the way.
"""
from __future__ import annotations

import argparse
import math
import os
import shutil
import signal
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .demo_session import (RECORDED_TOPICS, end_session, find_service, home_and_enable, launch_recorder,
                           prepare_config, wait_recording)
from .nodes import topics
from .nodes.dds import use_discovery_profile
from .nodes.spin import BackgroundSpinner

__all__ = ['main', 'prepare_config', 'RECORDED_TOPICS']

class _Watch:
    """The demo's own node: measured pose / wrench and goal events for the progress line."""

    def __init__(self, node) -> None:
        from diagnostic_msgs.msg import DiagnosticStatus
        from geometry_msgs.msg import PoseStamped, WrenchStamped
        self.pose: np.ndarray | None = None
        self.wrench: np.ndarray | None = None
        self.events: list[tuple[str, str, str]] = []
        node.create_subscription(PoseStamped, topics.POSE, self._on_pose, topics.MEASURED_QOS)
        node.create_subscription(WrenchStamped, topics.WRENCH, self._on_wrench, topics.MEASURED_QOS)
        node.create_subscription(DiagnosticStatus, topics.GOAL_STATUS, self._on_status,
                                 topics.STATUS_QOS)

    def _on_pose(self, m) -> None:
        o = m.pose.orientation
        self.pose = np.array([m.pose.position.x, m.pose.position.y,
                              math.atan2(2 * (o.w * o.z + o.x * o.y), 1 - 2 * (o.y ** 2 + o.z ** 2))])

    def _on_wrench(self, m) -> None:
        self.wrench = np.array([m.wrench.force.x, m.wrench.force.y, m.wrench.torque.z])

    def _on_status(self, m) -> None:
        v = {kv.key: kv.value for kv in m.values}
        self.events.append((v.get('goal_id', '?'), v.get('state', m.message), v.get('reason', '')))

    def ended(self, state: str) -> int:
        return sum(1 for _, s, _ in self.events if s == state)


class _Progress:
    def __init__(self, watch: _Watch, goals) -> None:
        self.watch = watch
        self.goals = goals
        self.tty = sys.stdout.isatty()
        self._last = 0.0

    def __call__(self, t: float, duration: float) -> None:
        now = time.monotonic()
        if now - self._last < (0.2 if self.tty else 2.0) and t < duration:
            return
        self._last = now
        k = sum(1 for g in self.goals if g.t <= t + 1e-9)
        label = self.goals[k - 1].label if k else 'starting'
        pose, wrench = self.watch.pose, self.watch.wrench
        parts = [f'[{t:5.1f}/{duration:4.1f} s] goal {k}/{len(self.goals)} {label:26s}',
                 f'done {self.watch.ended("succeeded")} failed '
                 f'{self.watch.ended("aborted") + self.watch.ended("rejected")}']
        if pose is not None:
            parts.append(f'x={pose[0] * 1e3:+6.1f} mm y={pose[1] * 1e3:6.1f} mm '
                         f'th={math.degrees(pose[2]):+5.1f} deg')
        if wrench is not None:
            parts.append(f'F=({wrench[0]:+6.1f}, {wrench[1]:+6.1f}) N M={wrench[2]:+5.2f} N·m')
        line = ' | '.join(parts)
        print(('\r' + line) if self.tty else line, end='' if self.tty else '\n', flush=True)


#: Human (rehabilitation) pace: Fitts' law intercept of 2 s instead of the YAML's 0.2 s, so a
#: 15 mm shift or a 5 deg turn takes ~2.5 s. Fast reaches near the lumbar brace's
#: theta = 0 singularity amplify microns of actuator lag into millimetres of pose error
#: (at theta = 5 deg, 10 um on a2 moves x by 3.4 mm) and trip the tracking check.
DEMO_PARAMS = ('-p', 'trajectory.fitts_a:=2.0')


def run_demo(device: str, out: Path, *, rate: float = 1.0, settle: float = 3.0,
             processes: bool = False, extra_args: Sequence[str] = DEMO_PARAMS) -> int:
    """The demo; see the module docstring. Returns the exit code."""
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    from .bag import BagError, replay
    from .bringup import (BringUp, ProcessBringUp, wait_for_links,
                          wait_until_ready)
    from .exercise import build_exercise_bag

    out.mkdir(parents=True, exist_ok=True)
    for old in ('exercise', 'run.mcap', 'run.png'):
        p = out / old
        if p.is_dir():
            shutil.rmtree(p)
        elif p.exists():
            p.unlink()
    config, note = prepare_config(device, out)
    if note:
        print(f'note: {note}')
    bag, goals = build_exercise_bag(out / 'exercise', config, spacing=4.0)
    print(f'exercise: {len(goals)} goals over {goals[-1].t:.0f} s -> {bag}')

    stop = threading.Event()
    use_discovery_profile()
    rclpy.init(args=['brace-demo'], signal_handler_options=SignalHandlerOptions.NO)
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    bringup = None
    recorder = None
    failure = None
    node = rclpy.create_node('brace_demo')
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    BackgroundSpinner(executor, 'demo-executor').start()     # nodes/spin.py
    watch = _Watch(node)
    try:
        t0 = time.monotonic()
        if processes:
            bringup = ProcessBringUp(config, extra_args=extra_args).start()
        else:
            bringup = BringUp(config, sim=True, extra_args=extra_args).start()
        services = {}
        for what in ('home', 'enable'):
            name = find_service(node, what, 30.0)
            if name is None:
                raise RuntimeError(f'the CAN driver offers no {what!r} Trigger service')
            services[what] = name
        mode = 'as processes' if processes else 'in this process'
        print(f'bring-up: {len(bringup.names)} nodes + simulated brace {mode} in '
              f'{time.monotonic() - t0:.1f} s')
        recorder = launch_recorder(out / 'run.mcap', RECORDED_TOPICS)
        wait_recording(node, list(RECORDED_TOPICS), recorder)
        home_and_enable(node, services, executor)
        wait_for_links(node, timeout=30.0)     # the node processes have found each other
        wait_until_ready(node, timeout=30.0)   # ... each in its own discovery
        stats = replay(node, bag, rate=rate, wait_subscribers=1, wait_topics=[topics.POSE_GOAL],
                       stop=stop, progress=_Progress(watch, goals))
        print()
        if stop.is_set():
            raise RuntimeError('interrupted')
        if not stats.ok:
            raise RuntimeError('the exercise was not delivered: ' + '; '.join(stats.problems))
        # let the last motion finish (the last goal arrives at its bag time)
        deadline = time.monotonic() + settle + 5.0
        while time.monotonic() < deadline and not stop.is_set():
            if len([e for e in watch.events if e[1] != 'accepted']) >= len(goals):
                break
            time.sleep(0.1)
        time.sleep(0.5)
        print(f'replayed {stats.total} goals in {stats.duration_s:.1f} s (every one acknowledged)')
    except (RuntimeError, BagError) as exc:
        failure = str(exc)
    finally:
        failure = end_session(node, executor, bringup, recorder, processes=processes, failure=failure)
    if failure:
        print(f'demo failed: {failure}', file=sys.stderr)
        if not (out / 'run.mcap').exists():
            return 1
    return _report(device, config, out, goals, failed=failure is not None)


def _report(device: str, config: Path, out: Path, goals: Sequence[Any], *, failed: bool) -> int:
    """Read ``OUT/run.mcap`` back: ``run.png``, the summary, the three verdicts; the exit code."""
    from .demo_report import excess_limit, plot_run, read_run, static_load, summarise
    from .sim import SimulatedBrace
    run = read_run(out / 'run.mcap', config=config)
    load = static_load(run, SimulatedBrace(config, start=False))
    limit, _ = excess_limit(config)
    summary = summarise(run, goals_expected=len(goals), load=load, limit=limit)
    plot_run(run, out / 'run.png', title=f'{device}: exercise on the simulated bus', load=load)
    print(f'recorded {out / "run.mcap"}, plotted {out / "run.png"}')
    label = {round(g.t * 1e9): g.label for g in goals}
    for line in summary.lines():
        print('  ' + line)
    for g in summary.goals:
        if g.state != 'succeeded':
            print(f'  goal {g.goal_id} ({label.get(g.stamp, "?")}) {g.state}: {g.reason}')
    if failed or not summary.ok:
        _explain()
        return 1
    return 0


def _explain() -> None:
    """What else a failed run should be read with (the summary above has the goals' reasons,
    the protective stops and the SYNC overruns): the machine's load. A heartbeat lost or a
    planning budget exceeded on a busy machine is the host's, not the brace's."""
    load1, load5, _ = os.getloadavg()
    print(f'  load average {load1:.1f} (5 min {load5:.1f}) on {os.cpu_count()} CPUs')


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog='brace-demo', description=__doc__.split('\n\n')[0])
    ap.add_argument('--device', default='lumbar_brace', help='device YAML or name in config/')
    ap.add_argument('--out', default='demo_output', help='output directory')
    ap.add_argument('--rate', type=float, default=1.0, help='replay speed factor')
    ap.add_argument('--mode', choices=('position', 'interaction'), default='position',
                    help='position: the bundled exercise (this module); interaction: a scripted '
                         'zero-torque and wrench-goal session (brace_control.demo_interaction)')
    ap.add_argument('--quick', action='store_true',
                    help='interaction mode: a shorter session (one period of sway, 1.5 s per wrench goal)')
    ap.add_argument('--in-process', action='store_true',
                    help='all nodes and the simulator in this process (default: each node as '
                         'its own process; one process needs ~1 core of Python under one GIL, '
                         'see bench/RESULTS.md "End to end")')
    args, ros = ap.parse_known_args(argv)
    extra = list(DEMO_PARAMS) + (ros[ros.index('--ros-args') + 1:] if '--ros-args' in ros else [])
    if ros and '--ros-args' not in ros:
        ap.error(f'unrecognized arguments: {ros}')
    if args.mode == 'interaction':
        from .demo_interaction import run_interaction_demo
        return run_interaction_demo(args.device, Path(args.out), processes=not args.in_process,
                                    extra_args=extra, quick=args.quick)
    return run_demo(args.device, Path(args.out), rate=args.rate, processes=not args.in_process,
                    extra_args=extra)


if __name__ == '__main__':
    raise SystemExit(main())
