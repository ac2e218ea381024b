"""A test stuck in native code ends its pytest-xdist worker once, and the run ends
(watchdog_plugin).

pytest-xdist's ``--dist loadfile`` hands a crashed worker's unfinished file out again, the
crashed test included: each replacement worker hung in the same test until CI's 25-min
budget ended the run (CI run 815, issue 26). Each check here runs a small suite of its own
in a pytest of its own, with the watchdog plugin alone (not the suite's conftest) and a
3 s limit.
"""
from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

HERE = Path(__file__).resolve().parent

#: s: the inner runs' watchdog limit
LIMIT_S = 3
#: s: the most an inner run may take: a run that hangs is killed then
RUN_TIMEOUT_S = 60

#: the file whose second test hangs in native code holding the GIL, as a Fast DDS deadlock
#: does (eProsima/Fast-DDS#6502); every attempt at its body leaves a line in ATTEMPTS
HANGING_FILE = '''
import ctypes
import os


def test_before():
    pass


def test_hangs():
    with open(os.environ['ATTEMPTS'], 'a') as f:
        f.write('attempt\\n')
    ctypes.PyDLL(None).sleep(600)


def test_after():
    pass
'''
QUICK_FILE = '''
import pytest


@pytest.mark.parametrize('n', range(4))
def test_quick(n):
    pass
'''


#: a test that fails, then hangs in its fixture's teardown (a Fast DDS deadlock destroying an
#: endpoint, fresh-clone run 1405): pytest's faulthandler plugin cancels the process's one
#: faulthandler timer on the failure
FAILS_THEN_HANGS_FILE = '''
import ctypes
import os

import pytest


@pytest.fixture
def endpoint():
    yield
    with open(os.environ['ATTEMPTS'], 'a') as f:
        f.write('attempt\\n')
    ctypes.PyDLL(None).sleep(600)


def test_hangs(endpoint):
    assert False, 'the body fails'
'''


def _run_suite(tmp_path: Path, *args: str, hanging: str = HANGING_FILE) -> tuple[int | None, str]:
    """The small suite run in ``tmp_path`` with ``args`` (``hanging``: test_hang.py's text):
    the exit code (None if it hung and was killed) and what it printed."""
    (tmp_path / 'pytest.ini').write_text('[pytest]\n')          # not the project's setup.cfg
    (tmp_path / 'test_hang.py').write_text(hanging)
    (tmp_path / 'test_quick.py').write_text(QUICK_FILE)
    env = {k: v for k, v in os.environ.items()
           if not k.startswith('PYTEST_XDIST_') and k not in ('PYTEST_CURRENT_TEST', 'PYTEST_ADDOPTS')}
    env.update(BRACE_TEST_LIMIT_S=str(LIMIT_S), ATTEMPTS=str(tmp_path / 'attempts.txt'),
               PYTHONPATH=os.pathsep.join(filter(None, [str(HERE), env.get('PYTHONPATH')])))
    cmd = [sys.executable, '-m', 'pytest', '-q', '-rA', '-p', 'no:cacheprovider', '-p', 'watchdog_plugin',
           '--rootdir', str(tmp_path), '--confcutdir', str(tmp_path), *args, 'test_hang.py', 'test_quick.py']
    proc = subprocess.Popen(cmd, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, start_new_session=True)       # its workers: its group
    try:
        out, _ = proc.communicate(timeout=RUN_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, _ = proc.communicate()
        return None, out
    return proc.returncode, out


def _attempts(tmp_path: Path) -> int:
    path = tmp_path / 'attempts.txt'
    return len(path.read_text().splitlines()) if path.exists() else 0


def _outcomes(out: str) -> dict[str, set[str]]:
    """Per test, the outcomes in the run's short summary (``-rA``) and xdist's crash lines."""
    found: dict[str, set[str]] = {}
    for outcome, nodeid in re.findall(r'^(PASSED|FAILED|ERROR) (\S+)', out, re.MULTILINE):
        found.setdefault(nodeid, set()).add(outcome)
    for nodeid in re.findall(r"crashed while running '([^']+)'", out):
        found.setdefault(nodeid, set()).add('CRASHED')
    return found


def test_a_test_that_ends_its_xdist_worker_is_not_run_again_and_the_run_ends(tmp_path):
    code, out = _run_suite(tmp_path, '-n', '2', '--dist', 'loadfile', '--no-loadscope-reorder')
    assert code is not None, f'the run hung: killed after {RUN_TIMEOUT_S} s\n{out[-4000:]}'
    assert code == 1, out[-4000:]
    assert _attempts(tmp_path) == 1, out[-4000:]          # the body ran once, never again
    outcomes = _outcomes(out)
    assert 'CRASHED' in outcomes.get('test_hang.py::test_hangs', ()), out[-4000:]
    assert 'PASSED' not in outcomes['test_hang.py::test_hangs'], out[-4000:]
    # the rest of the crashed worker's file still ran, and the other file
    passing = ['test_hang.py::test_before', 'test_hang.py::test_after',
               *(f'test_quick.py::test_quick[{n}]' for n in range(4))]
    assert all(outcomes.get(t) == {'PASSED'} for t in passing), (outcomes, out[-4000:])
    assert 'not run again' in out and 'test_hangs' in out.split('not run again')[0][-600:], out[-4000:]
    assert re.search(r'Timeout \(0:00:03\)!', out), out[-4000:]      # the stacks, on stderr
    assert re.search(r'line \d+ in test_hangs', out), out[-4000:]


def test_without_xdist_the_watchdog_ends_the_run_after_its_limit(tmp_path):
    code, out = _run_suite(tmp_path, '-p', 'no:xdist')
    assert code == 1, out[-4000:]                 # faulthandler's exit
    assert _attempts(tmp_path) == 1, out[-4000:]
    assert re.search(r'Timeout \(0:00:03\)!', out), out[-4000:]
    assert re.search(r'line \d+ in test_hangs', out), out[-4000:]


def test_a_teardown_that_hangs_after_its_test_failed_is_ended_too(tmp_path):
    """pytest's faulthandler plugin cancels the process's one faulthandler timer when a test
    fails (pytest_exception_interact): the watchdog is armed again, so a teardown stuck in
    native code after a failure ends its process as well (run 1405 hung 20 min there)."""
    code, out = _run_suite(tmp_path, '-p', 'no:xdist', hanging=FAILS_THEN_HANGS_FILE)
    assert code is not None, f'the run hung: killed after {RUN_TIMEOUT_S} s\n{out[-4000:]}'
    assert code == 1, out[-4000:]
    assert _attempts(tmp_path) == 1, out[-4000:]
    assert re.search(r'Timeout \(0:00:03\)!', out), out[-4000:]
    assert re.search(r'line \d+ in endpoint', out), out[-4000:]
