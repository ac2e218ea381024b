"""Test-wide settings and fixtures: DDS stays on loopback, each run on its own ROS domain.

The environment is set before anything imports rclpy, so every node, and every subprocess a
test starts, inherits it.
"""
import os
import threading

import pytest

os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')


#: consecutive ROS domains a run reserves: one per pytest-xdist worker (make test runs four)
DOMAIN_BLOCK = 8
#: where a run's reservation lives: one lock file per domain id, locked (flock) by the run's
#: first process for as long as it runs; the kernel drops a lock when its holder ends, however
DOMAIN_LOCKS = os.path.join('/tmp', 'brace_control_test_domains')
_held_domain_locks: list[int] = []


def _reserve_domains(first: int) -> int:
    """The first of :data:`DOMAIN_BLOCK` consecutive domain ids (below 233) that no other
    test run on this machine holds, searched from ``first`` on; held until this process
    ends. Without it two runs could draw the same domain (the run's pid modulo 200: 1 in 100
    for two runs side by side, more for a user's fixed ``ROS_DOMAIN_ID``), and one run's
    nodes then took the other's joint states: a kinetics test's estimate 30 mm off its
    input, a probe's estimate 52 mm off the simulator's truth."""
    import fcntl
    os.makedirs(DOMAIN_LOCKS, mode=0o777, exist_ok=True)
    last = 233 - DOMAIN_BLOCK
    for k in range(last + 1):
        base = (first + k) % (last + 1)
        fds: list[int] = []
        for d in range(base, base + DOMAIN_BLOCK):
            fd = os.open(os.path.join(DOMAIN_LOCKS, f'{d}.lock'), os.O_CREAT | os.O_RDWR, 0o666)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                os.close(fd)
                break
            fds.append(fd)
        if len(fds) == DOMAIN_BLOCK:
            _held_domain_locks.extend(fds)
            return base
        for fd in fds:
            os.close(fd)                  # closing the file drops its lock
    raise RuntimeError(f'every block of {DOMAIN_BLOCK} ROS domains is held by another test run '
                       f'({DOMAIN_LOCKS}): end one, or wait')


def _domain_id() -> str:
    """Our own ROS domain per test run, so two runs on one machine never cross-talk, and one
    per pytest-xdist worker: the workers inherit the environment of the run's first process,
    and two stacks on one domain answer each other's probes (a worker's node "up" because the
    other worker's node of that name is). The run's first process reserves a block of
    domains (:func:`_reserve_domains`), from the one the user set, else from its pid's; the
    worker ``gwN`` takes the block's N-th."""
    worker = os.environ.get('PYTEST_XDIST_WORKER', '')      # 'gw0', 'gw1', ...
    index = int(worker[2:]) if worker[2:].isdigit() else 0
    base = os.environ.get('BRACE_TEST_DOMAIN_BASE')
    if base is None or not worker:
        wanted = int(base or os.environ.get('ROS_DOMAIN_ID') or 1 + os.getpid() % 200)
        base = str(_reserve_domains(wanted))
        os.environ['BRACE_TEST_DOMAIN_BASE'] = base            # the workers' common base
    if index >= DOMAIN_BLOCK:
        raise RuntimeError(f'pytest-xdist worker {worker}: a run reserves {DOMAIN_BLOCK} ROS domains, '
                           f'one per worker; run at most {DOMAIN_BLOCK} workers')
    return str(int(base) + index)


os.environ['ROS_DOMAIN_ID'] = _domain_id()

# the participants the tests make (probes, in-process stacks) announce themselves as the
# package's entry points do (brace_control.nodes.dds): a probe or a node started beside a
# running stack is found in its first two seconds, not at the next periodic announcement
# (3 s later); the processes a test starts inherit it
from brace_control.nodes.dds import use_discovery_profile  # noqa: E402

use_discovery_profile()

# Property tests run the same examples on every run (derandomized, no example database):
# a suite that passes or fails by the draw is not deterministic. ``HYPOTHESIS_PROFILE=explore``
# draws new ones on every run to hunt for counterexamples; one found that way goes into the
# test as an ``@example``.
from hypothesis import settings as _hypothesis_settings  # noqa: E402

_hypothesis_settings.register_profile('brace', derandomize=True, database=None)
_hypothesis_settings.register_profile('explore', database=None)
_hypothesis_settings.load_profile(os.environ.get('HYPOTHESIS_PROFILE', 'brace'))
os.environ.setdefault('MPLBACKEND', 'Agg')
os.environ.setdefault('RCUTILS_LOGGING_BUFFERED_STREAM', '1')
# A native crash of any process a test starts (a node, a bring-up, the cycle process) prints
# its Python stack on its stderr, which the test keeps: one full run saw can_driver_node end
# with SIGSEGV before its first log line, and nothing said where
os.environ.setdefault('PYTHONFAULTHANDLER', '1')


def _clean_zombie_shm() -> str:
    """Fast DDS's own ``fastdds shm clean``: delete the shared-memory ports and segments of
    processes that are gone (a segment whose lock file nobody holds), before this run's
    first participant. A killed DDS process leaves its segments in /dev/shm; once, with
    hundreds of them from a day of killed runs, a new participant spun for good in boost's
    ``managed_open_or_create_impl::priv_open_or_create`` opening a half-made port. Segments
    of live processes (another run, a user's nodes) keep their lock and are left alone.

    The tool ships with the ``ros-fastdds`` wheel (``<prefix>/tools/fastdds``); its command
    line also imports psutil, which ``shm clean`` does not use, so its ``Clean`` class is
    loaded alone. Without the tool (another ROS install), nothing is done."""
    import contextlib
    import importlib.util
    import io
    import sys
    path = os.path.join(sys.prefix, 'tools', 'fastdds', 'shm', 'clean.py')
    if not os.path.isfile(path):
        return f'no {path}: stale Fast DDS segments not cleaned'
    spec = importlib.util.spec_from_file_location('_fastdds_shm_clean', path)
    module = importlib.util.module_from_spec(spec)
    out = io.StringIO()
    half_made = []
    try:
        spec.loader.exec_module(module)
        with contextlib.redirect_stdout(out):
            module.Clean().run(force=False)
        half_made = _remove_half_made_ports()
    except Exception as exc:  # noqa: BLE001 - a cleanup that fails must not fail the run
        return f'fastdds shm clean failed: {exc!r}'
    return ' '.join(out.getvalue().split()) + (f'; half-made ports removed: {half_made}' if half_made else '')


def _remove_half_made_ports(shm: str = '/dev/shm') -> list[str]:
    """Remove the shared-memory ports whose creator died while making them: a port file
    with no lock file (``_el``) beside it, 10 s old. Fast DDS's clean tool does not look at
    them (it goes by the lock files), and every new participant that opens the port waits
    on it for good, in any ROS domain (the SHM port numbers are shared): seen empty
    (fastdds_port7001, 0 bytes, left by a run the watchdog ended) and full size
    (fastdds_port7003, 52 400 bytes: both workers of a run, then their replacements, spun
    in boost's ``priv_open_or_create``). A port being made has its lock file within
    microseconds, not 10 s.

    Also a port's creation mutex (``sem.fastdds_port<N>_mutex``, a named semaphore) whose
    port is gone, 10 s old: a process killed while it held one leaves it taken, and the next
    participant to make port N waits on it for good (the clean tool leaves them: 721 of them
    here after a day of runs; the twelfth session's final clone, twice, had three node
    starts in one worker hang 30 s). A live port has its file, so its mutex stays."""
    import glob
    import time
    removed: list[str] = []

    def remove_old(paths: list[str]) -> None:
        for path in paths:
            try:
                if time.time() - os.stat(path).st_mtime > 10.0:
                    os.remove(path)
                    removed.append(os.path.basename(path))
            except OSError:
                continue              # made or removed meanwhile
    remove_old([path for path in glob.glob(os.path.join(shm, 'fastdds_port*'))
                if not path.endswith(('_el', '_sl')) and not os.path.exists(path + '_el')])
    # after the ports: the mutex of a half-made port just removed goes too
    remove_old([path for path in glob.glob(os.path.join(shm, 'sem.fastdds_port*_mutex'))
                if not os.path.exists(os.path.join(shm, os.path.basename(path)[len('sem.'):-len('_mutex')]))])
    return removed


def pytest_sessionstart(session):
    if 'PYTEST_XDIST_WORKER' not in os.environ:     # once per run, before any worker's DDS
        session.config._fastdds_shm_clean = _clean_zombie_shm()
    else:
        # a worker that replaces one the watchdog ended starts here: a port its predecessor's
        # processes left half-made would hang it too
        _remove_half_made_ports()


#: per file, the seconds it took in a measured run (``make test``'s two parts with
#: ``--durations=0``: each file's setup, call and teardown summed; bench/RESULTS.md "Test suite
#: time"); a file not listed counts as UNTIMED_FILE_S
FILE_TIMES = os.path.join(os.path.dirname(__file__), 'file_times.json')
UNTIMED_FILE_S = 30.0


def pytest_collection_modifyitems(session, config, items):
    """The longest files first, each file's tests in their own order: pytest-xdist's
    ``--dist loadfile`` hands the files out in this order, so the workers end within
    a short file of each other instead of one running a long file alone at the end. The
    order changes nothing else (every test sets up its own state, or its module's)."""
    import json
    try:
        with open(FILE_TIMES) as f:
            times = json.load(f)
    except (OSError, ValueError):
        return
    items.sort(key=lambda item: -float(times.get(item.path.name, UNTIMED_FILE_S)))


def pytest_report_header(config):
    report = getattr(config, '_fastdds_shm_clean', None)
    base = int(os.environ['BRACE_TEST_DOMAIN_BASE'])
    domains = f'ROS domains {base}..{base + DOMAIN_BLOCK - 1} reserved for this run ({DOMAIN_LOCKS})'
    return [domains] + ([report] if report else [])


@pytest.fixture
def ros(_rcl_logging_stays_up):
    """A fresh :class:`ros_helpers.Ros` (own executor, its nodes destroyed after the test) on
    the session's one context, so on one DDS participant: see :func:`_rcl_logging_stays_up`."""
    # Imported here, not at the top, so rclpy loads only after the environment above is set
    # and only for tests that start nodes.
    from ros_helpers import Ros
    r = Ros(_rcl_logging_stays_up)
    try:
        yield r
    finally:
        r.close()


@pytest.fixture(scope='session', autouse=True)
def _rcl_logging_stays_up():
    """One rclpy context open for the whole session, never shut down by a test.

    rcl's logging is shared by every context of a process and torn down when the last one
    shuts down (``rcl_logging_fini``: it destroys the ``/rosout`` publishers). Tests that
    each init and shut down their own context tear it down and set it up again many times;
    once in a full run that teardown deadlocked inside Fast DDS (``PDP::removeWriterProxyData``
    waiting on a mutex while delivering the writer's removal to another participant of this
    process, seen with py-spy). With this context open the count never reaches zero during
    the run; the process exit takes it down.

    It is also the context of every ``ros`` fixture, with one node of its own (the anchor)
    so that its DDS participant lives for the whole session: rmw_fastrtps deletes a
    context's participant with its last node, and deleting a participant while another
    participant of this process delivers discovery data to it can livelock inside Fast DDS
    3.2 (seen in CI: ``DomainParticipant::set_listener`` spinning in ``destroy_participant``,
    holding the GIL, while an ``on_writer_discovery`` callback waits for its mutex; gdb).
    Tests that make contexts of their own still delete participants.

    The anchor is not destroyed at the session's end either: destroying its publishers
    deadlocked a worker once (``DataWriterImpl`` waiting in ``unregister_timer``, py-spy:
    this fixture's teardown, right after a bring-up's nodes had left), the same Fast DDS
    race. The process's exit takes both down; a pytest-xdist worker that does not end is
    killed by xdist 10 s after its last result.
    """
    import rclpy
    from rclpy.context import Context
    keep = Context()
    rclpy.init(context=keep)
    _SESSION_DDS.append((keep, rclpy.create_node('test_session_anchor', context=keep)))
    yield keep


#: the session's context and anchor node, alive until the process exits
_SESSION_DDS: list = []


def pytest_configure(config):
    """The per-test watchdog (:mod:`watchdog_plugin`): a test stuck in native code ends its
    worker after ``TEST_LIMIT_S``, its stacks on the run's stderr, and is not run again."""
    import watchdog_plugin
    if not config.pluginmanager.is_registered(watchdog_plugin):       # -p watchdog_plugin
        config.pluginmanager.register(watchdog_plugin, 'watchdog_plugin')


_gc_module: list = [None]


def _frozen_heap(item) -> None:
    """What is alive when a test starts is kept out of the collector's way during the test.

    A worker that has run a few hundred tests holds ~140 000 tracked objects; a full
    collection scanning them stopped every thread of the process for 90-105 ms on a quiet
    machine (bench/RESULTS.md, 2026-11-28 second session), twice that on a loaded one: in a
    test whose simulated drives and control cycle run in this process, the drives' heartbeats
    went silent for 200 ms (a heartbeat-loss stop) and a test's 200 Hz setpoint stream stalled
    (a step-limit stop). So before each test the collector runs over what the last test left
    and :func:`gc.freeze` moves the survivors out of its reach; at each new file everything
    is unfrozen and collected once first, so what a file left behind is freed. The nodes do
    the same for their own start-up heap (``runner``, ``can.process``)."""
    import gc
    if item.path != _gc_module[0]:
        _gc_module[0] = item.path
        gc.unfreeze()
    gc.collect()
    gc.freeze()


#: SCHED_FIFO priority of the control cycle's threads a test runs in this process: below
#: the cycle processes' ``can.cycle_priority`` (50), above every normally scheduled process
IN_PROCESS_CYCLE_PRIORITY = 40
#: the modules whose threads are the control cycle's or the drives': the master's SYNC,
#: the simulated drives' timers, python-can's receive and periodic-send threads
IN_PROCESS_CYCLE_MODULES = ('brace_control.can.', 'brace_control.sim.', 'can.', 'canopen.')
#: the test's own thread meanwhile (its setpoint streams, its checks): niceness, not FIFO
IN_PROCESS_TEST_NICE = -10
#: the interpreter's switch interval meanwhile, as the cycle process sets it
#: (``can.gil_switch_interval_us``)
IN_PROCESS_SWITCH_INTERVAL_S = 200e-6


@pytest.fixture(autouse=True)
def _in_process_cycle_as_the_cycle_process_runs(monkeypatch):
    """A test that runs a master (``BraceMaster``) or simulated drives (``SimulatedBrace``)
    in this process gets them scheduled as ``can_driver_node``'s cycle process schedules
    its own (docs/can.md, "Scheduling"): once either is made, every thread started from
    the modules of ``IN_PROCESS_CYCLE_MODULES`` runs at SCHED_FIFO, and the interpreter's
    switch interval is 200 us. The test's own thread, which streams setpoints and checks
    the results, gets niceness -10: a large share of a core at normal scheduling. All is
    set back when the test ends.

    Without it the drives' heartbeats, the SYNC and the test's own setpoint stream ran
    at normal scheduling beside the other workers' stacks, whose cycle processes run at
    SCHED_FIFO 50: a loaded host tripped the drives' heartbeat consumers (EMCY 8130h),
    slowed the SYNC below 400 Hz or stalled a stream, each in a different test
    (bench/RESULTS.md, fifth and sixth sessions). The test's own thread is not raised to
    SCHED_FIFO: tests parse dictionaries, boot drives and check records for seconds, and a
    thread so raised took a core from every normally scheduled process of the machine
    meanwhile (the other workers' nodes: up to 1.8 of the 2 cores ran at SCHED_FIFO;
    bench/RESULTS.md, seventh session). Where SCHED_FIFO is refused (no CAP_SYS_NICE) the
    test runs as before."""
    import sys

    from brace_control.can.cycle import set_thread_priority
    raised: list[tuple[float, int]] = []

    def fifo_allowed() -> bool:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(IN_PROCESS_CYCLE_PRIORITY))
        except (AttributeError, OSError):
            return False
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        return True

    def raise_priority() -> None:
        if raised or threading.current_thread() is not threading.main_thread() or not fifo_allowed():
            return
        nice = os.getpriority(os.PRIO_PROCESS, 0)          # Linux: this thread's
        os.setpriority(os.PRIO_PROCESS, 0, IN_PROCESS_TEST_NICE)
        raised.append((sys.getswitchinterval(), nice))
        sys.setswitchinterval(IN_PROCESS_SWITCH_INTERVAL_S)

    def wrap(cls: type) -> None:
        init = cls.__init__

        def __init__(self, *args, **kwargs):
            raise_priority()
            init(self, *args, **kwargs)
        monkeypatch.setattr(cls, '__init__', __init__)

    thread_start = threading.Thread.start

    def start(self: threading.Thread) -> None:
        target = getattr(self, '_target', None)
        module = getattr(target, '__module__', None) or type(self).__module__
        if raised and module.startswith(IN_PROCESS_CYCLE_MODULES):
            run = self.run

            def run_raised() -> None:
                set_thread_priority(IN_PROCESS_CYCLE_PRIORITY)      # the SYNC thread's own call
                os.setpriority(os.PRIO_PROCESS, 0, 0)               # (not the test's niceness)
                run()
            self.run = run_raised
        thread_start(self)
    monkeypatch.setattr(threading.Thread, 'start', start)

    from brace_control.can.master import BraceMaster
    from brace_control.sim.brace import SimulatedBrace
    wrap(BraceMaster)
    wrap(SimulatedBrace)
    yield
    if raised:
        sys.setswitchinterval(raised[0][0])
        os.setpriority(os.PRIO_PROCESS, 0, raised[0][1])


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    _frozen_heap(item)
    yield
