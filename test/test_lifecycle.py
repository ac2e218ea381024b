"""can_driver_node as a ROS 2 lifecycle node, driven through its lifecycle_msgs services.

A probe node calls ``/can_driver_node/get_state``, ``change_state`` and
``get_available_transitions`` like ``ros2 lifecycle`` does; a second python-can bus on the
driver's virtual channel watches what is on the wire. The oracles are the protocols, not the
driver: CiA 301 (a heartbeat 700h + id whose byte is 05h = OPERATIONAL, SYNC = 080h) and CiA
402-2 table 30 (statusword & 004Fh = 0040h: SWITCH ON DISABLED; & 006Fh = 0027h: OPERATION
ENABLED), and ros2 lifecycle's state ids (lifecycle_msgs/State).
"""
from __future__ import annotations

import itertools
import os
import struct
import time

import can
import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import PoseStamped, WrenchStamped
from lifecycle_msgs.msg import State, Transition
from lifecycle_msgs.srv import ChangeState, GetAvailableTransitions, GetState
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger
from trajectory_msgs.msg import JointTrajectory

from brace_control.mechanisms import load_mechanism
from brace_control.nodes import topics
from brace_control.nodes.can_driver_node import CanDriverNode
from brace_control.nodes.msgs import joint_trajectory_msg
from brace_control.trajectory import MinimumJerk
from ros_helpers import LUMBAR_YAML

pytestmark = pytest.mark.ros
_ids = itertools.count()
_MECH = load_mechanism(LUMBAR_YAML)
Q_HOME = _MECH.inverse(_MECH.home_pose)
NODE_IDS = (1, 2, 3)
DRIVER = '/can_driver_node'
LATCHED = topics.LATCHED_QOS


# ----------------------------------------------------------------------------- helpers

def _channel() -> str:
    return f'lifecycle-{os.getpid()}-{next(_ids)}'


class Wire:
    """A second python-can bus on the driver's virtual channel: what is on the wire."""

    def __init__(self, channel: str) -> None:
        self.bus = can.Bus(interface='virtual', channel=channel, receive_own_messages=False)

    def drain(self) -> None:
        while self.bus.recv(timeout=0.0) is not None:
            pass

    def frames(self, seconds: float) -> list[can.Message]:
        """Every frame received during the next ``seconds``."""
        out, deadline = [], time.monotonic() + seconds
        while (left := deadline - time.monotonic()) > 0:
            msg = self.bus.recv(timeout=left)
            if msg is not None:
                out.append(msg)
        return out

    def pending(self) -> list[can.Message]:
        """The frames received since the last read."""
        out = []
        while (msg := self.bus.recv(timeout=0.0)) is not None:
            out.append(msg)
        return out

    def close(self) -> None:
        self.bus.shutdown()


def heartbeat_states(frames: list[can.Message]) -> dict[int, int]:
    """CiA 301 heartbeat of the drives: node id -> the last NMT state byte (05h = OPERATIONAL)."""
    return {m.arbitration_id - 0x700: m.data[0] for m in frames
            if m.arbitration_id - 0x700 in NODE_IDS and len(m.data) == 1}


def statuswords(frames: list[can.Message]) -> dict[int, int]:
    """TPDO1 (180h + id, 6041h first): node id -> the last statusword."""
    return {m.arbitration_id - 0x180: struct.unpack_from('<H', bytes(m.data))[0] for m in frames
            if m.arbitration_id - 0x180 in NODE_IDS and len(m.data) >= 2}


def switch_on_disabled(sw: int) -> bool:
    return sw & 0x4F == 0x40              # CiA 402-2 table 30


def operation_enabled(sw: int) -> bool:
    return sw & 0x6F == 0x27


class Lifecycle:
    """The ``ros2 lifecycle`` client side: lifecycle_msgs services of the driver."""

    def __init__(self, ros, probe, name: str = DRIVER) -> None:
        self.ros, self.probe = ros, probe
        self.get = probe.create_client(GetState, f'{name}/get_state')
        self.change = probe.create_client(ChangeState, f'{name}/change_state')
        self.transitions = probe.create_client(GetAvailableTransitions,
                                               f'{name}/get_available_transitions')
        self.name = name
        self._triggers: dict = {}
        self._answered: set = set()             # clients that had an answer

    def _call(self, client, request, timeout: float = 15.0, *, resend_s: float | None = None):
        """One call; ``resend_s``: an idempotent request is sent again when no answer came
        within that long (a server whose response writer has not yet matched this client's
        reader loses its answer: DDS discovery, slower on a loaded host).

        ``service_is_ready`` is waited for until the client's first answer only: rmw_fastrtps
        calls a server unavailable while its DDS endpoint counts disagree, e.g. while another
        participant of the domain is being discovered or removed; the server that answered
        is still there."""
        if client not in self._answered:
            self.ros.spin_until(client.service_is_ready, timeout,
                                lambda: f'{client.srv_name} available; {self.graph(client.srv_name)}')
        deadline = time.monotonic() + timeout
        while True:
            future = client.call_async(request)
            end = deadline if resend_s is None else min(deadline, time.monotonic() + resend_s)
            while not future.done() and time.monotonic() < end:
                self.ros.executor.spin_once(timeout_sec=0.01)
            if future.done():
                self._answered.add(client)
                return future.result()
            future.cancel()
            if time.monotonic() >= deadline:
                pytest.fail(f'{client.srv_name} did not answer within {timeout} s; '
                            f'{self.graph(client.srv_name)}')

    def graph(self, service: str) -> str:
        """The service's DDS endpoints as this probe sees them (rmw_fastrtps calls a server
        available only when their counts agree): for a failure message."""
        name = service.lstrip('/')
        parts = []
        for topic, kind in ((f'rq/{name}Request', 'request readers'), (f'rr/{name}Reply', 'response writers')):
            info = (self.probe.get_subscriptions_info_by_topic if kind.endswith('readers')
                    else self.probe.get_publishers_info_by_topic)(topic, no_mangle=True)
            parts.append(f"{kind}: {[f'{i.node_namespace.rstrip(chr(47))}/{i.node_name}' for i in info]}")
        return ', '.join(parts)

    def wait_answering(self, timeout: float = 20.0) -> None:
        """Until a ``get_state`` round trip succeeds: a server process that has just started
        may not yet match the client's response reader (its first answers are lost)."""
        self._call(self.get, GetState.Request(), timeout, resend_s=1.0)

    def state(self) -> tuple[int, str]:
        s = self._call(self.get, GetState.Request(), resend_s=2.0).current_state
        return s.id, s.label

    def set(self, transition_id: int) -> bool:
        req = ChangeState.Request()
        req.transition.id = transition_id
        return self._call(self.change, req).success

    def available(self) -> set[str]:
        return {t.transition.label for t in
                self._call(self.transitions, GetAvailableTransitions.Request(),
                           resend_s=2.0).available_transitions}

    def trigger_client(self, service: str):
        """The client of the driver's ``std_srvs/Trigger`` service (made once: discovery
        matches it while the test goes on)."""
        if service not in self._triggers:
            self._triggers[service] = self.probe.create_client(Trigger, f'{self.name}/{service}')
        return self._triggers[service]

    def trigger(self, service: str) -> Trigger.Response:
        return self._call(self.trigger_client(service), Trigger.Request())


@pytest.fixture
def rig(ros):
    """(driver node unconfigured, lifecycle client, wire) on a fresh virtual channel."""
    def make(**overrides):
        channel = _channel()
        wire = Wire(channel)
        made.append(wire)
        # the wire listens on the virtual bus, which exists inside one process: the
        # driver's cycle runs in this one (test_cycle_process covers the cycle's own process)
        driver = ros.device_node(CanDriverNode, **{'can.channel': channel, 'can.cycle_process': False,
                                                   **overrides})
        made.append(driver)
        probe = ros.node(f'probe{next(_ids)}')
        return driver, Lifecycle(ros, probe), wire, probe
    made: list = []
    yield make
    for obj in reversed(made):
        if isinstance(obj, Wire):
            obj.close()
        else:
            obj.shutdown()


# ----------------------------------------------------------------------------- tests

def test_unconfigured_inactive_active_inactive_unconfigured_and_again(ros, rig):
    driver, lc, wire, probe = rig()
    js = ros.collect(probe, JointState, topics.JOINT_STATES)
    truth = {t: ros.collect(probe, m, t) for t, m in ((topics.SIM_JOINT_STATES, JointState),
                                                      (topics.SIM_POSE, PoseStamped),
                                                      (topics.SIM_WRENCH, WrenchStamped))}
    states = ros.collect(probe, DiagnosticStatus, topics.DRIVER_STATE, LATCHED)
    events = ros.collect(probe, DiagnosticStatus, topics.EXECUTION_STATUS, topics.STATUS_QOS)

    # unconfigured: nothing on the wire, only configure and shutdown possible
    assert lc.state() == (State.PRIMARY_STATE_UNCONFIGURED, 'unconfigured')
    assert lc.available() == {'configure', 'shutdown'}
    assert wire.frames(0.2) == []
    res = lc.trigger('home')
    assert not res.success and 'unconfigured' in res.message

    # configure: the drives booted and configured, OPERATIONAL, power stage off
    wire.drain()
    assert lc.set(Transition.TRANSITION_CONFIGURE)
    assert lc.state() == (State.PRIMARY_STATE_INACTIVE, 'inactive')
    assert lc.available() == {'cleanup', 'activate', 'shutdown'}
    on_wire = wire.frames(0.3)
    assert heartbeat_states(on_wire) == {1: 0x05, 2: 0x05, 3: 0x05}      # OPERATIONAL
    assert any(m.arbitration_id == 0x080 for m in on_wire)                  # SYNC
    sw = statuswords(on_wire)
    assert set(sw) == set(NODE_IDS) and all(switch_on_disabled(v) for v in sw.values()), sw
    # inactive: commands refused naming the state, no measurement published
    for service in ('home', 'enable', 'relieve'):
        res = lc.trigger(service)
        assert not res.success and 'inactive' in res.message, (service, res.message)
    assert lc.trigger('disable').success                                    # stopping is fine
    ros.spin_until(lambda: states and states[-1].message.startswith('inactive'), 3.0, 'state')
    assert {kv.key: kv.value for kv in states[-1].values}['enabled'] == 'false'
    pub = probe.create_publisher(JointTrajectory, topics.ACTUATOR_TRAJECTORY, topics.TRAJECTORY_QOS)
    ros.wait_matched(pub)
    q_end = _MECH.inverse(_MECH.home_pose + np.array([0.0, 0.003, 0.0]))
    pub.publish(_trajectory(Q_HOME, q_end, 1.0, probe))
    ros.spin_until(lambda: any(e.message == 'rejected' for e in events), 3.0, 'rejection')
    reason = {kv.key: kv.value for kv in events[-1].values}['reason']
    assert 'inactive' in reason
    ros.spin_for(0.3)
    assert js == [] and all(box == [] for box in truth.values())

    # activate: the simulator's truth flows; joint states once homed (incremental encoders)
    assert lc.set(Transition.TRANSITION_ACTIVATE)
    assert lc.state() == (State.PRIMARY_STATE_ACTIVE, 'active')
    ros.spin_until(lambda: all(len(box) >= 3 for box in truth.values()), 3.0, '/brace/sim/*')
    assert lc.trigger('home').success
    ros.spin_until(lambda: len(js) >= 3, 3.0, '/brace/joint_states')
    assert np.array(js[-1].position) == pytest.approx(Q_HOME, abs=1e-6)
    res = lc.trigger('enable')
    assert res.success, res.message
    wire.drain()
    sw = statuswords(wire.frames(0.1))
    assert all(operation_enabled(v) for v in sw.values()), sw

    # deactivate during a motion: braked along its path, drives disabled, nothing moves
    # (a 3 s motion: on a busy host the first 0.2 mm can take a second to show; the check
    # that the deactivation came mid-motion is the one after it: not at q_end)
    t0 = time.monotonic()
    pub.publish(_trajectory(Q_HOME, q_end, 3.0, probe))
    ros.spin_until(lambda: np.max(np.abs(driver.sim.truth().lengths - Q_HOME)) > 2e-4, 3.0, 'moving')
    assert time.monotonic() - t0 < 2.5
    assert lc.set(Transition.TRANSITION_DEACTIVATE)
    assert lc.state() == (State.PRIMARY_STATE_INACTIVE, 'inactive')
    wire.drain()
    sw = statuswords(wire.frames(0.1))
    assert set(sw) == set(NODE_IDS) and all(switch_on_disabled(v) for v in sw.values()), sw
    stopped = driver.sim.truth().lengths
    assert np.max(np.abs(stopped - q_end)) > 1e-4          # it did not finish the motion
    ros.spin_for(0.3)
    assert np.max(np.abs(driver.sim.truth().lengths - stopped)) < 1e-6
    ros.spin_until(lambda: any(e.message == 'stopped' for e in events), 3.0, 'trajectory stopped')
    n_js = len(js)
    ros.spin_for(0.2)
    assert len(js) == n_js                                   # measurements stop when inactive
    assert not lc.trigger('enable').success

    # cleanup: the bus closed, the wire silent; configure again boots the drives again
    assert lc.set(Transition.TRANSITION_CLEANUP)
    assert lc.state() == (State.PRIMARY_STATE_UNCONFIGURED, 'unconfigured')
    assert driver.master is None
    wire.drain()
    assert wire.frames(0.3) == []
    assert lc.set(Transition.TRANSITION_CONFIGURE)
    assert heartbeat_states(wire.frames(0.3)) == {1: 0x05, 2: 0x05, 3: 0x05}
    # the simulated brace was powered off, not moved: its legs are where they stopped
    assert driver.sim.truth().lengths == pytest.approx(stopped, abs=1e-6)
    assert lc.set(Transition.TRANSITION_ACTIVATE)
    res = lc.trigger('enable')
    assert not res.success and 'home' in res.message          # encoders restarted: home again


def _trajectory(q0: np.ndarray, q1: np.ndarray, duration: float, node) -> object:
    """A minimum-jerk motion q0 -> q1 in actuator space, 50 knots, starting now."""
    tr = MinimumJerk(q0, q1, duration)
    times = np.linspace(0.0, duration, 50)
    p, v, a = zip(*(tr.sample(t) for t in times))
    return joint_trajectory_msg(['a1', 'a2', 'a3'], times, np.array(p), np.array(v), np.array(a),
                                stamp=node.get_clock().now().to_msg())


@pytest.mark.parametrize('start', ['unconfigured', 'inactive', 'active'])
def test_shutdown_from_each_primary_state_disables_and_closes(ros, rig, start):
    driver, lc, wire, probe = rig()
    transition = Transition.TRANSITION_UNCONFIGURED_SHUTDOWN
    if start != 'unconfigured':
        assert lc.set(Transition.TRANSITION_CONFIGURE)
        transition = Transition.TRANSITION_INACTIVE_SHUTDOWN
    if start == 'active':
        assert lc.set(Transition.TRANSITION_ACTIVATE)
        assert lc.trigger('home').success and lc.trigger('enable').success
        transition = Transition.TRANSITION_ACTIVE_SHUTDOWN
    # before and during the transition: an inactive driver's drives are off already, and
    # the shutdown may close the bus before another SYNC is answered
    during = wire.pending()
    assert lc.set(transition)
    assert lc.state() == (State.PRIMARY_STATE_FINALIZED, 'finalized')
    assert driver.master is None
    during += wire.pending()
    if start != 'unconfigured':        # the last statusword each drive sent: power stage off
        sw = statuswords(during)
        assert set(sw) == set(NODE_IDS) and all(switch_on_disabled(v) for v in sw.values()), sw
    assert wire.frames(0.3) == []
    res = lc.trigger('disable')
    assert not res.success and 'finalized' in res.message


def test_deactivate_is_refused_while_a_protective_stop_holds_the_load(ros, rig):
    """docs/safety.md §15: with a latched stop the drives hold in QUICK STOP ACTIVE; relieve and
    recover need the node active, so deactivate is refused (the node stays active)."""
    driver, lc, wire, probe = rig()
    assert lc.set(Transition.TRANSITION_CONFIGURE) and lc.set(Transition.TRANSITION_ACTIVATE)
    assert lc.trigger('home').success and lc.trigger('enable').success
    for node_id in NODE_IDS:                  # 3 x 120 N: a platform force above max_wrench
        driver.sim.faults.set_load_cell(node_id, 120.0)
    ros.spin_until(lambda: driver.master.latched, 3.0, 'protective stop')
    wire.drain()
    ros.spin_until(lambda: statuswords(wire.frames(0.05)).get(2, 0) & 0x6F == 0x07, 3.0,
                   'QUICK STOP ACTIVE')       # CiA 402-2 table 30
    assert not lc.set(Transition.TRANSITION_DEACTIVATE)
    assert lc.state() == (State.PRIMARY_STATE_ACTIVE, 'active')
    assert 'relieve' in driver.last_transition_error and 'protective stop' in driver.last_transition_error
    for node_id in NODE_IDS:
        driver.sim.faults.set_load_cell(node_id, None)
    res = lc.trigger('recover')
    assert res.success, res.message
    assert lc.set(Transition.TRANSITION_DEACTIVATE)
    assert lc.state() == (State.PRIMARY_STATE_INACTIVE, 'inactive')


def test_a_drive_that_does_not_answer_fails_configure_cleanly(ros, rig, capfd):
    driver, lc, wire, probe = rig(**{'can.boot_timeout': 0.5})
    assert lc.set(Transition.TRANSITION_CONFIGURE)
    assert lc.set(Transition.TRANSITION_CLEANUP)
    driver.sim.faults.disconnect(2)                          # a2's cable pulled
    assert not lc.set(Transition.TRANSITION_CONFIGURE)
    assert lc.state() == (State.PRIMARY_STATE_UNCONFIGURED, 'unconfigured')
    assert driver.master is None
    wire.drain()
    assert wire.frames(0.3) == []                            # everything opened was closed
    err = capfd.readouterr().err
    assert 'configure failed' in err and 'a2 (node 2)' in err and 'can.boot_timeout' in err, err
    res = lc.trigger('home')
    assert not res.success and 'unconfigured' in res.message
    driver.sim.faults.disconnect(2, False)                   # plugged in again: configure works
    assert lc.set(Transition.TRANSITION_CONFIGURE)
    assert lc.state() == (State.PRIMARY_STATE_INACTIVE, 'inactive')


def test_a_bus_that_does_not_open_fails_configure_naming_it(ros, rig, capfd):
    driver, lc, wire, probe = rig(**{'can.sim': False, 'can.interface': 'no_such_interface'})
    assert not lc.set(Transition.TRANSITION_CONFIGURE)
    assert lc.state() == (State.PRIMARY_STATE_UNCONFIGURED, 'unconfigured')
    err = capfd.readouterr().err
    assert 'configure failed' in err and "interface='no_such_interface'" in err, err
    assert lc.set(Transition.TRANSITION_UNCONFIGURED_SHUTDOWN)


def test_the_driver_builds_one_mechanism_model(ros, monkeypatch):
    """Node, master (home lengths, actuator ranges) and simulated brace share one model; the
    simulator's physics has its own (stroke widened 1 cm), a different mechanism."""
    import brace_control.mechanisms as mechanisms
    import brace_control.sim.brace as sim_brace
    built: list[dict] = []
    original = mechanisms.mechanism_from_config

    def counting(cfg):
        built.append(dict(cfg['mechanism']))
        return original(cfg)
    monkeypatch.setattr(mechanisms, 'mechanism_from_config', counting)
    monkeypatch.setattr(sim_brace, 'mechanism_from_config', counting)
    # counted in this process: the cycle (and the simulator) run in it
    driver = ros.device_node(CanDriverNode, **{'can.channel': _channel(), 'can.cycle_process': False})
    try:
        driver.autostart()
        assert len(built) == 2, [m.get('stroke_min') for m in built]
        assert driver.sim.mechanism is driver.mechanism
        widened = np.asarray(built[1]['stroke_max']) - np.asarray(built[0]['stroke_max'])
        assert widened == pytest.approx(0.01)
    finally:
        driver.shutdown()


@pytest.mark.slow
def test_manual_lifecycle_process_waits_unconfigured_for_ros2_lifecycle(ros):
    """``brace-bringup --processes --manual-lifecycle``: the driver process stays
    unconfigured until a ChangeState call; SIGINT then ends it with exit code 0."""
    from brace_control.bringup import ProcessBringUp
    group = ProcessBringUp(LUMBAR_YAML, nodes=['can_driver_node'], manual_lifecycle=True,
                           extra_args=['-p', f'can.channel:={_channel()}']).start()
    try:
        probe = ros.node('probe_manual')
        lc = Lifecycle(ros, probe)
        lc.trigger_client('home')
        lc.wait_answering()
        assert lc.state() == (State.PRIMARY_STATE_UNCONFIGURED, 'unconfigured')
        assert lc.set(Transition.TRANSITION_CONFIGURE)
        assert lc.set(Transition.TRANSITION_ACTIVATE)
        assert lc.state() == (State.PRIMARY_STATE_ACTIVE, 'active')
        assert lc.trigger('home').success
    finally:
        codes = group.stop()
    assert codes == {'can_driver_node': 0}
