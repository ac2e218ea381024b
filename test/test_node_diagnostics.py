"""nodes.diagnostics.NodeDiagnostics: what a bring-up waits on comes when it changes.

The periodic publication here is every 60 s, so a status that arrives within a few seconds
was published because something changed: a new reader of ``/diagnostics``, a new subscriber
of a watched publisher, or a value marked prompt.
"""
from __future__ import annotations

import pytest
from diagnostic_msgs.msg import DiagnosticArray
from std_msgs.msg import Empty

from brace_control.nodes.diagnostics import OK, NodeDiagnostics
from ros_helpers import RELIABLE_10

pytestmark = pytest.mark.ros

PERIOD = 60.0
SOON = 5.0            # far below PERIOD: only an event-driven publication arrives this soon


def _values(box: list, name: str) -> list[dict[str, str]]:
    return [{kv.key: kv.value for kv in s.values} for m in list(box) for s in m.status if s.name == name]


def test_a_change_is_published_at_once_not_at_the_next_period(ros):
    subject = ros.node('diag_subject')
    watched = subject.create_publisher(Empty, '/diag_subject_out', RELIABLE_10)
    diag = NodeDiagnostics(subject, 'test/diag_subject', period=PERIOD)
    diag.watch(watched)
    diag.prompt('driver')
    diag.set(OK, 'up', driver='disabled')
    name = 'test/diag_subject'

    # a reader joins /diagnostics: it is told the status without waiting for the period
    listener = ros.node('diag_listener')
    box = ros.collect(listener, DiagnosticArray, '/diagnostics')
    ros.spin_until(lambda: _values(box, name), SOON, 'a status for the new reader')
    assert _values(box, name)[-1]['subscribers /diag_subject_out'] == '0'

    # the watched publisher matches a subscriber
    ros.collect(listener, Empty, '/diag_subject_out')
    ros.spin_until(lambda: _values(box, name)[-1].get('subscribers /diag_subject_out') == '1', SOON,
                   lambda: f'the new subscriber count, got {_values(box, name)}')

    # a prompt value changes (the trajectory node's view of the driver's state)
    diag.values['driver'] = 'enabled'
    ros.spin_until(lambda: _values(box, name)[-1].get('driver') == 'enabled', SOON,
                   lambda: f'the driver state, got {_values(box, name)}')

    # an unmarked value does not publish by itself
    n = len(_values(box, name))
    diag.values['counter'] = 7
    ros.spin_for(1.0)
    assert len(_values(box, name)) == n, _values(box, name)[n:]
