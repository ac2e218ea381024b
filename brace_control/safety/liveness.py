"""The nodes alive and answering: heartbeats (docs/safety.md §2), fresh feedback (§9) and a
measured speed the actuator cannot have (§8). Plain logic on numbers the receive side keeps;
the CAN master evaluates it in its SYNC cycle (:mod:`brace_control.can.monitors`).

Silence is judged on what was received, in bus order, not on when this process got to look:
frames still queued for a receive thread that did not run are not silence, and a drive is
silent when the others went on answering without it. Only when nothing at all has arrived for
longer than the bounds below is the wall clock the judge (the bus, the wiring, or a host too
starved to receive; by then the drives, watching the master's heartbeat, stop themselves).
"""
from __future__ import annotations

from .verdict import OK, Action, Verdict

__all__ = ['heartbeat_age', 'heartbeat', 'stale_feedback', 'overspeed']


def heartbeat_age(heard: float, newest: float, now: float, *, consumer_time: float,
                  all_silent: float) -> float:
    """Seconds since a node's last heartbeat, on the bus's clock.

    :param heard: the bus time (wall clock) of the node's last heartbeat.
    :param newest: the bus time of the newest frame received from any node.
    :param now: the wall clock now.
    :param consumer_time: the master's heartbeat consumer time for the node (s).
    :param all_silent: how long every node may be silent before the wall clock judges (s).

    While the newest frame is at most ``max(consumer_time, all_silent)`` old, the age is the
    span of frames received since the heartbeat (``newest - heard``); beyond that, ``now -
    heard``."""
    if now - newest <= max(consumer_time, all_silent):
        return newest - heard
    return now - heard


def heartbeat(age: float, consumer_time: float, node_id: int) -> Verdict:
    """docs/safety.md §2: a heartbeat older than the consumer time is a protective stop."""
    if age > consumer_time:
        return Verdict(Action.PROTECTIVE_STOP,
                       f'no heartbeat from node {node_id} for {age * 1e3:.0f} ms '
                       f'(consumer time {consumer_time * 1e3:.0f} ms)')
    return OK


def stale_feedback(*, behind: int, others: int, stale_periods: int, syncs_silent: int,
                   all_silent_periods: int, silent_s: float, period: float,
                   timed: bool = True) -> bool:
    """docs/safety.md §9: a drive's feedback (its TPDO1) is stale.

    :param behind: TPDO1s the other drives sent since this drive's last one.
    :param others: how many other drives there are.
    :param stale_periods: SYNCs a drive may miss (``safety.stale_periods``).
    :param syncs_silent: SYNCs sent since the one its last TPDO1 answered.
    :param all_silent_periods: SYNCs every drive may be silent before the clock judges.
    :param silent_s: seconds since its last TPDO1 was received.
    :param period: the SYNC period (s).
    :param timed: judge by the clock as well (not right after a stall of this process).

    Stale when the others answered ``stale_periods`` SYNCs each without it, or (``timed``)
    when ``all_silent_periods`` SYNCs and as many periods have passed without it."""
    if others and behind >= stale_periods * others:
        return True
    return timed and syncs_silent >= all_silent_periods and silent_s > all_silent_periods * period


def overspeed(velocity: float, v_max: float, factor: float, unit: str = 'm') -> Verdict:
    """docs/safety.md §8: a measured speed above ``factor`` x the actuator's maximum is a
    protective stop (a runaway, or an encoder that jumps)."""
    if abs(velocity) > factor * v_max:
        if unit == 'm':
            text = f'{velocity * 1e3:.1f} mm/s exceeds {factor:g} x {v_max * 1e3:.1f} mm/s'
        else:
            text = f'{velocity:.3f} rad/s exceeds {factor:g} x {v_max:.3f} rad/s'
        return Verdict(Action.PROTECTIVE_STOP, f'measured speed {text}')
    return OK
