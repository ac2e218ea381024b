"""Small helper shared by ik_node and kinetics_node: one ``DiagnosticStatus`` per node.

Composed around a node (not a subclass): the node keeps a :class:`NodeDiagnostics`,
updates its level/message/values, and the helper publishes ``/diagnostics`` at a fixed
rate and immediately (throttled) when the level gets worse. :meth:`NodeDiagnostics.watch`
adds, at each publication, how many subscribers a publisher has matched (``subscribers
/brace/pose_trajectory: 1``): whether the node downstream is connected, as this node's own
DDS discovery sees it (a bring-up waits on it before the first goal).
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
    """

    def __init__(self, node: Node, name: str, *, period: float = 1.0,
                 min_interval: float = 0.1, callback_group: Any = None) -> None:
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

    def watch_subscription(self, subscription: Any) -> None:
        """Report ``publishers <topic>`` of ``subscription``: matched publishers where rclpy
        has ``Subscription.get_publisher_count`` (Iron and later), else the publishers the
        graph knows (Humble)."""
        self._watched_subs.append(subscription)

    def status(self) -> DiagnosticStatus:
        for pub in self._watched:
            self.values[f'subscribers {pub.topic_name}'] = pub.get_subscription_count()
        for sub in self._watched_subs:
            count = getattr(sub, 'get_publisher_count', None)
            self.values[f'publishers {sub.topic_name}'] = (
                count() if count is not None else self._node.count_publishers(sub.topic_name))
        return DiagnosticStatus(
            level=self.level, name=self.name, message=self.message,
            hardware_id=self.hardware_id,
            values=[KeyValue(key=str(k), value=str(v)) for k, v in self.values.items()])

    def publish(self) -> None:
        msg = DiagnosticArray()
        msg.header.stamp = self._node.get_clock().now().to_msg()
        msg.status = [self.status()]
        self._pub.publish(msg)
