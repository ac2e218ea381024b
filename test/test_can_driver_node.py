"""can_driver_node with rclpy: services, joint_states, setpoint validation, diagnostics.

The node runs in-process with the simulated brace on its own virtual channel, brought to
active by :meth:`CanDriverNode.autostart` (configure + activate; the lifecycle itself is
tested in test_lifecycle.py).
"""
from __future__ import annotations

import itertools
import os
import time

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger

from brace_control.can import FaultKind
from brace_control.mechanisms import load_mechanism
from brace_control.nodes.can_driver_node import CanDriverNode, main
from ros_helpers import LUMBAR_YAML, RELIABLE_10

pytestmark = pytest.mark.ros
_ids = itertools.count()
_MECH = load_mechanism(LUMBAR_YAML)
Q_HOME = _MECH.inverse(_MECH.home_pose)          # homing method 35: IK(home_pose)


def call(ros, node, service, timeout=5.0):
    client = node.create_client(Trigger, service)
    ros.spin_until(client.service_is_ready, timeout, f'{service} available')
    future = client.call_async(Trigger.Request())
    ros.spin_until(future.done, timeout, f'{service} answered')
    return future.result()


@pytest.fixture
def driver(ros):
    node = ros.device_node(CanDriverNode, **{'can.channel': f'nodetest-{os.getpid()}-{next(_ids)}'})
    node.autostart()
    yield node
    node.shutdown()


def setpoint(names, q, node):
    msg = JointState()
    msg.header.stamp = node.get_clock().now().to_msg()
    msg.name = list(names)
    msg.position = [float(v) for v in q]
    return msg


def test_services_joint_states_and_setpoints(ros, driver):
    probe = ros.node('probe')
    states = ros.collect(probe, JointState, '/brace/joint_states')
    diags = ros.collect(probe, DiagnosticArray, '/diagnostics')
    pub = probe.create_publisher(JointState, '/brace/actuator_setpoint', RELIABLE_10)

    res = call(ros, probe, '/can_driver_node/enable')
    assert not res.success and 'home' in res.message            # says why
    res = call(ros, probe, '/can_driver_node/home')
    assert res.success, res.message
    res = call(ros, probe, '/can_driver_node/enable')
    assert res.success and 'OPERATION ENABLED' in res.message, res.message

    ros.spin_until(lambda: len(states) >= 3, 5.0, 'joint_states')
    js = states[-1]
    assert list(js.name) == ['a1', 'a2', 'a3']
    assert np.array(js.position) == pytest.approx(Q_HOME, abs=1e-6)
    assert len(js.effort) == 3 and all(abs(f) < 50.0 for f in js.effort)     # N

    # a short ramp lifting the ring 0.5 mm (names in another order than the YAML's)
    ros.wait_matched(pub)
    delta = _MECH.inverse(_MECH.home_pose + np.array([0.0, 0.0005, 0.0])) - Q_HOME
    target = Q_HOME + delta
    for k in range(1, 41):
        pub.publish(setpoint(['a3', 'a2', 'a1'], (Q_HOME + delta * k / 40)[::-1], probe))
        ros.spin_for(0.004)
    ros.spin_until(lambda: driver.accepted + driver.rejected >= 40, 10.0, 'setpoints processed')
    # a late delivery is not a rejection (staleness is judged by arrival in the master)
    assert driver.rejected == 0, driver.last_rejection


    def reached():      # the final setpoint again, freshly stamped, until the drives are there
        # and stay there: three joint states (20 ms at 100 Hz) at the target, not one caught
        # as the command passes through it (the stream's stop from 3 mm/s takes 9 um at a_max)
        pub.publish(setpoint(['a1', 'a2', 'a3'], target, probe))
        ros.spin_for(0.005)
        return len(states) >= 3 and all(np.allclose(js.position, target, rtol=0, atol=2e-6)
                                        for js in states[-3:])
    ros.spin_until(reached, 10.0, 'moved')
    ros.spin_for(0.1)                   # the stream stopped: the command decelerated and holds
    held = np.array(states[-1].position)
    assert held == pytest.approx(target, abs=1e-5)      # the stream's tracking settles within um

    # malformed setpoints: rejected with a reason, nothing sent
    before = driver.rejected
    bad = setpoint(['a1', 'a2', 'a3'], [target[0], float('nan'), target[2]], probe)
    pub.publish(bad)
    pub.publish(setpoint(['a1', 'a2'], target[:2], probe))
    ros.spin_until(lambda: driver.rejected >= before + 2, 3.0, 'rejections')
    assert 'lacks' in driver.last_rejection or 'not finite' in driver.last_rejection
    ros.spin_for(0.05)
    assert np.array(states[-1].position) == pytest.approx(held, abs=3e-7)      # nothing moved
    assert not driver.master.latched

    ros.spin_until(lambda: any(s.name.endswith('/drive/a2') for d in diags for s in d.status),
                   3.0, 'per-drive diagnostics')
    names = {s.name.rsplit('/', 1)[-1] for d in diags for s in d.status}
    assert {'a1', 'a2', 'a3', 'bus', 'cycle', 'safety'} <= names
    drive = next(s for d in diags for s in d.status if s.name.endswith('/drive/a2'))
    keys = {kv.key for kv in drive.values}
    assert {'nmt', 'state_402', 'last_emcy', 'heartbeat_age_s'} <= keys
    # the simulated brace's own count of its CPU (bench_stack's split of the cycle's process)
    cpu = [float(kv.value) for d in diags for s in d.status if s.name.endswith('/cycle')
           for kv in s.values if kv.key == 'simulator_cpu_s']
    assert cpu and cpu[-1] > 0.0

    for name in ('halt', 'recover', 'disable'):
        res = call(ros, probe, f'/can_driver_node/{name}')
        assert res.success, (name, res.message)


def test_platform_wrench_limit_stops_and_reports(ros, driver):
    """docs/safety.md §8: three legs each under the 250 N actuator limit, but together a
    platform force above safety.max_wrench (150 N): protective stop, in /diagnostics."""
    probe = ros.node('probe')
    diags = ros.collect(probe, DiagnosticArray, '/diagnostics')
    assert call(ros, probe, '/can_driver_node/home').success
    assert call(ros, probe, '/can_driver_node/enable').success
    for node_id in (1, 2, 3):
        driver.sim.faults.set_load_cell(node_id, 120.0)
    ros.spin_until(lambda: driver.master.supervisor.has(FaultKind.WRENCH_LIMIT), 2.0, 'wrench stop')
    ros.spin_until(lambda: any(s.name.endswith('/safety') and 'wrench' in s.message
                               for d in diags for s in d.status), 3.0, 'wrench in diagnostics')
    res = call(ros, probe, '/can_driver_node/recover')
    assert not res.success and 'wrench' in res.message                 # cause still there
    for node_id in (1, 2, 3):
        driver.sim.faults.set_load_cell(node_id, None)
    res = call(ros, probe, '/can_driver_node/recover')
    assert res.success, res.message


def test_executable_boots_and_exits_0_on_sigint(tmp_path):
    """``ros2 run brace_control can_driver_node``: configures itself (boots the simulated
    brace), Ctrl-C ends it cleanly (drives disabled, bus closed, exit code 0)."""
    import signal
    import subprocess
    import sys
    import time
    cmd = [sys.executable, '-c', 'import sys; from brace_control.nodes.can_driver_node import main; '
           'sys.exit(main())', '--ros-args', '--params-file', str(LUMBAR_YAML),
           '-p', f'can.channel:=proc-{os.getpid()}']
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            cwd=str(LUMBAR_YAML.parent.parent))
    out = []
    try:
        deadline = time.monotonic() + 20.0
        while time.monotonic() < deadline:
            line = proc.stdout.readline()
            out.append(line)
            if 'OPERATIONAL' in line or not line:
                break
        assert any('3 drives OPERATIONAL' in line for line in out), ''.join(out)
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=10.0) == 0, ''.join(out) + proc.stdout.read()
    finally:
        if proc.poll() is None:
            proc.kill()


def test_bad_parameter_exits_2_naming_it(capsys):
    code = main(['can_driver_node', '--ros-args', '--params-file', str(LUMBAR_YAML),
                 '-p', 'safety.force_limit:=-5.0'])
    assert code == 2              # a configuration error, as for every node (runner.EXIT_CONFIG)
    assert 'safety.force_limit' in capsys.readouterr().err


@pytest.mark.parametrize('name, value', [('safety.command_timeout', 0.0),
                                         ('safety.force_limit', -1.0),
                                         ('can.sync_rate_hz', 5000.0)])
def test_a_bad_safety_value_stops_start_up_naming_the_parameter(ros, name, value):
    from brace_control.config import ConfigError
    with pytest.raises(ConfigError, match=name.replace('.', r'\.')):
        ros.device_node(CanDriverNode, **{name: value})


def test_safety_limits_are_read_only_at_run_time(ros):
    from rclpy.parameter import Parameter
    node = ros.device_node(CanDriverNode)
    try:
        result = node.set_parameters([Parameter('safety.force_limit', value=1000.0)])[0]
        assert not result.successful and 'read-only' in result.reason
        assert node.get_parameter('safety.force_limit').value == 250.0    # the YAML's value
    finally:
        node.shutdown()


def test_a_dead_cycle_process_is_a_protective_stop_and_every_service_says_so(ros, driver):
    """The control cycle's process killed (can.cycle_process, the default): the driver's
    state turns to a protective stop naming it, ~/enable answers why instead of hanging, and
    the node still shuts down cleanly."""
    import signal

    from diagnostic_msgs.msg import DiagnosticStatus

    from brace_control.nodes import topics
    probe = ros.node('probe_dead_cycle')
    states = ros.collect(probe, DiagnosticStatus, topics.DRIVER_STATE, topics.LATCHED_QOS)
    assert call(ros, probe, '/can_driver_node/home').success
    pid = driver.master.pid
    os.kill(pid, signal.SIGKILL)
    ros.spin_until(lambda: any('control cycle process' in s.message and s.level == DiagnosticStatus.ERROR
                               for s in states), 5.0,
                   lambda: f'a protective stop on {topics.DRIVER_STATE}; got {[s.message for s in states]}')
    res = call(ros, probe, '/can_driver_node/enable', timeout=10.0)
    assert not res.success and 'control cycle process' in res.message, res.message
    driver.shutdown()
    assert driver.lifecycle_state == 'finalized'


def test_a_stuck_cycle_process_is_ended_and_every_service_says_so(ros, driver, monkeypatch):
    """The control cycle's process alive but silent (SIGSTOP here; a deadlock or a native call
    that never returns alike): after CYCLE_SILENT_S without a sample the driver ends it
    (SIGKILL: a child that woke later would command drives the node reports stopped), its
    state turns to a protective stop naming it, and a service called meanwhile answers why
    instead of waiting for good."""
    import signal
    import threading

    from diagnostic_msgs.msg import DiagnosticStatus

    from brace_control.can import DriverError, process
    from brace_control.nodes import topics
    monkeypatch.setattr(process, 'CYCLE_SILENT_S', 1.0)
    probe = ros.node('probe_stuck_cycle')
    states = ros.collect(probe, DiagnosticStatus, topics.DRIVER_STATE, topics.LATCHED_QOS)
    assert call(ros, probe, '/can_driver_node/home').success
    child = driver.master._proc
    os.kill(child.pid, signal.SIGSTOP)
    try:
        # a call that reaches the stuck child waits on it (in the node's thread), then answers
        answer = []

        def status():
            try:
                answer.append(driver.master.status())
            except DriverError as exc:
                answer.append(exc)
        worker = threading.Thread(target=status, daemon=True)
        worker.start()
        ros.spin_until(lambda: any('sent nothing' in s.message and s.level == DiagnosticStatus.ERROR
                                   for s in states), 5.0,
                       lambda: f'a protective stop on {topics.DRIVER_STATE}; got {[s.message for s in states]}')
        worker.join(timeout=2.0)
        assert not worker.is_alive(), 'the call waiting on the stuck child did not end'
        assert isinstance(answer[0], DriverError) and 'sent nothing' in str(answer[0]), answer
        ros.spin_until(lambda: child.poll() is not None, 5.0, 'the stuck child ended')
        assert child.returncode == -signal.SIGKILL
        res = call(ros, probe, '/can_driver_node/enable', timeout=10.0)
        assert not res.success and 'control cycle process' in res.message, res.message
    finally:
        if child.poll() is None:
            os.kill(child.pid, signal.SIGCONT)
    driver.shutdown()
    assert driver.lifecycle_state == 'finalized'


def test_a_hole_in_the_ground_truth_is_said_in_the_log(ros, driver, capfd, caplog):
    """The control cycle's process stopped for 1.5 s (SIGSTOP: a host that did not run it;
    below CYCLE_SILENT_S, so it lives on): the simulated world stood still, and the ground
    truth a recorder gets has a 1.5 s hole. Both sides say so in the log: the driver that the
    truths it published are that far apart, the cycle process link whose side the time was
    on. A reader that came 1.5 s after the one before is no such hole (it gets the newest).
    Oracle: the stamps of the truth received here, and the 1.5 s the test stopped it."""
    import signal

    from geometry_msgs.msg import PoseStamped

    from brace_control.nodes import topics
    probe = ros.node('probe_truth_hole')
    # a reader that leaves, and one that comes 1.5 s later, is no hole: it gets the newest
    first: list = []
    sub = probe.create_subscription(PoseStamped, topics.SIM_POSE, first.append, topics.truth_qos(100.0))
    ros.spin_until(lambda: len(first) > 10, 10.0, 'the ground truth')
    probe.destroy_subscription(sub)
    pose_pub = driver._truth_pubs[1]
    ros.spin_until(lambda: pose_pub.get_subscription_count() == 0, 10.0, 'the first reader gone')
    gone = time.monotonic()
    ros.spin_until(lambda: time.monotonic() > gone + 1.5, 5.0)      # the driver's timer runs on
    t_sub = time.time()
    got = ros.collect(probe, PoseStamped, topics.SIM_POSE, topics.truth_qos(100.0))
    ros.spin_until(lambda: len(got) > 10, 10.0, 'the ground truth')
    first_stamp = got[0].header.stamp.sec + 1e-9 * got[0].header.stamp.nanosec
    assert first_stamp > t_sub - 0.5, f'the new reader got truths {t_sub - first_stamp:.2f} s old first'
    child = driver.master._proc
    # 0.2 s unspun first: truths of before the stop wait in the driver, so the hole lies
    # between two truths of one tick, not at the first (run 1203 missed it there)
    time.sleep(0.2)
    os.kill(child.pid, signal.SIGSTOP)
    try:
        time.sleep(1.5)
    finally:
        os.kill(child.pid, signal.SIGCONT)
    n = len(got)
    ros.spin_until(lambda: len(got) > n + 20, 10.0, 'the ground truth after the stop')
    stamps = np.array([m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec for m in got])
    assert np.diff(stamps).max() > 1.4                   # the hole is in the truth itself
    err = capfd.readouterr().err
    said = [line for line in err.splitlines() if 'ground truth:' in line and 'between two truths' in line]
    assert len(said) == 1, err[-3000:]
    hole = float(said[0].split('ground truth: ')[1].split(' s')[0])
    assert hole == pytest.approx(np.diff(stamps).max(), abs=0.02), said
    why = [r.getMessage() for r in caplog.records if 'no snapshot from the control cycle' in r.getMessage()]
    assert len(why) == 1 and 'the cycle process did not run meanwhile' in why[0], why
    assert driver.master.faults == (), driver.master.faults


def test_a_control_cycle_closed_on_purpose_is_no_safety_error(ros, driver):
    """Between the driver closing its control cycle's process (its shutdown) and the node's own
    teardown, a diagnostics pass says the bus is closed (WARN), not that the process is gone
    (ERROR, which a report counts as a protective stop)."""
    from diagnostic_msgs.msg import DiagnosticStatus as Status

    from brace_control.can.process import MasterProcess
    m = driver.master
    assert isinstance(m, MasterProcess), type(m)          # can.cycle_process is the default
    m.shutdown()
    safety = [s for s in driver.diagnostics().status if s.name.endswith('/safety')]
    assert len(safety) == 1 and safety[0].level == Status.WARN, safety
    assert 'CAN bus closed' in safety[0].message, safety[0].message


def test_the_truth_topics_are_made_only_while_read(ros, driver):
    """``/brace/sim/*`` are volatile: with no reader nothing is made; a reader of one topic
    gets that one (its pose the simulator's true pose), the others stay unmade."""
    from geometry_msgs.msg import PoseStamped

    from brace_control.nodes import topics
    made = [0, 0, 0, 0]                  # joint states, pose, wrench, body pose
    for i, pub in enumerate(driver._truth_pubs):
        publish = pub.publish

        def counted(msg, i=i, publish=publish):
            made[i] += 1
            publish(msg)
        pub.publish = counted
    probe = ros.node('truth_probe')
    ros.spin_for(0.3)                    # six periods of sim.truth_rate_hz (20 Hz)
    assert made == [0, 0, 0, 0]
    poses = ros.collect(probe, PoseStamped, topics.SIM_POSE)
    ros.spin_until(lambda: len(poses) >= 2, 3.0, '/brace/sim/pose')
    assert made[1] >= 2 and made[0] == made[2] == made[3] == 0
    true = driver.sim.truth().pose
    got = np.array([poses[-1].pose.position.x, poses[-1].pose.position.y])
    np.testing.assert_allclose(got, true[:2], atol=1e-4)    # the ring at rest: the newest truth


def test_a_truth_publisher_that_falls_behind_publishes_the_truths_it_missed(ros, driver):
    """The cycle's process keeps sending snapshots while this node's executor does not run
    (a starved process: 1.2 s here, 1.5 s beside two busy loops in run 307's demo): the next
    tick publishes the truths it missed, each stamped with its own SYNC, ``sim.truth_rate_hz``
    (20 Hz) apart, not one sample and a hole: no gap between distinct stamps over 1.6 periods,
    their median one period."""
    from geometry_msgs.msg import PoseStamped
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    from brace_control.nodes import topics
    probe = ros.node('truth_probe')
    deep = QoSProfile(depth=200, reliability=ReliabilityPolicy.RELIABLE)
    poses = ros.collect(probe, PoseStamped, topics.SIM_POSE, deep)
    ros.spin_until(lambda: len(poses) >= 3, 3.0, '/brace/sim/pose')
    time.sleep(1.2)                                   # the executor stands still
    n = len(poses)
    ros.spin_until(lambda: len(poses) >= n + 20, 3.0, 'the missed truths')
    stamps = np.array(sorted({p.header.stamp.sec + p.header.stamp.nanosec * 1e-9 for p in poses}))
    gaps = np.diff(stamps)
    rate = 20.0
    assert gaps.max() < 1.6 / rate, gaps                # no hole: at most a tick late
    assert np.median(gaps) == pytest.approx(1.0 / rate, abs=0.006), gaps


def test_a_trunk_stream_sent_while_the_executor_stood_still_moves_the_trunk_without_a_step(ros, driver):
    """A patient streams its trunk's rest pose (``/brace/sim/body_rest``, 50 Hz, a 6 mm ramp
    over 1.18 s) while this node's executor stands still (a starved process): once it runs,
    the simulator plays the whole stream out by its stamps. The trunk's true pose
    (``/brace/sim/body_pose``) never moves faster than the ramp's rate times the play-out's
    catch-up (``REST_STREAM_CATCH_UP``), and it ends at the last sample. A reader that kept
    only the newest samples saw its first one 1 s into the ramp: a step of 5 mm."""
    from geometry_msgs.msg import PoseStamped
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    from brace_control.nodes import topics
    from brace_control.nodes.msgs import ns_to_stamp, pose_msg, stamp_to_sec
    from brace_control.sim.brace import REST_STREAM_CATCH_UP
    probe = ros.node('patient')
    pub = probe.create_publisher(PoseStamped, topics.SIM_BODY_REST, topics.STATE_QOS)
    bodies = ros.collect(probe, PoseStamped, topics.SIM_BODY_POSE,
                         QoSProfile(depth=200, reliability=ReliabilityPolicy.RELIABLE))
    ros.wait_matched(pub)
    ros.spin_until(lambda: len(bodies) >= 3, 3.0, '/brace/sim/body_pose')
    rest = np.array(driver.cfg['sim']['rest_pose'], dtype=float)
    rise, n, period = 0.006, 60, 0.02
    t0 = probe.get_clock().now().nanoseconds
    for k in range(n):                                # the executor stands still meanwhile
        pose = rest + np.array([0.0, rise * k / (n - 1), 0.0])
        pub.publish(pose_msg(pose, frame_id='brace_base', mechanism=None,
                             stamp=ns_to_stamp(t0 + round(k * period * 1e9))))
    end = rest[1] + rise
    ros.spin_until(lambda: abs(bodies[-1].pose.position.y - end) < 1e-7, 5.0,
                   lambda: f'the trunk at the stream\'s end ({end:.4f} m): at {bodies[-1].pose.position.y:.4f}')
    seen = sorted({(stamp_to_sec(b.header.stamp), b.pose.position.y) for b in bodies})
    t = np.array([s for s, _ in seen])
    y = np.array([v for _, v in seen])
    rate = np.abs(np.diff(y)) / np.diff(t)
    bound = REST_STREAM_CATCH_UP * rise / ((n - 1) * period)
    assert rate.max() <= 1.2 * bound, (f'the trunk moved at {rate.max() * 1e3:.1f} mm/s (the stream '
                                       f'{bound / REST_STREAM_CATCH_UP * 1e3:.2f} mm/s)')
    assert np.count_nonzero(np.diff(y) > 0) >= 10            # it went through the ramp
