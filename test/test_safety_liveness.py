"""docs/safety.md §2 (heartbeats), §9 (fresh feedback) and §8's impossible speed, as plain
logic (brace_control.safety.liveness). The oracles are the rules of the document, worked by
hand on numbers; the bus-level behaviour of the same rules is in test_can_master.py
(heartbeat loss, stale TPDO, overspeed) and test_sim_drive.py (the drives' side)."""
from __future__ import annotations

import pytest

from brace_control.safety import Action
from brace_control.safety.liveness import heartbeat, heartbeat_age, overspeed, stale_feedback

CONSUMER = 0.15          # s, can.heartbeat_consumer_ms of the lumbar brace
ALL_SILENT = 0.2         # s, 2 x master_heartbeat_ms


def test_the_age_of_a_heartbeat_is_the_span_of_frames_received_since_while_frames_arrive():
    """Frames go on arriving (the newest 10 ms old): the node's heartbeat is as old as the
    frames received after it, however late this process looks (here 0.5 s after it)."""
    heard, newest, now = 100.00, 100.12, 100.13
    assert heartbeat_age(heard, newest, now, consumer_time=CONSUMER, all_silent=ALL_SILENT) == pytest.approx(0.12)
    # a receive thread 0.19 s behind (its queue not yet read) is not a lost heartbeat
    assert heartbeat_age(heard, 100.05, 100.24, consumer_time=CONSUMER, all_silent=ALL_SILENT) == pytest.approx(0.05)


def test_when_nothing_has_arrived_for_longer_than_both_bounds_the_wall_clock_judges():
    heard, newest = 100.00, 100.05
    now = newest + ALL_SILENT + 0.001                      # past max(0.15, 0.2)
    assert heartbeat_age(heard, newest, now, consumer_time=CONSUMER, all_silent=ALL_SILENT) == pytest.approx(now - heard)
    now = newest + ALL_SILENT - 0.001                      # within it: still the frames' span
    assert heartbeat_age(heard, newest, now, consumer_time=CONSUMER, all_silent=ALL_SILENT) == pytest.approx(0.05)


def test_a_heartbeat_older_than_the_consumer_time_is_a_protective_stop_naming_node_and_times():
    assert heartbeat(0.149, CONSUMER, 2).ok
    verdict = heartbeat(0.151, CONSUMER, 2)
    assert verdict.action is Action.PROTECTIVE_STOP
    assert verdict.reason == 'no heartbeat from node 2 for 151 ms (consumer time 150 ms)'


@pytest.mark.parametrize('behind, others, expected', [
    (8, 2, False),       # the other two sent 4 each: fewer than stale_periods = 5 each
    (10, 2, True),       # 5 each without this drive: stale
    (9, 2, False),
    (5, 1, True),        # two drives: the other one answered 5 SYNCs alone
])
def test_a_drive_is_stale_when_the_others_answered_stale_periods_syncs_each_without_it(behind, others, expected):
    assert stale_feedback(behind=behind, others=others, stale_periods=5, syncs_silent=0,
                          all_silent_periods=100, silent_s=0.0, period=0.002) is expected


def test_every_drive_silent_is_stale_only_after_the_all_silent_bound_by_count_and_by_time():
    args = dict(behind=0, others=2, stale_periods=5, all_silent_periods=100, period=0.002)
    assert not stale_feedback(syncs_silent=99, silent_s=1.0, **args)            # count not reached
    assert not stale_feedback(syncs_silent=100, silent_s=0.199, **args)         # time not reached
    assert stale_feedback(syncs_silent=100, silent_s=0.201, **args)
    # right after a stall of this process the clock does not judge; the others' answers still do
    assert not stale_feedback(syncs_silent=500, silent_s=5.0, timed=False, **args)
    assert stale_feedback(syncs_silent=0, silent_s=0.0, timed=False, **{**args, 'behind': 10})


def test_a_speed_above_the_factor_times_the_maximum_is_a_protective_stop_in_the_axis_unit():
    assert overspeed(0.0974, 0.065, 1.5).ok                      # 97.4 mm/s < 97.5 mm/s
    v = overspeed(-0.0976, 0.065, 1.5)
    assert v.action is Action.PROTECTIVE_STOP
    assert v.reason == 'measured speed -97.6 mm/s exceeds 1.5 x 65.0 mm/s'
    r = overspeed(3.1, 2.0, 1.5, unit='rad')
    assert r.reason == 'measured speed 3.100 rad/s exceeds 1.5 x 2.000 rad/s'
