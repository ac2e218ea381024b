"""The simulated patient: a trunk that sways by itself, moves on request and has limited effort.

Oracles written here from the model's definition (docs/interaction.md, "The simulated
patient"): the trunk's wanted pose ``rest(t) = rest + A sin(2 pi f t + phi)``; the tissue
``W_body = -K (pose - rest(t)) - D (pose_dot - rest_dot(t))`` with K, D read from the YAML
by this test; the patient's effort ``K (rest - pose)`` saturated per axis at
``sim.patient_max_wrench``. The brace's drives hold their power-up lengths (no master:
the SYNC handler is called directly, ``dt`` = 2 ms), so the ring stays (within the legs'
compliance) at the home pose while the trunk moves.
"""
from __future__ import annotations

import copy
import math
import os
from pathlib import Path

import numpy as np
import pytest

from brace_control.config import ConfigError, DeviceConfig, load_device_config
from brace_control.sim import SimulatedBrace
from brace_control.sim.brace import REST_STREAM_CATCH_UP, REST_STREAM_DELAY_S, REST_STREAM_MAX_LEAD_S

ROOT = Path(__file__).resolve().parent.parent
CFG = ROOT / 'config' / 'lumbar_brace.yaml'
DT = 0.002


def lumbar(**sim: object) -> tuple[SimulatedBrace, dict]:
    params = copy.deepcopy(dict(load_device_config(CFG)))
    params['sim'].update(sim)
    params['sim']['load_cell_noise'] = 0.0
    brace = SimulatedBrace(DeviceConfig(params, CFG.resolve()), channel='unused', start=False)
    return brace, params


def run(brace: SimulatedBrace, n: int) -> None:
    for _ in range(n):
        brace.host.sync_handler(DT)


def test_sway_moves_the_trunk_and_a_held_ring_feels_the_tissue() -> None:
    amp = [0.0, 0.010, math.radians(5.0)]
    f_hz = 0.5
    brace, params = lumbar(sway_amplitude=amp, sway_frequency_hz=f_hz, sway_phase=[0.0, 0.0, 1.0])
    K = np.reshape(params['sim']['stiffness'], (3, 3))
    D = np.reshape(params['sim']['damping'], (3, 3))
    rest0 = np.asarray(params['sim']['rest_pose'])
    w = 2 * math.pi * f_hz
    peak = np.zeros(3)
    for k in range(1, 401):                       # 0.8 s: past the first peak of both axes
        run(brace, 1)
        tr = brace.truth()
        t = k * DT
        assert tr.time == pytest.approx(t)
        phase = w * t + np.array([0.0, 0.0, 1.0])
        body = rest0 + np.array(amp) * np.sin(phase)
        body_dot = np.array(amp) * w * np.cos(phase)
        np.testing.assert_allclose(tr.body_pose, body, atol=1e-12)
        np.testing.assert_allclose(tr.body_rate, body_dot, atol=1e-12)
        expected = -K @ (tr.pose - body) - D @ (tr.pose_dot - body_dot)
        np.testing.assert_allclose(tr.body_wrench, expected, rtol=1e-3, atol=1e-3)
        # quasi-static: the brace holds the ring against it
        np.testing.assert_allclose(tr.brace_wrench, -tr.body_wrench, atol=1e-3)
        # the legs hold the ring (laterally soft: the legs are nearly parallel, ARCHITECTURE.md)
        assert np.all(np.abs(tr.pose - rest0) < [1e-3, 1e-4, 1e-3])
        peak = np.maximum(peak, np.abs(tr.body_wrench))
    # the held ring feels the whole sway: K_y 10 mm = 40 N, K_theta 5 deg = 3.5 N·m
    assert peak[1] > 0.95 * K[1, 1] * amp[1]
    assert peak[2] > 0.95 * K[2, 2] * amp[2]


def test_no_sway_by_default_and_the_rest_pose_moves_on_request() -> None:
    brace, params = lumbar()
    K = np.reshape(params['sim']['stiffness'], (3, 3))
    run(brace, 5)
    tr = brace.truth()
    np.testing.assert_allclose(tr.body_pose, params['sim']['rest_pose'])
    np.testing.assert_allclose(tr.body_rate, 0.0)
    assert np.max(np.abs(tr.body_wrench)) < 1e-3
    target = np.asarray(params['sim']['rest_pose']) + [0.0, 0.004, 0.01]
    brace.set_rest_pose(target)
    run(brace, 250)                               # 0.5 s: the lateral mode (D_x / K_x) settles
    tr = brace.truth()
    np.testing.assert_allclose(tr.body_pose, target)
    np.testing.assert_allclose(tr.body_wrench, K @ (target - tr.pose), rtol=1e-3, atol=1e-3)


def test_a_streamed_rest_pose_is_a_moving_trunk_not_a_staircase() -> None:
    """/brace/sim/body_rest at 50 Hz along a line at 30 mm/s: from the second sample on the
    trunk moves at that rate (no 20 ms steps), each sample reached REST_STREAM_DELAY_S after
    it was sent, and the held ring feels the tissue on that motion: ``-K (pose - rest(t)) -
    D (pose_dot - v)`` with ``rest(t)`` the line, that much late. A jump within the stream is
    a ramp over one interval, never beyond the sample."""
    brace, params = lumbar()
    K = np.reshape(params['sim']['stiffness'], (3, 3))
    D = np.reshape(params['sim']['damping'], (3, 3))
    rest0 = np.asarray(params['sim']['rest_pose'])
    v = np.array([0.0, 0.030, 0.0])
    delay = REST_STREAM_DELAY_S
    run(brace, 5)
    t_set = brace.truth().time
    seen = []
    for k in range(25):                           # 0.5 s: a sample every 10 SYNCs
        brace.set_rest_pose(rest0 + v * (brace.truth().time - t_set))
        for _ in range(10):
            run(brace, 1)
            seen.append(brace.truth())
    for _ in range(round(delay / DT) + 30):       # the stream ends: the trunk stops at the last
        run(brace, 1)                             # sample (0.48 s along the line)
        seen.append(brace.truth())
    on_line = [tr for tr in seen if t_set + 0.02 + delay + 1e-9 < tr.time <= t_set + 0.48 + delay]
    assert len(on_line) > 200
    for tr in on_line:
        line = rest0 + v * (tr.time - t_set - delay)
        np.testing.assert_allclose(tr.body_pose, line, atol=1e-9)
        np.testing.assert_allclose(tr.body_rate, v, atol=1e-9)
        expected = -K @ (tr.pose - line) - D @ (tr.pose_dot - v)
        np.testing.assert_allclose(tr.body_wrench, expected, rtol=1e-3, atol=1e-3)
    tr = brace.truth()
    np.testing.assert_allclose(tr.body_pose, rest0 + v * 0.48, atol=1e-9)
    np.testing.assert_allclose(tr.body_rate, 0.0)
    # a jump of 10 mm within the stream: a ramp over the interval, ending at the sample
    brace.set_rest_pose(rest0 + v * 0.48)
    run(brace, 10)
    jump = rest0 + v * 0.48 + [0.0, 0.010, 0.0]
    brace.set_rest_pose(jump)
    poses = []
    for _ in range(round(delay / DT) + 15):
        run(brace, 1)
        poses.append(brace.truth().body_pose[1])
    assert max(poses) <= jump[1] + 1e-12 and poses[-1] == pytest.approx(jump[1], abs=1e-12)
    assert np.all(np.diff(poses) <= 0.010 / 10 + 1e-12)          # 1 mm per SYNC at most


def test_the_patient_effort_saturates_at_patient_max_wrench() -> None:
    limit = [0.0, 60.0, 1.0]                      # x unlimited, 60 N vertical, 1 N·m
    brace, params = lumbar(patient_max_wrench=limit)
    K = np.reshape(params['sim']['stiffness'], (3, 3))
    rest = np.asarray(params['sim']['rest_pose'])
    brace.set_rest_pose(rest + [0.002, 0.05, 0.05])     # the patient wants 5 cm up, 2.9 deg
    run(brace, 250)
    tr = brace.truth()
    free = K @ (brace.rest_pose - tr.pose)                # what an unlimited patient would do
    assert free[1] > 190.0 and free[2] > 1.9              # 200 N, 2 N·m wanted
    assert tr.body_wrench[1] == pytest.approx(60.0, abs=1e-3)
    assert tr.body_wrench[2] == pytest.approx(1.0, abs=1e-3)
    assert tr.body_wrench[0] == pytest.approx(free[0], rel=1e-3, abs=1e-3)   # unlimited axis
    # pushed the other way, the patient yields at the same effort
    brace.set_rest_pose(rest - [0.0, 0.05, 0.05])
    run(brace, 250)
    tr = brace.truth()
    assert tr.body_wrench[1] == pytest.approx(-60.0, abs=1e-3)
    assert tr.body_wrench[2] == pytest.approx(-1.0, abs=1e-3)


def test_a_rigid_device_feels_the_sway_and_the_effort_limit() -> None:
    cfg = ROOT / 'config' / 'shoulder.yaml'
    params = copy.deepcopy(dict(load_device_config(cfg)))
    dof = 3
    K = np.reshape(params['sim']['stiffness'], (dof, dof))
    params['sim'].update(sway_amplitude=[0.0, 0.0, 0.1], sway_frequency_hz=0.25,
                         patient_max_wrench=[0.0, 0.0, 0.5 * K[2, 2] * 0.1])
    params['sim']['load_cell_noise'] = 0.0
    brace = SimulatedBrace(DeviceConfig(params, cfg.resolve()), channel='unused', start=False)
    run(brace, 500)                              # 1 s: sin(pi/2) = 1, the trunk at +0.1 rad
    tr = brace.truth()
    assert tr.body_pose[2] - np.asarray(params['sim']['rest_pose'])[2] == pytest.approx(0.1, rel=1e-6)
    assert tr.body_wrench[2] == pytest.approx(0.5 * K[2, 2] * 0.1, rel=1e-6)


@pytest.mark.parametrize('key, value, words', [
    ('sway_amplitude', [0.0, 0.01], r'sim\.sway_amplitude: expected 3 finite numbers'),
    ('sway_amplitude', [0.0, float('nan'), 0.0], r"sim\.sway_amplitude.*non-finite"),
    ('sway_frequency_hz', -0.2, r'sim\.sway_frequency_hz'),
    ('patient_max_wrench', [10.0, -1.0, 1.0], r"sim\.patient_max_wrench.*out of range"),
])
def test_bad_patient_parameters_are_config_errors(key: str, value: object, words: str) -> None:
    with pytest.raises(ConfigError, match=words):
        lumbar(**{key: value})


def test_set_sway_starts_the_sine_now() -> None:
    brace, params = lumbar()
    run(brace, 100)                               # 0.2 s without sway
    brace.set_sway([0.0, 0.004, 0.0], 1.0)
    rest = np.asarray(params['sim']['rest_pose'])
    for k in range(1, 101):
        run(brace, 1)
        tr = brace.truth()
        expected = rest[1] + 0.004 * math.sin(2 * math.pi * k * DT)
        assert tr.body_pose[1] == pytest.approx(expected, abs=1e-12)
    with pytest.raises(ValueError, match='3 finite amplitudes'):
        brace.set_sway([0.0, 0.01], 1.0)


def test_a_streamed_rest_pose_takes_its_rate_from_the_stamps_not_the_arrivals() -> None:
    """Samples 20 ms apart by their stamps that arrive bunched (two in one 4 ms window, as a
    DDS hop may deliver them): the trunk moves at the stamps' rate, 30 mm/s exactly, each
    sample reached REST_STREAM_DELAY_S after its stamp (on the clock of the first). A sample
    later than that: the trunk goes on from where it is, at the stamps' rate. Samples whose
    stamps run ahead of the simulated clock: each reached at most REST_STREAM_MAX_LEAD_S
    after its arrival."""
    brace, params = lumbar()
    rest0 = np.asarray(params['sim']['rest_pose'])
    v = np.array([0.0, 0.030, 0.0])
    delay = REST_STREAM_DELAY_S
    run(brace, 5)
    t0 = brace.truth().time
    brace.set_rest_pose(rest0, stamp=100.0)
    run(brace, 10)
    brace.set_rest_pose(rest0 + v * 0.02, stamp=100.02)
    run(brace, 8)                                 # the next arrives 16 ms later ...
    brace.set_rest_pose(rest0 + v * 0.04, stamp=100.04)
    run(brace, 2)
    brace.set_rest_pose(rest0 + v * 0.06, stamp=100.06)   # ... and this one 4 ms after it
    seen = []
    while brace.truth().time < t0 + delay + 0.08:
        run(brace, 1)
        seen.append(brace.truth())
    on_line = [tr for tr in seen if t0 + delay + 0.02 + 1e-9 < tr.time <= t0 + delay + 0.06]
    assert len(on_line) >= 19                     # 40 ms of SYNCs
    for tr in on_line:
        np.testing.assert_allclose(tr.body_rate, v, atol=1e-9)
        np.testing.assert_allclose(tr.body_pose, rest0 + v * (tr.time - t0 - delay), atol=1e-9)
    np.testing.assert_allclose(brace.truth().body_pose, rest0 + v * 0.06, atol=1e-12)
    # late: the next sample arrives after the instant it was due; from the last one, held,
    # over its stamped interval
    brace.set_rest_pose(rest0 + v * 0.08, stamp=100.08)
    t_late = brace.truth().time
    rates = []
    for _ in range(15):
        run(brace, 1)
        rates.append(brace.truth().body_rate[1])
    # (the truth of a SYNC is the state at its end: 9 SYNCs on the way, the 10th arrives)
    assert rates[:9] == pytest.approx([v[1]] * 9, abs=1e-9) and rates[9:] == [0.0] * 6
    np.testing.assert_allclose(brace.truth().body_pose, rest0 + v * 0.08, atol=1e-12)
    assert brace.truth().time - t_late > 0.02 - 1e-9
    # stamps 20 ms apart arriving once per 2 ms SYNC (4 s of samples in 0.4 s): the trunk
    # lags their arrival by at most REST_STREAM_MAX_LEAD_S, never more and more
    slow = v / 10
    for k in range(1, 201):
        brace.set_rest_pose(rest0 + v * 0.08 + slow * 0.02 * k, stamp=100.08 + 0.02 * k)
        run(brace, 1)
    t_last = brace.truth().time - DT
    while brace.truth().body_rate[1] != 0.0:
        run(brace, 1)
    np.testing.assert_allclose(brace.truth().body_pose, rest0 + v * 0.08 + slow * 4.0, atol=1e-12)
    assert REST_STREAM_MAX_LEAD_S - 0.1 < brace.truth().time - t_last <= REST_STREAM_MAX_LEAD_S + DT + 1e-9

def test_a_stream_ahead_of_the_simulated_clock_catches_up_at_a_bounded_rate() -> None:
    """Stamps 20 ms apart arriving every 16 ms of simulated time (SYNCs skipped: the
    simulated clock runs 20 % slow): the trunk never moves faster than REST_STREAM_CATCH_UP
    times the stamps' rate, and it stays within REST_STREAM_DELAY_S + 50 ms + one interval
    of the samples instead of lagging more and more."""
    brace, params = lumbar()
    rest0 = np.asarray(params['sim']['rest_pose'])
    v = np.array([0.0, 0.030, 0.0])
    run(brace, 5)
    rates, lags = [], []
    for k in range(150):                          # 3 s of stamps in 2.4 s
        brace.set_rest_pose(rest0 + v * 0.02 * k, stamp=50.0 + 0.02 * k)
        for _ in range(8):
            run(brace, 1)
            tr = brace.truth()
            rates.append(tr.body_rate[1])
            lags.append((rest0[1] + v[1] * 0.02 * k - tr.body_pose[1]) / v[1])    # s behind
    assert max(rates) <= REST_STREAM_CATCH_UP * v[1] + 1e-9
    assert max(rates) > 1.2 * v[1]                # it did catch up
    # behind the newest sample: the playout lead (at most 50 ms beyond the delay) plus the
    # segment in play (up to two intervals), and not growing
    assert max(lags[-400:]) <= REST_STREAM_DELAY_S + 0.05 + 0.04 + 1e-6
    assert max(lags[-400:]) <= max(lags[-800:-400]) + 1e-6


def test_the_trunk_path_is_read_while_a_stream_adds_to_it() -> None:
    """The physics reads the trunk's path (``body_at``, the SYNC's thread) while a stream
    adds samples to it (``set_rest_pose``, the subscriber's thread): no read fails because
    the path changed under it. The interpreter switches threads every microsecond here, so
    a read that iterates the path while it grows meets a change within a few hundred tries;
    it did in a full test run ("deque mutated during iteration": one SYNC without physics)."""
    import sys
    import threading
    brace, params = lumbar()
    # two threads that never sleep for ~3 s: at the default niceness, not the -10 that
    # test/conftest.py gave this thread when the brace was made (at SCHED_FIFO, as it once
    # was, they took a core from every other process of the machine for that long)
    os.setpriority(os.PRIO_PROCESS, 0, 0)
    rest0 = np.asarray(params['sim']['rest_pose'])
    errors: list[BaseException] = []
    stop = threading.Event()

    def stream() -> None:                       # a 100 Hz trunk stream on the simulated clock
        k = 0
        while not stop.is_set():
            k += 1
            brace.set_rest_pose(rest0 + np.array([0.0, 1e-5 * (k % 100), 0.0]), stamp=0.002 * k)

    interval = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)
    streamer = threading.Thread(target=stream, daemon=True)
    streamer.start()
    try:
        for i in range(20000):
            try:
                brace.body_at(brace.truth().time + 0.002 * (i % 50))
                if i % 10 == 0:
                    run(brace, 1)                 # the simulated clock on (the path pruned)
            except RuntimeError as exc:
                errors.append(exc)
                break
    finally:
        stop.set()
        streamer.join(timeout=5.0)
        sys.setswitchinterval(interval)
    assert not errors, errors
