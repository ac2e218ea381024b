"""Replay rosbag2 bags into the ROS graph and record topics to mcap, with ``rosbags``.

::

    brace-bag replay BAG [--rate R] [--topics T ...] [--wait-for-subscribers N]
                         [--wait-timeout S] [--wait-topics T ...] [--ack-timeout S]
                         [--qos-profile-overrides-path FILE] [--delay S]
    brace-bag record OUT.mcap --topics T ... [--duration S]
    brace-bag info BAG

*Replay* reads every rosbag2 layout: a bag directory (``metadata.yaml`` versions 4-9;
older ones are read the same way, untested) with one or several storage files (sqlite3 or
mcap, zstd file or message compression), or a bare ``.mcap`` / ``.db3`` file. It publishes every message's recorded CDR bytes unchanged
(``Publisher.publish(bytes)``, rclpy's serialized publish), keeping the recorded spacing of
the messages divided by ``--rate``. The storage files are read directly and their
connections matched to ``metadata.yaml`` by topic name and type, so a bag whose metadata
and storage spell the same QoS differently (``ros2 bag record`` wrote ``deadline sec: 0``
in one and ``sec: 2147483647`` in the other) replays every message. A storage connection
that ``metadata.yaml`` does not list is an error, never a silent omission. Message types
are ``pkg/msg/Name`` (``pkg/Name`` in old bags), service events ``pkg/srv/Name_Event`` and
action parts ``pkg/action/Name_Part``; a topic whose type this Python lacks and that holds
no message (``/events/write_split`` of ``ros2 bag record -a``) is skipped with a warning,
as rosbag2 does. A .db3 with a non-empty ``-wal`` beside it (a recording that did not close,
rosbag2's "resilient" preset) is refused, saying how to merge it: a read-only open would miss
its last messages. A storage file that cannot be read to its end stops the replay with the
count published so far as a problem.

Each topic is published with the QoS its publishers offered when it was recorded
(:func:`recorded_qos`; ``--qos-profile-overrides-path`` overrides it per topic). A reliable
topic never holds more unacknowledged messages than its history keeps: after ``depth``
messages the replay waits until the matched readers acknowledged them
(``Publisher.wait_for_all_acked``), so a burst is delayed rather than overwritten. At the
end it waits (``--ack-timeout``) until every reliable message was acknowledged.

The replay counts what it published against the bag's counts; any difference (messages
not published or not acknowledged, a topic filter that selects nothing, storage that holds
other counts than ``metadata.yaml`` lists) is a *problem*: :func:`replay` returns it in
:attr:`ReplayStats.problems`, the command prints it and exits 1.

*Record* subscribes the topics with ``raw=True`` (the CDR bytes as they arrive) and writes
them to an mcap bag with the message definitions (``rosbags`` typestore), so Foxglove,
PlotJuggler, ``ros2 bag`` and ``rosbags`` open it. ``OUT.mcap`` is a single mcap file;
an output path without the ``.mcap`` suffix becomes a rosbag2 bag directory. A recording
that holds no message is removed (no empty bag is left behind); one that holds messages is
always kept.

Errors (:class:`BagError`, exit code 1 on the command line): a missing bag, an unknown
storage format, a message type this Python cannot import (the graph lacks it), a replay
whose subscribers do not appear (``--wait-for-subscribers``), a requested topic that never
appears while recording or a recording without any message.
"""
from __future__ import annotations

import argparse
import heapq
import math
import importlib
import shutil
import signal
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Collection, Iterable, Iterator, Mapping, Sequence
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path, PurePath
from typing import Any

__all__ = [
    'BagError', 'Bag', 'BagTopic', 'open_bag', 'bag_info', 'message_class',
    'recorded_qos', 'qos_with_overrides', 'load_qos_overrides', 'ReplayStats', 'replay',
    'Recorder', 'main', 'DEFAULT_DEPTH', 'DEFAULT_ACK_TIMEOUT_S',
]

#: ``record`` after its stop (SIGINT, SIGTERM, ``--duration``): it goes on taking what was
#: already published until this long passes without a message ...
RECORD_DRAIN_QUIET_S = 0.25
#: ... and at most this long (nothing new is published by then when the stack stopped first,
#: as the demos stop it: the drain ends as soon as the backlog is taken. 2 s was too short
#: for a recorder a loaded host kept seconds behind: the interaction demo's bag lost the
#: session's last statuses, its position goal's success and the mode's 'stopped', 2026-11-29)
RECORD_DRAIN_MAX_S = 10.0

#: History depth of a replayed topic whose recording does not say (``ros2 bag record`` sees
#: other publishers' history as UNKNOWN, depth 0) -- and the pacing window of KEEP_ALL.
DEFAULT_DEPTH = 100
#: History depth of the recorder's subscriptions (reliable): a recorder process starved for a
#: few seconds (a busy machine) still takes every message of a 100 Hz topic its publisher
#: kept (the ground truth keeps 20 s, ``topics.truth_qos``) instead of the newest 100.
RECORD_DEPTH = 2000
#: Seconds the replay waits for reliable readers to acknowledge (a pacing step, the end).
DEFAULT_ACK_TIMEOUT_S = 5.0
#: rosbag2 metadata versions this reader knows (rosbag2's own reader stops at 9 too).
MAX_METADATA_VERSION = 9
#: DDS's ``DURATION_INFINITE`` is {sec 0x7fffffff, nanosec 0xffffffff}; the Foxy RMW
#: sentinels {0x7fffffff, 0xffffffff | 0x7fffffff} and ``RMW_DURATION_INFINITE``
#: {9223372036, 854775807} all have sec >= 2^31 - 1, the largest DDS ``Duration_t.sec``.
_INFINITE_SEC = 0x7FFFFFFF
_STORAGE_SUFFIX = {'sqlite3': '.db3', 'mcap': '.mcap'}


class BagError(RuntimeError):
    """A bag that cannot be read, replayed or written; the message says what to do."""


# --------------------------------------------------------------------------- reading

@dataclass(frozen=True)
class BagTopic:
    """One topic of a bag as the bag lists it.

    :param count: messages the bag lists (``metadata.yaml``, or a bare file's own index).
    :param offered_qos: the QoS profiles its publishers offered while it was recorded
        (``rosbags.interfaces.Qos``, one per publisher; empty when the bag does not say).
    """

    name: str
    msgtype: str
    count: int
    offered_qos: tuple = ()


class Bag:
    """An open rosbag2 bag: its topics and counts, and its messages in time order.

    Use :func:`open_bag`. Every storage file is opened on its own (``rosbags`` reader of a
    ``.db3`` or ``.mcap`` file) and its connections matched to the bag's topics by name
    and type; the QoS text may differ between ``metadata.yaml`` and the storage file.

    :ivar kind: ``'directory'``, ``'mcap'`` or ``'sqlite3'`` (a bare file).
    :ivar version: ``metadata.yaml`` version (None for a bare file).
    :ivar files: the storage files in the order ``metadata.yaml`` lists them.
    :ivar topics: ``{name: BagTopic}``.
    :ivar message_count: messages the bag lists.
    :ivar start_ns: time (ns) of the earliest stored message; ``end_ns`` of the latest.
    :ivar unlisted: ``{topic: [description, ...]}``: storage connections with messages
        that ``metadata.yaml`` does not list with that topic and type (not replayable).
    :ivar warnings: what looks wrong but does not stop a replay (printed by ``info``).
    """

    def __init__(self, path: Path) -> None:
        self.path = path
        self.kind = ''
        self.version: int | None = None
        self.storage_id = ''
        self.files: list[Path] = []
        self.topics: dict[str, BagTopic] = {}
        self.message_count = 0
        self.start_ns = 0
        self.end_ns = 0
        self.unlisted: dict[str, list[str]] = {}
        self.warnings: list[str] = []
        self._compressed_messages = False
        self._readers: list[Any] = []            # rosbags Reader per storage file
        self._conn_topic: list[dict[int, str]] = []   # per file: connection id -> topic
        self._stack = ExitStack()

    # -- lifetime
    def close(self) -> None:
        self._stack.close()
        self._readers.clear()

    def __enter__(self) -> Bag:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def duration_s(self) -> float:
        """Time between the first and the last stored message (s)."""
        return max(self.end_ns - self.start_ns, 0) * 1e-9

    # -- messages
    def messages(self, topics: Collection[str] | None = None) -> Iterator[tuple[str, int, bytes]]:
        """``(topic, time_ns, cdr_bytes)`` of every stored message of ``topics`` (all if
        None), in time order across the storage files (a split bag's files in turn)."""
        wanted = set(self.topics) if topics is None else set(topics)
        streams = []
        for index, (reader, conn_topic) in enumerate(zip(self._readers, self._conn_topic)):
            conns = [c for c in reader.connections if conn_topic.get(c.id) in wanted]
            if conns:     # rosbags reads *every* connection when given none
                streams.append(self._stream(index, reader, conns, conn_topic))
        # heapq.merge is stable: equal stamps keep the file order, then the stored order
        for t_ns, _, topic, data in heapq.merge(*streams, key=lambda m: m[0]):
            yield topic, t_ns, data

    def _stream(self, index: int, reader: Any, conns: list,
                conn_topic: dict[int, str]) -> Iterator[tuple[int, int, str, bytes]]:
        zstd = _zstd() if self._compressed_messages else None
        try:
            for conn, t_ns, data in reader.messages(connections=conns):
                yield (t_ns, index, conn_topic[conn.id],
                       zstd.decompress(data) if zstd else bytes(data))
        except Exception as exc:  # noqa: BLE001 - a damaged file: rosbags, sqlite, zstd errors
            raise BagError(f'cannot read the messages of {str(self.files[index])!r}: '
                           f'{type(exc).__name__}: {exc}') from exc

    def stored_counts(self) -> dict[str, int]:
        """Messages per topic that the storage files index (their own counts)."""
        counts = dict.fromkeys(self.topics, 0)
        for reader, conn_topic in zip(self._readers, self._conn_topic):
            for conn in reader.connections:
                if conn.id in conn_topic:
                    counts[conn_topic[conn.id]] += conn.msgcount
        return counts


def _zstd():
    if sys.version_info >= (3, 14):
        from compression import zstd
    else:
        from backports import zstd     # rosbags' own dependency
    return zstd


def open_bag(path: str | Path) -> Bag:
    """Open a rosbag2 bag for reading: a bag directory, or a bare ``.mcap`` / ``.db3`` file.

    :raises BagError: the path does not exist, or is neither a bag directory nor a
        ``.mcap`` / ``.db3`` file, or its metadata or storage cannot be read; a topic
        with several message types.
    """
    p = Path(path)
    if not p.exists():
        raise BagError(f'bag {str(p)!r} does not exist')
    if p.is_dir() and not (p / 'metadata.yaml').is_file():
        raise BagError(f'{str(p)!r} is a directory without metadata.yaml: not a rosbag2 bag')
    if p.is_file() and p.suffix not in ('.mcap', '.db3'):
        raise BagError(f'unknown storage format {p.suffix or "(no suffix)"!r} of {str(p)!r}: '
                       'expected a rosbag2 bag directory, a .mcap or a .db3 file '
                       '(ROS 1 .bag files: convert them with `rosbags-convert`)')
    bag = Bag(p)
    try:
        if p.is_dir():
            _open_directory(bag)
        else:
            _open_file(bag)
    except BaseException:
        bag.close()
        raise
    return bag


def _lenient_mcap_schemas() -> None:
    """rosbags 0.11 refuses an mcap schema encoding it does not know ('unknown': rosbag2 writes
    it for a service type without message fields); the replay never needs the definition."""
    try:
        from rosbags.rosbag2 import storage_mcap
        strict = storage_mcap.get_msgdef
    except (ImportError, AttributeError):       # another rosbags: its own reading stands
        return
    if getattr(strict, 'lenient', False):
        return

    def get_msgdef(schema):
        if schema is not None and schema.encoding not in ('ros2msg', 'ros2idl', 'omgidl', ''):
            schema = schema._replace(encoding='', data='')
        return strict(schema)
    get_msgdef.lenient = True
    storage_mcap.get_msgdef = get_msgdef


def _open_storage(bag: Bag, path: Path) -> Any:
    from rosbags.rosbag2 import Reader
    _lenient_mcap_schemas()
    try:
        reader = Reader(path)
        reader.open()
    except Exception as exc:  # noqa: BLE001 - rosbags raises several error types
        raise BagError(f'cannot read storage file {str(path)!r} of bag {str(bag.path)!r}: '
                       f'{exc}') from exc
    bag._stack.callback(reader.close)
    bag._readers.append(reader)
    wal = path.with_name(path.name + '-wal')
    if path.suffix == '.db3' and wal.is_file() and wal.stat().st_size:
        raise BagError(f'{str(path)!r} has a non-empty {wal.name} (a recording that did not '
                       'close): its last messages are not in the .db3 and would be missed; '
                       f"merge them first: sqlite3 {path} 'PRAGMA wal_checkpoint(TRUNCATE)'")
    return reader


def _topics_of(bag: Bag, entries: Iterable[tuple[str, str, int, Sequence]], where: str) -> None:
    """Fill ``bag.topics`` from ``(name, type, count, qos_list)``; one type per topic."""
    for name, msgtype, count, qos in entries:
        old = bag.topics.get(name)
        if old is not None and old.msgtype != msgtype:
            raise BagError(f'topic {name} of bag {str(bag.path)!r} has two message types in '
                           f'{where} ({old.msgtype} and {msgtype}); one publisher per topic '
                           'cannot replay both: split the bag (rosbags, ros2 bag convert)')
        bag.topics[name] = BagTopic(name, msgtype, count + (old.count if old else 0),
                                    (old.offered_qos if old else ()) + tuple(qos))


def _open_file(bag: Bag) -> None:
    bag.kind = 'mcap' if bag.path.suffix == '.mcap' else 'sqlite3'
    bag.storage_id = bag.kind
    reader = _open_storage(bag, bag.path)
    bag.files = [bag.path]
    _topics_of(bag, ((c.topic, c.msgtype, c.msgcount,
                      getattr(c.ext, 'offered_qos_profiles', ())) for c in reader.connections),
               bag.path.name)
    bag._conn_topic.append({c.id: c.topic for c in reader.connections})
    bag.message_count = sum(t.count for t in bag.topics.values())
    bag.start_ns, bag.end_ns = (reader.start_time, reader.end_time) if bag.message_count else (0, 0)


def _open_directory(bag: Bag) -> None:
    import yaml
    from rosbags.rosbag2.metadata import parse_qos
    bag.kind = 'directory'
    where = str(bag.path / 'metadata.yaml')
    try:
        doc = yaml.safe_load((bag.path / 'metadata.yaml').read_text())
        meta = doc['rosbag2_bagfile_information']
        bag.version = int(meta['version'])
        if bag.version > MAX_METADATA_VERSION:
            raise BagError(f'{where}: metadata version {bag.version} is newer than this '
                           f'reader knows ({MAX_METADATA_VERSION}); upgrade rosbags and '
                           'brace_control, or convert the bag with `ros2 bag convert`')
        bag.storage_id = str(meta['storage_identifier'])
        if bag.storage_id not in _STORAGE_SUFFIX:
            raise BagError(f'{where}: storage {bag.storage_id!r} is not supported '
                           f'(expected one of {sorted(_STORAGE_SUFFIX)})')
        mode = str(meta.get('compression_mode') or '').lower()
        fmt = str(meta.get('compression_format') or '')
        if mode not in ('', 'none', 'file', 'message'):
            raise BagError(f'{where}: unknown compression_mode {mode!r} '
                           "(expected '', 'file' or 'message')")
        if mode in ('file', 'message') and fmt != 'zstd':
            raise BagError(f'{where}: compression format {fmt!r} is not supported (zstd is)')
        bag._compressed_messages = mode == 'message'
        # before version 4 the paths include the bag's directory name; the file is ours
        bag.files = [bag.path / PurePath(str(x)).name for x in meta['relative_file_paths']]
        entries = []
        for x in meta['topics_with_message_count']:
            tm = x['topic_metadata']
            if tm.get('serialization_format', 'cdr') != 'cdr':
                raise BagError(f'{where}: topic {tm["name"]} is serialized as '
                               f'{tm["serialization_format"]!r}; only cdr is replayable')
            entries.append((tm['name'], tm['type'], int(x['message_count']),
                            parse_qos(tm.get('offered_qos_profiles') or [])))
        listed_count = int(meta['message_count'])
    except BagError:
        raise
    except KeyError as exc:
        raise BagError(f'{where} lacks the key {exc} (a rosbag2 metadata file has it)') from exc
    except Exception as exc:  # noqa: BLE001 - YAML, types, rosbags' QoS parser
        raise BagError(f'cannot read {where}: {exc}') from exc
    _topics_of(bag, entries, 'metadata.yaml')
    bag.message_count = listed_count
    if listed_count != sum(t.count for t in bag.topics.values()):
        bag.warnings.append(f'metadata.yaml lists {listed_count} messages in all but '
                            f'{sum(t.count for t in bag.topics.values())} per topic')
    missing = [f.name for f in bag.files if not f.is_file()]
    if missing:
        raise BagError(f'storage file(s) {missing} listed in {where} are missing')
    listed = {f.name for f in bag.files}
    stray = sorted(f.name for f in bag.path.iterdir() if f.name not in listed
                   and any(f.name.endswith(s) or f.name.endswith(s + '.zstd')
                           for s in _STORAGE_SUFFIX.values()))
    if stray:
        bag.warnings.append(f'storage file(s) {stray} in the bag directory are not listed in '
                            'metadata.yaml and are not replayed (replay them on their own)')
    tmp = None
    for path in bag.files:
        if mode == 'file':
            if tmp is None:
                tmp = Path(bag._stack.enter_context(tempfile.TemporaryDirectory(
                    prefix='brace-bag-')))
            plain = tmp / path.name.removesuffix('.zstd')
            try:
                with path.open('rb') as src, _zstd().open(src, 'rb') as z, \
                        plain.open('wb') as dst:
                    shutil.copyfileobj(z, dst)
            except Exception as exc:  # noqa: BLE001 - zstd errors, OSError
                raise BagError(f'{where}: compression_mode is file but {path.name!r} does not '
                               f'decompress as zstd: {type(exc).__name__}: {exc}') from exc
            path = plain
        if path.suffix != _STORAGE_SUFFIX[bag.storage_id]:
            raise BagError(f'{where}: storage is {bag.storage_id} but file {path.name!r} is '
                           f'not a {_STORAGE_SUFFIX[bag.storage_id]} file')
        reader = _open_storage(bag, path)
        conn_topic: dict[int, str] = {}
        for conn in reader.connections:
            listed_topic = bag.topics.get(conn.topic)
            if listed_topic is not None and listed_topic.msgtype == conn.msgtype:
                conn_topic[conn.id] = conn.topic       # by name and type; QoS text may differ
            elif conn.msgcount:
                what = ('lists it as ' + listed_topic.msgtype) if listed_topic else 'lacks it'
                bag.unlisted.setdefault(conn.topic, []).append(
                    f'{path.name} holds {conn.msgcount} message(s) of {conn.topic} '
                    f'({conn.msgtype}); metadata.yaml {what}')
        bag._conn_topic.append(conn_topic)
    starts = [r.start_time for r in bag._readers if r.message_count]
    ends = [r.end_time for r in bag._readers if r.message_count]
    bag.start_ns, bag.end_ns = (min(starts), max(ends)) if starts else (0, 0)
    for topic, n in bag.stored_counts().items():
        if n != bag.topics[topic].count:
            bag.warnings.append(f'{topic}: metadata.yaml lists {bag.topics[topic].count} '
                                f'messages, the storage files index {n}')
    for descriptions in bag.unlisted.values():
        bag.warnings.extend(descriptions)


def message_class(msgtype: str, *, topic: str = '') -> type:
    """The Python class of a ROS message type name (``geometry_msgs/msg/PoseStamped``).

    :raises BagError: the type's package is not importable here.
    """
    parts = msgtype.split('/')
    if len(parts) == 2:                      # 'pkg/Type' (Dashing) is 'pkg/msg/Type'
        parts.insert(1, 'msg')
    if len(parts) != 3 or parts[1] not in ('msg', 'srv', 'action'):
        raise BagError(f'message type {msgtype!r}{_on(topic)} is not a ROS 2 message type name')
    pkg, kind, name = parts
    try:
        module = importlib.import_module(f'{pkg}.{kind}')
        if kind == 'action' and not hasattr(module, name) and '_' in name:
            action, _, part = name.rpartition('_')     # Fibonacci_FeedbackMessage
            return getattr(getattr(module, action).Impl, part)
        return getattr(module, name)                   # srv: SetBool_Event
    except (ImportError, AttributeError) as exc:
        raise BagError(
            f'message type {msgtype!r}{_on(topic)} is not available in this Python '
            f'({exc}); install its package (ros-{pkg.replace("_", "-")} from pip, or '
            f'ros-<distro>-{pkg.replace("_", "-")}) or leave the topic out with --topics') from exc


def _on(topic: str) -> str:
    return f' of topic {topic}' if topic else ''


def bag_info(path: str | Path) -> dict[str, Any]:
    """Topics, types, counts and duration of a bag (``brace-bag info``).

    ``topics`` maps each topic to ``{'type', 'count'}`` (the counts the bag lists);
    ``warnings`` says what does not add up (see :class:`Bag`).
    """
    with open_bag(path) as bag:
        return {
            'path': str(path),
            'kind': bag.kind,
            'version': bag.version,
            'storage': bag.storage_id,
            'files': [f.name for f in bag.files],
            'duration_s': bag.duration_s,
            'messages': bag.message_count,
            'topics': {t.name: {'type': t.msgtype, 'count': t.count}
                       for t in bag.topics.values()},
            'warnings': list(bag.warnings),
        }


# ------------------------------------------------------------------------------- QoS

def _duration(value: Any, *, topic: str, policy: str):
    """An rclpy Duration of a recorded ``{sec, nsec}`` (rosbags ``QosTime`` or a mapping).

    ``{0, 0}`` is "unspecified" (the RMW default: no deadline, no lifespan, no lease).
    Any ``sec >= 2^31 - 1`` is infinite: that is DDS's ``DURATION_INFINITE`` and every
    RMW's "infinite" sentinel (see ``_INFINITE_SEC``); passed on as seconds, it would
    overflow DDS's 32-bit seconds and fail to create the publisher.
    """
    from rclpy.duration import Duration, Infinite
    try:
        if isinstance(value, Mapping):
            sec, nsec = int(value['sec']), int(value['nsec'])
        else:
            sec, nsec = int(value.sec), int(value.nsec)
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise BagError(f'QoS {policy}{_on(topic)} is {value!r}: expected {{sec: int, '
                       'nsec: int}') from exc
    if sec < 0 or nsec < 0:
        raise BagError(f'QoS {policy}{_on(topic)} is {{sec: {sec}, nsec: {nsec}}}: '
                       'a duration is not negative')
    if sec >= _INFINITE_SEC:
        return Infinite
    if nsec >= 1_000_000_000:
        raise BagError(f'QoS {policy}{_on(topic)} is {{sec: {sec}, nsec: {nsec}}}: '
                       'nsec must be below 1e9 (only the "infinite" sentinels exceed it)')
    return Duration(seconds=sec, nanoseconds=nsec)


def _ns(d: Any) -> float:
    """Duration in ns for ordering: unspecified (0) and Infinite are both +inf."""
    from rclpy.duration import Infinite
    return float('inf') if d.nanoseconds == 0 or d == Infinite else float(d.nanoseconds)


def recorded_qos(offers: Sequence[Any], *, topic: str = '', default_depth: int = DEFAULT_DEPTH):
    """The rclpy ``QoSProfile`` a replay offers on a topic recorded with ``offers``.

    ``offers`` are the profiles the recorded publishers offered (``rosbags.interfaces.Qos``
    from ``offered_qos_profiles``; metadata versions 4-8 spell them as integers of the RMW
    enums, version 9 as names; ``rosbags`` reads both). One offer is copied policy by
    policy; several are merged into the offer that every subscription matched by one of
    them still matches: RELIABLE unless all were BEST_EFFORT, TRANSIENT_LOCAL if one was,
    the shortest deadline and liveliness lease, MANUAL_BY_TOPIC liveliness if one was
    manual, the longest lifespan. Unknown or system-default reliability and durability
    become RELIABLE and VOLATILE (matching every subscription that asks for less).

    History and depth: ``ros2 bag record`` sees other processes' history as UNKNOWN with
    depth 0. KEEP_ALL is kept. A TRANSIENT_LOCAL topic keeps its recorded KEEP_LAST depth
    (what a late-joining subscription receives), ``default_depth`` if it has none. A
    VOLATILE topic gets at least ``default_depth``: its depth only bounds how many
    unacknowledged messages the publisher holds, so a deeper one is invisible to
    subscribers and paces a burst in fewer acknowledgement round trips. Without offers
    (a bag written by ``rosbags``, or before metadata version 4): RELIABLE, VOLATILE,
    KEEP_LAST ``default_depth``. Durations: see :func:`_duration`.
    """
    from rclpy.qos import (DurabilityPolicy, HistoryPolicy, LivelinessPolicy, QoSProfile,
                           ReliabilityPolicy)
    if not default_depth > 0:
        raise BagError(f'default depth must be positive, got {default_depth}')
    profile = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=default_depth,
                         reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.VOLATILE)
    if not offers:
        return profile
    names = [(o.history.name, o.reliability.name, o.durability.name, o.liveliness.name)
             for o in offers]
    if all(r == 'BEST_EFFORT' for _, r, _, _ in names):
        profile.reliability = ReliabilityPolicy.BEST_EFFORT
    if any(d == 'TRANSIENT_LOCAL' for _, _, d, _ in names):
        profile.durability = DurabilityPolicy.TRANSIENT_LOCAL
    if any(h == 'KEEP_ALL' for h, *_ in names):
        profile.history = HistoryPolicy.KEEP_ALL
    else:
        depth = max((int(o.depth) for o, (h, *_) in zip(offers, names) if h == 'KEEP_LAST'),
                    default=0)
        if profile.durability == DurabilityPolicy.TRANSIENT_LOCAL:
            profile.depth = depth if depth > 0 else default_depth   # what a late joiner gets
        else:
            profile.depth = max(depth, default_depth)
    lively = {lv for *_, lv in names}
    if lively & {'MANUAL_BY_TOPIC', 'MANUAL_BY_NODE'}:      # MANUAL_BY_NODE: gone since Galactic
        profile.liveliness = LivelinessPolicy.MANUAL_BY_TOPIC
    elif 'AUTOMATIC' in lively:
        profile.liveliness = LivelinessPolicy.AUTOMATIC
    deadlines = [_duration(o.deadline, topic=topic, policy='deadline') for o in offers]
    leases = [_duration(o.liveliness_lease_duration, topic=topic,
                        policy='liveliness_lease_duration') for o in offers]
    lifespans = [_duration(o.lifespan, topic=topic, policy='lifespan') for o in offers]
    profile.deadline = min(deadlines, key=_ns)
    profile.liveliness_lease_duration = min(leases, key=_ns)
    # any unlimited lifespan keeps every message; else the longest
    profile.lifespan = max(lifespans, key=_ns)
    profile.avoid_ros_namespace_conventions = any(
        bool(o.avoid_ros_namespace_conventions) for o in offers)
    return profile


_POLICIES = ('history', 'depth', 'reliability', 'durability', 'deadline', 'lifespan',
             'liveliness', 'liveliness_lease_duration', 'avoid_ros_namespace_conventions')


def qos_with_overrides(base: Any, override: Mapping[str, Any], *, topic: str = ''):
    """``base`` (an rclpy ``QoSProfile``) with the policies ``override`` names replaced.

    The keys and values are those of ``ros2 bag play --qos-profile-overrides-path``:
    ``history: keep_last | keep_all``, ``depth: int``, ``reliability: reliable |
    best_effort``, ``durability: volatile | transient_local``, ``liveliness: automatic |
    manual_by_topic``, ``deadline`` / ``lifespan`` / ``liveliness_lease_duration``:
    ``{sec, nsec}``, ``avoid_ros_namespace_conventions: bool`` (policy names may also be
    the RMW integers). Policies it does not name keep their value in ``base``.

    :raises BagError: an unknown policy or value, naming the allowed ones.
    """
    from rclpy.qos import (DurabilityPolicy, HistoryPolicy, LivelinessPolicy, QoSProfile,
                           ReliabilityPolicy)
    enums = {'history': HistoryPolicy, 'reliability': ReliabilityPolicy,
             'durability': DurabilityPolicy, 'liveliness': LivelinessPolicy}
    unknown = sorted(set(override) - set(_POLICIES))
    if unknown:
        raise BagError(f'QoS override{_on(topic)}: unknown policy {unknown}; '
                       f'expected some of {list(_POLICIES)}')
    values = {k: getattr(base, k) for k in _POLICIES}
    for key, value in override.items():
        if key in enums:
            enum = enums[key]
            try:
                values[key] = enum(value) if isinstance(value, int) else \
                    enum.get_from_short_key(str(value).lower())
            except (KeyError, ValueError) as exc:
                raise BagError(f'QoS override{_on(topic)}: {key}: {value!r} is not one of '
                               f'{enum.short_keys()}') from exc
        elif key == 'depth':
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise BagError(f'QoS override{_on(topic)}: depth {value!r} is not a '
                               'positive integer')
            values[key] = value
        elif key == 'avoid_ros_namespace_conventions':
            if not isinstance(value, bool):
                raise BagError(f'QoS override{_on(topic)}: {key} {value!r} is not true/false')
            values[key] = value
        else:
            values[key] = _duration(value, topic=topic, policy=key)
    if 'history' in override and 'depth' not in override and \
            values['history'] == HistoryPolicy.KEEP_LAST and not values['depth']:
        values['depth'] = DEFAULT_DEPTH
    return QoSProfile(**values)


def load_qos_overrides(path: str | Path) -> dict[str, dict[str, Any]]:
    """``{topic: {policy: value}}`` from a YAML file (the schema of :func:`qos_with_overrides`,
    as ``ros2 bag play --qos-profile-overrides-path`` reads it)."""
    import yaml
    p = Path(path)
    try:
        doc = yaml.safe_load(p.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise BagError(f'cannot read QoS overrides {str(p)!r}: {exc}') from exc
    if not isinstance(doc, dict) or not all(isinstance(v, dict) for v in doc.values()):
        raise BagError(f'QoS overrides {str(p)!r}: expected a mapping of topic names to '
                       '{policy: value} mappings, e.g. "/scan: {reliability: best_effort}"')
    return {str(k): dict(v) for k, v in doc.items()}


# --------------------------------------------------------------------------- replay

@dataclass
class ReplayStats:
    """What a replay published, and every way it fell short of the bag.

    :ivar published: messages published per topic.
    :ivar duration_s: wall time from the first message's schedule to the end (s).
    :ivar late_max_s: worst lateness of a publish against its schedule (s).
    :ivar expected: messages the bag lists per replayed topic.
    :ivar unacknowledged: reliable topics whose matched readers had not acknowledged every
        message when the replay ended (``ack_timeout``).
    :ivar unmatched: messages per topic published while no subscription was matched
        (nobody could receive them; use ``wait_subscribers``).
    :ivar qos: the QoS profile each topic was published with.
    :ivar problems: every difference between the bag and what was delivered; empty when
        every listed message was published and every reliable one acknowledged.
    :ivar warnings: notes that are not a difference (best-effort topics, unmatched
        publishes, the bag's own inconsistencies).
    """

    published: dict[str, int] = field(default_factory=dict)
    duration_s: float = 0.0
    late_max_s: float = 0.0
    expected: dict[str, int] = field(default_factory=dict)
    unacknowledged: list[str] = field(default_factory=list)
    unmatched: dict[str, int] = field(default_factory=dict)
    qos: dict[str, Any] = field(default_factory=dict)
    problems: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    stopped: bool = False

    @property
    def total(self) -> int:
        return sum(self.published.values())

    @property
    def ok(self) -> bool:
        """True when the replay delivered the bag (no :attr:`problems`)."""
        return not self.problems


class _Topic:
    """A replayed topic: its publisher and the pacing that keeps a burst whole."""

    def __init__(self, name: str, publisher: Any, qos: Any) -> None:
        from rclpy.qos import HistoryPolicy, ReliabilityPolicy
        self.name = name
        self.publisher = publisher
        self.reliable = qos.reliability == ReliabilityPolicy.RELIABLE
        # at most this many unacknowledged messages in the history: a KEEP_LAST history
        # overwrites the oldest when full, acknowledged or not (KEEP_ALL never does)
        self.window = qos.depth if qos.history == HistoryPolicy.KEEP_LAST else None
        self.in_flight = 0
        self.ack_failed = False

    def wait_acked(self, timeout_s: float, stop: threading.Event | None) -> bool:
        """Until the matched readers acknowledged every message (True), or timeout / stop."""
        from rclpy.duration import Duration
        deadline = time.monotonic() + timeout_s
        while True:
            left = deadline - time.monotonic()
            if self.publisher.wait_for_all_acked(Duration(seconds=max(min(left, 0.1), 0.0))):
                self.in_flight = 0
                return True
            if left <= 0 or (stop is not None and stop.is_set()):
                return False


def replay(node: Any, path: str | Path, *, rate: float = 1.0,
           topics: Sequence[str] | None = None, wait_subscribers: int = 0,
           wait_topics: Sequence[str] | None = None,
           wait_timeout: float = 10.0, delay: float = 0.0,
           stop: threading.Event | None = None,
           progress: Callable[[float, float], None] | None = None,
           qos_overrides: Mapping[str, Any] | None = None,
           ack_timeout: float = DEFAULT_ACK_TIMEOUT_S) -> ReplayStats:
    """Publish the messages of bag ``path`` on ``node``'s publishers with their timing.

    Runs in the calling thread (the node need not be spun for publishing; spin it
    elsewhere if it has callbacks). The recorded CDR bytes are published unchanged, each
    topic with its recorded QoS (:func:`recorded_qos`). A reliable topic is paced so that
    its history never holds more unacknowledged messages than its depth (a burst is
    delayed, never overwritten); at the end the replay waits up to ``ack_timeout`` s for
    every reliable message to be acknowledged. What it could not deliver is in
    :attr:`ReplayStats.problems` (it does not raise for it).

    A subscription keeps what its own QoS keeps: a KEEP_LAST subscriber that takes
    messages slower than a burst arrives still drops the oldest, acknowledged ones.

    :param rate: playback speed factor (2.0 = twice as fast).
    :param topics: only these topics (default: all).
    :param wait_subscribers: before the first message, wait until every publisher in
        ``wait_topics`` has at least this many matched subscriptions, up to ``wait_timeout`` s.
    :param wait_topics: the topics that wait applies to (default: every replayed topic
        that has messages).
    :param delay: seconds to wait after the publishers are created (and matched).
    :param stop: set it to end the replay early (reported as a problem).
    :param progress: called as ``progress(bag_time_s, bag_duration_s)`` about 10 x / s.
    :param qos_overrides: ``{topic: QoSProfile}`` replaces a topic's recorded QoS;
        ``{topic: {policy: value}}`` replaces single policies (:func:`qos_with_overrides`).
    :param ack_timeout: seconds to wait for acknowledgements (per pacing step, and at
        the end).
    :raises BagError: see :func:`open_bag`, :func:`message_class`; a requested topic
        that is not in the bag; storage connections that ``metadata.yaml`` does not list;
        subscribers that do not appear; a rate that is not positive.
    """
    from rclpy.qos import QoSProfile
    if not rate > 0:
        raise BagError(f'--rate must be positive, got {rate}')
    if not ack_timeout >= 0:
        raise BagError(f'ack timeout must not be negative, got {ack_timeout}')
    with open_bag(path) as bag:
        selected = list(bag.topics) if topics is None else list(dict.fromkeys(topics))
        missing = sorted(set(selected) - set(bag.topics))
        if missing:
            raise BagError(f'topic(s) {missing} not in bag {str(path)!r} '
                           f'(it has {sorted(bag.topics)})')
        unknown = sorted(set(qos_overrides or {}) - set(bag.topics))
        if unknown:
            raise BagError(f'QoS override(s) for {unknown}: not topics of bag {str(path)!r} '
                           f'(it has {sorted(bag.topics)})')
        unlisted = [d for t, ds in bag.unlisted.items() if topics is None or t in selected
                    for d in ds]
        if unlisted:
            raise BagError(f'bag {str(path)!r}: ' + '; '.join(unlisted) + '. Replay the storage '
                           'file on its own, or leave the topic out with --topics')
        stats = ReplayStats(published=dict.fromkeys(selected, 0),
                            expected={t: bag.topics[t].count for t in selected},
                            warnings=list(bag.warnings))
        pubs: dict[str, _Topic] = {}
        for name in selected:
            t = bag.topics[name]
            qos = recorded_qos(t.offered_qos, topic=name)
            override = (qos_overrides or {}).get(name)
            if isinstance(override, QoSProfile):
                qos = override
            elif override is not None:
                qos = qos_with_overrides(qos, override, topic=name)
            stats.qos[name] = qos
            try:
                cls = message_class(t.msgtype, topic=name)
            except BagError:
                if bag.stored_counts()[name]:
                    raise
                stats.warnings.append(f'{name}: no publisher: its type {t.msgtype} is not '
                                      'available here and the bag holds no message of it')
                continue
            pubs[name] = _Topic(name, node.create_publisher(cls, name, qos), qos)
            if not pubs[name].reliable:
                stats.warnings.append(f'{name} is best effort (as recorded): its delivery '
                                      'is not acknowledged')
        try:
            _wait_for_subscribers(bag, pubs, wait_subscribers, wait_topics, wait_timeout, stop)
            if delay > 0:
                time.sleep(delay)
            _publish_all(bag, pubs, stats, rate, ack_timeout, stop, progress)
        finally:
            for p in pubs.values():
                node.destroy_publisher(p.publisher)
        _judge(bag, stats, topics)
        return stats


def _wait_for_subscribers(bag: Bag, pubs: dict[str, _Topic], n: int,
                          wait_topics: Sequence[str] | None, timeout: float,
                          stop: threading.Event | None) -> None:
    if n <= 0:
        return
    stored = bag.stored_counts()
    names = [t for t in pubs if stored[t]] if wait_topics is None else list(wait_topics)
    stray = sorted(set(names) - set(pubs))
    if stray:
        raise BagError(f'wait topic(s) {stray} are not replayed (replayed: {sorted(pubs)})')
    deadline = time.monotonic() + timeout
    while True:
        lacking = {t: pubs[t].publisher.get_subscription_count() for t in names}
        lacking = {t: c for t, c in lacking.items() if c < n}
        if not lacking:
            return
        if time.monotonic() > deadline or (stop is not None and stop.is_set()):
            have = ', '.join(f'{t} has {c}' for t, c in lacking.items())
            raise BagError(f'waited {timeout} s for {n} matched subscriber(s) per topic: {have} '
                           '(is the subscriber running, on this ROS_DOMAIN_ID, with a '
                           'compatible QoS?)')
        time.sleep(0.005)


def _publish_all(bag: Bag, pubs: dict[str, _Topic], stats: ReplayStats, rate: float,
                 ack_timeout: float, stop: threading.Event | None,
                 progress: Callable[[float, float], None] | None) -> None:
    start_ns, duration_s = bag.start_ns, bag.duration_s
    wall0 = time.monotonic()
    errors: dict[str, str] = {}
    try:
        _publish_messages(bag, pubs, stats, rate, ack_timeout, stop, progress, errors,
                          start_ns, duration_s, wall0)
    except BagError as exc:
        stats.problems.append(f'{exc}; the replay stopped after publishing {stats.total} of '
                              f'{sum(stats.expected.values())} messages')
    if stats.stopped:
        return
    for topic, pub in pubs.items():
        if pub.reliable and (pub.in_flight or pub.ack_failed):
            if not pub.wait_acked(ack_timeout, stop) or pub.ack_failed:
                stats.unacknowledged.append(topic)
    for topic, error in errors.items():
        stats.problems.append(f'{topic}: publishing failed ({error})')
    stats.duration_s = time.monotonic() - wall0


def _publish_messages(bag: Bag, pubs: dict[str, _Topic], stats: ReplayStats, rate: float,
                      ack_timeout: float, stop: threading.Event | None,
                      progress: Callable[[float, float], None] | None, errors: dict[str, str],
                      start_ns: int, duration_s: float, wall0: float) -> None:
    """Every message of the bag in time order, each at its recorded instant / ``rate``
    (:func:`_publish_all`; a storage that cannot be read further raises :class:`BagError`)."""
    next_progress = 0.0
    for topic, t_ns, data in bag.messages(pubs):
        bag_t = (t_ns - start_ns) * 1e-9
        due = wall0 + bag_t / rate
        while True:
            if stop is not None and stop.is_set():
                stats.stopped = True
                stats.duration_s = time.monotonic() - wall0
                return
            wait = due - time.monotonic()
            if wait <= 0:
                break
            time.sleep(min(wait, 0.05))
        pub = pubs[topic]
        if pub.reliable and pub.window and not pub.ack_failed and pub.in_flight >= pub.window:
            if not pub.wait_acked(ack_timeout, stop) and not (stop and stop.is_set()):
                pub.ack_failed = True       # report it; do not stall every later window
        stats.late_max_s = max(stats.late_max_s, time.monotonic() - due)
        if pub.publisher.get_subscription_count() == 0:
            stats.unmatched[topic] = stats.unmatched.get(topic, 0) + 1
        try:
            pub.publisher.publish(data)
        except Exception as exc:  # noqa: BLE001 - rclpy raises RCLError and others
            errors.setdefault(topic, f'{type(exc).__name__}: {exc}')
            continue
        pub.in_flight += 1
        stats.published[topic] += 1
        if progress is not None and time.monotonic() >= next_progress:
            next_progress = time.monotonic() + 0.1
            progress(bag_t, duration_s)
    if progress is not None:
        progress(duration_s, duration_s)


def _judge(bag: Bag, stats: ReplayStats, topics: Sequence[str] | None) -> None:
    """Compare what was published with what the bag lists; fill problems and warnings."""
    if stats.stopped:
        stats.problems.append(f'stopped after {stats.total} of {sum(stats.expected.values())} '
                              'messages')
    elif not sum(stats.expected.values()) and not stats.total:
        stats.problems.append('nothing to replay: ' + (
            f'the topic filter {list(topics)} selects no message' if topics is not None
            else 'the bag holds no message'))
    else:
        for topic, n in stats.expected.items():
            got = stats.published[topic]
            if topics is not None and n == 0:
                stats.problems.append(f'{topic}: the topic filter selects it but the bag '
                                      'holds no message of it')
            elif got != n:
                stats.problems.append(f'{topic}: published {got} of the {n} messages the bag '
                                      'lists' + (' (its storage holds other counts)'
                                                 if bag.stored_counts()[topic] != n else ''))
    listed = sum(t.count for t in bag.topics.values())
    if bag.kind == 'directory' and topics is None and bag.message_count != listed:
        stats.problems.append(f'metadata.yaml lists {bag.message_count} messages in all but '
                              f'{listed} per topic')
    for topic in stats.unacknowledged:
        stats.problems.append(f'{topic}: its subscribers did not acknowledge every message '
                              'within the ack timeout (a reader stalled or left)')
    for topic, n in stats.unmatched.items():
        stats.warnings.append(f'{topic}: {n} message(s) published while no subscriber was '
                              'matched (nobody received them; use --wait-for-subscribers)')


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
    they were received (node clock, ns) as ``ros2 bag record`` does. :meth:`close`
    removes the output when it holds no message, and keeps it otherwise.

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
        parent = self.out.parent if str(self.out.parent) else Path('.')
        if not parent.is_dir():
            raise BagError(f'cannot record to {str(self.out)!r}: directory {str(parent)!r} does not exist')
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

    @property
    def total(self) -> int:
        """Messages recorded so far."""
        return sum(self.counts.values())

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
        qos = self._qos or QoSProfile(depth=RECORD_DEPTH, reliability=ReliabilityPolicy.RELIABLE)
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
        """Stop recording and finish the file (mcap summary/index); returns the output path.

        A recording without any message is removed: the returned path then does not exist.
        """
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
            if self.total:
                files = sorted(self._bag_dir.glob('*.mcap'))
                shutil.move(str(files[0]), str(self.out))
            shutil.rmtree(self._tmp, ignore_errors=True)
        elif not self.total:
            shutil.rmtree(self._bag_dir, ignore_errors=True)
        return self.out


# ------------------------------------------------------------------------------ CLI

def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog='brace-bag', description=__doc__.split('\n\n')[0])
    sub = ap.add_subparsers(dest='command', required=True)
    rp = sub.add_parser('replay', help='publish a bag into the graph with its timing')
    rp.add_argument('bag', help='bag directory, .mcap or .db3 file')
    rp.add_argument('--rate', type=float, default=1.0, help='speed factor (default 1.0)')
    rp.add_argument('--topics', nargs='+', default=None, help='only these topics')
    rp.add_argument('--wait-for-subscribers', '--wait-subscribers', dest='wait_subscribers',
                    type=int, default=0, metavar='N',
                    help='before the first message, wait until each topic (--wait-topics) '
                         'has N matched subscribers; exit 1 if they do not appear')
    rp.add_argument('--wait-timeout', type=float, default=10.0, metavar='S',
                    help='seconds to wait for the subscribers (default 10)')
    rp.add_argument('--wait-topics', nargs='+', default=None, metavar='T',
                    help='topics the wait applies to (default: every replayed topic with '
                         'messages)')
    rp.add_argument('--ack-timeout', type=float, default=DEFAULT_ACK_TIMEOUT_S, metavar='S',
                    help='seconds to wait for reliable subscribers to acknowledge '
                         f'(default {DEFAULT_ACK_TIMEOUT_S:g})')
    rp.add_argument('--qos-profile-overrides-path', default=None, metavar='FILE',
                    help='YAML {topic: {policy: value}} replacing recorded QoS policies')
    rp.add_argument('--delay', type=float, default=0.5,
                    help='seconds between creating the publishers and the first message '
                         '(discovery; default 0.5)')
    rp.add_argument('--wait-goals', type=float, default=None, metavar='S',
                    help='after the replay, wait up to S s for one outcome on /brace/goal_status '
                         'per goal replayed (pose_goal, pose_path); exit 1 if one is missing. '
                         'Without it the replay does not wait for outcomes (and says so)')
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
        _check_arguments(args)
        if args.command == 'info':
            info = bag_info(args.bag)
            where = (f'{info["storage"]}, metadata version {info["version"]}'
                     if info['kind'] == 'directory' else info['kind'])
            print(f'{info["path"]}: {info["messages"]} messages, {info["duration_s"]:.3f} s '
                  f'({where}, {len(info["files"])} storage file(s))')
            for topic, t in info['topics'].items():
                print(f'  {topic}  {t["type"]}  {t["count"]}')
            for w in info['warnings']:
                print(f'brace-bag: warning: {w}', file=sys.stderr)
            return 0
        if args.command == 'replay':
            open_bag(args.bag).close()          # fail before starting ROS
            if args.qos_profile_overrides_path:
                args.qos_overrides = load_qos_overrides(args.qos_profile_overrides_path)
            else:
                args.qos_overrides = None
        return _run_ros(args, ros_args)
    except BagError as exc:
        print(f'brace-bag: error: {exc}', file=sys.stderr)
        return 1


def _check_arguments(args: argparse.Namespace) -> None:
    """Numbers of the command line: finite, and not negative (a count, a time).

    :raises BagError: naming the option and the value.
    """
    checks = {
        'replay': (('rate', '--rate', False), ('wait_timeout', '--wait-timeout', True),
                   ('ack_timeout', '--ack-timeout', True), ('delay', '--delay', True),
                   ('wait_subscribers', '--wait-for-subscribers', True),
                   ('wait_goals', '--wait-goals', True)),
        'record': (('duration', '--duration', False),),
    }.get(args.command, ())
    for attr, option, zero_ok in checks:
        value = getattr(args, attr, None)
        if value is None:
            continue
        if not math.isfinite(value) or value < 0 or (value == 0 and not zero_ok):
            raise BagError(f'{option} {value}: expected a finite number '
                           + ('of 0 or more' if zero_ok else 'above 0'))


#: topics whose messages are goals: each gets one outcome on /brace/goal_status
GOAL_TOPICS = ('/brace/pose_goal', '/brace/pose_path')
_TERMINAL = ('succeeded', 'rejected', 'aborted', 'cancelled')


class GoalOutcomes:
    """The outcomes (``/brace/goal_status``) of goals that arrive while it listens: goal id ->
    terminal state and reason, for goals whose first event it saw (they are new)."""

    def __init__(self, node: Any) -> None:
        from diagnostic_msgs.msg import DiagnosticStatus
        from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
        self._lock = threading.Lock()
        self.first: dict[str, str] = {}           # goal id -> first state seen
        self.ended: dict[str, tuple[str, str]] = {}
        qos = QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE)
        self._sub = node.create_subscription(DiagnosticStatus, '/brace/goal_status', self._on, qos)

    def _on(self, msg: Any) -> None:
        values = {kv.key: kv.value for kv in msg.values}
        gid, state = values.get('goal_id', msg.name.rsplit('/', 1)[-1]), values.get('state', msg.message)
        with self._lock:
            self.first.setdefault(gid, state)
            if state in _TERMINAL and self.first[gid] in ('accepted', 'rejected'):
                self.ended.setdefault(gid, (state, values.get('reason', '')))

    def wait(self, count: int, timeout: float, stop: threading.Event | None = None) -> dict[str, tuple[str, str]]:
        """Until ``count`` goals have ended (or ``timeout``); their outcomes."""
        end = time.monotonic() + timeout
        while time.monotonic() < end and not (stop is not None and stop.is_set()):
            with self._lock:
                if len(self.ended) >= count:
                    break
            time.sleep(0.02)
        with self._lock:
            return dict(self.ended)


def _run_ros(args: argparse.Namespace, ros_args: list[str]) -> int:
    import rclpy
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor

    from .nodes.spin import spin_once

    from .nodes.dds import use_discovery_profile
    use_discovery_profile()
    rclpy.init(args=['brace-bag', *ros_args])
    node = rclpy.create_node('brace_bag')
    stop = threading.Event()

    def _stop(*_: Any) -> None:
        stop.set()

    signal.signal(signal.SIGTERM, _stop)
    signal.signal(signal.SIGINT, _stop)
    try:
        if args.command == 'replay':
            outcomes, spinner, spin_thread, spun = None, None, None, threading.Event()
            if args.wait_goals is not None:
                outcomes = GoalOutcomes(node)
                spinner = SingleThreadedExecutor()
                spinner.add_node(node)
                spin_thread = threading.Thread(target=_spin_until, args=(spinner, spun), daemon=True)
                spin_thread.start()
            stats = replay(node, args.bag, rate=args.rate, topics=args.topics,
                           wait_subscribers=args.wait_subscribers, wait_topics=args.wait_topics,
                           wait_timeout=args.wait_timeout, delay=args.delay, stop=stop,
                           qos_overrides=args.qos_overrides, ack_timeout=args.ack_timeout,
                           progress=lambda t, d: print(f'\r{t:8.2f} / {d:.2f} s', end='',
                                                       file=sys.stderr, flush=True))
            print(f'\npublished {stats.total} messages in {stats.duration_s:.2f} s '
                  f'(the bag lists {sum(stats.expected.values())}): '
                  + ', '.join(f'{t} {n}/{stats.expected[t]}' for t, n in stats.published.items()),
                  file=sys.stderr)
            for w in stats.warnings:
                print(f'brace-bag: warning: {w}', file=sys.stderr)
            for p in stats.problems:
                print(f'brace-bag: error: {p}', file=sys.stderr)
            goals = sum(n for t, n in stats.published.items() if t in GOAL_TOPICS)
            ok = stats.ok
            if goals and outcomes is None:
                print(f'brace-bag: the replay does not wait for the outcomes of the {goals} goal(s) it '
                      'published: watch /brace/goal_status, or pass --wait-goals S', file=sys.stderr)
            elif goals:
                ended = outcomes.wait(goals, args.wait_goals, stop)
                states: dict[str, int] = {}
                for state, _ in ended.values():
                    states[state] = states.get(state, 0) + 1
                print(f'goal outcomes: {len(ended)} of {goals} goal(s) replayed ended ('
                      + ', '.join(f'{n} {s}' for s, n in states.items()) + ')', file=sys.stderr)
                for gid, (state, reason) in sorted(ended.items(), key=lambda kv: int(kv[0]) if kv[0].isdigit() else 0):
                    if state != 'succeeded':
                        print(f'  goal {gid}: {state}: {reason}', file=sys.stderr)
                if len(ended) < goals:
                    print(f'brace-bag: error: {goals - len(ended)} goal(s) got no outcome on '
                          f'/brace/goal_status within --wait-goals {args.wait_goals:g} s', file=sys.stderr)
                    ok = False
            if spin_thread is not None:
                spun.set()                        # the spin thread ends before the node goes
                spin_thread.join(timeout=2.0)
                spinner.shutdown(timeout_sec=1.0)
            return 0 if ok else 1
        recorder = Recorder(node, args.out, args.topics).start()
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        t_end = None if args.duration is None else time.monotonic() + args.duration
        try:
            while not stop.is_set() and (t_end is None or time.monotonic() < t_end):
                spin_once(executor, 0.05)                 # nodes/spin.py
            # what was published before the stop and not taken yet (a loaded host delivers
            # late: a demo's last goal status once missed its bag): spin on until
            # RECORD_DRAIN_QUIET_S pass without a message, at most RECORD_DRAIN_MAX_S
            deadline = time.monotonic() + RECORD_DRAIN_MAX_S
            seen, quiet_since = recorder.total, time.monotonic()
            while time.monotonic() < deadline and time.monotonic() - quiet_since < RECORD_DRAIN_QUIET_S:
                spin_once(executor, 0.02)
                if recorder.total != seen:
                    seen, quiet_since = recorder.total, time.monotonic()
        except ExternalShutdownException:
            pass
        out = recorder.close()
        executor.shutdown()
        counts = ', '.join(f'{t} {n}' for t, n in recorder.counts.items())
        if recorder.total:
            print(f'recorded {recorder.total} messages to {out}: {counts}', file=sys.stderr)
        else:
            print(f'recorded no message; removed {out} ({counts})', file=sys.stderr)
        failed = False
        if recorder.pending:
            print(f'brace-bag: error: topic(s) {recorder.pending} never appeared in the graph '
                  '(no publisher; check the names and ROS_DOMAIN_ID)', file=sys.stderr)
            failed = True
        if not recorder.total:
            print('brace-bag: error: nothing was recorded', file=sys.stderr)
            failed = True
        return 1 if failed else 0
    except BagError as exc:
        print(f'\nbrace-bag: error: {exc}', file=sys.stderr)
        return 1
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


def _spin_until(executor: Any, stop: threading.Event) -> None:
    # the replay destroys its publishers while this thread spins: nodes/spin.py
    from .nodes.spin import spin_until
    spin_until(executor, stop, period_s=0.05)


if __name__ == '__main__':
    raise SystemExit(main())
