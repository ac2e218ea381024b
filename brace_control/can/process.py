"""The control cycle in a process of its own (issue 27; ``can.cycle_process``, default on).

The SYNC deadline must not depend on what rclpy, a recorder or a plot does in the driver's
process: one Python interpreter lock serves every thread of a process, and rclpy's executor
holds it for whole callbacks (and through some native DDS calls). So the driver node runs the
:class:`~.master.BraceMaster` (CAN I/O, SYNC, trajectory execution, the safety tiers, the
in-cycle admittance) and, with ``can.sim``, the simulated brace on its virtual bus, in a child
process where rclpy never runs. That is ros2_control's split of a real-time loop and ROS,
done the way that works under Python's lock.

Parent (the node) and child talk over one socket pair (:mod:`multiprocessing.connection`):

* **commands in:** ``('call', id, target, name, pickled (args, kwargs))``: a method of the
  master (``target`` ``'master'``) or of the simulated brace (``'sim'``) by attribute path,
  or an attribute read (``name`` starting ``'peek:'``) or write (``'set:'``); ``'cast'``
  the same without an answer (a stream's samples). The 402 transitions, homing, reliefs and
  shutdown (up to seconds) each run in a thread of their own; everything else (a
  trajectory, a setpoint, a stop) inline, so a stream never queues behind a service.
* **samples and events out:** a :class:`Snapshot` after every command (in its reply) and at
  ``can.joint_state_rate_hz`` (what the node publishes, what its checks read), each built and
  sent under one lock, so they arrive in the order they were taken and every execution event
  is delivered exactly once. The child's log records go out too.

:class:`MasterProcess` is the parent's side. It answers the node's reads (state, faults,
feedback, the execution's state, the newest pose, the simulator's truth) from the newest
snapshot, with no round trip; commands are calls that return the child's answer (or raise
its exception).

Supervision (docs/safety.md §20, "never unsupervised"): the child ignores SIGINT and SIGHUP
(a terminal's signals are the parent's to handle: it disables the drives through the child);
when the parent's end of the socket closes, whatever ended the parent (a crash, SIGKILL), the
child disables the drives, closes the bus and exits. SIGTERM does the same. If the child
dies, every call raises :class:`~.errors.DriverError` and the snapshot's state is FAULT with
a ``cycle_stopped`` fault (on hardware the drives stop on the master's heartbeat loss).
"""
from __future__ import annotations

import contextlib
import copyreg
import dataclasses
import enum
import gc
import io
import itertools
import logging
import math
import os
import pickle
import signal
import socket
import subprocess
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import numpy as np

from ..control.execution import ExecutionEvent, ExecutionState
from .errors import DriverError, DriverInitializationError
from .state import Feedback, MasterConfig, MasterState, MasterStatus
from .supervision import Fault, FaultKind
from .sync import stamped_after

__all__ = ['MasterProcess', 'Snapshot', 'label_threads', 'snapshot_of', 'wrench_capacity_context']

log = logging.getLogger('brace_control.can.process')

#: calls that may take seconds (a 402 transition, homing, a relief): a thread each in the child
SLOW_CALLS = frozenset({'boot', 'enable', 'disable', 'halt', 'home', 'recover', 'relieve',
                        'take_up', 'shutdown'})
#: slow calls whose work is start-up work (the boot's dictionary checks and SDO configuration,
#: a recovery's reconfiguration), all CPU where the simulated drives answer in the caller's
#: thread: run one real-time priority below the cycle's (:func:`start_up_work`)
START_UP_CALLS = frozenset({'boot', 'recover'})
#: calls of a stream (at its rate) and reads that change nothing: answered without a snapshot
NO_SNAPSHOT = frozenset({'set_targets', 'set_interaction_goal', 'status', 'trace_cycles', 'take_cycle_trace'})
#: longest a log record waits for the link before it goes to stderr instead (s)
LOG_SEND_WAIT_S = 0.05
#: longest the child may take to start (interpreter, numpy, canopen, the simulator) (s)
START_TIMEOUT_S = 60.0
#: longest the child may take to end once told (s); then it is killed
EXIT_TIMEOUT_S = 5.0
#: s the parent waits, once the link closed, for the child's exit code (what ended it)
LINK_CLOSED_EXIT_S = 1.0
#: s without a periodic snapshot from a running child before the parent takes it for stuck
#: (alive, silent: a deadlock, a native call that never returns, SIGSTOP): it ends the child
#: (SIGKILL) and reports CYCLE_STOPPED, so that every call waiting on it answers. A loaded
#: 2-core host stalled the child for up to 1.84 s in the suite's runs; a child that lives
#: on unheard would keep commanding drives the node reports stopped. While a start-up call
#: (:data:`START_UP_CALLS`) runs, :data:`START_TIMEOUT_S` instead
CYCLE_SILENT_S = 5.0
#: s between two periodic snapshots (at ``can.joint_state_rate_hz``) past which the parent
#: logs a warning saying on whose side the time went (:meth:`MasterProcess._warn_gap`):
#: the evidence for a hole in the recorded truth, which only the logs of a run can show
SNAPSHOT_GAP_WARN_S = 1.0
#: the simulator's truths the parent keeps, one per snapshot (20 s at 100 Hz): a ground-truth
#: publisher starved for a while publishes the ones it missed, stamped as they were. 5 s
#: (500) was too few: an in-process stack beside two other test workers (load 10 on 2
#: cores) stood 4-11 s behind, and the demo's recorded truth had holes of 1.9-5.1 s
TRUTH_BACKLOG = 2000


def _array_from(dtype: str, shape: tuple[int, ...], data: bytes) -> np.ndarray:
    return np.frombuffer(data, dtype).reshape(shape).copy()


def _reduce_array(a: np.ndarray) -> tuple[Any, ...]:
    """An array as the link sends it: a vector as its list of numbers (a snapshot's are 3-12
    long), anything else as its bytes; numpy's own reduction (dtype and flags objects, a
    generic reconstructor) costs three times as much both ways."""
    if a.dtype.hasobject:
        return a.__reduce_ex__(pickle.HIGHEST_PROTOCOL)
    if a.ndim == 1:
        return np.array, (a.tolist(), a.dtype.str)
    return _array_from, (a.dtype.str, a.shape, a.tobytes())


def _reduce_record(obj: Any) -> tuple[Any, ...]:
    """A dataclass of the snapshot (every field an ``__init__`` argument) as its constructor
    and its values in order: no field names, no state dictionary to set."""
    return type(obj), tuple([getattr(obj, name) for name in _RECORD_FIELDS[type(obj)]])


#: the snapshot's dataclasses, sent at 100 Hz: their fields in constructor order
_RECORD_FIELDS: dict[type, tuple[str, ...]] = {}


def send_as_record(cls: type) -> type:
    """Have the link send ``cls`` (a dataclass whose fields are all ``__init__`` arguments)
    by :func:`_reduce_record`."""
    fields = dataclasses.fields(cls)
    if not all(f.init for f in fields):
        raise TypeError(f'{cls.__name__}: a field that is not an __init__ argument')
    _RECORD_FIELDS[cls] = tuple(f.name for f in fields)
    _LinkPickler.dispatch_table[cls] = _reduce_record
    return cls


class _LinkPickler(pickle.Pickler):
    """The link's pickler: ``multiprocessing``'s ``ForkingPickler`` copies the whole copyreg
    table on every message, and numpy's arrays reduce slowly; a snapshot at 100 Hz costs
    80 us to pickle and 50 us to unpickle that way, 28 and 25 us this way (bench/RESULTS.md,
    "The stack as processes at rest and in motion, before and after (8c15928 -> b8f433c)").
    The snapshot's dataclasses go as records (:func:`send_as_record`)."""

    dispatch_table = {**copyreg.dispatch_table, np.ndarray: _reduce_array}


def link_dumps(msg: Any) -> bytes:
    """``msg`` as the bytes one side of the link sends (:func:`link_loads` reads them)."""
    buf = io.BytesIO()
    _LinkPickler(buf, pickle.HIGHEST_PROTOCOL).dump(msg)
    return buf.getvalue()


link_loads = pickle.loads


@dataclass(frozen=True)
class Snapshot:
    """What the node reads of the master between commands: one consistent sample."""

    state: MasterState
    homed: bool
    taking_up: bool
    relieved: bool
    faults: tuple[Fault, ...]
    latched: bool
    fault_summary: str
    execution: ExecutionState
    command: tuple[float, ...] | None     # the executor's command, if anchored
    interacting: bool                     # the in-cycle admittance drives the command
    last_pose: np.ndarray | None          # the newest pose the wrench tiers solved
    feedback: Feedback
    events: tuple[ExecutionEvent, ...]    # execution events since the previous snapshot
    truth: Any = None                     # the simulator's truth of the feedback's SYNC
    #: the simulator's truths (at ``sim.truth_rate_hz``) between the previous snapshot sent and
    #: this one, when more than a truth period lies between them (the link was full: the node's
    #: process read nothing for a while); oldest first, ``truth`` not included
    missed: tuple = ()


send_as_record(Snapshot)
send_as_record(Feedback)


def portable(value: Any) -> Any:
    """``value`` without what cannot cross a process boundary: a fault's ``still_present``
    predicate (it is evaluated where the fault was latched, at ``recover()``)."""
    if isinstance(value, Fault):
        return dataclasses.replace(value, still_present=None) if value.still_present else value
    if isinstance(value, MasterStatus):
        return dataclasses.replace(value, faults=portable(value.faults))
    if isinstance(value, (list, tuple)):
        return type(value)(portable(v) for v in value)
    return value


def snapshot_of(master: Any, sim: Any = None) -> Snapshot:
    """The master's (and the simulator's) state now; drains the master's execution events."""
    fb = master.feedback()
    truth = None if sim is None else sync_truth(sim, fb.wall)
    return Snapshot(state=master.state, homed=master.homed, taking_up=master.taking_up,
                    relieved=master.relieved, faults=portable(master.faults),
                    latched=master.latched, fault_summary=master.fault_summary(),
                    execution=master.execution, command=master.command,
                    interacting=master.interacting, last_pose=master.last_pose, feedback=fb,
                    events=tuple(master.execution_events()), truth=truth)


def sync_truth(sim: Any, wall: float) -> Any:
    """The simulator's truth of the SYNC sent at ``wall`` (wall clock, s; a measurement's
    stamp): a comparison with the estimate pairs the same instant, not two SYNCs ms apart.
    No recent SYNC (``wall`` 0 or older than 0.1 s): the newest truth."""
    return sim.truth_at(wall) if wall and time.time() - wall < 0.1 else sim.truth()


def wrench_capacity_context(master: Any, mechanism: Any, max_force: float) -> Callable[[int, float], str]:
    """What a soft-limit stop adds to its reason (docs/safety.md §14): the platform's wrench
    capacity at the pose the actuators measure (``master.soft_limit_context``)."""
    def context(index: int, force: float) -> str:
        if mechanism is None or not hasattr(mechanism, 'wrench_capacity'):
            return ''
        guess = master.last_pose
        if guess is None:
            guess = np.asarray(mechanism.home_pose, float)
        try:
            pose = np.asarray(mechanism.forward_nearest(master.feedback().position, guess), float)
            cap, _ = mechanism.wrench_capacity(pose, max_force, return_limiting=True)
        except ValueError as exc:
            return f' (capacity unknown: {exc})'
        axes = getattr(mechanism, 'wrench_axes', tuple(f'#{i}' for i in range(len(cap))))
        parts = ', '.join(f'{a} {c:.3g}' for a, c in zip(axes, cap))
        return f'; wrench capacity at pose {np.round(pose, 4).tolist()}: {parts}'
    return context


# ---------------------------------------------------------------------------------- parent

class _Remote:
    """An object in the child, reached by attribute path: ``remote.faults.disconnect(2)``
    calls there; reading an attribute returns its value when it can cross (else another
    path); setting one sets it there. For what a user or a test reaches into (the simulated
    brace's fault injection, the patient); the node's own reads come from snapshots."""

    def __init__(self, owner: MasterProcess, target: str, path: str = '') -> None:
        object.__setattr__(self, '_owner', owner)
        object.__setattr__(self, '_target', target)
        object.__setattr__(self, '_path', path)

    def _sub(self, name: str) -> str:
        return f'{self._path}.{name}' if self._path else name

    def __getattr__(self, name: str) -> Any:
        if name.startswith('__'):
            raise AttributeError(name)
        path = self._sub(name)
        kind, value = self._owner.call(self._target, 'peek:' + path)
        return value if kind == 'value' else _Remote(self._owner, self._target, path)

    def __setattr__(self, name: str, value: Any) -> None:
        self._owner.call(self._target, 'set:' + self._sub(name), value)

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        return self._owner.call(self._target, self._path, *args, **kwargs)


class _SimView(_Remote):
    """The simulated brace as the node sees it from the parent: its truth from the
    snapshots (no round trip), the rest by path (:class:`_Remote`). Its start and end are
    the child's."""

    def truth(self) -> Any:
        return self._owner.snapshot.truth

    def truth_at(self, wall: float) -> Any:
        return self._owner.snapshot.truth

    def truths_since(self, stamp: float) -> list[Any]:
        """The truths of the snapshots received after the one stamped ``stamp`` (wall clock,
        s), oldest first, among the last :data:`TRUTH_BACKLOG`: none is lost to a reader that
        falls behind the snapshots for a while."""
        owner = self._owner
        with owner._truths_lock:
            return stamped_after(owner._truths, stamp)

    def set_rest_pose(self, pose: np.ndarray, stamp: float | None = None) -> None:
        """A stream (the patient's trunk, 50-100 Hz): sent, not waited for."""
        self._owner.cast('sim', 'set_rest_pose', np.asarray(pose, float), stamp)

    def start(self) -> _SimView:
        return self

    def shutdown(self) -> None:
        pass


class _SupervisorView(_Remote):
    """``master.supervisor``: its reads from the newest snapshot, the rest by path."""

    def __init__(self, owner: MasterProcess) -> None:
        super().__init__(owner, 'master', 'supervisor')

    @property
    def faults(self) -> tuple[Fault, ...]:
        return self._owner.snapshot.faults

    @property
    def latched(self) -> bool:
        return self._owner.snapshot.latched

    def summary(self) -> str:
        return self._owner.snapshot.fault_summary

    def has(self, kind: FaultKind, drive: str | None = ...) -> bool:  # type: ignore[assignment]
        return any(f.kind == kind and (drive is ... or f.drive == drive) for f in self.faults)


class _ExecutorView(_Remote):
    """``master.executor``: its reads from the newest snapshot, the rest by path."""

    def __init__(self, owner: MasterProcess) -> None:
        super().__init__(owner, 'master', 'executor')

    @property
    def state(self) -> ExecutionState:
        return self._owner.snapshot.execution

    @property
    def anchored(self) -> bool:
        return self._owner.snapshot.command is not None

    @property
    def q(self) -> np.ndarray:
        return np.asarray(self._owner.snapshot.command or (), float)

    @property
    def source(self) -> bool | None:
        """True while the in-cycle admittance drives the command (the object stays there)."""
        return True if self._owner.snapshot.interacting else None


class MasterProcess:
    """A :class:`~.master.BraceMaster` (and, with ``can.sim``, the simulated brace) in a
    child process (module docstring); the node calls it as it would the master.

    :param cfg: the device configuration (the child builds the simulator from it).
    :param config: the master's configuration (its mechanism included).
    :param on_snapshot: called (in the reader thread) after each periodic snapshot (at
        ``can.joint_state_rate_hz``) arrives: the node publishes its joint states then.
    """

    def __init__(self, cfg: Mapping[str, Any], config: MasterConfig, *,
                 on_snapshot: Callable[[], None] | None = None,
                 start_timeout: float = START_TIMEOUT_S) -> None:
        self.config = config
        self.names = config.names
        self.limits = config.limits
        self._on_snapshot = on_snapshot
        self._ids = itertools.count(1)
        self._pending: dict[int, list] = {}
        self._pending_lock = threading.Lock()
        self._send_lock = threading.Lock()
        self._events: list[ExecutionEvent] = []
        self._events_lock = threading.Lock()
        self._ended: str | None = None
        self._closing = False
        self._snapshot: Snapshot | None = None
        self._truths: deque[Any] = deque(maxlen=TRUTH_BACKLOG)    # each new one a snapshot brought
        self._truths_lock = threading.Lock()
        self._ready = threading.Event()
        self._info: dict[str, Any] = {}
        ours, theirs = socket.socketpair()
        package_root = str(Path(__file__).resolve().parents[2])
        env = dict(os.environ)
        env['PYTHONPATH'] = os.pathsep.join(p for p in (package_root, env.get('PYTHONPATH')) if p)
        for var in ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS'):
            env.setdefault(var, '1')   # 3x3 algebra: a BLAS thread pool only spins and contends
        try:
            self._proc = subprocess.Popen(
                [sys.executable, '-m', 'brace_control.can.process', str(theirs.fileno())],
                pass_fds=(theirs.fileno(),), env=env, stdin=subprocess.DEVNULL)
        finally:
            theirs.close()
        self._conn = Connection(ours.detach())
        self._fresh = threading.Event()
        self._heard = time.monotonic()         # the last periodic snapshot's arrival
        #: a gap whose first snapshot was taken on time, judged on the next one
        self._gap_pending: tuple[float, float, float] | None = None
        self._taken = 0.0                       # and when the child took it (time.monotonic)
        self._reader = threading.Thread(target=self._read, name='brace_cycle_reader', daemon=True)
        self._reader.start()
        if on_snapshot is not None:
            threading.Thread(target=self._notify, name='brace_cycle_samples', daemon=True).start()
        try:
            self._send(('setup', pickle.dumps((cfg, config))))
            if not self._ready.wait(start_timeout) or self._ended:
                raise DriverInitializationError(
                    f'the control cycle process did not start within {start_timeout:g} s'
                    + (f': {self._ended}' if self._ended else ''))
            if 'error' in self._info:
                raise self._info['error']
        except BaseException:
            self.close()
            raise
        if float(cfg['can']['joint_state_rate_hz']) > 0:
            self._heard = time.monotonic()
            threading.Thread(target=self._watch, name='brace_cycle_watchdog', daemon=True).start()
        self.sim = _SimView(self, 'sim') if self._info.get('sim') else None
        #: the master's supervisor and executor, read-only, as of the newest snapshot
        self.supervisor = _SupervisorView(self)
        self.executor = _ExecutorView(self)

    # -- the child's answers

    def _read(self) -> None:
        try:
            while True:
                msg = link_loads(self._conn.recv_bytes())
                kind = msg[0]
                if kind == 'snap':
                    self._apply(msg[1], periodic=True, taken=msg[2])
                elif kind == 'reply':
                    _, ident, ok, value, snap = msg
                    self._apply(snap)
                    with self._pending_lock:
                        slot = self._pending.pop(ident, None)
                    if slot is not None:
                        slot[1], slot[2] = ok, value
                        slot[0].set()
                elif kind == 'log':
                    _, name, level, text = msg
                    logging.getLogger(name).log(level, '%s', text)
                elif kind == 'ready':
                    self._info = msg[1]
                    if msg[2] is not None:
                        self._apply(msg[2])
                    self._ready.set()
        except (EOFError, OSError) as exc:
            code = self._proc.poll()
            if code is None and not self._closing:
                # the link closes as the child exits: its exit code says how it ended
                try:
                    code = self._proc.wait(LINK_CLOSED_EXIT_S)
                except subprocess.TimeoutExpired:
                    code = None
            self._end('the control cycle process was closed' if self._closing else
                      f'the control cycle process {ended_how(code)}' if code is not None
                      else f'the control cycle process stopped answering ({exc!r})')
        except Exception as exc:  # noqa: BLE001 - an unreadable message: the link is lost
            if self._closing:             # closed under the reader (close() gave up waiting)
                self._end('the control cycle process was closed')
                return
            self._end(f'the control cycle process link broke: {exc!r}')
            log.exception('reading the control cycle process')

    def _apply(self, snap: Snapshot | None, *, periodic: bool = False, taken: float = 0.0) -> None:
        if snap is None:
            return
        if snap.events:
            with self._events_lock:
                self._events.extend(snap.events)
        truth = snap.truth
        if truth is not None:
            with self._truths_lock:
                for t in snap.missed + (truth,):
                    if not self._truths or t.stamp > self._truths[-1].stamp:
                        self._truths.append(t)
        self._snapshot = snap
        if periodic:
            now = time.monotonic()
            pending, self._gap_pending = self._gap_pending, None
            if pending is not None:
                # the snapshot after a gap was taken on time: the child may have been stopped
                # between taking it and sending it; this next one says (taken as long after it:
                # the child did not run; on time again: this process fell behind)
                gap, taken_apart, before = pending
                self._warn_gap(gap, max(taken_apart, taken - before))
            elif now - self._heard > SNAPSHOT_GAP_WARN_S:
                gap, taken_apart = now - self._heard, taken - self._taken
                if taken_apart > 0.5 * gap:
                    self._warn_gap(gap, taken_apart)
                else:
                    self._gap_pending = (gap, taken_apart, taken)
            self._heard, self._taken = now, taken
            if self._on_snapshot is not None:
                self._fresh.set()         # the callback runs in its own thread (it may call)

    def _warn_gap(self, gap: float, taken_apart: float) -> None:
        """Say that the periodic snapshots stopped for ``gap`` s, and on whose side: the child
        takes one every 1/``can.joint_state_rate_hz`` while it runs, so the first after the gap
        taken as long after the one before is a child that did not run (a stalled host,
        SIGSTOP: its simulated world stood still meanwhile, a hole in the truth itself);
        taken on time is a parent that fell behind in reading the link (the simulator's
        truths of that time come along)."""
        log.warning('no snapshot from the control cycle process for %.2f s: %s', gap,
                    f'it took this one {taken_apart:.2f} s after the one before: the cycle process '
                    'did not run meanwhile (its simulated world stood still)'
                    if taken_apart > 0.5 * gap else
                    f'it took this one {taken_apart * 1e3:.0f} ms after the one before: this '
                    'process fell behind in reading the link')

    def _watch(self, tick: float = 0.25) -> None:
        """End a child that sends nothing for :data:`CYCLE_SILENT_S` (stuck, not gone: its
        link stays open, so the reader waits for good and so would every call). Judged only
        on ticks this thread itself took on time, with nothing waiting unread on the link: a
        starved parent (its reader behind, or this thread late) is not a silent child."""
        last = time.monotonic()
        while self._ended is None and not self._closing:
            time.sleep(tick)
            now = time.monotonic()
            on_time, last = now - last < 4 * tick, now
            silent = now - self._heard
            with self._pending_lock:
                starting = any(slot[3] in START_UP_CALLS for slot in self._pending.values())
            # start-up work (a boot's, a recovery's) runs one real-time priority below the
            # cycle's and may hold a core for seconds on a loaded host: the start's bound then
            bound = START_TIMEOUT_S if starting else CYCLE_SILENT_S
            if not on_time or silent < bound or self._closing or self._ended is not None:
                continue
            try:
                if self._conn.poll(0):            # the reader is behind, the child spoke
                    continue
            except (OSError, ValueError):
                return                            # closed meanwhile: the reader reports it
            why = (f'the control cycle process sent nothing for {silent:.1f} s (stuck; ended, '
                   f'pid {self._proc.pid})')
            log.error('%s', why)
            self._end(why)
            try:
                self._proc.kill()
            except OSError:
                pass
            return

    def _notify(self) -> None:
        """Call ``on_snapshot`` for the newest periodic snapshot (a slow callback skips to
        the newest; it may call the child: the reader thread never waits on a reply)."""
        while True:
            self._fresh.wait()
            self._fresh.clear()
            if self._ended is not None:
                return
            try:
                self._on_snapshot()
            except DriverError:
                pass                      # the child is going: the reader reports it
            except Exception:  # noqa: BLE001 - the samples must go on
                log.exception('snapshot callback')

    def _end(self, why: str) -> None:
        """The child is gone: the snapshot says FAULT (a ``cycle_stopped`` stop), then every
        waiting and later call raises ``why``."""
        snap = self._snapshot
        if self._ended is None and snap is not None and snap.state is not MasterState.CLOSED \
                and not self._closing:
            fault = Fault(FaultKind.CYCLE_STOPPED, f'{why}; restart the driver', None, None,
                          time.monotonic())
            summary = fault.describe() if not snap.faults else f'{snap.fault_summary}; {fault.describe()}'
            self._snapshot = dataclasses.replace(snap, state=MasterState.FAULT, faults=snap.faults + (fault,),
                                                 latched=True, fault_summary=summary, events=())
        if self._ended is None:
            self._ended = why
        self._ready.set()
        self._fresh.set()
        with self._pending_lock:
            pending, self._pending = self._pending, {}
        for slot in pending.values():
            slot[1], slot[2] = False, DriverError(why)
            slot[0].set()

    def __getattr__(self, name: str) -> Any:
        """Anything else of the master, by path in the child (:class:`_Remote`): a value
        that can cross, or an object whose methods are called there."""
        if name.startswith('_'):
            raise AttributeError(name)
        return getattr(_Remote(self, 'master'), name)

    # -- calls

    def _send(self, msg: Any) -> None:
        with self._send_lock:
            self._conn.send_bytes(link_dumps(msg))

    def call(self, target: str, name: str, *args: Any, **kwargs: Any) -> Any:
        """``target.name(*args, **kwargs)`` in the child; its result, or its exception."""
        if self._ended is not None:
            raise DriverError(self._ended)
        ident = next(self._ids)
        slot: list = [threading.Event(), False, None, name]
        with self._pending_lock:
            self._pending[ident] = slot
        payload = pickle.dumps((args, kwargs))      # what cannot cross raises here, in the caller
        try:
            self._send(('call', ident, target, name, payload))
        except (OSError, ValueError) as exc:
            with self._pending_lock:
                self._pending.pop(ident, None)
            raise DriverError(self._ended or f'the control cycle process is gone: {exc!r}') from exc
        slot[0].wait()
        if slot[1]:
            return slot[2]
        raise slot[2]

    def cast(self, target: str, name: str, *args: Any, **kwargs: Any) -> None:
        """``target.name(*args, **kwargs)`` in the child without waiting for it: for a stream
        whose sender must not block on each sample (the patient's rest pose); an error is
        logged there (and forwarded to this process's log)."""
        if self._ended is not None:
            raise DriverError(self._ended)
        payload = pickle.dumps((args, kwargs))
        try:
            self._send(('cast', 0, target, name, payload))
        except (OSError, ValueError) as exc:
            raise DriverError(self._ended or f'the control cycle process is gone: {exc!r}') from exc

    # -- reads, from the newest snapshot

    @property
    def snapshot(self) -> Snapshot:
        snap = self._snapshot
        if snap is None:
            raise DriverError(self._ended or 'the control cycle process has sent no sample yet')
        return snap

    state = property(lambda self: self.snapshot.state)
    homed = property(lambda self: self.snapshot.homed)
    taking_up = property(lambda self: self.snapshot.taking_up)
    relieved = property(lambda self: self.snapshot.relieved)
    faults = property(lambda self: self.snapshot.faults)
    latched = property(lambda self: self.snapshot.latched)
    execution = property(lambda self: self.snapshot.execution)
    command = property(lambda self: self.snapshot.command)
    interacting = property(lambda self: self.snapshot.interacting)
    last_pose = property(lambda self: self.snapshot.last_pose)

    def fault_summary(self) -> str:
        return self.snapshot.fault_summary

    def feedback(self) -> Feedback:
        return self.snapshot.feedback

    def execution_events(self) -> list[ExecutionEvent]:
        with self._events_lock:
            events, self._events = self._events, []
        return events

    @property
    def ended(self) -> str | None:
        """Why the child is gone (``None`` while it runs)."""
        return self._ended

    @property
    def closing(self) -> bool:
        """:meth:`shutdown` was called: the child ends because it was told to."""
        return self._closing

    @property
    def pid(self) -> int:
        return self._proc.pid

    # -- commands: the master's API

    def boot(self) -> None:
        self.call('master', 'boot')

    def home(self, **kw: Any) -> None:
        self.call('master', 'home', **kw)

    def enable(self, **kw: Any) -> None:
        self.call('master', 'enable', **kw)

    def disable(self, **kw: Any) -> None:
        self.call('master', 'disable', **kw)

    def halt(self, **kw: Any) -> None:
        self.call('master', 'halt', **kw)

    def recover(self, **kw: Any) -> list[Fault]:
        return self.call('master', 'recover', **kw)

    def relieve(self, **kw: Any) -> str:
        return self.call('master', 'relieve', **kw)

    def take_up(self, **kw: Any) -> str:
        return self.call('master', 'take_up', **kw)

    def status(self) -> MasterStatus:
        return self.call('master', 'status')

    def execute(self, trajectory: Any, *, start: float, tag: int) -> str | None:
        return self.call('master', 'execute', trajectory, start=start, tag=tag)

    def stop_motion(self, reason: str, *, tag: int | None = None) -> None:
        self.call('master', 'stop_motion', reason, tag=tag)

    def set_targets(self, positions: Any, *, stamp: float | None = None, velocities: Any = None) -> None:
        self.call('master', 'set_targets', np.asarray(positions, float), stamp=stamp,
                  velocities=None if velocities is None else np.asarray(velocities, float))

    def start_interaction(self, source: Any, tag: int) -> str | None:
        return self.call('master', 'start_interaction', source, tag)

    def stop_interaction(self, reason: str) -> None:
        self.call('master', 'stop_interaction', reason)

    def set_interaction_goal(self, wrench: Any) -> None:
        self.call('master', 'set_interaction_goal', list(wrench))

    def protective_stop(self, kind: FaultKind, cause: str, *, drive: str | None = None) -> Any:
        return self.call('master', 'protective_stop', kind, cause, drive=drive)

    def trace_cycles(self, on: bool = True) -> None:
        self.call('master', 'trace_cycles', on)

    def take_cycle_trace(self) -> dict[str, list]:
        return self.call('master', 'take_cycle_trace')

    def shutdown(self, *, timeout: float = 0.5) -> None:
        """Drives disabled, bus closed, simulator off (in the child), then the child ends."""
        if self._ended is None:
            try:
                self.call('master', 'shutdown', timeout=timeout)
            except DriverError:
                pass
        self.close()

    def close(self) -> None:
        """End the child (told first; SIGTERM, then SIGKILL, if it does not end) and the link."""
        self._closing = True
        if self._proc.poll() is None:
            try:
                self._send(('exit',))
            except (OSError, ValueError):
                pass
            try:
                self._proc.wait(EXIT_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                self._proc.terminate()
                try:
                    self._proc.wait(EXIT_TIMEOUT_S)
                except subprocess.TimeoutExpired:
                    self._proc.kill()
                    self._proc.wait()
        # the reader first: the child's end is closed, so it reads end-of-file and ends. A
        # link closed under a reader still in recv_bytes made it fail in multiprocessing's
        # own code (TypeError: the handle None), logged as a broken link at every shutdown
        # that lost the race (fresh-clone run 605)
        self._reader.join(timeout=EXIT_TIMEOUT_S)
        try:
            self._conn.close()
        except OSError:
            pass
        self._reader.join(timeout=EXIT_TIMEOUT_S)
        if self._ended is None:
            self._ended = 'the control cycle process was closed'

    def __enter__(self) -> MasterProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.shutdown()


def label_threads(master: Any) -> None:
    """Name this process's OS threads after their job (``/proc/<pid>/task/*/comm``: ``top
    -H``, ``ps -L``, bench_stack's split of the master's CPU from the simulator's): the
    master's SYNC thread ``master-sync`` and receive thread ``master-rx``; any other
    python-can receive thread is the simulated brace's ``sim-rx`` (on the virtual bus it has
    none: its drives take frames in the sender's thread); its clock ``sim-timer``."""
    import can
    master_rx = getattr(getattr(master, 'network', None), 'notifier', None)
    for t in threading.enumerate():
        owner = getattr(getattr(t, '_target', None), '__self__', None)
        if isinstance(owner, can.Notifier):
            name = 'master-rx' if owner is master_rx else 'sim-rx'
        elif t is threading.main_thread():
            continue
        else:
            name = {'brace-can-sync': 'master-sync', 'brace_cycle_push': 'cycle-push'}.get(
                t.name, 'sim-timer' if t.name.startswith('sim-timer') else t.name)
        try:
            with open(f'/proc/self/task/{t.native_id}/comm', 'w') as f:
                f.write(name[:15])
        except OSError:                      # not Linux, or the thread just ended
            pass


# ----------------------------------------------------------------------------------- child

class _Child:
    """The child's side: the master (and the simulator), the commands, the snapshots."""

    def __init__(self, conn: Connection) -> None:
        self.conn = conn
        self.send_lock = threading.Lock()
        self.master: Any = None
        self.sim: Any = None
        self.stop = threading.Event()
        #: the parent went without saying (its link closed, or SIGTERM): say what was left
        self.orphaned = False
        self.frozen = False
        #: the cycle's scheduling (``can.cycle_priority``, ``can.cycle_nice``), set at setup
        self.priority, self.nice = 0, 0
        #: the newest truth's stamp sent (wall clock, s) and the truth's period (s, setup)
        self.truth_sent, self.truth_period = 0.0, math.inf

    def send(self, msg: Any) -> None:
        self.try_send(msg)

    def try_send(self, msg: Any, *, wait: float = -1) -> bool:
        """Send ``msg``; ``False`` if the parent is gone or (``wait`` >= 0) the link stayed
        busy that long: a parent that stopped reading never blocks the caller for longer."""
        if not self.send_lock.acquire(timeout=wait):
            return False
        try:
            self.conn.send_bytes(link_dumps(msg))
            return True
        except (OSError, ValueError):
            self.stop.set()           # the parent is gone
            return False
        finally:
            self.send_lock.release()

    def send_with_snapshot(self, make: Callable[[Snapshot | None], Any]) -> None:
        """Take a snapshot and send it (inside ``make``'s message) under one lock: the parent
        gets them in the order they were taken, each event once, and every truth at
        ``sim.truth_rate_hz`` (:meth:`with_missed_truths`)."""
        try:
            with self.send_lock:
                self.conn.send_bytes(link_dumps(make(self.with_missed_truths(self.snapshot()))))
        except (OSError, ValueError):
            self.stop.set()

    def with_missed_truths(self, snap: Snapshot | None) -> Snapshot | None:
        """``snap`` with the simulator's truths since the last snapshot sent, when more than a
        truth period lies between the two (``Snapshot.missed``). A node process that read
        nothing for seconds (a loaded host) filled the link: the pusher waited in its send
        with the snapshot it had taken, and the truths of the time in between were never
        taken (runs 901 and 910: holes of 0.8-1.4 s in the interaction demo's recorded
        truth, a third of a sway's samples gone). Within the simulator's record
        (``sim.brace.TRUTH_RECORD_S``)."""
        truth = None if snap is None else snap.truth
        recorded_since = getattr(self.sim, 'recorded_since', None)
        if truth is None or recorded_since is None:
            return snap
        last, self.truth_sent = self.truth_sent, max(self.truth_sent, truth.stamp)
        period = self.truth_period
        if not last or truth.stamp - last <= 1.5 * period:
            return snap
        missed = tuple(t for t in recorded_since(last + 0.5 * period)
                       if t.stamp <= truth.stamp - 0.5 * period)
        return dataclasses.replace(snap, missed=missed) if missed else snap

    def snapshot(self) -> Snapshot | None:
        if self.master is None:
            return None
        try:
            return snapshot_of(self.master, self.sim)
        except Exception:  # noqa: BLE001 - e.g. before the first feedback
            log.exception('snapshot')
            return None

    def setup(self, payload: bytes) -> None:
        from .master import BraceMaster
        cfg, config = pickle.loads(payload)
        info: dict[str, Any] = {'sim': False}
        try:
            from ..config import as_device_config
            cfg = as_device_config(cfg)
            self.priority, self.nice = int(cfg['can']['cycle_priority']), int(cfg['can']['cycle_nice'])
            set_scheduling(self.priority, self.nice)
            if os.sched_getscheduler(0) == os.SCHED_FIFO and not config.thread_priority:
                # the SYNC thread one above its process: on waking it preempts the
                # simulator's threads (which then hold the interpreter lock at most
                # gil_switch_interval_us longer) rather than queueing behind them
                config = dataclasses.replace(config, thread_priority=int(cfg['can']['cycle_priority']) + 1)
            switch_us = int(cfg['can']['gil_switch_interval_us'])
            if switch_us > 0:
                sys.setswitchinterval(switch_us * 1e-6)
            with start_up_work(self.priority, self.nice):
                if cfg['can']['sim']:
                    from ..sim import SimulatedBrace
                    from ..sim.brace import BraceTruth
                    send_as_record(BraceTruth)      # in every snapshot
                    self.truth_period = 1.0 / float(cfg['sim']['truth_rate_hz'])
                    self.sim = SimulatedBrace(cfg, channel=config.channel, interface=config.interface,
                                              eds=config.eds, mechanism=config.mechanism, start=False)
                    self.sim.start()
                    info['sim'] = True
                master = BraceMaster(config)
                master.soft_limit_context = wrench_capacity_context(
                    master, config.mechanism, float(cfg['actuator']['max_force']))
                self.master = master
        except Exception as exc:  # noqa: BLE001 - the parent raises it
            info['error'] = _portable_error(exc)
        self.send_with_snapshot(lambda snap: ('ready', info, snap))
        rate = float(cfg['can']['joint_state_rate_hz']) if 'error' not in info else 0.0
        if rate > 0:
            threading.Thread(target=self.push, args=(1.0 / rate,), name='brace_cycle_push',
                             daemon=True).start()

    def push(self, period: float) -> None:
        next_t = time.monotonic()
        while not self.stop.is_set():
            next_t += period
            delay = next_t - time.monotonic()
            if delay < -period:                 # fell behind (a stalled host): start afresh
                next_t = time.monotonic()
            elif delay > 0 and self.stop.wait(delay):
                break
            # with when it was taken (CLOCK_MONOTONIC: one clock for every process)
            self.send_with_snapshot(lambda snap: ('snap', snap, time.monotonic()))

    def resolve(self, target: str, path: str) -> tuple[Any, str]:
        """The object holding the last attribute of ``path`` (dotted) on ``target``, and
        that attribute's name."""
        obj = self.master if target == 'master' else self.sim
        if obj is None:
            raise DriverError(f'no {target} in the control cycle process')
        *parents, last = path.split('.')
        for part in parents:
            obj = getattr(obj, part)
        return obj, last

    def run_cast(self, target: str, name: str, payload: bytes) -> None:
        """A call nobody waits for: its error is logged."""
        try:
            args, kwargs = pickle.loads(payload)
            obj, last = self.resolve(target, name)
            getattr(obj, last)(*args, **kwargs)
        except Exception as exc:  # noqa: BLE001 - nobody to raise it to
            log.warning('%s.%s ignored: %s', target, name, exc)

    def run_call(self, ident: int, target: str, name: str, payload: bytes) -> None:
        if name in START_UP_CALLS:
            with start_up_work(self.priority, self.nice):
                self._run_call(ident, target, name, payload)
        else:
            self._run_call(ident, target, name, payload)

    def _run_call(self, ident: int, target: str, name: str, payload: bytes) -> None:
        try:
            args, kwargs = pickle.loads(payload)
            op, _, path = name.rpartition(':')
            obj, last = self.resolve(target, path)
            if op == 'peek':
                value = getattr(obj, last)
                value = ('value', value) if _plain(value) else ('object', None)
            elif op == 'set':
                setattr(obj, last, *args)
                value = None
            else:
                value = getattr(obj, last)(*args, **kwargs)
            value = portable(value)
            pickle.dumps(value)
            ok = True
        except BaseException as exc:  # noqa: BLE001 - the caller gets it
            ok, value = False, _portable_error(exc)
        if name in SLOW_CALLS:
            label_threads(self.master)          # boot and enable start threads
        if name == 'boot' and ok and not self.frozen:
            # the start-up heap (modules, the object dictionaries, the models) out of the
            # cyclic collector's passes, which hold the GIL (bench/RESULTS.md "Host stalls")
            gc.freeze()
            self.frozen = True
        if name in NO_SNAPSHOT or name.startswith(('peek:', 'set:')):
            self.send(('reply', ident, ok, value, None))
        else:
            self.send_with_snapshot(lambda snap: ('reply', ident, ok, value, snap))

    def serve(self) -> None:
        while not self.stop.is_set():
            try:
                msg = link_loads(self.conn.recv_bytes())
            except (EOFError, OSError):
                self.orphaned = True
                log.warning('control cycle process: the driver node is gone: disabling the drives '
                            'and closing the bus')
                break
            kind = msg[0]
            if kind == 'setup':
                self.setup(msg[1])
            elif kind == 'call':
                _, ident, target, name, payload = msg
                if name in SLOW_CALLS:
                    threading.Thread(target=self.run_call, args=(ident, target, name, payload),
                                     name=f'brace_cycle_{name}', daemon=True).start()
                else:
                    self.run_call(ident, target, name, payload)
            elif kind == 'cast':
                _, _, target, name, payload = msg
                self.run_cast(target, name, payload)
            elif kind == 'exit':
                break

    def close(self) -> None:
        self.stop.set()
        if self.master is not None:
            try:
                self.master.shutdown()
                if self.orphaned:
                    states = ', '.join(f'{d.name} {d.state.value}' for d in self.master.status().drives)
                    log.warning('control cycle process: drives after shutdown: %s', states)
            except Exception:  # noqa: BLE001 - closing anyway
                log.exception('closing the CAN master')
        if self.sim is not None:
            try:
                self.sim.shutdown()
            except Exception:  # noqa: BLE001
                log.exception('stopping the simulated brace')


def set_scheduling(priority: int, nice: int) -> str:
    """The scheduling of this process's threads (those made later inherit it; call it before
    the master and the simulator start theirs): SCHED_FIFO ``priority``, else niceness
    ``nice``, else unchanged. Returns what was set.

    Measured (bench/RESULTS.md, "The control cycle in its own process"): with two busy loops
    on the two cores, SYNC overruns were 29 % at normal scheduling, 3.5 % at niceness -10 and
    0.14 % at SCHED_FIFO 50. Every thread of the process gets the priority, not only the
    SYNC thread: the threads share one interpreter lock, and a SYNC thread above the lock's
    holder only waits for it (priority inversion, bench/RESULTS.md "CAN"). Both need
    CAP_SYS_NICE, or an allowance (``/etc/security/limits.conf``: ``@realtime - rtprio 50``,
    ``- nice -10``), as ros2_control's node asks for its real-time loop; without, the log
    says which was refused.
    """
    refused = []
    if priority > 0:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
            return f'SCHED_FIFO {priority}'
        except (OSError, AttributeError) as exc:
            refused.append(f'can.cycle_priority {priority} ({getattr(exc, "strerror", None) or exc})')
    if nice != 0:
        try:
            os.setpriority(os.PRIO_PROCESS, 0, nice)
            got = f'niceness {nice}'
        except OSError as exc:
            refused.append(f'can.cycle_nice {nice} ({exc.strerror})')
            got = f'niceness {os.getpriority(os.PRIO_PROCESS, 0)}'
    else:
        got = 'normal scheduling'
    if refused:
        log.warning('control cycle process runs at %s: %s refused; allow it with CAP_SYS_NICE or '
                    'limits.conf (rtprio %d, nice %d)', got, ' and '.join(refused), priority, nice)
    return got


#: native ids of the threads doing start-up work (:func:`start_up_work`)
_starting: set[int] = set()
_starting_lock = threading.Lock()


@contextlib.contextmanager
def start_up_work(priority: int, nice: int) -> Iterator[None]:
    """The calling thread's work one real-time priority below the cycle's while the process
    runs at SCHED_FIFO ``priority`` (at normal scheduling, niceness ``nice``, where
    ``priority`` is 1); afterwards every thread of the process below ``priority`` (the
    threads this work started, the calling one) at SCHED_FIFO ``priority``, except those
    still inside such work. A thread above keeps its priority (the SYNC thread, one above).

    Start-up work (the simulator's and the master's construction; the boot's dictionary
    checks and SDO configuration, which the simulated drives answer in the same thread) is
    CPU for up to a second. At the cycle's own priority it held a core against every running
    cycle's threads of that priority: two stacks starting at once on a two-core host (a test
    run's workers) starved a running stack's receive thread for 200 ms while its SYNC thread
    (one above) went on, and a false "heartbeat lost" / "no TPDO1 from any drive" stop
    latched (runs 711 and 803, bench/RESULTS.md). At normal scheduling instead, the boot
    waited behind the running cycles and every other process: on a host loaded 13 deep an
    SDO answer took longer than ``can.sdo_timeout`` twice, and the configuration failed
    (run 902). One below, a running cycle preempts it and nothing else does. Nothing changes
    when the process is not at SCHED_FIFO (``can.cycle_priority`` 0, or refused).
    """
    if priority <= 0 or os.sched_getscheduler(0) != os.SCHED_FIFO:
        yield
        return
    tid = threading.get_native_id()
    with _starting_lock:
        _starting.add(tid)
    try:
        if priority > 1:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority - 1))
        else:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
            with contextlib.suppress(OSError):
                os.setpriority(os.PRIO_PROCESS, tid, nice)     # Linux: a thread's own niceness
        yield
    finally:
        with _starting_lock:
            _starting.discard(tid)
            raise_to_fifo(priority, skip=frozenset(_starting))


def raise_to_fifo(priority: int, *, skip: frozenset[int] = frozenset()) -> None:
    """Every thread of this process below SCHED_FIFO ``priority`` (normal scheduling, or a
    lower real-time priority), and not in ``skip``, to SCHED_FIFO ``priority``; a thread that
    ended meanwhile is passed over."""
    for name in os.listdir('/proc/self/task'):
        tid = int(name)
        if tid in skip:
            continue
        try:
            if (os.sched_getscheduler(tid) != os.SCHED_FIFO
                    or os.sched_getparam(tid).sched_priority < priority):
                os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(priority))
        except OSError:
            pass


def _plain(value: Any) -> bool:
    """``value`` is data (numbers, text, arrays, enums, dataclass records and containers of
    them): it crosses as a copy. Anything else (an object with state and methods) stays in
    the child, reached by path, so that a call acts on the original."""
    if isinstance(value, (type(None), bool, int, float, complex, str, bytes, np.ndarray, np.generic,
                          enum.Enum)):
        return True
    if isinstance(value, (list, tuple, set, frozenset)):
        return all(_plain(v) for v in value)
    if isinstance(value, dict):
        return all(_plain(k) and _plain(v) for k, v in value.items())
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return all(_plain(getattr(value, f.name)) for f in dataclasses.fields(value))
    return False


def _portable_error(exc: BaseException) -> BaseException:
    """``exc`` if it survives pickling as itself, else a :class:`DriverError` saying it."""
    try:
        back = pickle.loads(pickle.dumps(exc))
        if type(back) is type(exc) and str(back) == str(exc):
            return exc
    except Exception:  # noqa: BLE001
        pass
    return DriverError(f'{type(exc).__name__}: {exc}')


class _ForwardLog(logging.Handler):
    """The child's log records, to the parent's loggers of the same names."""

    def __init__(self, child: _Child) -> None:
        super().__init__(logging.INFO)
        self.child = child

    def emit(self, record: logging.LogRecord) -> None:
        try:
            text = self.format(record)
        except Exception:  # noqa: BLE001
            text = str(record.msg)
        # the SYNC thread logs too: it never waits on a link the parent stopped reading
        if self.child.stop.is_set() or not self.child.try_send(('log', record.name, record.levelno, text),
                                                               wait=LOG_SEND_WAIT_S):
            # the parent is gone (or going): the inherited stderr is what is left
            print(f'[{record.levelname}] [{record.name}] {text}', file=sys.stderr, flush=True)


def _child_main(fd: int) -> int:
    child = _Child(Connection(fd))
    # a terminal's signals are the parent's to handle; SIGTERM ends the child in order
    for sig in (signal.SIGINT, signal.SIGHUP):
        signal.signal(sig, signal.SIG_IGN)

    def terminate(signum: int, frame: Any) -> None:
        child.orphaned = True
        # a shell's convention, once the drives are disabled (close, below): 128 + the signal
        raise SystemExit(128 + signum)
    signal.signal(signal.SIGTERM, terminate)
    try:
        with open('/proc/self/comm', 'w') as f:
            f.write('cycle-commands')
    except OSError:
        pass
    root = logging.getLogger('brace_control')
    root.addHandler(_ForwardLog(child))
    root.setLevel(logging.INFO)
    root.propagate = False
    try:
        child.serve()
    finally:
        child.close()
    return 0


def ended_how(code: int) -> str:
    """What a cycle process's exit code says (Popen's returncode)."""
    def name(number: int) -> str:
        try:
            return signal.Signals(number).name
        except ValueError:
            return f'signal {number}'
    if code < 0:
        return f'was killed by {name(-code)} (the drives stop on the master\'s heartbeat loss)'
    if code > 128:
        return f'ended on {name(code - 128)} after disabling the drives'
    return f'ended (exit code {code})'


if __name__ == '__main__':
    # run as the package's module, not as __main__: the snapshot's classes are pickled by
    # their module's name, which the parent imports as brace_control.can.process
    from brace_control.can import process as _process
    sys.exit(_process._child_main(int(sys.argv[1])))
