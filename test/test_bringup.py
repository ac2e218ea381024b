"""Bring-up: nodes in one process (MultiThreadedExecutor) or as processes; clean shutdown."""
from __future__ import annotations

import ast
import os
import signal
import subprocess
import sys
import time

import pytest
import rclpy
from rclpy.context import Context
from sensor_msgs.msg import JointState

from brace_control.bringup import BringUp, find_executable, node_class
from brace_control.nodes.ik_node import IkNode
from brace_control.nodes.msgs import pose_msg
from brace_control.nodes.spin import BackgroundSpinner
from ros_helpers import LUMBAR_YAML, REPO, RELIABLE_10


MY_NODES = ['ik_node', 'kinetics_node']


def test_launch_file_is_valid_python_with_every_node():
    src = (REPO / 'launch' / 'brace.launch.py').read_text()
    tree = ast.parse(src)
    assert any(isinstance(n, ast.FunctionDef) and n.name == 'generate_launch_description'
               for n in tree.body)
    # the nodes come from the one list (brace_control.nodes.NODE_NAMES), as bring-up's do
    imported = {a.name for n in tree.body if isinstance(n, ast.ImportFrom) and n.module == 'brace_control.nodes'
                for a in n.names}
    assert {'NODE_NAMES', 'DRIVER_NODE'} <= imported, imported
    assert 'for name in NODES' in src
    # the driver is a launch_ros LifecycleNode that launch (not the executable) takes to active
    for needed in ('LifecycleNode(', "'--manual-lifecycle'", 'TRANSITION_CONFIGURE',
                   'TRANSITION_ACTIVATE', "goal_state='inactive'", "'manual_lifecycle'"):
        assert needed in src, needed


@pytest.mark.ros
@pytest.mark.parametrize('manual', [False, True], ids=['automatic', 'manual-lifecycle'])
def test_in_process_bringup_takes_the_driver_to_active_unless_manual(manual):
    ctx = Context()
    rclpy.init(context=ctx)
    try:
        b = BringUp(LUMBAR_YAML, nodes=['can_driver_node'], context=ctx, manual_lifecycle=manual,
                    extra_args=['-p', f'can.channel:=bringup-{os.getpid()}-{int(manual)}']).start()
        try:
            driver = b.node('can_driver_node')
            assert driver.lifecycle_state == ('unconfigured' if manual else 'active')
            assert (driver.master is None) == manual
            ok, msg = b.call('/can_driver_node/home', timeout=10)
            assert ok != manual and (not manual or 'unconfigured' in msg), msg
        finally:
            b.shutdown()
        assert driver.lifecycle_state == 'finalized' and driver.master is None
    finally:
        rclpy.shutdown(context=ctx)


def test_node_class_finds_the_node_of_a_module():
    assert node_class('ik_node') is IkNode


def test_find_executable_falls_back_to_the_module(monkeypatch):
    monkeypatch.delenv('AMENT_PREFIX_PATH', raising=False)
    cmd = find_executable('ik_node')
    assert cmd[0].endswith('ik_node') or 'brace_control.nodes.ik_node' in cmd[-1]


@pytest.mark.ros
def test_in_process_bringup_carries_a_setpoint_and_shuts_down():
    ctx = Context()
    rclpy.init(context=ctx)
    try:
        b = BringUp(LUMBAR_YAML, nodes=MY_NODES, context=ctx).start()
        try:
            got: list = []
            b.helper.create_subscription(JointState, '/brace/actuator_setpoint', got.append, RELIABLE_10)
            pub = b.helper.create_publisher(type(pose_msg([0, 0.39, 0.05], frame_id='x')),
                                            '/brace/pose_setpoint', RELIABLE_10)
            import time
            deadline = time.monotonic() + 10
            while pub.get_subscription_count() < 1 or b.node('ik_node')._pub.get_subscription_count() < 1:
                assert time.monotonic() < deadline, 'discovery'
                time.sleep(0.01)
            pub.publish(pose_msg([0.0, 0.39, 0.05], frame_id='brace_base'))
            while not got:
                assert time.monotonic() < deadline, 'no actuator setpoint'
                time.sleep(0.01)
            assert list(got[0].name) == ['a1', 'a2', 'a3']
        finally:
            b.shutdown()
        assert not b.running
    finally:
        rclpy.shutdown(context=ctx)


def _ended_log(proc: subprocess.Popen) -> str:
    """The end of what ``proc`` printed, killed first (its pipes are read only once it ends)."""
    if proc.poll() is None:
        proc.kill()
    out, err = proc.communicate(timeout=30)
    return f'brace-bringup (exit {proc.returncode}) printed:\n{out[-1500:]}{err[-3000:]}'


@pytest.mark.ros
@pytest.mark.slow
@pytest.mark.parametrize('mode', [[], ['--processes']], ids=['one-process', 'processes'])
def test_cli_stops_cleanly_on_sigint_and_sigterm(ros, mode):
    for sig in (signal.SIGINT, signal.SIGTERM):
        proc = subprocess.Popen(
            [sys.executable, '-m', 'brace_control.bringup', str(LUMBAR_YAML), *mode,
             '--nodes', *MY_NODES], cwd=REPO, env=dict(os.environ),
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            probe = ros.node(f'probe_{sig.name.lower()}')
            for name in ('ik_node', 'kinetics_node'):
                # 30 s: the node processes start beside the other workers' stacks
                ros.wait_node_answers(probe, name, timeout=30, stop=lambda: proc.poll() is not None,
                                      context=lambda: _ended_log(proc))
            assert proc.poll() is None, proc.communicate()[1][-2000:]
            # the probe hears them now (so its silence below is theirs, not the probe's)
            assert ros.nodes_answering(probe, MY_NODES, 20) == MY_NODES
            proc.send_signal(sig)
            _, err = proc.communicate(timeout=30)
            assert proc.returncode == 0, err[-2000:]
            # gone: no node of that name answers any more (the graph keeps a killed
            # process's nodes for a while, see ros_helpers.Ros.node_answers)
            alive = ros.nodes_answering(probe, MY_NODES, 2.0)
            assert not alive, f'{alive} still answer after brace-bringup exited'
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()


@pytest.mark.ros
@pytest.mark.parametrize('service, asked, outcome', [
    ('home', 2, (True, 'done, request 2')),      # idempotent: asked again, its answer counts
    ('halt', 1, (False, 'no answer')),           # not idempotent: asked once only
])
def test_call_trigger_asks_an_idempotent_service_again_when_its_answer_is_lost(service, asked, outcome):
    """A server whose answer to the first request never comes (as when rmw_fastrtps drops
    it: the new client's reader not yet matched): ``call_trigger`` sends ``home``,
    ``enable`` or ``disable`` again and returns the second answer; anything else it reports
    unanswered."""
    from rclpy.callback_groups import ReentrantCallbackGroup
    from rclpy.executors import MultiThreadedExecutor
    from rclpy.task import Future
    from std_srvs.srv import Trigger

    from brace_control.bringup import call_trigger

    ctx = Context()
    rclpy.init(context=ctx)
    try:
        server = rclpy.create_node('lossy_server', context=ctx)
        requests = []

        async def handle(request, response):
            requests.append(request)
            if len(requests) == 1:
                await Future()                   # the first answer never goes out
            response.success, response.message = True, f'done, request {len(requests)}'
            return response

        server.create_service(Trigger, f'~/{service}', handle, callback_group=ReentrantCallbackGroup())
        client = rclpy.create_node('caller', context=ctx)
        executor = MultiThreadedExecutor(context=ctx)
        executor.add_node(server)
        executor.add_node(client)
        BackgroundSpinner(executor).start()
        ok, message = call_trigger(client, f'/lossy_server/{service}', timeout=3.0, executor=executor)
        assert ok is outcome[0] and outcome[1] in message, message
        assert len(requests) == asked
        executor.shutdown(timeout_sec=1.0)
    finally:
        rclpy.shutdown(context=ctx)


@pytest.mark.ros
def test_call_trigger_returns_a_slow_first_answer_not_the_repeat_served_after_it():
    """``enable`` on a cable brace after a relief takes the slack up for seconds, longer
    than :data:`~brace_control.bringup.RESEND_S`: ``call_trigger`` asks again, and the
    driver serves the repeat after the first (one service at a time). The first answer,
    with what the enable did, is the one returned; the repeat's ("already enabled") is not."""
    import threading

    from rclpy.callback_groups import ReentrantCallbackGroup
    from rclpy.executors import MultiThreadedExecutor, SingleThreadedExecutor
    from std_srvs.srv import Trigger

    from brace_control.bringup import RESEND_S, call_trigger

    ctx = Context()
    rclpy.init(context=ctx)
    try:
        server = rclpy.create_node('slow_server', context=ctx)
        requests = []
        one_at_a_time = threading.Lock()

        def handle(request, response):
            requests.append(request)
            with one_at_a_time:
                if len(requests) == 1:
                    time.sleep(RESEND_S + 0.5)
                    response.success, response.message = True, 'OPERATION ENABLED; cables taken up'
                else:
                    response.success, response.message = True, 'OPERATION ENABLED'
            return response

        server.create_service(Trigger, '~/enable', handle, callback_group=ReentrantCallbackGroup())
        client = rclpy.create_node('caller', context=ctx)
        executors = [MultiThreadedExecutor(num_threads=4, context=ctx), SingleThreadedExecutor(context=ctx)]
        executors[0].add_node(server)
        executors[1].add_node(client)
        for e in executors:
            BackgroundSpinner(e).start()
        ok, message = call_trigger(client, '/slow_server/enable', timeout=RESEND_S + 3.0,
                                   executor=executors[1])
        assert ok and message == 'OPERATION ENABLED; cables taken up', message
        assert len(requests) == 2
        for e in executors:
            e.shutdown(timeout_sec=1.0)
    finally:
        rclpy.shutdown(context=ctx)


def test_a_spinner_whose_context_shuts_down_mid_pass_ends_quietly_and_a_live_ones_error_is_raised():
    """rclpy shut down between the spinner's ``context.ok()`` and its pass: ``spin_once`` raises
    ``RCLError`` ("the given context is not valid", seen in CI as a thread traceback among
    pytest's warnings). That is the end of spinning, not a fault; the same error while the
    context is still valid is one, and is raised."""
    import threading

    from brace_control.nodes.spin import spin_until
    from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy

    class Context:
        def __init__(self):
            self.valid = True

        def ok(self):
            return self.valid

    class Executor:
        def __init__(self, shuts_down: bool):
            self.context = Context()
            self.passes = 0
            self.shuts_down = shuts_down

        def spin_once(self, timeout_sec=None):
            self.passes += 1
            if self.shuts_down:
                self.context.valid = False
            raise _rclpy.RCLError('failed to create timer: the given context is not valid')

    closing = Executor(shuts_down=True)
    spin_until(closing, threading.Event())
    assert closing.passes == 1
    with pytest.raises(_rclpy.RCLError):
        spin_until(Executor(shuts_down=False), threading.Event())
