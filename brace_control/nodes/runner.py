"""``main()`` for a node executable: ``--help``, start-up errors, Ctrl-C, clean exit.

``ros2 run brace_control ik_node --ros-args --params-file config/lumbar_brace.yaml``
ends up in :func:`run_node`. Exit codes: 0 clean (Ctrl-C / SIGTERM / shutdown),
1 start-up error of the device (``can_driver_node``: the CAN bus or a drive did not come
up), 2 configuration error (bad parameter file or value, message on stderr). Ended by
SIGALRM (:data:`TEARDOWN_CUT`, shell status 142), its threads' stacks on stderr: the node's
own work was done (drives disabled, goals reported) and the DDS teardown after it did not
end within :data:`TEARDOWN_S` (a deadlock inside Fast DDS, eProsima/Fast-DDS#6502); or its
spin loop stopped turning for :data:`SPIN_STALL_S` (a native call that never returned: such
a node serves nothing, and would not see a stop signal or its parent's end either); or its
own shutdown took longer than :data:`SHUTDOWN_S`. A driver node ended so leaves the drives to
the control cycle's process, which disables them when its link to the node closes (real
drives also stop on the master's heartbeat).

SIGINT, SIGTERM, SIGHUP and SIGQUIT (Ctrl-C, launch, systemd, a closed terminal or an SSH
drop, ``brace-bringup --processes``) end the spin loop, not the ROS context: the node's
``shutdown()`` then runs while it can still publish (the trajectory node reports its running
and queued goals aborted, the driver disables the drives), and only then is the context shut
down.

Never unsupervised: a node that ``brace-bringup`` started ends when the bring-up ends, by
any means, SIGKILL included (:func:`watch_parent`): the bring-up hands each node the read end
of a pipe (``BRACE_PARENT_FD``) and keeps the write end; when the bring-up process is gone
the pipe reads end-of-file and the node stops as on SIGTERM (drives disabled first). On
Linux the kernel's parent-death signal (SIGTERM) backs it up.
"""
from __future__ import annotations

import faulthandler
import gc
import math
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import rclpy
from rclpy.executors import Executor, ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions

from ..config import ConfigError, load_device_config
from .dds import use_discovery_profile
from .spin import spin_once

__all__ = ['run_node', 'usage', 'make_executor', 'freeze_start_up_heap', 'watch_parent',
           'cut_short_after', 'STOP_SIGNALS', 'PARENT_FD_ENV', 'EXIT_STARTUP', 'EXIT_CONFIG',
           'StallWatch', 'spin_stall_s', 'TEARDOWN_CUT', 'TEARDOWN_S', 'SPIN_STALL_S',
           'SPIN_STALL_ENV', 'SHUTDOWN_S', 'LONG_WORK_S', 'allow_long_work']

EXIT_STARTUP = 1
EXIT_CONFIG = 2
#: s run_node waits at exit for callbacks still running
EXECUTOR_SHUTDOWN_S = 2.0
#: s: the most the DDS teardown at exit may take (after the node's own shutdown) before
#: the process ends itself with its stacks on stderr; less than the bring-up's 10 s
#: before SIGKILL (``ProcessBringUp.stop``)
TEARDOWN_S = 6.0
#: the exit status (``Popen.returncode``) of a node whose DDS teardown :data:`TEARDOWN_S` cut
#: short after its own work was done: killed by SIGALRM's default action, which needs no
#: interpreter lock (the stuck native call holds it). Told apart from an error (1, 2) and a
#: crash (SIGSEGV, SIGABRT): the bring-up reports it as a warning
TEARDOWN_CUT = -signal.SIGALRM
#: s the spin loop may stop turning before the process ends itself (module docstring); the
#: environment variable ``BRACE_SPIN_STALL_S`` sets it (0: never, e.g. under a debugger)
SPIN_STALL_S = 5.0
SPIN_STALL_ENV = 'BRACE_SPIN_STALL_S'
#: s a watched loop may stand still for work known to take long (:func:`allow_long_work`):
#: longer than the cycle process's start (60 s) and a boot's SDO timeouts on a loaded host
LONG_WORK_S = 90.0
#: s the node's own shutdown (the driver: disabling the drives; the trajectory node: its goals
#: reported) may take before the process ends itself
SHUTDOWN_S = 15.0
#: the signals that stop a node (and the bring-up) cleanly: the drives are disabled first
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT)
#: environment variable: the read end of the pipe a parent (brace-bringup) keeps open
PARENT_FD_ENV = 'BRACE_PARENT_FD'


def cut_short_after(seconds: float | None) -> None:
    """From now on this process lives at most ``seconds`` more (``None``: no limit again).

    For DDS calls that may deadlock inside Fast DDS holding the interpreter lock
    (eProsima/Fast-DDS#6502), so that no Python code runs again: a teardown, a shutdown, or
    (re-armed by :class:`StallWatch`) a loop that must keep turning. Two watchdogs that need
    no GIL: faulthandler's C thread prints every thread's stack on stderr after ``seconds``,
    and the kernel ends the process half a second later with SIGALRM's default action
    (:data:`TEARDOWN_CUT`, shell status 142). Called again, it replaces the limit."""
    if seconds is None:
        signal.setitimer(signal.ITIMER_REAL, 0.0)
        faulthandler.cancel_dump_traceback_later()
        return
    faulthandler.dump_traceback_later(seconds, exit=False)
    if threading.current_thread() is threading.main_thread():
        # only the main thread may set a handler; another thread re-arms the timer of a
        # watch that the main thread made (StallWatch: its action set there, at its start)
        signal.signal(signal.SIGALRM, signal.SIG_DFL)
    signal.setitimer(signal.ITIMER_REAL, seconds + 0.5)


class StallWatch:
    """A loop's dead-man's switch: :meth:`turn` once per iteration re-arms
    :func:`cut_short_after` with ``stall_s`` (at most once a second: each arming starts
    faulthandler's watchdog thread anew), so the process ends once the loop has not turned
    for ``stall_s``. ``stall_s`` 0: never (:func:`spin_stall_s`).

    Work known to take long in the loop's thread (a bring-up's start-up, a driver's lifecycle
    transition: the cycle process's start and the drives' boot, seconds on a loaded host or a
    slow bus) first calls :func:`allow_long_work`: the newest watch of the process then
    allows :data:`LONG_WORK_S` until the loop turns again."""

    #: the newest watch of this process (:func:`allow_long_work` acts on it), if any
    active: 'StallWatch | None' = None

    def __init__(self, stall_s: float) -> None:
        self.stall_s = stall_s
        self._armed = -math.inf
        #: the watched loop's thread: only work in it can stop the loop turning
        self.thread = threading.current_thread()
        if stall_s and self.thread is threading.main_thread():
            signal.signal(signal.SIGALRM, signal.SIG_DFL)
        StallWatch.active = self

    def turn(self) -> None:
        if time.monotonic() - self._armed >= 1.0:
            self.rearm()

    def rearm(self) -> None:
        """``stall_s`` from now, whatever was allowed before (nothing when the watch is off)."""
        self.allow(self.stall_s)

    def allow(self, seconds: float) -> None:
        """The loop may stand still ``seconds`` (at least ``stall_s``) from now; its next
        turn a second or more later re-arms ``stall_s``. Nothing when the watch is off."""
        if self.stall_s:
            cut_short_after(max(seconds, self.stall_s))
            self._armed = time.monotonic()


def allow_long_work(seconds: float | None = None) -> None:
    """Long work is about to run in the watched loop's thread (:class:`StallWatch`): allow it
    ``seconds`` (default :data:`LONG_WORK_S`). Nothing in a process without a watch (a test,
    the demo), nor in another thread than the watched loop's: the loop turns on meanwhile
    (an in-process bring-up's main loop while a node's executor thread runs a transition)."""
    watch = StallWatch.active
    if watch is not None and threading.current_thread() is watch.thread:
        watch.allow(LONG_WORK_S if seconds is None else seconds)


def spin_stall_s(env: dict[str, str] | None = None) -> float:
    """:data:`SPIN_STALL_S`, or the environment's ``BRACE_SPIN_STALL_S`` (s, 0: off).

    :raises ConfigError: a value that is not a number >= 0 (named, with what is expected)."""
    text = (os.environ if env is None else env).get(SPIN_STALL_ENV, '')
    if not text.strip():
        return SPIN_STALL_S
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (value >= 0.0 and math.isfinite(value)):
        raise ConfigError(f'{SPIN_STALL_ENV}={text!r}: expected seconds >= 0 (0: no limit)')
    return value


def _parent_death_signal(sig: int) -> bool:
    """Linux: the kernel sends ``sig`` to this process when its parent ends (prctl
    PR_SET_PDEATHSIG). Returns whether it took effect."""
    if not sys.platform.startswith('linux'):
        return False
    try:
        import ctypes
        libc = ctypes.CDLL(None, use_errno=True)
        return libc.prctl(1, int(sig), 0, 0, 0) == 0          # PR_SET_PDEATHSIG = 1
    except (OSError, AttributeError):
        return False


def watch_parent(stop: threading.Event, env: dict[str, str] | None = None) -> threading.Thread | None:
    """Set ``stop`` when the parent that started this process is gone (module docstring).

    Reads the pipe named by ``BRACE_PARENT_FD`` in a daemon thread: the parent never writes
    to it, so a read returns only at end-of-file, when the parent's write end closed, i.e.
    when the parent exited, by any signal. Returns the thread (``None`` without a pipe).
    """
    env = os.environ if env is None else env
    text = env.get(PARENT_FD_ENV, '')
    if not text.isdigit():
        return None
    fd = int(text)
    _parent_death_signal(signal.SIGTERM)

    def wait_for_eof() -> None:
        try:
            while os.read(fd, 64):
                pass
        except OSError:
            pass
        stop.set()
    thread = threading.Thread(target=wait_for_eof, name='brace-parent-watch', daemon=True)
    thread.start()
    return thread


def make_executor(context: object = None) -> Executor:
    """The executor of one node: rclpy's ``EventsExecutor`` where this rclpy has it (Jazzy
    and later, ``rclpy.experimental``), else a ``SingleThreadedExecutor`` (Humble).

    The events executor does not rebuild a wait set on every wake: a 100 Hz subscription
    costs a quarter of the CPU of the wait-set executor's (bench/RESULTS.md, "Executors").
    ``BRACE_EXECUTOR=single`` in the environment forces the wait-set executor.
    """
    if os.environ.get('BRACE_EXECUTOR', '') != 'single':
        try:
            from rclpy.experimental import EventsExecutor
        except ImportError:
            pass
        else:
            return EventsExecutor(context=context)
    return SingleThreadedExecutor(context=context)


def freeze_start_up_heap() -> None:
    """Take every object built so far out of the cyclic garbage collector's passes
    (:func:`gc.freeze`).

    A node's start-up builds ~10^5 long-lived objects (modules, message classes, the object
    dictionary, the mechanism); Python's full collection walks all of them and holds the GIL
    meanwhile: 0.1-0.5 s on a loaded machine, longer than the drives' heartbeat consumer
    time (bench/RESULTS.md, "Host stalls"). Frozen, they are never walked again; objects
    made later are collected as usual. Call it once the node is up, before it spins.
    """
    gc.freeze()


def usage(executable: str, summary: str) -> str:
    """The ``--help`` text: what the node does, how to start it, where the package lives."""
    import brace_control
    where = Path(brace_control.__file__).resolve().parent
    return (f'{executable}: {summary}\n\n'
            f'usage: {executable} [--help] --ros-args --params-file <device>.yaml '
            '[-r __ns:=/ns] [-p name:=value]\n\n'
            f'brace_control {getattr(brace_control, "__version__", "")} from {where}\n')


def run_node(factory: Callable[[], Node], *, executable: str, summary: str,
             args: Sequence[str] | None = None,
             executor: Callable[[], Executor] = make_executor,
             start: Callable[[Node], None] | None = None,
             startup_errors: tuple[type[Exception], ...] = ()) -> int:
    """Init rclpy with ``args``, build the node, spin until shutdown; return the exit code.

    :param executor: builds the executor (a multi-threaded one for a node whose services
        block).
    :param start: called with the node before spinning (e.g. booting the drives); Ctrl-C
        during it ends cleanly like Ctrl-C while spinning.
    :param startup_errors: exceptions of ``start`` (or of spinning) that end the process
        with :data:`EXIT_STARTUP` and their message on stderr.
    """
    argv = list(sys.argv if args is None else args)
    user_args = argv[1:argv.index('--ros-args')] if '--ros-args' in argv else argv[1:]
    if '-h' in user_args or '--help' in user_args:
        print(usage(executable, summary))
        return 0
    # our own signal handling (module docstring): the context outlives the spin loop. Installed
    # first, so a signal during start-up (rclpy.init, building the node) ends the process
    # cleanly too, not with a KeyboardInterrupt traceback.
    stop = threading.Event()
    for sig in STOP_SIGNALS:
        signal.signal(sig, lambda *_: stop.set())
    from .. import nodes as _package
    if getattr(_package, 'STOPPED_WHILE_STARTING', False):
        # a stop signal during the imports whose SystemExit something swallowed (the final
        # clone of the twelfth session: the node then ran on, its SIGINT lost): nothing
        # started yet, the clean end of a stop while starting
        return 0
    watch_parent(stop)
    from .params import params_files
    try:
        for f in params_files(argv):            # ours first: rcl's parser takes a key twice
            load_device_config(f)
        stall_s = spin_stall_s()
    except ConfigError as exc:
        print(f'{executable}: configuration error: {exc}', file=sys.stderr)
        return EXIT_CONFIG
    use_discovery_profile()
    try:
        rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    except Exception as exc:  # noqa: BLE001 - rcl reports bad --ros-args as RCLError
        print(f'{executable}: cannot start: {exc}', file=sys.stderr)
        return EXIT_CONFIG
    node = None
    try:
        node = factory()
    except ConfigError as exc:
        print(f'{executable}: configuration error: {exc}', file=sys.stderr)
        rclpy.try_shutdown()
        return EXIT_CONFIG
    except KeyboardInterrupt:
        rclpy.try_shutdown()
        return 0
    spinner = executor()
    code = 0
    try:
        if start is not None and not stop.is_set():     # a signal while building: no start
            start(node)
        freeze_start_up_heap()
        spinner.add_node(node)
        watch = StallWatch(stall_s)
        # wake at least every 0.1 s to see a signal (Python runs handlers between bytecodes);
        # the loop's own dead-man's switch (module docstring)
        while not stop.is_set() and rclpy.ok():
            watch.turn()
            spin_once(spinner, 0.1)                     # nodes/spin.py
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except startup_errors as exc:
        print(f'{executable}: start-up failed: {exc}', file=sys.stderr)
        code = EXIT_STARTUP
    except RuntimeError:
        # rclpy under load: a message taken while the signal handler shuts the context
        # down fails in the bindings ("Unable to convert call argument", seen also in
        # ros/joint_state_publisher#117). A shutdown, not an error; anything else is.
        if rclpy.ok():
            raise
    finally:
        StallWatch.active = None           # the shutdown's bound is not extended by its work
        shutdown = getattr(node, 'shutdown', None)
        if callable(shutdown):
            cut_short_after(SHUTDOWN_S)
            shutdown()
        # The node's own work is done (drives disabled, goals reported). What is left is
        # DDS teardown, native code that has deadlocked in Fast DDS (eProsima/Fast-DDS#6502:
        # a remote participant's removal and its lease check, each waiting for the other)
        # holding the interpreter lock: ended after TEARDOWN_S with its stacks on stderr
        # (TEARDOWN_CUT), instead of leaving it for the bring-up's SIGKILL or forever.
        cut_short_after(TEARDOWN_S)
        # a callback still awaiting a peer that is gone (a service call to a node already
        # stopped) must not hold the exit: wait a bounded time for the running callbacks
        spinner.shutdown(timeout_sec=EXECUTOR_SHUTDOWN_S)
        # The events executor keeps callbacks registered on the node's publishers and
        # subscriptions: destroying those under it can crash (ros2/rclpy#1644, open), and so
        # can the executor itself when the interpreter frees it after the context is gone (a
        # node that ended its work cleanly, then exited with SIGSEGV in the suite). Take the
        # node out of it, destroy the node, then the executor, then the context, in that order.
        try:
            spinner.remove_node(node)
        except Exception:  # noqa: BLE001 - a teardown step; the next ones still run
            pass
        node.destroy_node()
        del spinner
        gc.collect()
        rclpy.try_shutdown()
    return code
