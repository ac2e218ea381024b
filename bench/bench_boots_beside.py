"""A running lumbar brace (enabled, at rest, its control cycle in a process of its own) while
other stacks boot beside it, two at a time: does it latch a protective stop?

On a two-core host, a test run's workers start stacks while others run. The cycle's process
runs at SCHED_FIFO ``can.cycle_priority``; start-up work (the simulator's and the master's
construction, the boot's dictionary checks and SDO configuration) is CPU for up to a second.
Run at SCHED_FIFO, two boots held both cores against the running stack's receive thread (the
same priority) and a false "heartbeat lost" / "no TPDO1 from any drive" stop latched (test
runs 711 and 803). ``process.start_up_work`` runs that work one real-time priority below.

    ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST .venv/bin/python bench/bench_boots_beside.py [rounds]

Prints, per run, how many rounds (two boots each) the running stack went through, and the
stop it latched if any. SCHED_FIFO needs the privilege (root, or CAP_SYS_NICE): without it
the processes run at their niceness and the comparison says nothing.
"""
from __future__ import annotations

import itertools
import os
import sys
import threading
import time

from _timing import machine_line

from brace_control.can import MasterConfig
from brace_control.can.process import MasterProcess
from brace_control.config import load_device_config
from brace_control.mechanisms import mechanism_from_config

CFG = load_device_config('lumbar_brace')
MECH = mechanism_from_config(CFG)
_ids = itertools.count()


def _config() -> MasterConfig:
    return MasterConfig.from_device_config(CFG, mechanism=MECH, channel=f'boots-{os.getpid()}-{next(_ids)}')


def _boot_one() -> None:
    m = MasterProcess(CFG, _config())
    try:
        m.boot()
    finally:
        m.shutdown()


def main(rounds: int) -> None:
    print(machine_line())
    running = MasterProcess(CFG, _config())
    try:
        running.boot()
        running.home()
        running.enable()
        print(f'running stack: pid {running.pid}, scheduler '
              f'{"SCHED_FIFO" if os.sched_getscheduler(running.pid) == os.SCHED_FIFO else "normal"}')
        t0 = time.monotonic()
        for r in range(1, rounds + 1):
            boots = [threading.Thread(target=_boot_one) for _ in range(2)]
            for t in boots:
                t.start()
            for t in boots:
                t.join()
            if running.faults:
                print(f'round {r}: protective stop: ' + '; '.join(f.describe()[:100] for f in running.faults[:2]))
                break
        print(f'{r} rounds ({2 * r} boots) in {time.monotonic() - t0:.1f} s; running stack {running.state.value}')
    finally:
        running.shutdown()


if __name__ == '__main__':
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 25)
