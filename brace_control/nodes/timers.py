"""Timer callbacks whose signature rclpy does not have to work out on every call.

rclpy's executors (the ``EventsExecutor`` too) call ``inspect.signature(timer.callback)``
each time a timer fires, to see whether the callback takes a ``TimerInfo`` argument
(rclpy/executors.py, ``_take_timer``: "the user might change the callback at runtime").
For a bound method that is ~10 us of Python per call (~40 us with cold caches, as a
callback that runs every 10 ms has): a fifth of what the driver's 100 Hz joint-state
callback itself costs. :func:`timer_callback` wraps the callback in a plain function that
carries its signature (no parameters) in ``__signature__``, which ``inspect.signature``
returns as it is. The executor then calls it without arguments, exactly as it calls a
method that takes none.
"""
from __future__ import annotations

import inspect
from collections.abc import Callable

__all__ = ['timer_callback']

_NO_PARAMETERS = inspect.Signature()


def timer_callback(fn: Callable[[], object]) -> Callable[[], object]:
    """``fn`` (taking no argument) as a timer callback with a precomputed signature.

    :raises TypeError: ``fn`` takes arguments (a ``TimerInfo`` callback must stay as it is).
    """
    if inspect.signature(fn).parameters:
        raise TypeError(f'timer_callback: {fn!r} takes arguments {inspect.signature(fn)}; '
                        'expected a callback without parameters')

    def callback() -> object:
        return fn()

    callback.__signature__ = _NO_PARAMETERS     # type: ignore[attr-defined]
    callback.__name__ = getattr(fn, '__name__', 'callback')
    callback.__qualname__ = getattr(fn, '__qualname__', 'callback')
    callback.__doc__ = getattr(fn, '__doc__', None)
    return callback
