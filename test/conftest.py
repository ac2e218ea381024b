"""Test-wide settings and fixtures: DDS stays on loopback, each run on its own ROS domain.

The environment is set before anything imports rclpy, so every node, and every subprocess a
test starts, inherits it.
"""
import os

import pytest

os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
# Our own domain per test run so two runs on one machine never cross-talk
# (1..200; Fast DDS domain ids stay below 233).
os.environ.setdefault('ROS_DOMAIN_ID', str(1 + os.getpid() % 200))
os.environ.setdefault('MPLBACKEND', 'Agg')
os.environ.setdefault('RCUTILS_LOGGING_BUFFERED_STREAM', '1')


@pytest.fixture
def ros():
    """A fresh :class:`ros_helpers.Ros` (own Context and executor), shut down after the test."""
    # Imported here, not at the top, so rclpy loads only after the environment above is set
    # and only for tests that start nodes.
    from ros_helpers import Ros
    r = Ros()
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
    """
    import rclpy
    from rclpy.context import Context
    keep = Context()
    rclpy.init(context=keep)
    yield keep
