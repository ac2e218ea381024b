"""SYNC timing of the CAN master with three simulated drives in the same process.

    python bench/bench_can.py [--seconds 8] [--rates 500 1000] [--switch-interval-us 0]

For each rate, in alternating rounds (so both see the same background load of a shared
machine): the floor — the same absolute-deadline loop (sleep, then spin) with an empty
body, in this process, with nothing else running — and the master (SYNC + 3 RPDO1 per
cycle, 3 simulated drives answering with TPDO1, a 200 Hz setpoint stream moving the
brace) for the same time. Reports period error |measured − nominal| p50 /
p99 / max, overruns (missed deadlines), frames/s and bus load at 1 Mbit/s (worst-case
bit stuffing, both directions). Target (issue 4): p99 within 1.5x the floor, overruns
<= 0.1 %.
"""
from __future__ import annotations

import argparse
import math
import platform
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from brace_control.can import BraceMaster  # noqa: E402
from brace_control.can.cycle import set_thread_priority  # noqa: E402
from brace_control.can.timing import PeriodStats, run_periodic  # noqa: E402
from brace_control.config import load_device_config  # noqa: E402
from brace_control.mechanisms import mechanism_from_config  # noqa: E402
from brace_control.sim import SimulatedBrace  # noqa: E402


def floor(rate: float, seconds: float, spin_s: float, priority: int) -> PeriodStats:
    """The bare loop, in its own thread with the SYNC thread's scheduling."""
    stats = PeriodStats(1.0 / rate, window=int(rate * seconds) + 10)

    def run() -> None:
        set_thread_priority(priority)
        run_periodic(1.0 / rate, lambda k, t: None, threading.Event(), stats=stats,
                     spin_s=spin_s, max_cycles=int(rate * seconds))
    th = threading.Thread(target=run)
    th.start()
    th.join()
    return stats


def master_run(rate: float, seconds: float, channel: str, spin_s: float,
               priority: int) -> tuple[PeriodStats, dict]:
    cfg = load_device_config('config/lumbar_brace.yaml')
    cfg['can'] = dict(cfg['can'], sync_rate_hz=rate)
    mech = mechanism_from_config(cfg)
    home = np.asarray(mech.home_pose, float)
    sim = SimulatedBrace(cfg, channel=channel)
    master = BraceMaster.from_device_config(cfg, channel=channel, spin_s=spin_s,
                                            thread_priority=priority)
    master.cycle.stats = PeriodStats(1.0 / rate, window=int(rate * seconds) + 10)
    stop = threading.Event()
    costs: list[float] = []
    body = master.cycle.cycle

    def timed_cycle(k: int, t: float) -> None:        # work per cycle (SYNC + RPDOs + monitors)
        t0 = time.perf_counter()
        body(k, t)
        costs.append(time.perf_counter() - t0)
    master.cycle.cycle = timed_cycle                       # type: ignore[method-assign]

    def stream() -> None:             # 200 Hz setpoints: ring lifts ±3 mm at 0.25 Hz
        t0 = time.perf_counter()
        while not stop.is_set():
            t = time.perf_counter() - t0
            pose = home + np.array([0.0, 0.003 * math.sin(2 * math.pi * 0.25 * t), 0.0])
            master.set_targets(mech.inverse(pose))
            time.sleep(0.005)

    try:
        master.boot()
        master.home()
        master.enable()
        th = threading.Thread(target=stream, daemon=True)
        th.start()
        time.sleep(0.5)                                   # warm-up
        master.stats.reset()
        tr = master.traffic
        f0, b0 = tr.rx_frames + tr.tx_frames, tr.rx_bits + tr.tx_bits
        t0 = time.perf_counter()
        time.sleep(seconds)
        dt = time.perf_counter() - t0
        frames = tr.rx_frames + tr.tx_frames - f0
        bits = tr.rx_bits + tr.tx_bits - b0
        stop.set()
        th.join()
        faults = master.supervisor.summary()
        cost = np.array(costs[-int(rate * seconds):]) if costs else np.zeros(1)
        extra = {'frames_per_s': frames / dt, 'load': bits / dt / master.config.bitrate,
                 'faults': faults, 'cost_p50': float(np.percentile(cost, 50)),
                 'cost_p99': float(np.percentile(cost, 99))}
        return master.stats, extra
    finally:
        stop.set()
        master.shutdown()
        sim.shutdown()


@dataclass
class Pooled:
    """Period errors and overruns pooled over the rounds of one configuration."""

    errors: list = field(default_factory=list)
    cycles: int = 0
    overruns: int = 0

    def add(self, stats: PeriodStats) -> None:
        self.errors.append(stats.samples())
        self.cycles += stats.cycles
        self.overruns += stats.overruns

    def p(self, q: float) -> float:
        return float(np.percentile(np.concatenate(self.errors), q))

    def row(self) -> str:
        e = np.concatenate(self.errors)
        return (f'p50 {np.percentile(e, 50) * 1e6:6.2f} us  p99 {np.percentile(e, 99) * 1e6:7.1f} us  '
                f'max {e.max() * 1e6:7.1f} us  overruns {self.overruns}/{self.cycles} '
                f'({100 * self.overruns / max(1, self.cycles):.3f} %)')


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('--seconds', type=float, default=12.0, help='per configuration, split in rounds')
    ap.add_argument('--rounds', type=int, default=4, help='alternating floor / master rounds')
    ap.add_argument('--rates', type=float, nargs='+', default=[500.0, 1000.0])
    ap.add_argument('--spin-us', type=float, default=300.0, help='busy-wait before each deadline')
    ap.add_argument('--priority', type=int, default=0, help='SCHED_FIFO priority (0: normal)')
    ap.add_argument('--switch-interval-us', type=float, default=200.0,
                    help="sys.setswitchinterval, as can_driver_node does (can.gil_switch_interval_us); "
                         "0: keep Python's 5000 us")
    args = ap.parse_args()
    if args.switch_interval_us > 0:
        sys.setswitchinterval(args.switch_interval_us * 1e-6)
    print(f'python {platform.python_version()} on {platform.machine()}, '
          f'GIL switch interval {sys.getswitchinterval() * 1e6:.0f} us, spin {args.spin_us:.0f} us, '
          f'SCHED_FIFO {args.priority or "off"}')
    for rate in args.rates:
        fl, ms = Pooled(), Pooled()
        extras = []
        chunk = args.seconds / args.rounds
        for r in range(args.rounds):        # alternate: both see the same background load
            fl.add(floor(rate, chunk, args.spin_us * 1e-6, args.priority))
            stats, extra = master_run(rate, chunk, f'bench-{int(rate)}-{r}', args.spin_us * 1e-6,
                                      args.priority)
            ms.add(stats)
            extras.append(extra)
        print(f'{rate:6.0f} Hz floor : {fl.row()}')
        print(f'{rate:6.0f} Hz master: {ms.row()}  ratio p99 {ms.p(99) / fl.p(99):.2f}')
        fps = np.mean([e['frames_per_s'] for e in extras])
        load = np.mean([e['load'] for e in extras])
        faults = '; '.join(sorted({e['faults'] for e in extras}))
        print(f'{"":9} bus   : {fps:.0f} frames/s, load {100 * load:.1f} % of 1 Mbit/s; cycle work '
              f'p50 {np.median([e["cost_p50"] for e in extras]) * 1e6:.0f} us p99 '
              f'{np.max([e["cost_p99"] for e in extras]) * 1e6:.0f} us; faults: {faults}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
