"""``main()`` for a node executable: ``--help``, start-up errors, Ctrl-C, clean exit.

``ros2 run brace_control ik_node --ros-args --params-file config/lumbar_brace.yaml``
ends up in :func:`run_node`. Exit codes: 0 clean (Ctrl-C / SIGTERM / shutdown),
2 configuration error (bad parameter file or value, message on stderr).
"""
from __future__ import annotations

import signal
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node

from ..config import ConfigError

__all__ = ['run_node', 'usage']

EXIT_CONFIG = 2


def usage(executable: str, summary: str) -> str:
    """The ``--help`` text: what the node does, how to start it, where the package lives."""
    import brace_control
    where = Path(brace_control.__file__).resolve().parent
    return (f'{executable}: {summary}\n\n'
            f'usage: {executable} [--help] --ros-args --params-file <device>.yaml '
            '[-r __ns:=/ns] [-p name:=value]\n\n'
            f'brace_control {getattr(brace_control, "__version__", "")} from {where}\n')


def run_node(factory: Callable[[], Node], *, executable: str, summary: str,
             args: Sequence[str] | None = None) -> int:
    """Init rclpy with ``args``, build the node, spin until shutdown; return the exit code."""
    argv = list(sys.argv if args is None else args)
    user_args = argv[1:argv.index('--ros-args')] if '--ros-args' in argv else argv[1:]
    if '-h' in user_args or '--help' in user_args:
        print(usage(executable, summary))
        return 0
    try:
        rclpy.init(args=argv)
    except Exception as exc:  # noqa: BLE001 - rcl reports bad --ros-args as RCLError
        print(f'{executable}: cannot start: {exc}', file=sys.stderr)
        return EXIT_CONFIG
    # SIGTERM (launch, systemd, bring-up --processes) ends like Ctrl-C.
    signal.signal(signal.SIGTERM, lambda *_: rclpy.try_shutdown())
    node = None
    try:
        node = factory()
    except ConfigError as exc:
        print(f'{executable}: configuration error: {exc}', file=sys.stderr)
        rclpy.try_shutdown()
        return EXIT_CONFIG
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    try:
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        shutdown = getattr(node, 'shutdown', None)
        if callable(shutdown):
            shutdown()
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
    return 0
