"""Small helper shared by ik_node and kinetics_node: one ``DiagnosticStatus`` per node.

Composed around a node (not a subclass): the node keeps a :class:`NodeDiagnostics`,
updates its level/message/values, and the helper publishes ``/diagnostics`` at a fixed
rate and immediately (throttled) when the level gets worse. :meth:`NodeDiagnostics.watch`
adds, at each publication, how many subscribers a publisher has matched (``subscribers
/brace/pose_trajectory: 1``): whether the node downstream is connected, as this node's own
DDS discovery sees it (a bring-up waits on it before the first goal). A change of those
counts, of a value the node marks :meth:`~NodeDiagnostics.prompt`, or of the readers of
``/diagnostics`` is published within ``check_period`` instead of at the next periodic
publication: a bring-up that waits for the stack to be ready learns it when it happens (or
when it starts listening), not up to a second later.
"""
from __future__ import annotations

import time
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy

__all__ = ['NodeDiagnostics', 'OK', 'WARN', 'ERROR', 'STALE']

OK = DiagnosticStatus.OK
WARN = DiagnosticStatus.WARN
ERROR = DiagnosticStatus.ERROR
STALE = DiagnosticStatus.STALE


def _level(value: Any) -> bytes:
    return value if isinstance(value, bytes) else bytes([int(value)])


class NodeDiagnostics:
    """Publishes the node's status on ``/diagnostics``.

    :param node: the node the publisher and timer belong to.
    :param name: status name (``'brace_control/ik_node'``).
    :param period: seconds between periodic publications.
    :param min_interval: shortest time between event-driven publications (throttle).
    :param check_period: seconds between looks at the watched counts and prompt values (only
        while something is watched or prompt).
    """

    def __init__(self, node: Node, name: str, *, period: float = 1.0,
                 min_interval: float = 0.1, check_period: float = 0.1, callback_group: Any = None) -> None:
        self._node = node
        self.name = name
        self.hardware_id = node.get_fully_qualified_name()
        # /diagnostics is state: reliable, a short history is plenty at 1 Hz.
        self._pub = node.create_publisher(
            DiagnosticArray, '/diagnostics',
            QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
        self.level: bytes = _level(OK)
        self.message = 'starting'
        self.values: dict[str, Any] = {}
        self._min_interval = min_interval
        self._last_event = 0.0
        self._watched: list[Any] = []
        self._watched_subs: list[Any] = []
        self._prompt: set[str] = set()
        self._published: dict[str, str] = {}      # the watched and prompt values last published
        self._check_period = check_period
        self._callback_group = callback_group
        self._check_timer: Any = None
        self._timer = node.create_timer(period, self.publish, callback_group=callback_group)

    def set(self, level: Any, message: str, **values: Any) -> None:
        """Update the status; publishes at once (throttled) if the level got worse."""
        level = _level(level)
        worse = level > self.level
        self.level, self.message = level, message
        self.values.update(values)
        now = time.monotonic()
        if worse and now - self._last_event >= self._min_interval:
            self._last_event = now
            self.publish()

    def watch(self, publisher: Any) -> None:
        """Report ``subscribers <topic>`` (matched subscriptions) of ``publisher``."""
        self._watched.append(publisher)
        self._start_checking()

    def watch_subscription(self, subscription: Any) -> None:
        """Report ``publishers <topic>`` of ``subscription``: matched publishers where rclpy
        has ``Subscription.get_publisher_count`` (Iron and later), else the publishers the
        graph knows (Humble)."""
        self._watched_subs.append(subscription)
        self._start_checking()

    def prompt(self, *keys: str) -> None:
        """Publish within ``check_period`` whenever one of ``keys`` (in :attr:`values`) changes."""
        self._prompt.update(keys)
        self._start_checking()

    def _start_checking(self) -> None:
        if self._check_timer is None:
            self._check_timer = self._node.create_timer(self._check_period, self._check,
                                                        callback_group=self._callback_group)

    def _counts(self) -> None:
        for pub in self._watched:
            self.values[f'subscribers {pub.topic_name}'] = pub.get_subscription_count()
        for sub in self._watched_subs:
            count = getattr(sub, 'get_publisher_count', None)
            self.values[f'publishers {sub.topic_name}'] = (
                count() if count is not None else self._node.count_publishers(sub.topic_name))

    def _snapshot(self) -> dict[str, str]:
        keys = [k for k in self.values if k in self._prompt or k.startswith(('subscribers ', 'publishers '))]
        out = {k: str(self.values[k]) for k in keys}
        # a new reader of /diagnostics (a bring-up starting to wait) gets the status at once
        out[' readers'] = str(self._pub.get_subscription_count())
        return out

    def _check(self) -> None:
        self._counts()
        now = time.monotonic()
        if self._snapshot() != self._published and now - self._last_event >= self._min_interval:
            self._last_event = now
            self.publish()

    def status(self) -> DiagnosticStatus:
        self._counts()
        self._published = self._snapshot()
        return DiagnosticStatus(
            level=self.level, name=self.name, message=self.message,
            hardware_id=self.hardware_id,
            values=[KeyValue(key=str(k), value=str(v)) for k, v in self.values.items()])

    def publish(self) -> None:
        msg = DiagnosticArray()
        msg.header.stamp = self._node.get_clock().now().to_msg()
        msg.status = [self.status()]
        self._pub.publish(msg)
