"""Two test runs on one machine never share a ROS domain (test/conftest.py).

A run reserves a block of domains with lock files before any DDS starts; another run that
asks for the same domains gets a block of its own. Side by side without it, one run's
kinetics node took the other run's joint states (2026-11-28: estimates 30 and 52 mm off).
"""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import conftest

HERE = Path(__file__).resolve().parent


def _other_run_base(env_domain: str) -> int:
    """The block a second run's first process reserves, asking for ``env_domain``."""
    env = {k: v for k, v in os.environ.items()
           if k not in ('BRACE_TEST_DOMAIN_BASE', 'PYTEST_XDIST_WORKER')}
    env['ROS_DOMAIN_ID'] = env_domain
    code = (f'import sys; sys.path.insert(0, {str(HERE)!r}); import os, conftest; '
            'print(os.environ["BRACE_TEST_DOMAIN_BASE"], os.environ["ROS_DOMAIN_ID"])')
    out = subprocess.run([sys.executable, '-c', code], env=env, capture_output=True, text=True,
                         timeout=60, check=False)
    assert out.returncode == 0, out.stderr[-2000:]
    base, domain = map(int, out.stdout.split())
    assert domain == base
    return base


def test_a_second_run_asking_for_this_runs_domain_gets_a_block_of_its_own():
    ours = int(os.environ['BRACE_TEST_DOMAIN_BASE'])
    mine = set(range(ours, ours + conftest.DOMAIN_BLOCK))
    assert int(os.environ['ROS_DOMAIN_ID']) in mine
    for asked in (ours, ours + conftest.DOMAIN_BLOCK - 1):
        theirs = _other_run_base(str(asked))
        block = set(range(theirs, theirs + conftest.DOMAIN_BLOCK))
        assert not block & mine, (sorted(mine), sorted(block))
        assert max(block) <= 232                    # Fast DDS's domain ids


def test_a_free_domain_asked_for_is_the_one_given():
    ours = int(os.environ['BRACE_TEST_DOMAIN_BASE'])
    # a block well away from ours (and, most likely, from any other run's)
    asked = (ours + 3 * conftest.DOMAIN_BLOCK) % (233 - conftest.DOMAIN_BLOCK)
    theirs = _other_run_base(str(asked))
    assert theirs >= asked            # the first free block from the one asked for


def test_stale_fast_dds_ports_and_port_mutexes_are_removed_live_ones_kept(tmp_path):
    """conftest's cleanup of /dev/shm (here a directory of its own): a half-made port (no
    lock file) and the creation mutex of a port that is gone, both 10 s old, are removed;
    a live port, its lock file and its mutex, and anything younger than 10 s, are kept."""
    import time

    from conftest import _remove_half_made_ports
    old = time.time() - 60
    names = ['fastdds_port7001',                                    # half-made, old: removed
             'fastdds_port7002', 'fastdds_port7002_el', 'sem.fastdds_port7002_mutex',  # live
             'sem.fastdds_port7003_mutex',                          # its port gone, old: removed
             'fastdds_port7004', 'sem.fastdds_port7005_mutex']      # young: kept
    for name in names:
        (tmp_path / name).write_bytes(b'')
        if not name.endswith(('7004', '7005_mutex')):
            os.utime(tmp_path / name, (old, old))
    removed = _remove_half_made_ports(str(tmp_path))
    assert sorted(removed) == ['fastdds_port7001', 'sem.fastdds_port7003_mutex']
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(set(names) - set(removed))
