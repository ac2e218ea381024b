"""Frame log of a live run, and its replay through python-can's LogReader + MessageSync."""
from __future__ import annotations

import itertools
import os
import time

import can
import numpy as np
import pytest

from brace_control.can import BraceMaster
from brace_control.can.framelog import BusMonitor, open_frame_log, read_frames, replay
from brace_control.can.framelog import main as framelog_main
from brace_control.can.units import scaling_from_config
from brace_control.config import load_device_config
from brace_control.sim import SimulatedBrace

CFG = load_device_config('config/lumbar_brace.yaml')
_ids = itertools.count()


@pytest.mark.parametrize('suffix', ['.blf', '.asc', '.log'])
def test_recorded_log_replays_to_the_same_result(tmp_path, suffix, capsys):
    channel = f'canlog-{os.getpid()}-{next(_ids)}'
    path = tmp_path / f'run{suffix}'
    sim = SimulatedBrace(CFG, channel=channel)
    master = BraceMaster.from_device_config(CFG, channel=channel, frame_log=str(path))
    try:
        master.boot()
        master.home()
        master.enable()
        q0 = master.feedback().position.copy()
        for k in range(60):                               # 0.3 s at 200 Hz, +0.5 mm
            master.set_targets(q0 + 0.0005 * (k + 1) / 60)
            time.sleep(0.005)
        target = q0 + 0.0005
        deadline = time.perf_counter() + 1.0
        # the stream holds its last setpoint (a stream that stops decelerates where it is)
        while not np.allclose(master.feedback().position, target, rtol=0, atol=2e-6):
            assert time.perf_counter() < deadline, 'drives did not reach the targets'
            master.set_targets(target)
            time.sleep(0.005)
        sim.faults.send_emcy(2, 0x4210)                   # a warning EMCY in the record
        deadline = time.perf_counter() + 1.0
        while not master.status().drives[1].last_emcy:
            assert time.perf_counter() < deadline, 'EMCY not seen'
            time.sleep(0.002)
        live_emcy = master.status().drives[1].last_emcy
    finally:
        master.shutdown()
        sim.shutdown()
    # the last TPDO1 the master decoded: the log's writer sat on the same Notifier
    live = master.feedback()
    scaling = scaling_from_config(CFG)

    # 1. the file decodes to what the master saw
    offline = BusMonitor([1, 2, 3], scaling).feed(read_frames(path))
    assert offline.syncs > 100
    # in bus order, each at its send time: canopen's own frames too (SDO requests, NMT; they
    # once carried python-can's 0.0, which the writers put at the log's first frame's time)
    frames = list(read_frames(path))
    assert any(m.arbitration_id == 0 for m in frames) and any(0x601 <= m.arbitration_id <= 0x603 for m in frames)
    late = [(k, f'{m.arbitration_id:03X}h', round(frames[k - 1].timestamp - m.timestamp, 3))
            for k, m in enumerate(frames) if k and m.timestamp < frames[k - 1].timestamp - 0.1]
    assert not late, f'frames stamped before the one logged ahead of them: {late[:5]}'
    # 2. replayed onto a bus with the recorded timing, a passive listener gets the same
    rx_channel = f'{channel}-replay'
    tx = can.Bus(interface='virtual', channel=rx_channel)
    rx = can.Bus(interface='virtual', channel=rx_channel)
    monitor = BusMonitor([1, 2, 3], scaling)
    notifier = can.Notifier(rx, [monitor])
    try:
        t0 = time.perf_counter()
        sent = replay(path, tx, realtime=True)
        elapsed = time.perf_counter() - t0
        deadline = time.perf_counter() + 2.0
        while monitor.frames < sent and time.perf_counter() < deadline:
            time.sleep(0.01)
    finally:
        notifier.stop()
        tx.shutdown()
        rx.shutdown()
    assert monitor.frames == sent
    duration = list(read_frames(path))[-1].timestamp - next(iter(read_frames(path))).timestamp
    assert elapsed == pytest.approx(duration, rel=0.2, abs=0.1)          # MessageSync timing
    for rec in (offline, monitor):
        pos = np.array([rec.drives[i].position for i in (1, 2, 3)])
        force = np.array([rec.drives[i].force for i in (1, 2, 3)])
        assert pos == pytest.approx(live.position, abs=1e-9)
        assert force == pytest.approx(live.force, abs=1e-9)
        assert [c for c, _ in rec.drives[2].emcy][:1] == [0x4210]
        assert rec.drives[2].emcy[0][1] == 'excess temperature device'
    assert live_emcy.startswith('4210h')
    # the command-line summary a user attaches to a bug report
    assert framelog_main([str(path), '--config', 'config/lumbar_brace.yaml']) == 0
    out = capsys.readouterr().out
    assert 'node 2:' in out and '4210h excess temperature device' in out


def test_frame_log_suffix_is_checked(tmp_path):
    with pytest.raises(ValueError, match='.blf'):
        open_frame_log(tmp_path / 'x.txt')
