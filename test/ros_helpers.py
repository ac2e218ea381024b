"""rclpy helpers for node tests: one executor per test on the session's context; spin until a condition.

The ``ros`` fixture that yields a :class:`Ros` lives in ``conftest.py``; test modules take it as
an argument and import from here only the helpers and constants they name.
No fixed sleeps: tests spin the executor until what they wait for has happened, with a
timeout that fails the test with a message.
"""
from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import pytest
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy

# a pass that a thread's destroyed entity cut short (ros2/rclpy#1284) is passed again: a
# replay in a thread destroys its publishers while the test spins (run 414)
from brace_control.nodes.spin import spin_once

REPO = Path(__file__).resolve().parent.parent
LUMBAR_YAML = REPO / 'config' / 'lumbar_brace.yaml'

RELIABLE_10 = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)

#: ROS parameters of every test bring-up that runs goals: the wall-clock deadlines of the
#: trajectory node that are not what any of those tests checks, widened for a busy host
#: (make test runs two stacks on two cores). ``trajectory.planning_budget`` 5 s (1 s in the
#: YAMLs: a trainer's path plan took 1.66 s, a shoulder's 1.13 s, both rejected), and
#: ``safety.report_timeout`` 3 s (1 s: "the driver did not start the motion within 1 s" and
#: "... did not report the motion finished within 1.32 s of its planned end", each once in a
#: run with two workers), and ``trajectory.plan_lookahead`` 0.4 s (0.15 s: a preempting
#: plan that reached the driver later than that, the running motion gone on, was rejected
#: as "its start is 15.224 mm ... from the command", once in the seeded operator and once in
#: the 200-goal flood). A goal still succeeds only with the TRUE platform at its target.
BUSY_HOST_ARGS = ['-p', 'trajectory.planning_budget:=5.0', '-p', 'safety.report_timeout:=3.0',
                  '-p', 'trajectory.plan_lookahead:=0.4']


def wait_until(predicate: Callable[[], bool], timeout: float, what: str,
               evidence: Callable[[], str] | None = None) -> None:
    """Poll ``predicate`` (every 20 ms) until true; AssertionError naming ``what`` after
    ``timeout`` s (for tests whose nodes spin in threads of their own), with what
    ``evidence()`` says then."""
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            said = ''
            if evidence is not None:
                try:
                    said = f'; {evidence()}'
                except Exception as exc:  # noqa: BLE001 - the failure is reported anyway
                    said = f'; no evidence: {exc!r}'
            raise AssertionError(f'timed out waiting for {what}{said}')
        time.sleep(0.02)


class KernelThread(NamedTuple):
    """One thread as the kernel has it (``/proc/<pid>/task/<tid>``)."""
    tid: int
    name: str
    state: str          # R running, S sleeping, D, Z ...
    policy: int         # os.SCHED_OTHER, os.SCHED_FIFO, ...
    rt_priority: int
    wchan: str          # where it waits ('-': nowhere)


def process_alive(pid: int) -> bool:
    """The process exists and is not a zombie (a child nobody reaped yet counts as gone)."""
    try:
        with open(f'/proc/{pid}/stat') as f:
            return f.read().rsplit(')', 1)[1].split()[0] != 'Z'
    except OSError:
        return False


def kernel_threads(pid: int) -> list[KernelThread]:
    """Each thread of ``pid`` (``/proc/<pid>/task/*/stat`` fields 3, 41 and 40, and
    ``wchan``); one that ended meanwhile is passed over."""
    out = []
    for tid in sorted(os.listdir(f'/proc/{pid}/task'), key=int):
        try:
            with open(f'/proc/{pid}/task/{tid}/stat') as f:
                stat = f.read()
            with open(f'/proc/{pid}/task/{tid}/wchan') as f:
                wchan = f.read().strip() or '-'
        except OSError:
            continue
        fields = stat.rsplit(')', 1)[1].split()
        out.append(KernelThread(int(tid), stat[stat.index('(') + 1:stat.rindex(')')], fields[0],
                                int(fields[38]), int(fields[37]), wchan))
    return out


def _threads_of(pid: int) -> str:
    """Each thread of ``pid``: name, scheduler state and where it waits."""
    return ', '.join(f'{t.name} {t.state} {t.wchan}' for t in kernel_threads(pid))


def cycle_evidence(node: Any) -> str:
    """What a stalled in-process stack's CAN driver shows (runs 901 and 904: its truth and its
    services went silent for 15 s on a loaded host): the age of the newest sample from its
    control cycle's process, that process's threads, and this process's threads' stacks
    (on stderr, captured with the test's output)."""
    import faulthandler
    import sys
    parts = []
    master = getattr(node, 'master', None)
    try:
        fb = master.feedback()
        parts.append(f'newest cycle sample {time.time() - fb.wall:.1f} s old, master {master.state.value}')
    except Exception as exc:  # noqa: BLE001
        parts.append(f'no cycle sample: {exc!r}')
    pid = getattr(master, 'pid', None)
    if pid:
        try:
            parts.append(f'cycle process {pid}: {_threads_of(pid)}')
        except OSError as exc:
            parts.append(f'cycle process {pid}: {exc!r}')
    parts.append(f'this process: {_threads_of(os.getpid())}; load {os.getloadavg()}')
    faulthandler.dump_traceback(file=sys.stderr, all_threads=True)
    return '; '.join(parts)


@contextlib.contextmanager
def stack_in_process(device: str | Path, out: Path, extra_args: Sequence[str]) -> Iterator[Any]:
    """The whole stack in this process (:class:`~brace_control.bringup.BringUp`) on a context of
    its own, for ``device`` as the demo prepares it (into ``out``); shut down after."""
    from brace_control.bringup import BringUp
    from brace_control.demo import prepare_config
    path, _ = prepare_config(str(device), out)
    ctx = Context()
    rclpy.init(context=ctx)
    b = BringUp(path, context=ctx, extra_args=list(extra_args)).start()
    try:
        yield b
    finally:
        b.shutdown()
        rclpy.shutdown(context=ctx)


def home_and_enable(b: Any, timeout: float = 15.0) -> None:
    """``~/home`` then ``~/enable`` on the CAN driver of a :func:`stack_in_process`."""
    for what in ('home', 'enable'):
        ok, msg = b.call(f'/can_driver_node/{what}', timeout=timeout)
        assert ok, f'{what}: {msg}'


def params_args(path: str | Path = LUMBAR_YAML, **overrides: Any) -> list[str]:
    """``cli_args`` that give a node the device file, as ``ros2 run`` would."""
    args = ['--ros-args', '--params-file', str(path)]
    for name, value in overrides.items():
        args += ['-p', f'{name}:={value}']
    return args


class Ros:
    """One executor on an rclpy context; nodes added to it are spun together.

    :param context: an initialised context shared with others (closing leaves it up);
        ``None``: a private one, shut down on :meth:`close`.
    """

    def __init__(self, context: Context | None = None) -> None:
        self._own_context = context is None
        if context is None:
            context = Context()
            rclpy.init(context=context)
        self.context = context
        self.executor = SingleThreadedExecutor(context=self.context)
        self.nodes: list[Node] = []
        self._answer_clients: dict[tuple[Node, str], Any] = {}

    def add(self, node: Node) -> Node:
        self.executor.add_node(node)
        self.nodes.append(node)
        return node

    def node(self, name: str) -> Node:
        """A plain helper node (test publishers and subscribers)."""
        return self.add(Node(name, context=self.context))

    def device_node(self, cls: type, path: str | Path = LUMBAR_YAML, **overrides: Any) -> Node:
        """``cls`` started with the device file; ``overrides`` that are keywords of its
        constructor (``boot=False``) go there, the rest are ``-p`` parameter overrides."""
        import inspect
        ctor = inspect.signature(cls).parameters
        kwargs = {k: overrides.pop(k) for k in list(overrides) if k in ctor}
        return self.add(cls(context=self.context, cli_args=params_args(path, **overrides), **kwargs))

    def collect(self, node: Node, msg_type: type, topic: str, qos: Any = RELIABLE_10) -> list:
        """Subscribe ``topic`` on ``node``; the returned list fills as messages arrive."""
        box: list = []
        node.create_subscription(msg_type, topic, box.append, qos)
        return box

    def spin_until(self, predicate: Callable[[], bool], timeout: float = 5.0,
                   what: str | Callable[[], str] = 'condition') -> None:
        """Spin until ``predicate()`` is true; fail the test after ``timeout`` seconds
        (``what``: the condition's name, or a function saying what was seen then)."""
        deadline = time.monotonic() + timeout
        while not predicate():
            if time.monotonic() > deadline:
                pytest.fail(f'timed out after {timeout} s waiting for {what() if callable(what) else what}')
            spin_once(self.executor, 0.01)

    def spin_for(self, duration: float) -> None:
        """Spin for ``duration`` seconds (to show that something does NOT happen)."""
        deadline = time.monotonic() + duration
        while time.monotonic() < deadline:
            spin_once(self.executor, 0.01)

    def wait_matched(self, publisher: Any, count: int = 1, timeout: float = 5.0) -> None:
        """Discovery: spin until ``publisher`` sees ``count`` subscriptions."""
        self.spin_until(lambda: publisher.get_subscription_count() >= count, timeout,
                        f'{count} subscriber(s) on {publisher.topic_name}')

    def node_answers(self, probe: Node, name: str, timeout: float = 1.0) -> bool:
        """Whether a live node called ``name`` answers ``/<name>/list_parameters`` within
        ``timeout`` s (every rclpy node serves it while it spins).

        The graph alone cannot tell: this context's one DDS participant lives for the whole
        session, so a node whose process was killed stays in ``get_node_names()`` until its
        participant's lease runs out (Fast DDS: 20 s).

        One client per probe and name, kept until the probe goes (:meth:`close`): asked again,
        it is matched already, and the session's participant does not make and destroy a
        reader and a writer per try (an endpoint destroyed while a remote participant's lease
        expires is the Fast DDS deadlock of eProsima/Fast-DDS#6502)."""
        return name in self.nodes_answering(probe, [name], timeout)

    def nodes_answering(self, probe: Node, names: Sequence[str], timeout: float = 1.0) -> list[str]:
        """The nodes of ``names`` that answer (:meth:`node_answers`) within ``timeout`` s,
        asked at once: a silent node costs the one ``timeout`` window each of them gets, not
        one window after the other."""
        from rcl_interfaces.srv import ListParameters
        clients = {}
        for name in names:
            key = (probe, name.lstrip('/'))
            if key not in self._answer_clients:
                self._answer_clients[key] = probe.create_client(ListParameters, f'/{key[1]}/list_parameters')
            clients[name] = self._answer_clients[key]
        deadline = time.monotonic() + timeout
        futures: dict[str, Any] = {}

        def settled() -> bool:
            for name, client in clients.items():
                if name not in futures and client.service_is_ready():
                    futures[name] = client.call_async(ListParameters.Request(depth=1))
            return (len(futures) == len(clients) and all(f.done() for f in futures.values())) \
                or time.monotonic() > deadline
        self.spin_until(settled, timeout + 1.0)
        for name, future in futures.items():
            if not future.done():
                clients[name].remove_pending_request(future)
        return [n for n in names if n in futures and futures[n].done() and futures[n].exception() is None]

    def wait_node_answers(self, probe: Node, name: str, timeout: float,
                          stop: Callable[[], bool] = lambda: False,
                          context: Callable[[], str] = lambda: '') -> None:
        """Ask :meth:`node_answers` again (1 s per try) until ``name`` answers or ``stop()``;
        fail the test after ``timeout`` s, saying what the probe's graph held then (a node
        not yet discovered, or discovered and silent) and ``context()`` (the process's log)."""
        deadline = time.monotonic() + timeout
        while not (stop() or self.node_answers(probe, name)):
            if time.monotonic() > deadline:
                client = self._answer_clients.get((probe, name.lstrip('/')))
                pytest.fail(f'timed out after {timeout} s waiting for {name} to answer '
                            f'/{name}/list_parameters; the probe sees the nodes '
                            f'{sorted(probe.get_node_names())}, the service '
                            f'{"matched" if client is not None and client.service_is_ready() else "not matched"}'
                            f'\n{context()}')

    def close(self) -> None:
        self.executor.shutdown()
        for node in self.nodes:
            node.destroy_node()
        if self._own_context:
            rclpy.shutdown(context=self.context)


def unclean_exits(codes: dict[str, int]) -> dict[str, int]:
    """The node processes of ``ProcessBringUp.stop()`` that did not end cleanly: any exit
    status but 0 and ``runner.TEARDOWN_CUT`` (the node's work done, its DDS teardown cut
    short by the node's own watchdog: a deadlock inside Fast DDS, eProsima/Fast-DDS#6502),
    which is printed on stderr so that a run's log still shows each one."""
    import sys

    from brace_control.nodes.runner import TEARDOWN_CUT
    cut = sorted(n for n, c in codes.items() if c == TEARDOWN_CUT)
    if cut:
        print(f'note: {", ".join(cut)}: DDS teardown cut short (Fast-DDS#6502)', file=sys.stderr)
    return {n: c for n, c in codes.items() if c not in (0, TEARDOWN_CUT)}
