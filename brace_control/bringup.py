"""Bring-up: the four nodes of a device, in one process or each as its own process.

::

    brace-bringup config/lumbar_brace.yaml              # one process, simulated brace
    brace-bringup lumbar_brace --processes              # one process per node (installed executables)
    brace-bringup config/lumbar_brace.yaml --no-sim     # real bus (can.sim:=false)
    brace-bringup lumbar_brace --manual-lifecycle       # driver left unconfigured (ros2 lifecycle set)
    ros2 run brace_control bringup <share>/config/lumbar_brace.yaml

Nodes (ARCHITECTURE.md, data flow): ``trajectory_node`` -> ``ik_node`` ->
``can_driver_node`` (with the simulated brace on the same virtual bus unless
``--no-sim``) -> ``kinetics_node``. Every node reads the device file as its ROS parameter
file (``--ros-args --params-file``), in both modes.

The CAN driver is a lifecycle node (docs/can.md, "Lifecycle"): the bring-up takes it to
*active* (configure: bus open, drives booted; activate: commands taken), in one process by
its transitions directly, as processes by the driver executable itself. A driver that does
not come up ends the bring-up with exit code 1 and the cause. ``--manual-lifecycle`` leaves it
unconfigured for an operator's ``ros2 lifecycle set /can_driver_node configure`` and
``activate`` (README, "Operator's sequence").

*One process* (default): every node has its own executor thread (``--executor
per-node``, the default) or all share one :class:`MultiThreadedExecutor` (``--executor
multi``). Either way each node keeps its callbacks in its own mutually exclusive
callback group (rclpy's default group per node; the driver's blocking services in a
second group), so a node's callbacks never overlap each other (no locking inside the
nodes) while the nodes run in parallel: the trajectory node's 200 Hz timer is never
queued behind the kinetics node's forward kinematics or the driver's services.

*Processes* (``--processes``): each node is started the way ``ros2 run`` does, from
``<prefix>/lib/brace_control/<node>`` (prefix from the ament index), else the executable
next to this Python, else ``python -c 'from brace_control.nodes.<node> import main'``.

Shutdown (Ctrl-C, SIGTERM): the drives are disabled first (the driver's ``disable``
``std_srvs/Trigger`` service, while every node still runs), then the nodes are stopped
(processes: SIGINT, then SIGKILL after a timeout) and rclpy is shut down. Exit code 0
after a clean shutdown, 1 when a node failed (a process died or a node could not start),
2 for a configuration error.
"""
from __future__ import annotations

import argparse
import gc
import importlib
import inspect
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
import weakref
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from .can.errors import DriverError
from .checks import check_device
from .config import ConfigError, load_device_config, resolve_device_file
from .nodes import DRIVER_NODE, NODE_NAMES, topics

if TYPE_CHECKING:
    from .nodes.runner import StallWatch

__all__ = ['NODE_NAMES', 'STACK_LINKS', 'IDEMPOTENT_SERVICES', 'BringUp', 'ProcessBringUp', 'node_class',
           'find_executable', 'call_trigger', 'disable_drives', 'missing_links', 'wait_for_links',
           'wait_until_ready', 'main']

DRIVER = DRIVER_NODE
_MANUAL_HINT = ('can_driver_node is unconfigured (--manual-lifecycle): ros2 lifecycle set '
                '/can_driver_node configure, then activate')


def node_class(name: str) -> type:
    """The ``rclpy.node.Node`` subclass defined in ``brace_control.nodes.<name>``."""
    from rclpy.node import Node
    module = importlib.import_module(f'brace_control.nodes.{name}')
    classes = [obj for _, obj in inspect.getmembers(module, inspect.isclass)
               if issubclass(obj, Node) and obj is not Node and obj.__module__ == module.__name__]
    if len(classes) != 1:
        raise ImportError(f'brace_control.nodes.{name} defines {len(classes)} Node classes, '
                          'expected exactly one')
    return classes[0]


def ros_args(config: Path, *, sim: bool = True, extra: Sequence[str] = ()) -> list[str]:
    """``--ros-args --params-file <config> [-p can.sim:=false] ...`` for every node; the
    parameter file by its absolute path (the files it names are relative to it)."""
    args = ['--ros-args', '--params-file', str(Path(config).absolute())]
    if not sim:
        args += ['-p', 'can.sim:=false']
    return args + list(extra)


def _trigger_services(node: Any, suffix: str) -> list[str]:
    return sorted(name for name, types in node.get_service_names_and_types()
                  if name.rstrip('/').endswith(suffix) and 'std_srvs/srv/Trigger' in types)


#: the driver's services whose repetition is harmless: the answer to a repeat is the state
#: reached (home while disabled homes at the same position again; enable when enabled and
#: disable when disabled return at once)
IDEMPOTENT_SERVICES = frozenset({'home', 'enable', 'disable'})
#: s without an answer after which :func:`call_trigger` sends an idempotent request again
RESEND_S = 2.0


def call_trigger(node: Any, service: str, *, timeout: float = 5.0,
                 executor: Any = None, resend_s: float | None = None) -> tuple[bool, str]:
    """Call a ``std_srvs/Trigger`` service from ``node``; ``(success, message)``.

    If ``executor`` is given the node is already spun by it (another thread);
    otherwise the call spins ``node`` itself.

    A server drops its answer when it has not yet matched the new client's response reader
    (rmw_fastrtps waits 100 ms for it: "failed to send response (timeout): client will not
    receive response"; discovery can take longer on a loaded host). The request was carried
    out; only the answer is lost. A service in :data:`IDEMPOTENT_SERVICES` (by its last
    name component) is therefore asked again after ``resend_s`` (default :data:`RESEND_S`)
    without an answer, within ``timeout``; any other is asked once (``resend_s`` given:
    that service too). The requests asked before stay awaited: the first answer that comes
    is the one returned. A request that was only slow (an enable that takes a cable
    brace's slack up for seconds) answers first, with what it did; the repeat, served
    after it, would only say the state it found.
    """
    import rclpy
    from std_srvs.srv import Trigger
    if resend_s is None and service.rstrip('/').rsplit('/', 1)[-1] in IDEMPOTENT_SERVICES:
        resend_s = RESEND_S
    client = _trigger_client(node, service)
    if not client.wait_for_service(timeout_sec=timeout):
        return False, f'{service} not available'
    deadline = time.monotonic() + timeout
    futures: list[Any] = []

    def answered() -> Any:
        return next((f for f in futures if f.done()), None)
    try:
        while True:
            futures.append(client.call_async(Trigger.Request()))
            end = deadline if resend_s is None else min(deadline, time.monotonic() + resend_s)
            while answered() is None and time.monotonic() < end:
                if executor is None:
                    rclpy.spin_once(node, timeout_sec=min(0.05, max(end - time.monotonic(), 0.0)))
                else:
                    time.sleep(0.005)
            first = answered()
            if first is not None:
                res = first.result()
                return bool(res.success), str(res.message)
            if time.monotonic() >= deadline:
                asked = f' (asked {len(futures)} times)' if len(futures) > 1 else ''
                return False, f'{service}: no answer within {timeout} s{asked}'
    finally:
        for f in futures:
            if not f.done():
                forget = getattr(client, 'remove_pending_request', None)
                if forget is not None:
                    forget(f)
                f.cancel()


#: node -> {service: its Trigger client}: made once, kept for the node's life (see
#: :func:`_trigger_client`)
_TRIGGER_CLIENTS: 'weakref.WeakKeyDictionary[Any, dict[str, Any]]' = weakref.WeakKeyDictionary()


def _trigger_client(node: Any, service: str) -> Any:
    """``node``'s client of the ``std_srvs/Trigger`` ``service``, made on first use and kept:
    destroying a client while another thread's executor waits on the node's entities hung a
    test run (the spinner stuck in rclpy's wait-set teardown holding the interpreter lock,
    the same Fast DDS class as eProsima/Fast-DDS#6502); a node's clients go with the node."""
    from std_srvs.srv import Trigger
    clients = _TRIGGER_CLIENTS.setdefault(node, {})
    client = clients.get(service)
    if client is None:
        client = clients[service] = node.create_client(Trigger, service)
    return client


#: the stack's topic links: (topic, publishing node, subscribing node)
STACK_LINKS = ((topics.POSE_TRAJECTORY, 'trajectory_node', 'ik_node'),
               (topics.ACTUATOR_TRAJECTORY, 'ik_node', 'can_driver_node'),
               (topics.EXECUTION_STATUS, 'can_driver_node', 'trajectory_node'),
               (topics.EXECUTION_STATUS, 'ik_node', 'trajectory_node'),
               (topics.DRIVER_STATE, 'can_driver_node', 'trajectory_node'),
               (topics.ACTUATOR_SETPOINT, 'ik_node', 'can_driver_node'),
               (topics.JOINT_STATES, 'can_driver_node', 'kinetics_node'),
               (topics.POSE, 'kinetics_node', 'trajectory_node'))


def missing_links(node: Any, nodes: Sequence[str] = NODE_NAMES) -> list[str]:
    """The links of :data:`STACK_LINKS` between ``nodes`` that ``node`` does not yet see in
    the ROS graph (``'topic: publisher -> subscriber'``); ``[]`` when all are there."""
    out = []
    for topic, pub, sub in STACK_LINKS:
        if pub not in nodes or sub not in nodes:
            continue
        pubs = {i.node_name for i in node.get_publishers_info_by_topic(topic)}
        subs = {i.node_name for i in node.get_subscriptions_info_by_topic(topic)}
        if pub not in pubs or sub not in subs:
            out.append(f'{topic}: {pub} -> {sub}')
    return out


def wait_for_links(node: Any, *, timeout: float = 20.0, nodes: Sequence[str] = NODE_NAMES) -> None:
    """Wait until ``node`` sees every link of the stack in the graph.

    Nodes started as separate processes find each other by DDS discovery, which takes
    from milliseconds to seconds on a loaded host. A goal sent before the IK node's
    setpoints reach the driver starts a motion the drives do not follow; the first
    setpoint that does arrive is then a jump, and the driver's step limit stops the
    brace (docs/safety.md §7). Send goals after this returns.

    :raises TimeoutError: a link still missing after ``timeout`` s (named).
    """
    deadline = time.monotonic() + timeout
    while missing := missing_links(node, nodes):
        if time.monotonic() > deadline:
            raise TimeoutError(f'the stack is not connected after {timeout} s: missing {missing}')
        time.sleep(0.05)


def wait_until_ready(node: Any, *, timeout: float = 20.0, driver: str | None = 'enabled',
                     nodes: Sequence[str] = ('trajectory_node', 'ik_node')) -> None:
    """Wait until each of ``nodes`` reports on ``/diagnostics`` that its trajectory output
    has a subscriber besides ``node``'s own (``subscribers <topic>``, by that node's own
    discovery), the
    trajectory node that it hears the execution reports of the ik node and the driver
    (``publishers /brace/execution_status``), and that the driver's state is ``driver``
    (``None``: any; then only the ik node's reports are required).

    :func:`wait_for_links` sees the graph from ``node``'s side; a node process matches the
    others in its own discovery, maybe later: a goal planned before the IK node matched is
    rejected ("nothing subscribes to /brace/pose_trajectory"). ``node`` must be spinning in
    another thread (its subscription receives the diagnostics: at 1 Hz, and within 0.1 s of
    a change of what is waited on here, or of this subscription joining).

    :raises TimeoutError: not ready after ``timeout`` s (what was last reported, named).
    """
    from diagnostic_msgs.msg import DiagnosticArray
    seen: dict[str, dict[str, str]] = {}
    lock = threading.Lock()

    def on_diagnostics(msg: Any) -> None:
        with lock:
            for st in msg.status:
                name = st.name.rsplit('/', 1)[-1]
                if name in nodes:
                    seen[name] = {kv.key: kv.value for kv in st.values}

    def own(topic: str) -> int:
        # ``node``'s own subscriptions count in the others' matches: a probe that records
        # /brace/actuator_trajectory is not the driver
        return sum(1 for s in node.subscriptions if s.topic_name == topic)

    def ready() -> bool:
        with lock:
            for name in nodes:
                values = seen.get(name)
                if values is None:
                    return False
                counts = {k.split(' ', 1)[1]: v for k, v in values.items() if k.startswith('subscribers ')}
                if not counts or any(not v.isdigit() or int(v) < 1 + own(topic)
                                     for topic, v in counts.items()):
                    return False
            if 'trajectory_node' in nodes:
                # the execution reports: the ik node's, and the driver's when one is expected
                reports = seen['trajectory_node'].get(f'publishers {topics.EXECUTION_STATUS}', '0')
                if not reports.isdigit() or int(reports) < (1 if driver is None else 2):
                    return False
            if driver is not None and 'trajectory_node' in nodes:
                return seen['trajectory_node'].get('driver', '').startswith(driver)
            return True

    sub = node.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, on_diagnostics, 50)
    try:
        deadline = time.monotonic() + timeout
        while not ready():
            if time.monotonic() > deadline:
                with lock:
                    raise TimeoutError(f'the stack is not ready after {timeout} s: {seen or "no diagnostics"}')
            time.sleep(0.05)
    finally:
        node.destroy_subscription(sub)


def disable_drives(node: Any, *, timeout: float = 5.0, executor: Any = None) -> tuple[bool, str]:
    """Call every ``.../disable`` Trigger service in the graph (the CAN driver's)."""
    deadline = time.monotonic() + min(timeout, 2.0)
    services = _trigger_services(node, 'disable')
    while not services and time.monotonic() < deadline:     # discovery may lag a little
        time.sleep(0.05)
        services = _trigger_services(node, 'disable')
    if not services:
        return False, 'no disable service in the graph'
    results = [call_trigger(node, s, timeout=timeout, executor=executor) for s in services]
    return all(ok for ok, _ in results), '; '.join(f'{s}: {m}' for s, (_, m) in zip(services, results))


# --------------------------------------------------------------------- one process

class BringUp:
    """All nodes of a device in this process.

    :param config: device YAML path or device name.
    :param sim: start the simulated brace with the driver (``can.sim``).
    :param nodes: which nodes (default all four, in data-flow order).
    :param context: an rclpy ``Context`` (default: the global one, initialised by the caller).
    :param extra_args: more ``--ros-args`` items for every node (``['-p', 'x:=1']``).
    :param executor: ``'multi'``: one :class:`MultiThreadedExecutor` holds every node
        (``num_threads``, default one per node + 1); each node's callbacks stay in their
        own mutually exclusive group, the driver's blocking services in a separate one.
        ``'per-node'`` (default): each node on its own executor (:func:`~.nodes.runner.
        make_executor`: the events executor where rclpy has it) in its own thread (the driver's services run their work in a thread of their own and await it,
        so they never hold up its streams). Same isolation between nodes, less executor
        overhead: the CAN driver's SYNC thread (same interpreter, same GIL) keeps its period
        far better, see bench/RESULTS.md.
    :param manual_lifecycle: leave the CAN driver unconfigured (default: configured and
        activated here, :meth:`~.nodes.can_driver_node.CanDriverNode.autostart`).
    :raises DriverError: the driver's configure or activate failed (the message says why).
    """

    def __init__(self, config: str | Path, *, sim: bool = True,
                 nodes: Sequence[str] = NODE_NAMES, context: Any = None,
                 extra_args: Sequence[str] = (), num_threads: int | None = None,
                 executor: str = 'per-node', manual_lifecycle: bool = False) -> None:
        from rclpy.executors import MultiThreadedExecutor

        from .nodes.runner import make_executor
        if executor not in ('multi', 'per-node'):
            raise ValueError(f"executor must be 'multi' or 'per-node', got {executor!r}")
        self.config_path = resolve_device_file(config)
        self.config = load_device_config(self.config_path)
        self.context = context
        self.sim = sim
        self.names = tuple(nodes)
        self.nodes: dict[str, Any] = {}
        self.mode = executor
        self._executors: list[Any] = []
        self._args = ros_args(self.config_path, sim=sim, extra=extra_args)
        self._threads: list[threading.Thread] = []
        self._stop = threading.Event()
        self._helper = None
        self._closed = False
        shared = (MultiThreadedExecutor(num_threads=num_threads or len(self.names) + 1,
                                        context=context) if executor == 'multi' else None)
        if shared is not None:
            self._executors.append(shared)
        try:
            import rclpy
            for name in self.names:
                cls = node_class(name)
                self.nodes[name] = cls(context=context, cli_args=self._args)
            if DRIVER in self.nodes and not manual_lifecycle:
                self.nodes[DRIVER].autostart()          # configure + activate, before spinning
            self._helper = rclpy.create_node('brace_bringup', context=context)
            for name, node in [*self.nodes.items(), ('helper', self._helper)]:
                if shared is not None:
                    shared.add_node(node)
                    continue
                ex = make_executor(context=context)
                ex.add_node(node)
                self._executors.append(ex)
        except BaseException:
            self.shutdown(disable=False)
            raise

    def node(self, name: str) -> Any:
        return self.nodes[name]

    @property
    def helper(self) -> Any:
        """A plain node of the bring-up (service clients, test probes), spun with the others."""
        return self._helper

    @property
    def running(self) -> bool:
        return bool(self._threads) and all(t.is_alive() for t in self._threads)

    def start(self) -> 'BringUp':
        """Spin the executor(s) in background threads."""
        from .nodes.runner import freeze_start_up_heap
        freeze_start_up_heap()
        for i, ex in enumerate(self._executors):
            t = threading.Thread(target=self._spin, args=(ex,), name=f'bringup-executor-{i}',
                                 daemon=True)
            t.start()
            self._threads.append(t)
        return self

    def _spin(self, executor: Any) -> None:
        # spin_once in a loop, not spin(): rclpy's events executor (Kilted) busy-waits a
        # core in spin() and blocks other threads adding entities to its nodes meanwhile;
        # and a helper's client destroyed meanwhile must not end the loop (nodes/spin.py)
        from .nodes.spin import spin_until
        spin_until(executor, self._stop)

    def call(self, service: str, *, timeout: float = 5.0) -> tuple[bool, str]:
        """Call a Trigger service (``/can_driver_node/enable`` ...) while the nodes spin."""
        return call_trigger(self._helper, service, timeout=timeout,
                            executor=self._executors[0] if self._threads else None)

    def disable_drives(self, timeout: float = 5.0) -> tuple[bool, str]:
        """Disable the drives through the driver's service (nodes still running)."""
        if DRIVER not in self.nodes or self._helper is None:
            return True, 'no driver'
        state = getattr(self.nodes[DRIVER], 'lifecycle_state', 'active')
        if state not in ('inactive', 'active'):
            return True, f'the driver is {state}: no bus open, nothing to disable'
        return disable_drives(self._helper, timeout=timeout,
                              executor=self._executors[0] if self._threads else None)

    def shutdown(self, *, disable: bool = True, timeout: float = 5.0) -> None:
        """Drives disabled first, then the executor(s) and the nodes (idempotent)."""
        if self._closed:
            return
        self._closed = True
        if disable and self._threads:
            ok, msg = self.disable_drives(timeout)
            log = self._helper.get_logger() if self._helper else None
            if log:
                if ok:
                    log.info(f'drives disabled: {msg}')
                else:
                    log.error(f'disabling the drives failed: {msg}')
        for node in reversed(list(self.nodes.values())):
            stop = getattr(node, 'shutdown', None)
            if callable(stop):
                try:
                    stop()
                except Exception as exc:  # noqa: BLE001 - keep shutting the others down
                    node.get_logger().error(f'shutdown: {exc}')
        self._stop.set()
        for t in self._threads:
            t.join(timeout)
        for ex in self._executors:
            ex.shutdown(timeout_sec=timeout)
        # as runner.run_node ends a node: out of its executor first, then destroyed, then the
        # executors dropped. The events executor keeps callbacks registered on a node's
        # subscriptions and publishers; a node destroyed still in it crashed the bring-up
        # (SIGSEGV in destroy_node, 1 Ctrl-C of 7 in a loop; ros2/rclpy#1644)
        for ex in self._executors:
            for node in list(ex.get_nodes()):
                try:
                    ex.remove_node(node)
                except Exception:  # noqa: BLE001 - a teardown step; the next ones still run
                    pass
        for node in list(self.nodes.values()) + ([self._helper] if self._helper else []):
            node.destroy_node()
        self._executors.clear()
        gc.collect()

    def __enter__(self) -> 'BringUp':
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.shutdown()


# --------------------------------------------------------------------- processes

def find_executable(name: str) -> list[str]:
    """The command that starts node ``name`` as ``ros2 run brace_control <name>`` would."""
    try:
        from ament_index_python.packages import PackageNotFoundError, get_package_prefix
        try:
            exe = Path(get_package_prefix('brace_control')) / 'lib' / 'brace_control' / name
            if os.access(exe, os.X_OK):
                return [str(exe)]
        except (PackageNotFoundError, OSError):    # not in the index / no AMENT_PREFIX_PATH
            pass
    except ImportError:
        pass
    beside = Path(sys.executable).parent / name
    if os.access(beside, os.X_OK):
        return [str(beside)]
    found = shutil.which(name)
    if found and Path(found).parent == Path(sys.executable).parent:
        return [found]
    return [sys.executable, '-c',
            f'import sys; from brace_control.nodes.{name} import main; sys.exit(main())']


class ProcessBringUp:
    """Each node as its own process (``--processes``). The CAN driver's executable configures
    and activates itself (exit code 1 if that fails) unless ``manual_lifecycle``: then it
    starts unconfigured (``can_driver_node --manual-lifecycle``)."""

    def __init__(self, config: str | Path, *, sim: bool = True, nodes: Sequence[str] = NODE_NAMES,
                 extra_args: Sequence[str] = (), env: dict[str, str] | None = None,
                 manual_lifecycle: bool = False) -> None:
        self.config_path = resolve_device_file(config)
        load_device_config(self.config_path)           # fail early on a broken file
        self.names = tuple(nodes)
        self.args = ros_args(self.config_path, sim=sim, extra=extra_args)
        self.env = dict(os.environ if env is None else env)
        pkg_root = str(Path(__file__).resolve().parent.parent)
        self.env['PYTHONPATH'] = os.pathsep.join(
            p for p in (self.env.get('PYTHONPATH', ''), pkg_root) if p)
        self.procs: dict[str, subprocess.Popen] = {}
        self.manual_lifecycle = manual_lifecycle
        #: the write end of the pipe every node watches: when this process is gone (by any
        #: signal, SIGKILL included) the nodes read end-of-file and stop, drives disabled
        #: first (:func:`~.nodes.runner.watch_parent`)
        self._lifeline: int | None = None

    def start(self) -> 'ProcessBringUp':
        from .nodes.can_driver_node import MANUAL_LIFECYCLE
        from .nodes.runner import PARENT_FD_ENV
        read_end, self._lifeline = os.pipe()          # neither end inheritable by default
        try:
            env = {**self.env, PARENT_FD_ENV: str(read_end)}
            for name in self.names:
                own = [MANUAL_LIFECYCLE] if name == DRIVER and self.manual_lifecycle else []
                # own session: a terminal Ctrl-C reaches only the bring-up, which disables the
                # drives before it forwards SIGINT to the nodes
                self.procs[name] = subprocess.Popen([*find_executable(name), *own, *self.args],
                                                    env=env, start_new_session=True,
                                                    pass_fds=(read_end,))
        finally:
            os.close(read_end)
        return self

    def failed(self) -> dict[str, int]:
        """Nodes whose process has ended (name -> return code)."""
        return {n: p.returncode for n, p in self.procs.items() if p.poll() is not None}

    def stop(self, timeout: float = 10.0) -> dict[str, int]:
        """SIGINT every process (reverse data-flow order), SIGKILL after ``timeout``."""
        for name in reversed(self.names):
            p = self.procs.get(name)
            if p is not None and p.poll() is None:
                p.send_signal(signal.SIGINT)
        deadline = time.monotonic() + timeout
        codes = {}
        for name, p in self.procs.items():
            try:
                codes[name] = p.wait(max(deadline - time.monotonic(), 0.1))
            except subprocess.TimeoutExpired:
                p.kill()
                codes[name] = p.wait()
        if self._lifeline is not None:
            os.close(self._lifeline)
            self._lifeline = None
        return codes


# ---------------------------------------------------------------------------- CLI

def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog='brace-bringup', description=__doc__.split('\n\n')[0])
    ap.add_argument('config', help='device YAML (path, or a device name in config/)')
    ap.add_argument('--processes', action='store_true', help='each node as its own process')
    ap.add_argument('--no-sim', action='store_true', help='real bus: do not start the simulated brace')
    ap.add_argument('--executor', choices=('per-node', 'multi'), default='per-node',
                    help='one process: an executor per node (default) or one MultiThreadedExecutor')
    ap.add_argument('--nodes', nargs='+', choices=NODE_NAMES, default=list(NODE_NAMES),
                    help='start only these nodes')
    ap.add_argument('--manual-lifecycle', action='store_true',
                    help='leave can_driver_node unconfigured: ros2 lifecycle set /can_driver_node '
                         'configure, then activate (default: brought to active)')
    return ap


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    extra: list[str] = []
    if '--ros-args' in argv:
        i = argv.index('--ros-args')
        argv, extra = argv[:i], argv[i + 1:]
    args = _parser().parse_args(argv)
    stop = threading.Event()
    # Our own handlers, first: on Ctrl-C, SIGTERM, a closed terminal (SIGHUP) or SIGQUIT the
    # context must stay up until the drives are disabled; a signal during start-up ends it
    # cleanly too (no KeyboardInterrupt traceback)
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT):
        signal.signal(sig, lambda *_: stop.set())
    try:
        # the whole device file, across its keys, before anything starts (exit 2, no traceback)
        check_device(load_device_config(resolve_device_file(args.config)))
        from .nodes.runner import LONG_WORK_S, StallWatch, cut_short_after, spin_stall_s
        stall_s = spin_stall_s()
    except ConfigError as exc:
        print(f'brace-bringup: configuration error: {exc}', file=sys.stderr)
        return 2
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    from .nodes.dds import use_discovery_profile
    use_discovery_profile()                   # this process's participant and the nodes'
    import rclpy
    from rclpy.signals import SignalHandlerOptions
    # The bring-up's dead-man's switch (runner.SPIN_STALL_S), armed before its first DDS call
    # and re-armed by its main loop, in both modes. A DDS call that deadlocks inside Fast DDS
    # holding the interpreter lock (eProsima/Fast-DDS#6502) stops every thread of this
    # process, the main loop and its signal handlers with it: a Ctrl-C would then do nothing,
    # ever (the one-process CLI test, fresh-clone run 1313). Instead the kernel ends the
    # bring-up once the loop has not turned for SPIN_STALL_S (SIGALRM, stacks on stderr); its
    # node processes, or in one process the control cycle's process, see it gone and disable
    # the drives. The participants' creation and the start-up may take LONG_WORK_S.
    watch = StallWatch(stall_s)
    watch.allow(LONG_WORK_S)
    rclpy.init(args=['brace-bringup'], signal_handler_options=SignalHandlerOptions.NO)
    try:
        running = nodes_already_running(args.nodes, stop, namespace=_namespace(extra))
        if running:
            print(f'brace-bringup: {", ".join(running)} already running on ROS_DOMAIN_ID '
                  f'{os.environ.get("ROS_DOMAIN_ID", "0")} (another brace-bringup?); two drivers '
                  'would command the same drives. Stop it first (ros2 node list)', file=sys.stderr)
            return 1
        if stop.is_set():
            return 0
        if args.processes:
            return _run_processes(args, extra, stop, watch)
        return _run_in_process(args, extra, stop, watch)
    except ConfigError as exc:
        print(f'brace-bringup: configuration error: {exc}', file=sys.stderr)
        return 2
    except DriverError as exc:
        print(f'brace-bringup: the CAN driver did not come up: {exc}', file=sys.stderr)
        return 1
    finally:
        StallWatch.active = None
        rclpy.try_shutdown()                  # under the shutdown's bound, if one was set
        cut_short_after(None)


#: s the bring-up watches the ROS graph for nodes of its names before it starts its own
#: (DDS discovery of a running node on this machine: 0.15-0.7 s measured on a quiet host,
#: bench/RESULTS.md; 1.5 s was not enough once in a full test run on a loaded one)
GRAPH_WATCH_S = 3.0
#: s a bring-up in processes mode listens for an earlier one's announcement after its start
#: (:class:`RivalWatch`; discovery on one machine takes seconds at worst)
RIVAL_WATCH_S = 30.0
#: s the CAN driver's disable service has to answer a bring-up that is stopping
DISABLE_CALL_S = 5.0
#: s the bring-up's shutdown may spend in DDS before its node processes are stopped: the
#: rival watch's end, the disable service's discovery (at most 2 s) and its answer
#: (DISABLE_CALL_S), and a margin; past it the kernel ends the bring-up (docs/safety.md §20)
SHUTDOWN_DDS_S = 2.0 + DISABLE_CALL_S + 1.5
#: s the whole shutdown of a bring-up in one process may take: the disable service's call
#: (SHUTDOWN_DDS_S), then the nodes' own shutdown (the driver's ends its control cycle's
#: process: ``runner.SHUTDOWN_S``, 15 s), the executors and the DDS teardown; past it the
#: kernel ends the bring-up (SIGALRM, stacks on stderr) and the control cycle's process, its
#: link closed, disables the drives (docs/safety.md §20)
IN_PROCESS_SHUTDOWN_S = SHUTDOWN_DDS_S + 15.0
#: announcements a bring-up's reader keeps until it takes them (one per bring-up running)
ANNOUNCEMENTS_KEPT = 32
#: s a node found in the graph has to answer before it counts as gone (a killed process's
#: nodes stay in the graph until their lease runs out); its service's discovery and answer
#: took longer than 2 s in test runs on a loaded host
ANSWER_S = 5.0


def _namespace(ros_args_: Sequence[str]) -> str:
    """The namespace ``-r __ns:=/ns`` in the extra ``--ros-args`` gives the nodes ('/' if none)."""
    for a in ros_args_:
        if a.startswith('__ns:='):
            ns = a.split(':=', 1)[1]
            return ns if ns.startswith('/') else '/' + ns
    return '/'


def nodes_already_running(names: Sequence[str], stop: threading.Event | None = None,
                          watch: float = GRAPH_WATCH_S, namespace: str = '/',
                          answer_s: float = ANSWER_S) -> list[str]:
    """The nodes of ``names`` (in ``namespace``) some other process already runs in this ROS
    domain, watched for ``watch`` s (discovery takes its time); [] when none appeared.

    A node counts only when it answers (``~/list_parameters``, which every rclpy node serves
    while it spins) within ``answer_s`` of appearing: the graph keeps the nodes of a process
    that was killed, or just ended, until its participant's lease runs out (Fast DDS: 20 s)."""
    import rclpy
    from rcl_interfaces.srv import ListParameters
    probe = rclpy.create_node(f'brace_bringup_graph_{os.getpid()}')
    clients: dict[str, Any] = {}
    seen: dict[str, float] = {}
    futures: dict[str, Any] = {}
    try:
        end = time.monotonic() + watch
        while not (stop is not None and stop.is_set()):
            now = time.monotonic()
            for n, ns in probe.get_node_names_and_namespaces():
                if n in names and ns == namespace and n not in seen:
                    seen[n] = now
                    clients[n] = probe.create_client(
                        ListParameters, f'{namespace.rstrip("/")}/{n}/list_parameters')
            for n, c in clients.items():
                if n not in futures and c.service_is_ready():
                    futures[n] = c.call_async(ListParameters.Request(depth=1))
            alive = sorted(n for n, f in futures.items() if f.done() and f.exception() is None)
            if alive:
                return alive
            waiting = [n for n, t in seen.items() if now - t < answer_s]
            if now >= end and not waiting:
                return []
            rclpy.spin_once(probe, timeout_sec=0.02)
        return []
    finally:
        for c in clients.values():
            probe.destroy_client(c)
        probe.destroy_node()


class RivalWatch:
    """Tells other ``brace-bringup`` processes of this one, and this one of a rival.

    The graph watch before the start (:func:`nodes_already_running`) sees a running stack
    only once DDS discovery has found it, which on a loaded host can take longer than its
    window. So every bring-up also announces itself on :data:`~.nodes.topics.BRINGUP`
    (latched: a bring-up that joins later still gets it, whenever discovery completes) with
    its start time, process, host, namespace and nodes. A bring-up that learns of another
    one in its namespace, running any of its nodes and started before it, has a
    :attr:`rival`: it stops its own stack (the earlier one keeps running; it sees the later
    one's announcement and ignores it). In processes mode it listens for
    :data:`RIVAL_WATCH_S` after the start; its announcement stays up while it runs.
    """

    def __init__(self, node: Any, names: Sequence[str], namespace: str = '/') -> None:
        import socket

        from diagnostic_msgs.msg import DiagnosticStatus
        from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

        from .nodes.msgs import status_msg
        self.names = tuple(names)
        self.namespace = namespace
        self.key = (time.time_ns(), socket.gethostname(), os.getpid())
        self.rival: dict[str, Any] | None = None
        #: every announcement taken (the keys: started, host, pid), this one's own included
        self.seen: list[tuple[int, str, int]] = []
        self._node = node
        self._pub = node.create_publisher(DiagnosticStatus, topics.BRINGUP, topics.LATCHED_QOS)
        # each bring-up keeps its one announcement (depth 1), but this reader must keep every
        # bring-up's until taken: with depth 1 the own announcement, arriving after an
        # earlier bring-up's, replaced it unread (full test runs: the later bring-up matched
        # the earlier one's announcement and kept running beside it)
        self._sub = node.create_subscription(
            DiagnosticStatus, topics.BRINGUP, self._on_announcement,
            QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=ANNOUNCEMENTS_KEPT,
                       reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.TRANSIENT_LOCAL))
        self._pub.publish(status_msg('brace_bringup', 'running', started=self.key[0], host=self.key[1],
                                     pid=self.key[2], namespace=namespace, nodes=list(self.names)))

    def _on_announcement(self, msg: Any) -> None:
        from .nodes.msgs import status_values
        v = status_values(msg)
        try:
            key = (int(v['started']), v['host'], int(v['pid']))
        except (KeyError, ValueError):
            return                                  # not a bring-up's announcement
        self.seen.append(key)
        shared = sorted(set(v.get('nodes', '').split(',')) & set(self.names))
        if key < self.key and v.get('namespace') == self.namespace and shared and self.rival is None:
            self.rival = {'nodes': shared, 'pid': key[2], 'host': key[1],
                          'before_s': (self.key[0] - key[0]) * 1e-9}

    def describe(self) -> str:
        """What the rival runs, for the error message ('' when none)."""
        r = self.rival
        if r is None:
            return ''
        return (f'{", ".join(r["nodes"])} already running on ROS_DOMAIN_ID '
                f'{os.environ.get("ROS_DOMAIN_ID", "0")}: brace-bringup pid {r["pid"]} on {r["host"]}, '
                f'started {r["before_s"]:.1f} s before this one; two drivers would command the same '
                'drives. Stopping this one')


def _run_in_process(args: argparse.Namespace, extra: list[str], stop: threading.Event,
                    watch: StallWatch) -> int:
    from .nodes.runner import LONG_WORK_S, StallWatch, cut_short_after
    watch.allow(LONG_WORK_S)                  # the nodes' creation, the driver's autostart
    bringup = BringUp(args.config, sim=not args.no_sim, nodes=args.nodes, extra_args=extra,
                      executor=args.executor, manual_lifecycle=args.manual_lifecycle)
    log = bringup.helper.get_logger()
    rivals = RivalWatch(bringup.helper, bringup.names, _namespace(extra))
    bringup.start()
    # from here on the executors' threads make the DDS calls, beside this loop: it waits,
    # turns the watch, and a stuck native call in any of them stops it turning
    watch.rearm()
    log.info(f'{", ".join(bringup.names)} up ({bringup.config_path}); Ctrl-C to stop')
    if args.manual_lifecycle and DRIVER in bringup.names:
        log.info(_MANUAL_HINT)
    rc = 0
    while not stop.wait(0.2):
        watch.turn()
        if not bringup.running:
            log.error('executor stopped unexpectedly')
            rc = 1
            break
        if rivals.rival is not None:
            log.error(rivals.describe())
            rc = 1
            break
    else:
        log.info('shutting down: disabling the drives first')
    # the whole shutdown (the disable service, the nodes' own shutdown, the executors, the
    # DDS teardown) is bounded, never extended: past it the kernel ends this process (stacks
    # on stderr) and the control cycle's process, its link closed, disables the drives
    StallWatch.active = None
    cut_short_after(IN_PROCESS_SHUTDOWN_S)
    bringup.shutdown()
    return rc


def _run_processes(args: argparse.Namespace, extra: list[str], stop: threading.Event,
                   watch: StallWatch) -> int:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    from .nodes.runner import (EXIT_CONFIG, LONG_WORK_S, TEARDOWN_CUT, TEARDOWN_S, StallWatch,
                               cut_short_after)
    from .nodes.spin import BackgroundSpinner
    group = ProcessBringUp(args.config, sim=not args.no_sim, nodes=args.nodes, extra_args=extra,
                           manual_lifecycle=args.manual_lifecycle)
    # the watch (main): the rival watch's DDS calls in the spinner thread may deadlock holding
    # the interpreter lock; then the main loop stops turning, the kernel ends the bring-up, and
    # its nodes, seeing their parent gone, stop themselves. Creating this process's
    # participants up to LONG_WORK_S (on a loaded host the start-up once took over
    # SPIN_STALL_S: fresh-clone run 210, two busy loops beside); from the rival watch's start
    # on, whose DDS callbacks may hang holding the lock, SPIN_STALL_S
    watch.allow(LONG_WORK_S)
    helper = rclpy.create_node('brace_bringup')
    log = helper.get_logger()
    # the announcements on a node of their own, spun beside the main thread (which only
    # waits): the helper stays free for disable_drives' own spinning. Spun for the first
    # RIVAL_WATCH_S only: after that this process makes no DDS calls of its own until the
    # shutdown (a stuck native call would keep the main thread from stopping the children)
    watcher = rclpy.create_node('brace_bringup_rivals')
    rivals = RivalWatch(watcher, group.names, _namespace(extra))
    executor = SingleThreadedExecutor()
    executor.add_node(watcher)
    watch.rearm()
    spinner: BackgroundSpinner | None = BackgroundSpinner(executor, 'bringup-rivals').start()
    watch_until = time.monotonic() + RIVAL_WATCH_S
    group.start()
    log.info(f'{", ".join(group.names)} started as processes; Ctrl-C to stop')
    if args.manual_lifecycle and DRIVER in group.names:
        log.info(_MANUAL_HINT)
    rc = 0
    while not stop.wait(0.2):
        watch.turn()
        dead = group.failed()
        if dead:
            log.error(f'node process(es) ended: {dead}; stopping the others')
            # a node that found a configuration error (exit 2) makes it the bring-up's
            rc = EXIT_CONFIG if EXIT_CONFIG in dead.values() else 1
            break
        if rivals.rival is not None:
            log.error(rivals.describe())
            rc = 1
            break
        if spinner is not None and time.monotonic() > watch_until:
            spinner.stop()
            spinner = None
    # The shutdown's DDS calls (the spinner's end, the disable service) may deadlock inside
    # Fast DDS holding the interpreter lock (eProsima/Fast-DDS#6502): then no Python code
    # of this process runs again, not even the SIGKILL of its nodes. The kernel ends it
    # after SHUTDOWN_DDS_S instead (status 142, its stacks on stderr); its node processes
    # see their parent gone and stop by themselves, each disabling what it drives.
    StallWatch.active = None                  # nothing extends the shutdown's bound
    cut_short_after(SHUTDOWN_DDS_S)
    if spinner is not None:
        spinner.stop()
    executor.shutdown()
    if DRIVER in group.names and group.procs[DRIVER].poll() is None:
        ok, msg = disable_drives(helper, timeout=DISABLE_CALL_S)
        (log.info if ok else log.error)(f'drives disabled: {msg}' if ok
                                        else f'disabling the drives failed: {msg}')
    cut_short_after(None)                     # no DDS call while the nodes are stopped
    codes = group.stop()
    # the last DDS calls (this process's own endpoints and participant), bounded the same way
    cut_short_after(TEARDOWN_S)
    cut = sorted(n for n, c in codes.items() if c == TEARDOWN_CUT)
    if cut:
        log.warning(f'{", ".join(cut)}: work done, DDS teardown cut short after {TEARDOWN_S:g} s '
                    '(a deadlock inside Fast DDS, eProsima/Fast-DDS#6502; stacks on stderr)')
    bad = {n: c for n, c in codes.items() if c not in (0, -signal.SIGINT, TEARDOWN_CUT)}
    if bad:
        log.error(f'exit codes: {bad}')
        rc = rc or 1
    watcher.destroy_node()                    # its announcement with it
    helper.destroy_node()
    return rc


if __name__ == '__main__':
    raise SystemExit(main())
