"""What the master's parts share: its state, the drives it supervises and the cycle's inputs.

:class:`~.master.BraceMaster` is made of parts, each an object with its own state:
:class:`~.boot.Boot` (plan, bus, NMT, SDO configuration, homing), :class:`~.receive.Receiver`
(what the drives send), :class:`~.monitors.Monitors` (the per-SYNC protective functions),
:class:`~.cycle.Cycle` (the SYNC thread: monitors, command, RPDOs, SYNC) and
:class:`~.stream.SetpointStream` (the teleoperation stream). What they share is here and
nowhere else:

* :class:`Lifecycle`: the master's :class:`~.state.MasterState`, the nodes, the 402 state the
  drives are driven towards and the flags the API sets for the cycle (tracking, reset pulse,
  homing start, closing, ...), the slow force-steered moves (relief, take-up) and a soft stop
  requested; with the waits the API makes on them;
* :class:`Motion`: the commanded motion (:class:`~brace_control.control.execution.PathExecutor`),
  its lock (the SYNC thread against the API threads), the execution events not yet read and,
  while asked for, the :class:`CycleTrace`.

Writers: the API threads (one at a time, under the master's API lock) and the SYNC thread;
each flag has one writer per phase (the docstrings say which).
"""
from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import TYPE_CHECKING

from .cia402 import OpMode, State402, Statusword, describe_statusword
from .errors import DriverOperationError, DriverTimeoutError, FaultLatchedError
from .state import MasterConfig, MasterState, Relief, TakeUp, _Drive, _Module, _Node

if TYPE_CHECKING:
    from ..control.execution import ExecutionEvent, PathExecutor
    from .supervision import Fault, Limits, Supervisor
    from .sync import SyncClock

__all__ = ['CycleTrace', 'Lifecycle', 'Motion']

log = logging.getLogger('brace_control.can.master')


class CycleTrace:
    """What the SYNC cycle commanded, cycle by cycle, while asked
    (:meth:`~.master.BraceMaster.trace_cycles`): to judge a controller on the simulated
    world's clock (one SYNC period per cycle, whatever the host's load) and from the instant a
    goal reached the cycle, not from a publish two DDS hops earlier. Wall clock
    (``time.time()``, the clock of the SYNC stamps); the last :data:`LENGTH` of each."""

    #: kept of each record (60 s at 500 Hz)
    LENGTH = 30_000

    def __init__(self) -> None:
        #: each cycle's command: when it was taken
        self.cycles: deque[float] = deque(maxlen=self.LENGTH)
        #: ``(when, positions)`` of each cycle the interaction's admittance drove the command
        self.commands: deque[tuple[float, tuple[float, ...]]] = deque(maxlen=self.LENGTH)
        #: when each interaction wrench goal reached the cycle (accepted or not)
        self.goals: deque[float] = deque(maxlen=self.LENGTH)

    def take(self) -> dict[str, list]:
        """The records since the last call (oldest first), as plain lists; emptied."""
        out = {'cycles': list(self.cycles), 'commands': [(t, list(q)) for t, q in self.commands],
               'goals': list(self.goals)}
        self.cycles.clear()
        self.commands.clear()
        self.goals.clear()
        return out


class Motion:
    """The commanded motion: the executor the SYNC cycle samples, the lock that serialises it
    between the SYNC thread and the API threads, its events not yet read, and the cycle's
    trace while one is asked for."""

    def __init__(self, executor: PathExecutor) -> None:
        self.executor = executor
        self.lock = threading.Lock()
        self.events: list[ExecutionEvent] = []
        self.trace: CycleTrace | None = None

    def collect(self) -> None:
        """Move the executor's new events to :attr:`events` (the caller holds :attr:`lock`)."""
        ex = self.executor
        if ex.events:
            self.events.extend(ex.events)
            ex.events.clear()

    def drain(self) -> list[ExecutionEvent]:
        """The events since the last call, oldest first."""
        with self.lock:
            events, self.events = self.events, []
        return events

    def release(self, reason: str) -> None:
        """Drop whatever the command follows, at once (reported with ``reason``)."""
        with self.lock:
            self.executor.release(reason)
            self.collect()


class Lifecycle:
    """The master's state and the cycle's inputs (see the module docstring)."""

    def __init__(self, config: MasterConfig, supervisor: Supervisor, clock: SyncClock) -> None:
        self.config = config
        self.supervisor = supervisor
        self.clock = clock
        #: the monitors' thresholds (the boot narrows the saturation to the load-cell inputs)
        self.limits: Limits = config.limits
        self.state = MasterState.CLOSED
        #: bumped on every change of :attr:`state` (a node publishes the state on change)
        self.state_changes = 0
        #: the drives (actuator order) and the load-cell module, made at open
        self.drives: list[_Drive] = []
        self.module: _Module | None = None
        # -- the cycle's inputs, set by the API
        self.pdo_running = False              # SYNC + RPDOs (else heartbeat only)
        self.supervising = False              # monitors armed (after boot)
        self.closing = False                  # shutdown: disable whatever the latch says
        self.desired = State402.SWITCH_ON_DISABLED
        self.reset_pulse = False
        self.homing_start = False
        self.tracking = False                 # targets follow the command
        #: 6060h the RPDOs carry where a drive maps it (homing: 6, else 8)
        self.mode = int(OpMode.CYCLIC_SYNC_POSITION)
        self.homed = False
        #: monotonic time of the last recover (an EMCY after it is a cause still present)
        self.recover_time = -math.inf
        #: a latched fault the cycle has not reacted to yet (set by the supervisor's callback)
        self.fault_to_handle = False
        #: (drive index, force) to brake for, or the reason of a soft limit found elsewhere
        self.soft_stop: tuple[int, float] | str | None = None
        #: the slow moves the load cells steer, while one runs
        self.relief: Relief | None = None
        self.take_up: TakeUp | None = None
        #: a relief moved the actuators since the last take-up: pull-only legs may hang slack
        self.relieved = False

    # ------------------------------------------------------------------ state
    def on_fault(self, fault: Fault) -> None:
        """First reaction to a newly latched fault (any thread; the supervisor's callback):
        commands stop being accepted; the cycle brakes or quick-stops on its next run."""
        log.error('protective stop: %s', fault.describe())
        self.tracking = False
        self.fault_to_handle = True
        if self.state not in (MasterState.CLOSED, MasterState.OPEN, MasterState.BOOTING):
            self.set_state(MasterState.FAULT)

    def set_state(self, state: MasterState) -> None:
        if state is not self.state:
            self.state = state
            self.state_changes += 1

    @property
    def nodes(self) -> list[_Node]:
        """Every node the master supervises: the drives, and the load-cell module."""
        return [*self.drives, *([self.module] if self.module is not None else [])]

    def actual_counts(self, d: _Drive) -> int:
        """Where drive ``d`` is (master counts), by its newest sample; else its target."""
        return self.config.scaling.to_counts(d.sample.position) if d.sample is not None else d.target

    def all_in(self, state: State402) -> bool:
        return all(d.state is state for d in self.drives)

    def require_open(self) -> None:
        if self.state in (MasterState.CLOSED, MasterState.OPEN, MasterState.BOOTING):
            raise DriverOperationError(f'master is {self.state.value}: boot() first')

    def require_ready(self) -> None:
        self.require_open()
        if self.supervisor.latched:
            raise FaultLatchedError(f'protective stop latched: {self.supervisor.summary()}; '
                                    'call recover() once the cause is gone')

    # ------------------------------------------------------------------ waits
    def wait_syncs(self, n: int, timeout: float = 1.0) -> None:
        """Until ``n`` more SYNCs were sent (at most ``timeout``), and one period for the
        answer to the last."""
        clock = self.clock
        target = clock.index + n
        end = time.monotonic() + timeout
        while clock.index < target and time.monotonic() < end:
            time.sleep(self.config.period / 2)
        time.sleep(self.config.period)

    def wait(self, cond: Callable[[], bool], *, timeout: float | None, what: str,
             raise_: bool = True) -> bool:
        """Poll ``cond`` each half period; raise on a latched fault or the time limit."""
        limit = self.config.transition_timeout if timeout is None else timeout
        end = time.monotonic() + limit
        while True:
            if cond():
                return True
            if raise_ and self.supervisor.latched:
                raise FaultLatchedError(f'waiting for {what}: protective stop: {self.supervisor.summary()}')
            if time.monotonic() > end:
                if not raise_:
                    return False
                states = ', '.join(f'{d.name}: {describe_statusword(d.sample.statusword) if d.sample else "no TPDO"}'
                                   f' (NMT {d.nmt})' for d in self.drives)
                local = [d.name for d in self.drives
                         if d.sample is not None and not d.sample.statusword & Statusword.REMOTE]
                hint = (f'; statusword bit 9 (remote) is clear on {", ".join(local)}: a drive under '
                        'local control (its panel, its setup tool) does not take the controlword '
                        'from the bus' if local else '')
                raise DriverTimeoutError(f'{what} not reached within {limit:g} s ({states}){hint}')
            time.sleep(self.config.period / 2)
