"""The interaction demo's scripted session (``demo_interaction.run_session``) against a
scripted patient: what the session does with the events the stack sends back, without a stack.

The events are the stack's contract (interaction_node's docstring): a wrench goal the node
accepted can still be rejected by the driver, which checks it again at its own pose; the node
then publishes ``rejected`` for the same goal name. A session that went on holding a goal the
driver never took would report a step response of a step that did not happen.
"""
from __future__ import annotations

import threading
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
            self.emit(f'{GOAL}/{len(self.goals)}', state, reason)

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
    script = SimpleNamespace(rest=np.zeros(3), centre=np.zeros(3), step=np.array([0.0, 30.0, 0.0]))
    phases: list = []
    run_session(patient, patient, script, services, executor=None, stop=threading.Event(),
                phases=phases, hold_s=0.0, log=lambda line: None)
    return [p[0] for p in phases]


def test_a_session_whose_goals_are_taken_runs_every_phase(services):
    patient = ScriptedPatient([[('accepted', '')], [('accepted', '')]])
    assert _run(patient, services) == ['zero-torque at rest', 'lean', 'sway', 'settle', 'wrench step',
                                      'wrench zero', 'return', 'position goal']
    assert patient.goals == [[0.0, 30.0, 0.0], [0.0, 0.0, 0.0]]


def test_a_step_the_driver_rejects_after_the_nodes_acceptance_ends_the_session_with_its_reason(services):
    patient = ScriptedPatient([[('accepted', ''), ('rejected', 'the driver: above the capacity at its pose')]])
    with pytest.raises(RuntimeError, match='wrench goal step rejected after its acceptance: '
                                           'the driver: above the capacity at its pose'):
        _run(patient, services)
    assert patient.goals == [[0.0, 30.0, 0.0]]         # no further goal was sent


def test_a_rejection_of_an_earlier_goal_does_not_count_against_the_next(services):
    # goal 1 rejected late, as seen by the step; the zero goal (2) is judged on its own events
    patient = ScriptedPatient([[('accepted', '')], [('accepted', '')]])
    patient.emit(f'{GOAL}/0', 'rejected', 'an earlier session')
    assert 'position goal' in _run(patient, services)
