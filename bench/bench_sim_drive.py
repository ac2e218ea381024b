"""Cost of one simulated CSP drive per SYNC (it shares the CAN driver's process at 500 Hz).

    python bench/bench_sim_drive.py [--syncs 20000] [--rate 500] [--bandwidth 30]

One :class:`~brace_control.sim.drive.SimulatedDrive` (config/lumbar_drive.eds, the lumbar
actuator), homed and in CSP, tracks a 5 mm, 1 Hz sine fed as the master feeds it: per
SYNC an RPDO1 (controlword + target one period ahead) and an RPDO2 (60B1h velocity
offset) through :meth:`on_frame`, then the SYNC. Timed per call with ``perf_counter``:

* ``on_frame`` x 2: receiving the two RPDOs (latched until the SYNC);
* ``on_sync(phase='motion')``: the position loop over the period (sub-steps, limits,
  following-error check) — the part this issue changed;
* ``on_sync(phase='comm')``: TPDO1 packed and sent (to a no-op), RPDOs applied, the next
  reference segment started.

A :class:`~brace_control.sim.brace.SimulatedBrace` calls both phases for each of its
drives, with its physics in between (not timed here).
"""
from __future__ import annotations

import argparse
import math
import struct
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _timing import machine_line, summary_us  # noqa: E402

from brace_control.sim.drive import DriveLimits, SimulatedDrive  # noqa: E402

EDS = Path(__file__).resolve().parent.parent / 'config' / 'lumbar_drive.eds'
CPM = 8192 / 0.001


def enabled_drive(bandwidth_hz: float, period_s: float) -> tuple[SimulatedDrive, int]:
    """A drive homed at 0.39 m, CSP, OPERATION ENABLED, NMT OPERATIONAL; its 6064h."""
    drive = SimulatedDrive(1, EDS, limits=DriveLimits(), initial_length_m=0.39,
                           send=lambda cob, data: None, bandwidth_hz=bandwidth_hz)
    drive.power_on()

    def sdo(index: int, sub: int, fmt: str, value: int) -> None:
        drive.set_data(index, sub, struct.pack('<' + fmt, value), check_writable=True)

    us = round(period_s * 1e6)
    sdo(0x1006, 0, 'I', us)
    sdo(0x60C2, 1, 'B', us // 1000 if us % 1000 == 0 and us < 256000 else 255)
    sdo(0x607C, 0, 'i', round(0.39 * CPM))
    sdo(0x6060, 0, 'b', 6)
    for cw in (0x06, 0x07, 0x0F, 0x1F, 0x0F):
        sdo(0x6040, 0, 'H', cw)
    sdo(0x6060, 0, 'b', 8)
    drive.on_frame(0x000, b'\x01\x01', 0.0)          # NMT start
    return drive, drive.read_od(0x6064)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--syncs', type=int, default=20000)
    ap.add_argument('--rate', type=float, default=500.0, help='SYNC rate (Hz)')
    ap.add_argument('--bandwidth', type=float, default=30.0, help='position loop (Hz)')
    args = ap.parse_args()
    period = 1.0 / args.rate
    drive, pos0 = enabled_drive(args.bandwidth, period)
    clock = time.perf_counter
    frames, motion, comm = [], [], []
    amp, w = 0.005, 2.0 * math.pi
    for k in range(args.syncs):
        t = (k + 2) * period       # SYNC k + 1 is at (k + 1) T: the target is for one T later
        p, v = amp * math.sin(w * t), amp * w * math.cos(w * t)
        f1 = struct.pack('<Hi', 0x0F, pos0 + round(p * CPM))
        f2 = struct.pack('<i', round(v * CPM))
        t0 = clock()
        drive.on_frame(0x201, f1, 0.0)
        drive.on_frame(0x301, f2, 0.0)
        t1 = clock()
        drive.on_sync(period, phase='motion')
        t2 = clock()
        drive.on_sync(period, phase='comm')
        t3 = clock()
        frames.append((t1 - t0) * 1e6)
        motion.append((t2 - t1) * 1e6)
        comm.append((t3 - t2) * 1e6)
    err = abs(drive.read_od(0x6064) - pos0 - round(amp * math.sin(w * args.syncs * period) * CPM))
    n_sub = max(1, math.ceil(period * drive.kp / 0.2))
    print(machine_line())
    print(f'{args.syncs} SYNCs at {args.rate:g} Hz, position loop {args.bandwidth:g} Hz '
          f'({n_sub} sub-steps per SYNC); tracking error at the end {err} counts')
    warm = slice(len(motion) // 10, None)
    for name, xs in (('on_frame x 2 (RPDO1 + RPDO2)', frames), ('on_sync motion', motion),
                     ('on_sync comm (TPDO1, RPDOs)', comm),
                     ('total per SYNC', [a + b + c for a, b, c in zip(frames, motion, comm)])):
        print(f'{name:30s} {summary_us(xs[warm])}')


if __name__ == '__main__':
    main()
