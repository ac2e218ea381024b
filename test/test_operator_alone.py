"""Operator sequences that need a stack of their own (issue 16): shutting the stack down
mid-goal, and a stack brought up with other safety parameters. The other operator
sequences share one stack per module (``test_operator.py``); these run after it is gone,
in their own module, so that two stacks never run at once on this run's ROS domain.

Same oracles as ``test_operator.py``: the goal's outcome, the simulator's truth, the paper's
IK and the YAML's body (:class:`test_e2e.Device`).
"""
from __future__ import annotations

import numpy as np
import pytest

from test_e2e import device_file  # noqa: F401 (fixture)
from ros_helpers import unclean_exits
from test_operator import SAFE_GOALS, check_one_end_each, operator_stack, recover_and_enable

pytestmark = [pytest.mark.ros, pytest.mark.e2e, pytest.mark.slow]


# ----------------------------------------------------------------------------- 11: shutdown

def test_shutdown_with_a_running_goal_aborts_it_without_a_traceback(device_file, capfd):
    """Stop the process group (SIGINT, as ``brace-bringup --processes`` does) while a goal
    runs: that goal is reported aborted with a shutdown / driver-stopped reason (collected
    until the trajectory node is gone), every node exits 0, no node printed a traceback
    (their stderr is this test's file descriptor 2, captured by ``capfd``)."""
    with operator_stack(device_file) as op:
        start = op.true_lengths()
        target = SAFE_GOALS[2]
        gid = op.goal(target)
        op.wait_travel(start, target, 0.3)
        codes = op.group.stop()
        assert not unclean_exits(codes), unclean_exits(codes)
        end = op.end(gid, timeout=5)
        assert end['state'] == 'aborted', end
        assert 'shutdown' in end['reason'] or 'stopped' in end['reason'], end
        check_one_end_each(op)
    err = capfd.readouterr().err
    print(f'shutdown: goal {end["goal_id"]} {end["state"]}: {end["reason"]}')
    assert f'[trajectory_node]: goal {gid} aborted' in err, 'the nodes\' stderr was not captured'
    assert 'Traceback' not in err, err[max(0, err.index('Traceback') - 2000):][:6000]


# ----------------------------------------------------------------------------- 12: loaded stop, relief

#: N: the hard force limit of this test (soft 16 N, release 4 N): the patient sinking 20 mm
#: loads each leg with ~27 N (Device.static_forces), the YAML's 250 N would need 190 mm
FORCE_LIMIT = 20.0
SINK = 0.020


def test_loaded_protective_stop_is_relieved_then_recovered(device_file):
    """The patient sinks 20 mm while the brace holds: the legs pass ``safety.force_limit``
    and a protective stop latches (driver_state). ``~/recover`` is refused (cause present);
    ``~/relieve`` backs off until the TRUE forces are below ``safety.release_force``;
    ``~/recover`` then succeeds, ``~/enable``; the patient rises back to rest in steps the
    brace follows (each step loads the legs below the soft limit), and a safe goal with
    the body back at rest succeeds."""
    with operator_stack(device_file, ['-p', f'safety.force_limit:={FORCE_LIMIT}']) as op:
        dev = op.dev
        release, soft = 0.2 * FORCE_LIMIT, 0.8 * FORCE_LIMIT
        rest = dev.rest.copy()
        sunk = rest - np.array([0.0, SINK, 0.0])
        dev.rest = sunk
        _, f = dev.static_forces(dev.lengths(dev.home), dev.home)
        assert np.max(np.abs(f)) > 1.2 * FORCE_LIMIT, f'premise: {f} N'
        op.move_body(sunk)
        op.wait_state('protective stop')
        assert 'force' in op.state(), op.state()
        op.wait_rest()
        ok, msg = op.driver('recover')
        assert not ok and 'cause still present' in msg, msg
        ok, relieved = op.driver('relieve')
        assert ok, relieved
        op.wait_rest()
        _, _, _, after_relief = op.truth()[-1]         # judged at the end: the rest still runs
        ok, msg = op.driver('recover')
        assert ok and 'recovered' in msg, msg
        op.wait_state('disabled')
        recover_and_enable(op)
        # the patient rises back to rest; the brace follows
        dev.soft_limit = soft
        here = op.true_pose()
        steps = np.linspace(0.0, 1.0, 4)[1:]
        for s in steps:
            body = sunk + s * (rest - sunk)
            dev.rest = body
            _, f = dev.static_forces(op.true_lengths(), here)
            assert np.max(np.abs(f)) < soft, f'premise: the body at {body} loads the legs {f} N'
            op.move_body(body)
            op.wait_samples(10)
            op.goal_succeeds(np.array([0.0, body[1], body[2]]))
            here = op.true_pose()
        assert np.all(np.abs(op.true_pose() - rest) <= dev.tolerance)
        check_one_end_each(op)
        assert np.all(np.abs(after_relief) < release), \
            f'true forces {after_relief.tolist()} N after the relief, release force {release} N: {relieved}'
