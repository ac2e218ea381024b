"""The interaction demo's scripted session (``demo_interaction.run_session``) against a
scripted patient: what the session does with the events the stack sends back, without a stack.

The events are the stack's contract (interaction_node's docstring): a wrench goal the node
accepted can still be rejected by the driver, which checks it again at its own pose; the node
then publishes ``rejected`` for the same goal name. A session that went on holding a goal the
driver never took would report a step response of a step that did not happen.
"""
from __future__ import annotations

import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest

from brace_control import bringup
from brace_control.demo_interaction import _Patient, run_session

GOAL = 'interaction_node/wrench_goal'


class ScriptedPatient:
    """The demo's patient without ROS: each wrench goal gets the answers ``answers`` holds
    for it (``(state, reason)`` in order), the interaction's start and stop their events, a
    position goal its success."""

    wait_event = _Patient.wait_event

    def __init__(self, answers: list[list[tuple[str, str]]]) -> None:
        self.lock = threading.Lock()
        self.events: list[tuple[str, str, str]] = []
        self.applied: dict[str, int] = {}
        self.answers = list(answers)
        self.goals: list[list[float]] = []
        self.mech = SimpleNamespace(home_pose=np.zeros(3))

    def emit(self, name: str, state: str, reason: str = '') -> None:
        with self.lock:
            self.events.append((name, state, reason))

    def rest(self, pose) -> None:
        pass

    def move(self, start, goal, duration, stop) -> None:
        pass

    def sway(self, script, stop) -> None:
        pass

    def wrench_goal(self, w) -> None:
        self.goals.append(list(w))
        for state, reason in self.answers.pop(0):
            name = f'{GOAL}/{len(self.goals)}'
            if state == 'applied':           # the driver's wall clock then (ns) in its reason slot
                self.applied[name] = int(reason)
            self.emit(name, state, reason)

    def pose_goal(self, pose) -> None:
        self.emit('trajectory_node/goal/1', 'succeeded')


@pytest.fixture
def services(monkeypatch):
    """``start`` and ``stop`` answered at once; their events sent as the node would."""
    def call_trigger(node, service, timeout, executor):
        node.emit('interaction_node/interaction/1', 'started' if service.endswith('start') else 'stopped')
        return True, 'ok'
    monkeypatch.setattr(bringup, 'call_trigger', call_trigger)
    monkeypatch.setattr('brace_control.demo_interaction._pause', lambda s, stop: None)
    return {'start': '/interaction_node/start', 'stop': '/interaction_node/stop'}


def _run(patient, services) -> list[str]:
    return [p[0] for p in _run_phases(patient, services)]


def _run_phases(patient, services) -> list:
    script = SimpleNamespace(rest=np.zeros(3), centre=np.zeros(3), step=np.array([0.0, 30.0, 0.0]))
    phases: list = []
    run_session(patient, patient, script, services, executor=None, stop=threading.Event(),
                phases=phases, hold_s=0.0, log=lambda line: None)
    return phases


def test_a_session_whose_goals_are_taken_runs_every_phase(services):
    patient = ScriptedPatient([[('accepted', ''), ('applied', '1')], [('accepted', ''), ('applied', '2')]])
    assert _run(patient, services) == ['zero-torque at rest', 'lean', 'sway', 'settle', 'wrench step',
                                      'wrench zero', 'return', 'position goal']
    assert patient.goals == [[0.0, 30.0, 0.0], [0.0, 0.0, 0.0]]


def test_a_step_s_phase_begins_when_the_driver_applied_its_goal(services):
    """The report times the step response from the phase's start: the driver's ``applied_ns``
    (a goal a starved host delivers late is not a slow controller), not the publish."""
    applied = time.time_ns() + 3_000_000_000               # 3 s after the publish, say
    patient = ScriptedPatient([[('accepted', ''), ('applied', str(applied))],
                               [('accepted', ''), ('applied', str(applied + 1))]])
    phases = {name: (t0, t1) for name, t0, t1 in _run_phases(patient, services)}
    assert phases['wrench step'][0] == applied
    assert phases['wrench zero'][0] == applied + 1
    assert phases['settle'][0] < applied                    # the other phases: their own start


def test_a_goal_the_driver_never_applies_ends_the_session(services, monkeypatch):
    monkeypatch.setattr('brace_control.demo_interaction.APPLY_TIMEOUT_S', 0.2)
    patient = ScriptedPatient([[('accepted', '')]])
    with pytest.raises(RuntimeError, match='step applied by the driver'):
        _run(patient, services)
    assert patient.goals == [[0.0, 30.0, 0.0]]


def test_a_step_the_driver_rejects_after_the_nodes_acceptance_ends_the_session_with_its_reason(services):
    patient = ScriptedPatient([[('accepted', ''), ('rejected', 'the driver: above the capacity at its pose')]])
    with pytest.raises(RuntimeError, match='wrench goal step rejected after its acceptance: '
                                           'the driver: above the capacity at its pose'):
        _run(patient, services)
    assert patient.goals == [[0.0, 30.0, 0.0]]         # no further goal was sent


def test_a_rejection_of_an_earlier_goal_does_not_count_against_the_next(services):
    # goal 1 rejected late, as seen by the step; the zero goal (2) is judged on its own events
    patient = ScriptedPatient([[('accepted', ''), ('applied', '1')], [('accepted', ''), ('applied', '2')]])
    patient.emit(f'{GOAL}/0', 'rejected', 'an earlier session')
    assert 'position goal' in _run(patient, services)
