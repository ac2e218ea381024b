"""Replay rosbag2 bags into the ROS graph and record topics to mcap, with ``rosbags``.

::

    brace-bag replay BAG [--rate R] [--topics T ...] [--wait-subscribers N] [--delay S]
    brace-bag record OUT.mcap --topics T ... [--duration S]
    brace-bag info BAG

*Replay* reads a rosbag2 bag (a bag directory with ``metadata.yaml``, or a bare ``.mcap``
or ``.db3`` file; sqlite3 or mcap storage; any metadata version ``rosbags`` reads, i.e.
Dashing to current) and publishes every message's recorded CDR bytes unchanged
(``Publisher.publish(bytes)``, rclpy's serialized publish), keeping the recorded spacing
of the messages divided by ``--rate``.

*Record* subscribes the topics with ``raw=True`` (the CDR bytes as they arrive) and writes
them to an mcap bag with the message definitions (``rosbags`` typestore), so Foxglove,
PlotJuggler, ``ros2 bag`` and ``rosbags`` open it. ``OUT.mcap`` is a single mcap file;
an output path without the ``.mcap`` suffix becomes a rosbag2 bag directory.

Errors (:class:`BagError`, exit code 1 on the command line): a missing bag, an unknown
storage format, a message type this Python cannot import (the graph lacks it), a topic
that never appears while recording.
"""
from __future__ import annotations

import argparse
import importlib
import shutil
import signal
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

__all__ = [
    'BagError', 'open_bag', 'bag_info', 'message_class', 'ReplayStats', 'replay',
    'Recorder', 'main',
]


class BagError(RuntimeError):
    """A bag that cannot be read, replayed or written; the message says what to do."""


# --------------------------------------------------------------------------- reading

def open_bag(path: str | Path):
    """Open a rosbag2 bag for reading (a ``rosbags.rosbag2.Reader``, already open).

    :raises BagError: the path does not exist, or is neither a bag directory nor a
        ``.mcap`` / ``.db3`` file, or ``rosbags`` cannot read its metadata.
    """
    from rosbags.rosbag2 import Reader
    p = Path(path)
    if not p.exists():
        raise BagError(f'bag {str(p)!r} does not exist')
    if p.is_dir() and not (p / 'metadata.yaml').is_file():
        raise BagError(f'{str(p)!r} is a directory without metadata.yaml: not a rosbag2 bag')
    if p.is_file() and p.suffix not in ('.mcap', '.db3'):
        raise BagError(f'unknown storage format {p.suffix or "(no suffix)"!r} of {str(p)!r}: '
                       'expected a rosbag2 bag directory, a .mcap or a .db3 file '
                       '(ROS 1 .bag files: convert them with `rosbags-convert`)')
    try:
        reader = Reader(p)
        reader.open()
    except Exception as exc:  # noqa: BLE001 - rosbags raises several error types
        raise BagError(f'cannot read bag {str(p)!r}: {exc}') from exc
    return reader


def message_class(msgtype: str, *, topic: str = '') -> type:
    """The Python class of a ROS message type name (``geometry_msgs/msg/PoseStamped``).

    :raises BagError: the type's package is not importable here.
    """
    parts = msgtype.replace('/msg/', '/').split('/')
    if len(parts) != 2:
        raise BagError(f'message type {msgtype!r}{_on(topic)} is not a ROS 2 message type name')
    pkg, name = parts
    try:
        return getattr(importlib.import_module(f'{pkg}.msg'), name)
    except (ImportError, AttributeError) as exc:
        raise BagError(
            f'message type {msgtype!r}{_on(topic)} is not available in this Python '
            f'({exc}); install its package (ros-{pkg.replace("_", "-")} from pip, or '
            f'ros-<distro>-{pkg.replace("_", "-")}) or leave the topic out with --topics') from exc


def _on(topic: str) -> str:
    return f' of topic {topic}' if topic else ''


def bag_info(path: str | Path) -> dict[str, Any]:
    """Topics, types, counts and duration of a bag (``brace-bag info``)."""
    with _closing(open_bag(path)) as reader:
        return {
            'path': str(path),
            'duration_s': reader.duration * 1e-9,
            'messages': reader.message_count,
            'topics': {c.topic: {'type': c.msgtype, 'count': c.msgcount}
                       for c in reader.connections},
        }


class _closing:
    def __init__(self, reader) -> None:
        self.reader = reader

    def __enter__(self):
        return self.reader

    def __exit__(self, *exc) -> None:
        self.reader.close()


# --------------------------------------------------------------------------- replay

def _replay_qos():
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    # Reliable with a deep queue: a replayed goal or setpoint stream must arrive whole.
    return QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)


@dataclass
class ReplayStats:
    """What a replay published."""

    published: dict[str, int] = field(default_factory=dict)
    duration_s: float = 0.0
    late_max_s: float = 0.0          # worst lateness of a publish against its schedule

    @property
    def total(self) -> int:
        return sum(self.published.values())


def replay(node: Any, path: str | Path, *, rate: float = 1.0,
           topics: Sequence[str] | None = None, wait_subscribers: int = 0,
           wait_topics: Sequence[str] | None = None,
           wait_timeout: float = 10.0, delay: float = 0.0,
           stop: threading.Event | None = None,
           progress: Callable[[float, float], None] | None = None) -> ReplayStats:
    """Publish the messages of bag ``path`` on ``node``'s publishers with their timing.

    Runs in the calling thread (the node need not be spun for publishing; spin it
    elsewhere if it has callbacks). The recorded CDR bytes are published unchanged.

    :param rate: playback speed factor (2.0 = twice as fast).
    :param topics: only these topics (default: all).
    :param wait_subscribers: before the first message, wait until every publisher has
        at least this many matched subscriptions (discovery), up to ``wait_timeout`` s.
    :param wait_topics: the topics that wait applies to (default: every replayed topic).
    :param delay: seconds to wait after the publishers are created (and matched).
    :param stop: set it to end the replay early.
    :param progress: called as ``progress(bag_time_s, bag_duration_s)`` about 10 x / s.
    :raises BagError: see :func:`open_bag`, :func:`message_class`; a requested topic
        that is not in the bag; a rate that is not positive.
    """
    if not rate > 0:
        raise BagError(f'--rate must be positive, got {rate}')
    reader = open_bag(path)
    try:
        connections = list(reader.connections)
        if topics:
            missing = sorted(set(topics) - {c.topic for c in connections})
            if missing:
                raise BagError(f'topic(s) {missing} not in bag {str(path)!r} '
                               f'(it has {sorted({c.topic for c in connections})})')
            connections = [c for c in connections if c.topic in set(topics)]
        publishers: dict[str, Any] = {}
        by_conn: dict[int, Any] = {}
        for conn in connections:
            if conn.topic not in publishers:
                cls = message_class(conn.msgtype, topic=conn.topic)
                publishers[conn.topic] = node.create_publisher(cls, conn.topic, _replay_qos())
            by_conn[conn.id] = publishers[conn.topic]
        stats = ReplayStats(published={t: 0 for t in publishers})
        if not connections:
            return stats
        if wait_subscribers > 0:
            deadline = time.monotonic() + wait_timeout
            waited = {t: p for t, p in publishers.items() if wait_topics is None or t in wait_topics}
            while any(p.get_subscription_count() < wait_subscribers for p in waited.values()):
                if time.monotonic() > deadline or (stop is not None and stop.is_set()):
                    lacking = [t for t, p in waited.items()
                               if p.get_subscription_count() < wait_subscribers]
                    raise BagError(f'no subscriber on {lacking} after {wait_timeout} s')
                time.sleep(0.005)
        if delay > 0:
            time.sleep(delay)
        start_ns = reader.start_time
        duration_s = max(reader.end_time - start_ns, 0) * 1e-9
        wall0 = time.monotonic()
        next_progress = 0.0
        for conn, t_ns, data in reader.messages(connections=connections):
            bag_t = (t_ns - start_ns) * 1e-9
            due = wall0 + bag_t / rate
            while True:
                if stop is not None and stop.is_set():
                    stats.duration_s = time.monotonic() - wall0
                    return stats
                wait = due - time.monotonic()
                if wait <= 0:
                    break
                time.sleep(min(wait, 0.05))
            stats.late_max_s = max(stats.late_max_s, time.monotonic() - due)
            by_conn[conn.id].publish(bytes(data))
            stats.published[conn.topic] += 1
            if progress is not None and time.monotonic() >= next_progress:
                next_progress = time.monotonic() + 0.1
                progress(bag_t, duration_s)
        if progress is not None:
            progress(duration_s, duration_s)
        # reliable delivery: the last messages may still be in flight to a matched reader
        # when the caller shuts down; wait (bounded) until every reader acknowledged them
        from rclpy.duration import Duration
        for pub in publishers.values():
            pub.wait_for_all_acked(Duration(seconds=2.0))
        stats.duration_s = time.monotonic() - wall0
        return stats
    finally:
        reader.close()


# --------------------------------------------------------------------------- record

def _typestore():
    from rosbags.typesys import Stores, get_typestore
    return get_typestore(Stores.ROS2_KILTED if hasattr(Stores, 'ROS2_KILTED') else Stores.LATEST)


def _ensure_type(store, msgtype: str) -> None:
    """Make ``msgtype`` known to the typestore, from the installed ``.msg`` file if needed."""
    if msgtype in store.fielddefs:
        return
    from rosbags.typesys import get_types_from_msg
    pkg, _, name = msgtype.split('/')
    try:
        from ament_index_python.packages import get_package_share_directory
        text = (Path(get_package_share_directory(pkg)) / 'msg' / f'{name}.msg').read_text()
        store.register(get_types_from_msg(text, msgtype))
    except Exception as exc:  # noqa: BLE001
        raise BagError(f'no message definition for {msgtype!r} (not in the rosbags typestore '
                       f'and no installed {pkg}/msg/{name}.msg): {exc}') from exc


class Recorder:
    """Record topics of the graph to an mcap bag (composed around a node).

    Topics are subscribed as soon as discovery shows their type (call :meth:`poll`
    from a timer or let :meth:`start` create one); messages are written with the time
    they were received (node clock, ns) as ``ros2 bag record`` does.

    :param node: the node whose executor delivers the messages.
    :param out: ``OUT.mcap`` (one mcap file) or a directory name (a rosbag2 bag).
    :param topics: topic names to record.
    :param types: ``{topic: 'pkg/msg/Type'}`` for topics whose type is known up front.
    """

    def __init__(self, node: Any, out: str | Path, topics: Iterable[str], *,
                 types: dict[str, str] | None = None, qos: Any = None) -> None:
        from rosbags.rosbag2 import StoragePlugin, Writer
        self.node = node
        self.out = Path(out)
        self.topics = list(dict.fromkeys(topics))
        if not self.topics:
            raise BagError('record: no topics given (--topics /a /b ...)')
        if self.out.exists():
            raise BagError(f'{str(self.out)!r} exists already; not overwriting')
        self._single_file = self.out.suffix == '.mcap'
        if self._single_file:
            self._tmp = Path(tempfile.mkdtemp(prefix='.brace-bag-', dir=self.out.parent or '.'))
            bag_dir = self._tmp / self.out.stem
        else:
            self._tmp = None
            bag_dir = self.out
        self._writer = Writer(bag_dir, version=9, storage_plugin=StoragePlugin.MCAP)
        self._writer.open()
        self._bag_dir = bag_dir
        self._store = _typestore()
        self._qos = qos
        self._lock = threading.Lock()
        self._conns: dict[str, Any] = {}
        self._subs: dict[str, Any] = {}
        self.counts: dict[str, int] = {t: 0 for t in self.topics}
        self._closed = False
        self._timer = None
        for topic, msgtype in (types or {}).items():
            if topic in self.counts:
                self._subscribe(topic, msgtype)

    def start(self, period: float = 0.1, callback_group: Any = None) -> 'Recorder':
        """Poll discovery every ``period`` s until every topic is subscribed."""
        self.poll()
        if self.pending:
            self._timer = self.node.create_timer(period, self.poll, callback_group=callback_group)
        return self

    @property
    def pending(self) -> list[str]:
        """Topics not subscribed yet (not seen in the graph)."""
        return [t for t in self.topics if t not in self._subs]

    def poll(self) -> None:
        if self._closed:
            return
        graph = dict(self.node.get_topic_names_and_types())
        for topic in self.pending:
            types = graph.get(topic)
            if types:
                self._subscribe(topic, types[0])
        if not self.pending and self._timer is not None:
            self._timer.cancel()

    def _subscribe(self, topic: str, msgtype: str) -> None:
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        cls = message_class(msgtype, topic=topic)
        _ensure_type(self._store, msgtype)
        with self._lock:
            self._conns[topic] = self._writer.add_connection(topic, msgtype, typestore=self._store)
        qos = self._qos or QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        self._subs[topic] = self.node.create_subscription(
            cls, topic, lambda data, t=topic: self._write(t, data), qos, raw=True)

    def _write(self, topic: str, data: bytes) -> None:
        now = self.node.get_clock().now().nanoseconds
        with self._lock:
            if self._closed:
                return
            self._writer.write(self._conns[topic], now, data)
            self.counts[topic] += 1

    def close(self) -> Path:
        """Stop recording, finish the file (mcap summary/index); returns the output path."""
        with self._lock:
            if self._closed:
                return self.out
            self._closed = True
        if self._timer is not None:
            self._timer.cancel()
        for sub in self._subs.values():
            self.node.destroy_subscription(sub)
        self._writer.close()
        if self._single_file:
            files = sorted(self._bag_dir.glob('*.mcap'))
            shutil.move(str(files[0]), str(self.out))
            shutil.rmtree(self._tmp, ignore_errors=True)
        return self.out


# ------------------------------------------------------------------------------ CLI

def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog='brace-bag', description=__doc__.split('\n\n')[0])
    sub = ap.add_subparsers(dest='command', required=True)
    rp = sub.add_parser('replay', help='publish a bag into the graph with its timing')
    rp.add_argument('bag', help='bag directory, .mcap or .db3 file')
    rp.add_argument('--rate', type=float, default=1.0, help='speed factor (default 1.0)')
    rp.add_argument('--topics', nargs='+', default=None, help='only these topics')
    rp.add_argument('--wait-subscribers', type=int, default=0, metavar='N',
                    help='wait until each topic has N subscribers before starting')
    rp.add_argument('--delay', type=float, default=0.5,
                    help='seconds between creating the publishers and the first message '
                         '(discovery; default 0.5)')
    rc = sub.add_parser('record', help='record topics to an mcap bag')
    rc.add_argument('out', help='OUT.mcap (single file) or a bag directory name')
    rc.add_argument('--topics', nargs='+', required=True)
    rc.add_argument('--duration', type=float, default=None, help='stop after this many seconds')
    info = sub.add_parser('info', help='topics, types and counts of a bag')
    info.add_argument('bag')
    return ap


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    ros_args: list[str] = []
    if '--ros-args' in argv:
        i = argv.index('--ros-args')
        argv, ros_args = argv[:i], argv[i:]
    args = _parser().parse_args(argv)
    try:
        if args.command == 'info':
            info = bag_info(args.bag)
            print(f'{info["path"]}: {info["messages"]} messages, {info["duration_s"]:.3f} s')
            for topic, t in info['topics'].items():
                print(f'  {topic}  {t["type"]}  {t["count"]}')
            return 0
        if args.command == 'replay':
            open_bag(args.bag).close()          # fail before starting ROS
        return _run_ros(args, ros_args)
    except BagError as exc:
        print(f'brace-bag: error: {exc}', file=sys.stderr)
        return 1


def _run_ros(args: argparse.Namespace, ros_args: list[str]) -> int:
    import rclpy
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor

    rclpy.init(args=['brace-bag', *ros_args])
    node = rclpy.create_node('brace_bag')
    stop = threading.Event()

    def _stop(*_: Any) -> None:
        stop.set()

    signal.signal(signal.SIGTERM, _stop)
    signal.signal(signal.SIGINT, _stop)
    try:
        if args.command == 'replay':
            stats = replay(node, args.bag, rate=args.rate, topics=args.topics,
                           wait_subscribers=args.wait_subscribers, delay=args.delay, stop=stop,
                           progress=lambda t, d: print(f'\r{t:8.2f} / {d:.2f} s', end='',
                                                       file=sys.stderr, flush=True))
            print(f'\npublished {stats.total} messages in {stats.duration_s:.2f} s: '
                  + ', '.join(f'{t} {n}' for t, n in stats.published.items()), file=sys.stderr)
            return 0
        recorder = Recorder(node, args.out, args.topics).start()
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        t_end = None if args.duration is None else time.monotonic() + args.duration
        try:
            while not stop.is_set() and (t_end is None or time.monotonic() < t_end):
                executor.spin_once(timeout_sec=0.05)
        except ExternalShutdownException:
            pass
        out = recorder.close()
        if recorder.pending:
            print(f'brace-bag: warning: never saw {recorder.pending}', file=sys.stderr)
        print(f'recorded {sum(recorder.counts.values())} messages to {out}: '
              + ', '.join(f'{t} {n}' for t, n in recorder.counts.items()), file=sys.stderr)
        executor.shutdown()
        return 0
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    raise SystemExit(main())
