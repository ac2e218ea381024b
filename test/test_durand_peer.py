"""Our CiA 301/402 master against a peer built on someone else's CANopen stack (issue 23).

Three :class:`durand_drive.DurandDrive` (``durand``: SDO server, NMT, heartbeat, SYNC-driven
PDOs, none of it ours) stand in for the lumbar brace's drives; the master reads their
dictionary from the EDS durand exports, plans the boot against it, boots, homes, enables and
runs a CSP motion. The oracle is each durand drive's own true position (its encoder counts
of the actuator it moves), not what the master reports. A drive that rejects a mapping its
EDS calls mappable stops the boot with the abort code and the object named.
"""
from __future__ import annotations

import copy
import itertools
import os
import time

import numpy as np
import pytest

from brace_control.can import ActuatorTrajectory, BraceMaster, DriverInitializationError, MasterConfig
from brace_control.config import DeviceConfig, load_device_config
from brace_control.mechanisms import mechanism_from_config
from durand_drive import DurandDrive

CFG = load_device_config('config/lumbar_brace.yaml')
MECH = mechanism_from_config(CFG)
CPM = 8192 / 0.001
_ids = itertools.count()


def _config(eds, **can) -> DeviceConfig:
    """The lumbar brace on durand drives. Three durand nodes answer SYNC from three receive
    threads of this test process, sharing one lock: on a loaded host one of them can lag the
    others by tens of SYNCs, which a real drive never does. The supervision's time bounds are
    widened for that (staleness, heartbeats); what is checked is the protocol and the motion."""
    params = copy.deepcopy(dict(CFG))
    params['can'].update(eds=str(eds), sim=False, load_cell_object='0x2100:1',
                         heartbeat_consumer_ms=1000, master_heartbeat_ms=250, **can)
    params['safety']['stale_periods'] = 250
    return DeviceConfig(params, CFG.path)


def _drives(channel, **kw) -> list[DurandDrive]:
    q0 = MECH.inverse(MECH.home_pose)
    return [DurandDrive(channel, node_id=i + 1, position_m=float(q0[i]), counts_per_m=CPM, **kw)
            for i in range(3)]


def _min_jerk(q0, q1, duration, n=41) -> ActuatorTrajectory:
    t = np.linspace(0.0, duration, n)
    s = t / duration
    p = 10 * s ** 3 - 15 * s ** 4 + 6 * s ** 5
    v = (30 * s ** 2 - 60 * s ** 3 + 30 * s ** 4) / duration
    a = (60 * s - 180 * s ** 2 + 120 * s ** 3) / duration ** 2
    d = np.asarray(q1) - np.asarray(q0)
    return ActuatorTrajectory(t, np.asarray(q0) + np.outer(p, d), np.outer(v, d), np.outer(a, d))


def _wait(cond, timeout, what):
    end = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > end:
            pytest.fail(f'{what} not reached within {timeout} s')
        time.sleep(0.005)


def test_master_boots_homes_and_moves_durand_drives(tmp_path):
    channel = f'durand-peer-{os.getpid()}-{next(_ids)}'
    drives = _drives(channel)
    eds = drives[0].write_eds(tmp_path / 'durand_drive.eds')
    master = BraceMaster(MasterConfig.from_device_config(_config(eds), channel=channel))
    try:
        for d in drives:
            d.start()
        master.boot()
        master.home()
        master.enable()
        q0 = MECH.inverse(MECH.home_pose)
        # the drives homed to IK(home): 6064h = 607Ch (their own counts, not ours)
        for i, d in enumerate(drives):
            assert abs(d.position_counts - round(q0[i] * CPM)) <= 1, (i, d.position_counts)
        q1 = MECH.inverse(MECH.home_pose + np.array([0.0, 0.008, 0.02]))
        assert master.execute(_min_jerk(q0, q1, 1.0), start=time.perf_counter() + 0.05, tag=7) is None
        _wait(lambda: not master.moving, 5.0, 'the motion to end')
        events = [(e.kind, e.reason) for e in master.execution_events() if e.tag == 7]
        assert events[-1][0] == 'finished', (events, master.supervisor.summary())
        # the oracle: each durand drive's own true position (its first-order loop settles)
        _wait(lambda: all(abs(d.position_m - q) < 2e-6 for d, q in zip(drives, q1)), 2.0,
              'the durand actuators at the end of the motion')
        assert not master.supervisor.latched, master.supervisor.summary()
        # the load cell the master reads is durand's 2100h:1 (a spring about the start)
        forces = master.feedback().force
        np.testing.assert_allclose(forces, [d.force_n for d in drives], atol=0.02)
        assert np.all(np.abs(forces) > 1.0)
    finally:
        master.shutdown()
        for d in drives:
            d.stop()


def test_a_mapping_the_peer_rejects_stops_the_boot_naming_the_object_and_code(tmp_path):
    channel = f'durand-peer-{os.getpid()}-{next(_ids)}'
    drives = _drives(channel)
    drives[1] = DurandDrive(channel, node_id=2, counts_per_m=CPM, reject_mapping=[(0x2100, 1)])
    eds = drives[0].write_eds(tmp_path / 'durand_drive.eds')
    master = BraceMaster(MasterConfig.from_device_config(_config(eds), channel=channel))
    try:
        for d in drives:
            d.start()
        before = [d.position_m for d in drives]
        with pytest.raises(DriverInitializationError) as err:
            master.boot()
        text = str(err.value)
        code = f'0x{DurandDrive.REJECT_ABORT_CODE:08X}'
        assert 'node 2' in text and '1A00h:3' in text and '2100h:1' in text, text
        assert code in text, (code, text)
        # nothing moved, nothing enabled
        assert [d.position_m for d in drives] == before
        assert all(d.state.name != 'OPERATION_ENABLED' for d in drives)
    finally:
        master.shutdown()
        for d in drives:
            d.stop()
