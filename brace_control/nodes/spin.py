"""Spinning an executor in a thread of its own, safe against entities destroyed meanwhile.

rclpy's wait-set executors (``SingleThreadedExecutor``, ``MultiThreadedExecutor``) collect a
node's entities, then add each to a wait set. If another thread destroys one of them in
between (a service client after its call, a subscription after a wait, a publisher after
a replay), adding it raises ``InvalidHandle`` ("cannot use Destroyable because destruction
was requested") out of ``spin_once`` (ros2/rclpy#1284, open in Humble to Kilted). A
``threading.Thread(target=executor.spin)`` then dies, its traceback only on stderr, and
nothing more is delivered to the node. That is issue 26's "lost" ``succeeded``: the goal's
status was in trajectory_node's log and never reached the test's reader, because the
reader's spin thread had died when a helper destroyed the publisher it had replayed the
goals with (seen again in a two-worker run: every topic of the probe silent from that
moment, the thread's ``InvalidHandle`` traceback in pytest's warnings). ``brace-bag replay
--wait-goals`` had the same fault: its replay destroys its publishers while its spin thread
waits for the outcomes.

The entity is gone from the node's lists by the next pass, so the loop here just passes
again. Every background spinner of the package (bring-up, demo, ``brace-bag``) and of the
tests runs through :func:`spin_until` or :class:`BackgroundSpinner`.
"""
from __future__ import annotations

import threading
from typing import Any

from rclpy.executors import ExternalShutdownException, ShutdownException
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy

__all__ = ['InvalidHandle', 'spin_once', 'spin_until', 'BackgroundSpinner']

#: rclpy's exception for a destroyed entity (``rclpy._rclpy_pybind11.InvalidHandle``)
InvalidHandle = _rclpy.InvalidHandle

#: s: the longest one pass waits, so a stop request is seen this soon
PERIOD_S = 0.1


def spin_once(executor: Any, timeout_sec: float = PERIOD_S) -> bool:
    """One ``executor.spin_once``; ``False`` when a destroyed entity cut the pass short
    (ros2/rclpy#1284: the next pass no longer sees it)."""
    try:
        executor.spin_once(timeout_sec=timeout_sec)
    except InvalidHandle:
        return False
    return True


def spin_until(executor: Any, stop: threading.Event, period_s: float = PERIOD_S) -> None:
    """Spin until ``stop`` is set or the executor's context is shut down."""
    try:
        while not stop.is_set() and executor.context.ok():
            try:
                spin_once(executor, period_s)
            except _rclpy.RCLError:
                # the context shut down between the check and the pass ("the given context
                # is not valid" out of the wait set's timer): the end, not a fault
                if executor.context.ok():
                    raise
                return
    except (ExternalShutdownException, ShutdownException):
        pass


class BackgroundSpinner:
    """An executor spun by a daemon thread (:func:`spin_until`) until :meth:`stop`."""

    def __init__(self, executor: Any, name: str = 'spinner') -> None:
        self.executor = executor
        self._stop = threading.Event()
        self.thread = threading.Thread(target=spin_until, args=(executor, self._stop),
                                       name=name, daemon=True)

    def start(self) -> 'BackgroundSpinner':
        self.thread.start()
        return self

    @property
    def alive(self) -> bool:
        return self.thread.is_alive()

    def stop(self, timeout: float = 2.0) -> bool:
        """Stop the loop (it ends within one pass) and wait for the thread; ``True`` if it
        ended within ``timeout``."""
        self._stop.set()
        if self.thread.is_alive() and self.thread is not threading.current_thread():
            self.thread.join(timeout)
        return not self.thread.is_alive()
