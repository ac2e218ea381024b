"""Test-wide settings: DDS stays on loopback, each run on its own ROS domain.

Set before anything imports rclpy, so every node, and every subprocess a test starts,
inherits them.
"""
import os

os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
# Our own domain per test run so two runs on one machine never cross-talk
# (1..200; Fast DDS domain ids stay below 233).
os.environ.setdefault('ROS_DOMAIN_ID', str(1 + os.getpid() % 200))
os.environ.setdefault('MPLBACKEND', 'Agg')
os.environ.setdefault('RCUTILS_LOGGING_BUFFERED_STREAM', '1')
