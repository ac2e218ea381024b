"""The admittance loop's delay on the simulated lumbar brace: body step -> command reacts.

    ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST python bench/bench_interaction_delay.py [--steps 6]
        [--config config/lumbar_brace.yaml] [--step-mm 3]

The whole stack in this process (:class:`~brace_control.bringup.BringUp`, the simulated
brace), homed, enabled, zero-torque mode started (``/interaction_node/start``). Then the
patient's trunk steps (``SimulatedBrace.set_rest_pose``, ``--step-mm`` vertically, up and
down alternately, 1.5 s apart). The body is a spring on the massless ring: the load cells
change at the first SYNC after the step. Recorded: every command the driver's executor
produces (``PathExecutor.step``, perf_counter). The **delay** is the time from the step to
the first command that departs from the one before the step by more than ``--threshold-um``
of actuator length, minus the time the admittance itself (equation (2) with the device's
``M``, ``D``, fed the step's wrench at once) needs to move the actuators that far: what is
left is the transport delay of the measured wrench to the command (the loop's ``T`` without
the RPDO -> drive part, which is two SYNC periods on any path: the target sent before SYNC
``k`` is latched at ``k`` and reached by the interpolating drive at ``k + 1``).

Prints one row per step and the median / spread, for docs/interaction.md and
bench/RESULTS.md.
"""
from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))
os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
os.environ.setdefault('ROS_DOMAIN_ID', str(100 + os.getpid() % 50))

import numpy as np  # noqa: E402

from _timing import machine_line  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent


def admittance_time_to(dx: float, e: float, M: float, D: float) -> float:
    """Time (s) for ``M a + D v = e`` from rest to travel ``dx``: ``x(t) = (e / D) (t - tau (1 -
    exp(-t / tau)))``, ``tau = M / D`` (bisection)."""
    tau, v = M / D, e / D
    lo, hi = 0.0, 10.0
    for _ in range(80):
        t = 0.5 * (lo + hi)
        x = v * (t - tau * (1.0 - math.exp(-t / tau)))
        lo, hi = (t, hi) if x < dx else (lo, t)
    return hi


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--config', default=str(ROOT / 'config' / 'lumbar_brace.yaml'))
    ap.add_argument('--steps', type=int, default=6)
    ap.add_argument('--step-mm', type=float, default=3.0)
    ap.add_argument('--threshold-um', type=float, default=5.0)
    args = ap.parse_args()

    import rclpy
    from rclpy.context import Context

    from brace_control.bringup import BringUp
    from brace_control.demo import prepare_config
    from brace_control.mechanisms import mechanism_from_config

    out = Path(tempfile.mkdtemp(prefix='delay'))
    path, _ = prepare_config(args.config, out)
    ctx = Context()
    rclpy.init(context=ctx)
    b = BringUp(path, context=ctx, extra_args=['-p', f'can.channel:=delay{os.getpid()}',
                                               '-p', 'can.sync_spin_us:=0']).start()
    rows = []
    try:
        for what in ('home', 'enable'):
            ok, msg = b.call(f'/can_driver_node/{what}', timeout=15)
            assert ok, f'{what}: {msg}'
        driver = b.node('can_driver_node')
        sim, ex = driver.sim, driver.master.executor
        cfg = b.config
        mech = mechanism_from_config(cfg)
        log: list[tuple[float, np.ndarray]] = []
        lock = threading.Lock()
        step = ex.step

        def recording_step(t: float):
            q, v = step(t)
            with lock:
                log.append((time.perf_counter(), q))
            return q, v
        ex.step = recording_step
        time.sleep(1.0)
        ok, msg = b.call('/interaction_node/start', timeout=5)
        assert ok, msg
        time.sleep(1.5)
        inter = cfg['interaction']
        M, D = float(inter['mass'][1]), float(inter['damping'][1])
        K = float(np.reshape(cfg['sim']['stiffness'], (3, 3))[1, 1])
        rest = np.asarray(sim.rest_pose, dtype=float)
        period = 1.0 / float(cfg['can']['sync_rate_hz'])
        for k in range(args.steps):
            sign = 1.0 if k % 2 == 0 else -1.0
            new = rest + np.array([0.0, sign * args.step_mm * 1e-3, 0.0])
            with lock:
                q0 = log[-1][1].copy()
            t0 = time.perf_counter()
            sim.set_rest_pose(new)
            time.sleep(1.5)
            with lock:
                after = [(t, q) for t, q in log if t > t0]
            moved = [t for t, q in after if np.max(np.abs(q - q0)) > args.threshold_um * 1e-6]
            if not moved:
                rows.append(math.nan)
                continue
            # the admittance's own time to move the legs that far: the pose step that moves
            # the most-moving leg by the threshold, from dq = J dx along y
            J = np.asarray(mech.jacobian(mech.forward_nearest(q0, mech.home_pose)), dtype=float)
            dy = args.threshold_um * 1e-6 / float(np.max(np.abs(J[:, 1])))
            own = admittance_time_to(dy, K * args.step_mm * 1e-3, M, D)
            total = moved[0] - t0
            rows.append(total - own)
            print(f'step {k}: {sign * args.step_mm:+.1f} mm: command departs after {total * 1e3:.1f} ms, '
                  f'admittance alone {own * 1e3:.1f} ms -> transport {(total - own) * 1e3:.1f} ms')
            rest = new
        b.call('/interaction_node/stop', timeout=5)
    finally:
        b.shutdown()
        rclpy.shutdown(context=ctx)
    good = [r for r in rows if math.isfinite(r)]
    if good:
        print(f'\ntransport delay (wrench -> command), {len(good)} steps: median '
              f'{statistics.median(good) * 1e3:.1f} ms, min {min(good) * 1e3:.1f}, max '
              f'{max(good) * 1e3:.1f} ms; + 2 SYNC periods ({2 * period * 1e3:.0f} ms) to the drive')
    print(machine_line())
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
