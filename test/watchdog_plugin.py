"""The per-test watchdog: a test stuck for :data:`TEST_LIMIT_S` ends its process, every
thread's stack on the run's stderr, and under pytest-xdist it is not run again.

``test/conftest.py`` registers this module; a pytest of its own, without the suite's
conftest (which starts rclpy), loads it with ``-p watchdog_plugin`` and ``test/`` on
``PYTHONPATH`` (``test_watchdog.py`` does).
"""
from __future__ import annotations

import faulthandler
import os
import shutil
import tempfile

import pytest

#: s: the most one test (setup, call, teardown) may take before its process is ended with
#: every thread's stack on stderr. A hang must not stall CI (its budget is 25 min): Fast DDS
#: 3.2 can deadlock when a participant of this process delivers a remote participant's
#: removal while its own announcement timer fires (eProsima/Fast-DDS#6502: the receive
#: thread holds the PDP mutex in unregister_timer, the event thread waits for it in
#: set_next_announcement_interval; seen once in a full run, in a fixture's teardown). The
#: watchdog is faulthandler's C thread: it needs no GIL, which a thread blocked in native
#: code may hold. pytest's own ``faulthandler_timeout`` only prints the stacks: the run would
#: still hang. Ended, an xdist worker is reported as crashed in that test and replaced, and
#: the run goes on without that test. xdist's ``--dist loadfile`` hands a crashed worker's
#: unfinished file out again, the test it crashed in included: each replacement hung in that
#: test in turn, up to xdist's restart limit (four per worker: 17 x 180 s = 51 min with four
#: workers), and CI's budget ended the run (CI run 815, issue 26). Here the worker's record
#: (:func:`records_dir`) names that test, and it fails at once in its next setup
#: (:func:`pytest_runtest_setup`), the rest of its file runs. Without xdist the watchdog ends
#: the run. The longest test takes 40 s (with its module's set-up, 2026-11-28: the
#: interaction sway test; the interaction demo's set-up 27 s), so 180 s leaves four times
#: that. ``BRACE_TEST_LIMIT_S`` sets another limit (test_watchdog.py: 3 s).
TEST_LIMIT_S = float(os.environ.get('BRACE_TEST_LIMIT_S') or 180.0)

#: the fallback for the stacks when pytest does not capture fd 2 (``-s``): appended to, so a
#: worker that replaces an ended one keeps its predecessor's stacks
WATCHDOG_FILE = os.path.abspath(os.path.join(os.path.dirname(__file__), '..', 'test-watchdog.txt'))

_watchdog_out = None
#: where the stacks go, as the message of a test not run again names it
_stacks_where = ''
#: this pytest-xdist worker's record: the file, its descriptor once opened
_record_path: str | None = None
_record_fd: list[int] = []
#: the controller's: the run's records directory, to remove at the session's end
_run_records: list[str] = []


def records_dir(testrunuid: str) -> str:
    """Where a pytest-xdist run keeps what each worker runs: one file per worker, named by
    its id (``gw0``, ``gw1``, ... ; a replacement gets a new one), holding the node id of
    the test it is in, empty between tests. The controller renames the file of a worker that
    goes down in error to ``<id>.ended``, before it hands that worker's work out again."""
    return os.path.join(tempfile.gettempdir(), f'brace_test_watchdog_{testrunuid}')


def pytest_configure(config):
    """Where the watchdog writes: the run's real stderr. pytest's capture has fd 2 pointing
    at a temporary file by now (lost when the watchdog ends the process); its capture
    manager keeps the original, else :data:`WATCHDOG_FILE`."""
    global _watchdog_out, _stacks_where, _record_path
    try:
        capman = config.pluginmanager.getplugin('capturemanager')
        fd = os.dup(capman._global_capturing.err.targetfd_save)
        _watchdog_out = os.fdopen(fd, 'w')
        _stacks_where = "the run's stderr"
    except Exception:  # noqa: BLE001 - no capture (-s) or another pytest: fall back to a file
        _watchdog_out = open(WATCHDOG_FILE, 'a')
        _stacks_where = WATCHDOG_FILE
    workerinput = getattr(config, 'workerinput', None)
    if workerinput is not None:
        _record_path = os.path.join(records_dir(workerinput['testrunuid']), workerinput['workerid'])
    elif config.getoption('testrunuid', None):
        # a run id given on the command line may be an earlier run's: not its records
        shutil.rmtree(records_dir(config.getoption('testrunuid')), ignore_errors=True)


def _record(text: str) -> None:
    """This worker's record says ``text`` (nothing outside pytest-xdist). Written before the
    watchdog is armed: the kernel has it when the watchdog ends the process."""
    if _record_path is None:
        return
    if not _record_fd:
        os.makedirs(os.path.dirname(_record_path), exist_ok=True)
        _record_fd.append(os.open(_record_path, os.O_CREAT | os.O_WRONLY | os.O_TRUNC, 0o644))
    os.ftruncate(_record_fd[0], 0)
    os.pwrite(_record_fd[0], text.encode(), 0)


def _ended_worker(nodeid: str) -> tuple[str, str] | None:
    """The id of an ended worker of this run that was in ``nodeid`` when it ended, and where
    its stacks went; None if none was."""
    if _record_path is None:
        return None
    folder = os.path.dirname(_record_path)
    try:
        names = [n for n in os.listdir(folder) if n.endswith('.ended')]
    except FileNotFoundError:
        return None
    for name in names:
        try:
            with open(os.path.join(folder, name)) as f:
                ended_in, _, where = f.read().partition('\n')
        except OSError:
            continue
        if ended_in == nodeid:
            return name.removesuffix('.ended'), where
    return None


#: a test's protocol is running (the watchdog is armed only then)
_in_test: list[bool] = [False]


def _arm() -> None:
    if _watchdog_out is not None and _in_test[0]:
        faulthandler.dump_traceback_later(TEST_LIMIT_S, exit=True, file=_watchdog_out)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    """The watchdog is armed for the test's setup, call and teardown; under pytest-xdist the
    worker's record names the test meanwhile."""
    _record(f'{item.nodeid}\n{_stacks_where}')
    _in_test[0] = True
    _arm()
    try:
        yield
    finally:
        _in_test[0] = False
        faulthandler.cancel_dump_traceback_later()
        _record('')


@pytest.hookimpl(trylast=True)
def pytest_exception_interact(node, call, report):
    """Armed again after a failure. The process has one faulthandler timer, and pytest's own
    faulthandler plugin cancels it in this hook (for a debugger), so the teardown after a
    failed test ran unwatched: fresh-clone run 1405 hung 20 minutes in a ``ros`` fixture's
    teardown (a publisher's destruction deadlocked inside Fast DDS) after its test failed."""
    _arm()


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_teardown(item, nextitem):
    """Armed again for the teardown, whatever the test body did with the process's one
    faulthandler timer (a test of ``runner.cut_short_after`` uses it too)."""
    _arm()
    yield


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_setup(item):
    """A test that ended its worker fails here, before any of its fixtures is set up: run
    again it would hang again and end the replacement worker too (CI run 815)."""
    ended = _ended_worker(item.nodeid)
    if ended is not None:
        worker, where = ended
        pytest.fail(f'{item.nodeid} ended pytest-xdist worker {worker} in an earlier attempt of this '
                    f'run (the watchdog ends a test after {TEST_LIMIT_S:g} s, or the process crashed): '
                    f'not run again. Its threads\' stacks: {where}', pytrace=False)


@pytest.hookimpl(optionalhook=True)
def pytest_testnodeready(node):
    if not _run_records:
        _run_records.append(records_dir(node.workerinput['testrunuid']))


@pytest.hookimpl(optionalhook=True)
def pytest_testnodedown(node, error):
    """The controller marks a worker that went down in error as ended. xdist calls this
    before it hands the worker's unfinished tests out again, the one it was in included;
    its ``pytest_handlecrashitem`` comes after that (too late to take the test out of the
    scheduler's queue, which is xdist's own)."""
    if error is None:
        return
    path = os.path.join(records_dir(node.workerinput['testrunuid']), node.workerinput['workerid'])
    try:
        os.replace(path, path + '.ended')
    except OSError:
        pass                          # ended before its first test: nothing to mark


def pytest_sessionfinish(session):
    if not hasattr(session.config, 'workerinput'):
        for folder in _run_records:
            shutil.rmtree(folder, ignore_errors=True)
