"""brace-bag: replay rosbag2 bags (sqlite3, mcap) into the graph; record topics to mcap.

Bags are written at test time with ``rosbags`` (its own CDR serializer, independent of
rclpy), replayed into a real subscriber, and recordings read back with ``rosbags``. Two bags
recorded by the real ``ros2 bag record`` (rosbag2's own test resources, test/data/rosbag2/
with their provenance) are replayed in every form: directory and bare storage file.

Oracles: the payloads a test wrote; for the real bags, their README (10 ``/topic`` strings
"Hello, world! k", 10 ``/rosout`` logs) and rosbags' reader of the bare storage file;
for QoS, rclpy's own compatibility check (``qos_check_compatible``) and the DDS
"infinite" duration sentinels; for the metadata versions, the fields rosbag2's
``rosbag2_storage/yaml.hpp`` reads per version.
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import yaml
from geometry_msgs.msg import PoseStamped
from rcl_interfaces.msg import Log
from rclpy.duration import Duration, Infinite
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, LivelinessPolicy, QoSCompatibility,
                       QoSProfile, ReliabilityPolicy, qos_check_compatible)
from rclpy.serialization import deserialize_message
from rosbags.interfaces import (Qos, QosDurability, QosHistory, QosLiveliness, QosReliability,
                                QosTime)
from rosbags.rosbag2 import CompressionFormat, CompressionMode, Reader, StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore
from std_msgs.msg import String

from brace_control.bag import (DEFAULT_DEPTH, BagError, Recorder, bag_info, load_qos_overrides,
                               message_class, open_bag, qos_with_overrides, recorded_qos, replay)
from brace_control.nodes.msgs import pose_msg, sec_to_stamp
from ros_helpers import RELIABLE_10

STORE = get_typestore(Stores.ROS2_HUMBLE)
POSE_T = 'geometry_msgs/msg/PoseStamped'
SPACING_NS = 40_000_000          # 40 ms between recorded messages
N = 6


def _pose_cdr(k: int) -> bytes:
    """A PoseStamped serialized by rosbags (not rclpy): x = k mm, stamp = k s."""
    T = STORE.types
    msg = T['geometry_msgs/msg/PoseStamped'](
        header=T['std_msgs/msg/Header'](stamp=T['builtin_interfaces/msg/Time'](sec=k, nanosec=7),
                                        frame_id='brace_base'),
        pose=T['geometry_msgs/msg/Pose'](
            position=T['geometry_msgs/msg/Point'](x=k * 1e-3, y=0.39, z=0.0),
            orientation=T['geometry_msgs/msg/Quaternion'](x=0.0, y=0.0, z=0.0, w=1.0)))
    return bytes(STORE.serialize_cdr(msg, POSE_T))


def write_bag(path, storage: StoragePlugin, *, version: int = 9, extra: bool = True) -> list[bytes]:
    """A bag with N poses on /brace/pose_goal (+ a string topic); returns the pose CDR bytes."""
    payloads = [_pose_cdr(k) for k in range(N)]
    with Writer(path, version=version, storage_plugin=storage) as w:
        c = w.add_connection('/brace/pose_goal', POSE_T, typestore=STORE)
        s = w.add_connection('/chatter', 'std_msgs/msg/String', typestore=STORE) if extra else None
        for k, data in enumerate(payloads):
            w.write(c, 1_000_000_000 + k * SPACING_NS, data)
            if s is not None:
                w.write(s, 1_000_000_000 + k * SPACING_NS + 1, bytes(STORE.serialize_cdr(
                    STORE.types['std_msgs/msg/String'](data=f'm{k}'), 'std_msgs/msg/String')))
    return payloads


def _replay_into(ros, bag, **kw):
    """Replay ``bag`` from a thread; collect /brace/pose_goal raw and parsed."""
    test = ros.node('bag_test')
    raw, parsed = [], []
    test.create_subscription(PoseStamped, '/brace/pose_goal', raw.append, RELIABLE_10, raw=True)
    test.create_subscription(PoseStamped, '/brace/pose_goal', parsed.append, RELIABLE_10)
    player = ros.node('player')
    result: dict = {}

    def run():
        try:
            result['stats'] = replay(player, bag, wait_subscribers=2, delay=0.3,
                                     wait_topics=['/brace/pose_goal'], **kw)
        except Exception as exc:  # noqa: BLE001
            result['error'] = exc

    th = threading.Thread(target=run)
    t0 = time.monotonic()
    th.start()
    ros.spin_until(lambda: 'stats' in result or 'error' in result, timeout=20, what='replay')
    elapsed = time.monotonic() - t0
    th.join()
    if 'error' in result:
        raise result['error']
    ros.spin_until(lambda: len(raw) == N and len(parsed) == N, what='all replayed messages')
    return result['stats'], raw, parsed, elapsed


@pytest.mark.ros
@pytest.mark.parametrize('storage, version', [
    (StoragePlugin.SQLITE3, 8), (StoragePlugin.SQLITE3, 9),
    (StoragePlugin.MCAP, 8), (StoragePlugin.MCAP, 9)],
    ids=['sqlite3-v8', 'sqlite3-v9', 'mcap-v8', 'mcap-v9'])
def test_replay_publishes_recorded_bytes_unchanged(ros, tmp_path, storage, version):
    bag = tmp_path / 'goals'
    payloads = write_bag(bag, storage, version=version)
    stats, raw, parsed, _ = _replay_into(ros, bag)
    assert raw == payloads                                    # CDR bytes unchanged, in order
    assert [m.pose.position.x for m in parsed] == pytest.approx([k * 1e-3 for k in range(N)])
    assert [m.header.stamp.sec for m in parsed] == list(range(N))   # stamps as recorded
    assert stats.published == {'/brace/pose_goal': N, '/chatter': N}


@pytest.mark.ros
def test_replay_keeps_timing_scaled_by_rate_and_filters_topics(ros, tmp_path):
    bag = tmp_path / 'goals'
    write_bag(bag, StoragePlugin.MCAP)
    stats, *_ = _replay_into(ros, bag, rate=0.5, topics=['/brace/pose_goal'])
    recorded_span = (N - 1) * SPACING_NS * 1e-9
    assert stats.published == {'/brace/pose_goal': N}
    assert recorded_span / 0.5 <= stats.duration_s < recorded_span / 0.5 + 0.15


@pytest.mark.ros
def test_replay_of_a_single_mcap_file(ros, tmp_path):
    bag = tmp_path / 'goals'
    payloads = write_bag(bag, StoragePlugin.MCAP)
    (single,) = bag.glob('*.mcap')
    _, raw, _, _ = _replay_into(ros, single, rate=4.0)
    assert raw == payloads


def test_missing_bag_is_a_clear_error(tmp_path):
    with pytest.raises(BagError, match='does not exist'):
        open_bag(tmp_path / 'nope.mcap')


def test_unknown_storage_format_is_a_clear_error(tmp_path):
    (tmp_path / 'old.bag').write_bytes(b'#ROSBAG V2.0\n')
    with pytest.raises(BagError, match="unknown storage format '.bag'"):
        open_bag(tmp_path / 'old.bag')
    (tmp_path / 'empty_dir').mkdir()
    with pytest.raises(BagError, match='without metadata.yaml'):
        open_bag(tmp_path / 'empty_dir')


@pytest.mark.ros
def test_message_type_this_python_lacks_is_a_clear_error(ros, tmp_path):
    from rosbags.typesys import get_types_from_msg
    store = get_typestore(Stores.ROS2_HUMBLE)
    store.register(get_types_from_msg('float64 force_n', 'brace_exotic_msgs/msg/Thing'))
    with Writer(tmp_path / 'exotic', version=9, storage_plugin=StoragePlugin.MCAP) as w:
        c = w.add_connection('/thing', 'brace_exotic_msgs/msg/Thing', typestore=store)
        w.write(c, 1, bytes(store.serialize_cdr(store.types['brace_exotic_msgs/msg/Thing'](force_n=1.0),
                                                'brace_exotic_msgs/msg/Thing')))
    with pytest.raises(BagError, match="'brace_exotic_msgs/msg/Thing' of topic /thing is not available"):
        replay(ros.node('player'), tmp_path / 'exotic')


def test_cli_errors_exit_1_with_message(tmp_path):
    r = subprocess.run([sys.executable, '-m', 'brace_control.bag', 'replay', str(tmp_path / 'x.mcap')],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 1 and 'does not exist' in r.stderr


def test_cli_info(tmp_path):
    write_bag(tmp_path / 'b', StoragePlugin.SQLITE3)
    info = bag_info(tmp_path / 'b')
    assert info['topics']['/brace/pose_goal'] == {'type': POSE_T, 'count': N}
    r = subprocess.run([sys.executable, '-m', 'brace_control.bag', 'info', str(tmp_path / 'b')],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and '/brace/pose_goal' in r.stdout


@pytest.mark.ros
@pytest.mark.parametrize('out_name', ['run.mcap', 'run_dir'])
def test_record_then_read_back(ros, tmp_path, out_name):
    pub_node = ros.node('talker')
    pub = pub_node.create_publisher(PoseStamped, '/brace/pose', RELIABLE_10)
    rec_node = ros.node('recorder')
    out = tmp_path / out_name
    recorder = Recorder(rec_node, out, ['/brace/pose']).start(period=0.02)
    ros.spin_until(lambda: not recorder.pending, what='recorder subscribed')
    ros.wait_matched(pub)
    for k in range(10):
        pub.publish(pose_msg([k * 1e-3, 0.39, 0.01 * k], frame_id='brace_base',
                             stamp=sec_to_stamp(k + 0.5)))
    ros.spin_until(lambda: recorder.counts['/brace/pose'] == 10, what='10 recorded')
    assert recorder.close() == out
    assert out.is_file() if out_name.endswith('.mcap') else (out / 'metadata.yaml').is_file()
    with Reader(out) as reader:
        (conn,) = reader.connections
        assert conn.msgtype == POSE_T and 'geometry_msgs/Pose' in conn.msgdef.data
        msgs = [STORE.deserialize_cdr(data, POSE_T) for _, _, data in reader.messages()]
        times = [t for _, t, _ in reader.messages()]
    assert [m.pose.position.x for m in msgs] == pytest.approx([k * 1e-3 for k in range(10)])
    assert [m.header.stamp.sec for m in msgs] == list(range(10))
    assert times == sorted(times)
    assert not list(tmp_path.glob('.brace-bag-*'))            # no temporary left behind


def test_record_refuses_to_overwrite(tmp_path):
    import rclpy
    from rclpy.context import Context
    ctx = Context()
    rclpy.init(context=ctx)
    try:
        node = rclpy.create_node('rec', context=ctx)
        (tmp_path / 'run.mcap').write_bytes(b'x')
        with pytest.raises(BagError, match='exists already'):
            Recorder(node, tmp_path / 'run.mcap', ['/a'])
        node.destroy_node()
    finally:
        rclpy.shutdown(context=ctx)


@pytest.mark.ros
@pytest.mark.slow
def test_cli_replay_into_cli_record(tmp_path):
    """`brace-bag replay` in one process, `brace-bag record` in another (env: conftest domain)."""
    bag = tmp_path / 'goals'
    payloads = write_bag(bag, StoragePlugin.SQLITE3, extra=False)
    out = tmp_path / 'rec.mcap'
    cmd = [sys.executable, '-m', 'brace_control.bag']
    rec = subprocess.Popen([*cmd, 'record', str(out), '--topics', '/brace/pose_goal', '--duration', '8'],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        play = subprocess.run([*cmd, 'replay', str(bag), '--rate', '2', '--wait-subscribers', '1',
                               '--delay', '1.0'],
                              capture_output=True, text=True, timeout=60)
        assert play.returncode == 0, play.stderr
        assert f'published {N} messages' in play.stderr
        rec.send_signal(2)                                   # Ctrl-C: the file is finished
        _, err = rec.communicate(timeout=30)
    finally:
        if rec.poll() is None:
            rec.kill()
    assert rec.returncode == 0, err
    with Reader(out) as reader:
        assert [bytes(d) for _, _, d in reader.messages()] == payloads


def test_recorder_without_messages_leaves_no_file(tmp_path):
    """A recording that holds no message is removed (both forms); nothing else is left."""
    import rclpy
    from rclpy.context import Context
    ctx = Context()
    rclpy.init(context=ctx)
    try:
        node = rclpy.create_node('rec', context=ctx)
        for name in ('quiet.mcap', 'quiet_dir'):
            rec = Recorder(node, tmp_path / name, ['/brace_test/quiet'])
            assert rec.close() == tmp_path / name
            assert not (tmp_path / name).exists()
        assert list(tmp_path.iterdir()) == []
        node.destroy_node()
    finally:
        rclpy.shutdown(context=ctx)


# ------------------------------------------------------------ bags from the real rosbag2

DATA = Path(__file__).resolve().parent / 'data' / 'rosbag2'
REAL = {'sqlite3': DATA / 'sqlite3_talker', 'mcap': DATA / 'mcap_talker'}
REAL_FORMS = [(storage, form) for storage in REAL for form in ('directory', 'file')]
#: test/data/rosbag2/README.md: what the two bags hold
REAL_COUNTS = {'/topic': 10, '/rosout': 10, '/parameter_events': 0}
REAL_TYPES = {'/topic': 'std_msgs/msg/String', '/rosout': 'rcl_interfaces/msg/Log',
              '/parameter_events': 'rcl_interfaces/msg/ParameterEvent'}
KEEP_ALL_RELIABLE = QoSProfile(history=HistoryPolicy.KEEP_ALL,
                               reliability=ReliabilityPolicy.RELIABLE)


def _real(storage: str, form: str) -> Path:
    d = REAL[storage]
    return d if form == 'directory' else d / f'talker.{"db3" if storage == "sqlite3" else "mcap"}'


def _stored(storage: str) -> dict[str, list[bytes]]:
    """Oracle: the bare storage file as rosbags' file reader reads it."""
    out: dict[str, list[bytes]] = {}
    with Reader(_real(storage, 'file')) as reader:
        for conn, _, data in reader.messages():
            out.setdefault(conn.topic, []).append(bytes(data))
    return out


def _run_replay(ros, player, bag, **kw):
    """``replay`` from a thread while the test spins its subscribers; returns the stats."""
    result: dict = {}

    def run():
        try:
            result['stats'] = replay(player, bag, **kw)
        except Exception as exc:  # noqa: BLE001
            result['error'] = exc

    th = threading.Thread(target=run)
    th.start()
    ros.spin_until(lambda: not th.is_alive(), timeout=60, what='replay')
    th.join()
    if 'error' in result:
        raise result['error']
    return result['stats']


@pytest.mark.parametrize('storage, form', REAL_FORMS)
def test_info_of_real_rosbag2_bags(storage, form):
    info = bag_info(_real(storage, form))
    assert info['messages'] == 20
    assert info['topics'] == {t: {'type': REAL_TYPES[t], 'count': n} for t, n in REAL_COUNTS.items()}
    assert info['duration_s'] == pytest.approx(4.531, abs=1e-3)
    assert info['version'] == (4 if form == 'directory' else None)
    assert info['warnings'] == []


@pytest.mark.parametrize('storage, form', REAL_FORMS)
def test_real_bag_reads_every_message_in_both_forms(storage, form):
    with open_bag(_real(storage, form)) as bag:
        got: dict[str, list[bytes]] = {}
        for topic, _, data in bag.messages():
            got.setdefault(topic, []).append(data)
    assert got == _stored(storage)
    assert [deserialize_message(m, String).data for m in got['/topic']] == \
        [f'Hello, world! {k}' for k in range(10)]


@pytest.mark.parametrize('storage', list(REAL))
def test_real_bag_qos_means_the_same_in_metadata_and_storage(storage):
    """The metadata says deadline {0, 0} (unspecified), the storage file Fast DDS's Foxy
    {2147483647, 4294967295} ("infinite"): both mean no deadline."""
    profiles = {}
    for form in ('directory', 'file'):
        with open_bag(_real(storage, form)) as bag:
            profiles[form] = {t: recorded_qos(bag.topics[t].offered_qos) for t in bag.topics}
    d, f = profiles['directory'], profiles['file']
    assert d['/topic'].deadline == Duration(nanoseconds=0) and f['/topic'].deadline == Infinite
    for topic in REAL_COUNTS:
        for key in ('history', 'depth', 'reliability', 'durability', 'liveliness'):
            assert getattr(d[topic], key) == getattr(f[topic], key), (topic, key)
    # /rosout: transient local with a 10 s lifespan, as rcl offers it
    assert d['/rosout'].durability == DurabilityPolicy.TRANSIENT_LOCAL
    assert d['/rosout'].lifespan == Duration(seconds=10) == f['/rosout'].lifespan
    assert d['/topic'].reliability == ReliabilityPolicy.RELIABLE
    assert d['/topic'].durability == DurabilityPolicy.VOLATILE


@pytest.mark.ros
@pytest.mark.parametrize('storage, form', REAL_FORMS)
def test_replay_of_real_bag_delivers_every_message(ros, storage, form):
    sub = ros.node('talker_listener')
    got = {'/topic': [], '/rosout': []}
    sub.create_subscription(String, '/topic', got['/topic'].append, KEEP_ALL_RELIABLE, raw=True)
    sub.create_subscription(Log, '/rosout', got['/rosout'].append, KEEP_ALL_RELIABLE, raw=True)
    stats = _run_replay(ros, ros.node('player'), _real(storage, form), rate=20.0,
                        wait_subscribers=1, wait_topics=['/topic', '/rosout'])
    want = _stored(storage)
    ros.spin_until(lambda: len(got['/topic']) == 10, what='10 /topic messages')
    assert got['/topic'] == want['/topic']
    # other nodes of this process may log to /rosout too: keep the bag's messages
    ros.spin_until(lambda: sum(m in want['/rosout'] for m in got['/rosout']) == 10,
                   what='10 /rosout messages')
    assert [m for m in got['/rosout'] if m in want['/rosout']] == want['/rosout']
    assert stats.published == REAL_COUNTS and stats.expected == REAL_COUNTS
    assert stats.ok, stats.problems
    assert stats.qos['/rosout'].durability == DurabilityPolicy.TRANSIENT_LOCAL


def _cli(*args: str, **kw) -> list[str]:
    return [sys.executable, '-m', 'brace_control.bag', *args]


def _spin_process(ros, proc, timeout: float = 60.0) -> tuple[str, str]:
    ros.spin_until(lambda: proc.poll() is not None, timeout=timeout, what=f'{proc.args[3:5]}')
    return proc.communicate(timeout=10)


@pytest.mark.ros
def test_cli_replay_of_real_bag_directory(ros):
    """The user's command: ``brace-bag replay sqlite3_talker`` published 0 and exited 0."""
    got: list[bytes] = []
    ros.node('listener').create_subscription(String, '/topic', got.append, KEEP_ALL_RELIABLE,
                                             raw=True)
    proc = subprocess.Popen(_cli('replay', str(REAL['sqlite3']), '--rate', '20',
                                 '--wait-for-subscribers', '1', '--wait-topics', '/topic'),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    _, err = _spin_process(ros, proc)
    assert proc.returncode == 0, err
    assert 'published 20 messages' in err and '(the bag lists 20)' in err
    ros.spin_until(lambda: len(got) == 10, what='10 /topic messages')
    assert [deserialize_message(m, String).data for m in got] == \
        [f'Hello, world! {k}' for k in range(10)]


# ------------------------------------------------------------------------- bursts

BURST = 5000


@pytest.mark.ros
def test_cli_replay_delivers_a_burst_whole(ros, tmp_path):
    """5000 messages stamped within one microsecond, replayed from another process into a
    reliable KEEP_ALL subscriber: every one arrives, in order, and the command says so."""
    t0 = 1_700_000_000_000_000_000
    stamps = [t0 + k * 1000 // BURST for k in range(BURST)]
    assert max(stamps) - min(stamps) < 1000                  # within 1 us
    payloads = [bytes(STORE.serialize_cdr(STORE.types['std_msgs/msg/String'](data=f'b{k:05d}'),
                                          'std_msgs/msg/String')) for k in range(BURST)]
    with Writer(tmp_path / 'burst', version=9, storage_plugin=StoragePlugin.MCAP) as w:
        c = w.add_connection('/brace_test/burst', 'std_msgs/msg/String', typestore=STORE)
        for t, data in zip(stamps, payloads):
            w.write(c, t, data)
    got: list[bytes] = []
    ros.node('burst_listener').create_subscription(String, '/brace_test/burst', got.append,
                                                   KEEP_ALL_RELIABLE, raw=True)
    proc = subprocess.Popen(_cli('replay', str(tmp_path / 'burst'), '--wait-for-subscribers', '1'),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    _, err = _spin_process(ros, proc)
    assert proc.returncode == 0, err
    assert f'published {BURST} messages' in err
    ros.spin_until(lambda: len(got) >= BURST, timeout=20, what=f'{BURST} messages')
    # across processes the middleware pads a payload to 4 bytes: compare the messages
    assert [deserialize_message(m, String).data for m in got] == [f'b{k:05d}' for k in range(BURST)]


@pytest.mark.ros
def test_cli_replay_without_the_awaited_subscriber_fails(tmp_path):
    proc = subprocess.run(_cli('replay', str(REAL['mcap']), '--topics', '/topic',
                               '--wait-for-subscribers', '1', '--wait-timeout', '0.5'),
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 1
    assert 'waited 0.5 s for 1 matched subscriber(s) per topic: /topic has 0' in proc.stderr
    assert 'published' not in proc.stderr


@pytest.mark.ros
@pytest.mark.parametrize('out_name', ['never.mcap', 'never_dir'])
def test_cli_record_of_a_topic_that_never_appears_exits_1(tmp_path, out_name):
    proc = subprocess.run(_cli('record', str(tmp_path / out_name), '--topics', '/brace_test/never',
                               '--duration', '0.5'), capture_output=True, text=True, timeout=60)
    assert proc.returncode == 1, proc.stderr
    assert "['/brace_test/never'] never appeared" in proc.stderr
    assert list(tmp_path.iterdir()) == []                   # no empty bag, no temporary


@pytest.mark.ros
@pytest.mark.slow
def test_replay_reports_a_subscriber_that_stops_acknowledging(ros, tmp_path):
    """A reliable subscriber in a process that is frozen (SIGSTOP) after discovery never
    acknowledges: the replay says which topic, within the ack timeout."""
    string = 'std_msgs/msg/String'
    with Writer(tmp_path / 'stall', version=9, storage_plugin=StoragePlugin.MCAP) as w:
        first = w.add_connection('/brace_test/first', string, typestore=STORE)
        late = w.add_connection('/brace_test/stalled', string, typestore=STORE)
        msg = bytes(STORE.serialize_cdr(STORE.types[string](data='x'), string))
        w.write(first, 1_000_000_000, msg)
        for k in range(3):                                   # 1.5 s after the first one
            w.write(late, 2_500_000_000 + k, msg)
    listener = subprocess.Popen([sys.executable, '-c', (
        'import rclpy, time\n'
        'from rclpy.qos import QoSProfile, HistoryPolicy, ReliabilityPolicy\n'
        'from std_msgs.msg import String\n'
        'rclpy.init(); n = rclpy.create_node("frozen")\n'
        'n.create_subscription(String, "/brace_test/stalled", lambda m: None, QoSProfile('
        'history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE))\n'
        'rclpy.spin(n)\n')])
    try:
        seen: list[bytes] = []
        ros.node('first_listener').create_subscription(String, '/brace_test/first', seen.append,
                                                       KEEP_ALL_RELIABLE, raw=True)
        result: dict = {}
        th = threading.Thread(target=lambda: result.setdefault('stats', replay(
            ros.node('player'), tmp_path / 'stall', wait_subscribers=1, wait_timeout=30.0,
            ack_timeout=1.0)))
        th.start()
        ros.spin_until(lambda: seen, timeout=40, what='the first message')
        os.kill(listener.pid, signal.SIGSTOP)                # before the stalled topic is due
        ros.spin_until(lambda: not th.is_alive(), timeout=20, what='replay')
        stats = result['stats']
    finally:
        os.kill(listener.pid, signal.SIGCONT)
        listener.kill()
        listener.wait(timeout=10)
    assert stats.published == {'/brace_test/first': 1, '/brace_test/stalled': 3}
    assert stats.unacknowledged == ['/brace_test/stalled']
    assert any('/brace_test/stalled: its subscribers did not acknowledge' in p
               for p in stats.problems)
    assert not stats.ok


# -------------------------------------------------------- counting what was delivered

def _edit_metadata(bag: Path, edit) -> None:
    """Apply ``edit(info_dict)`` to ``bag/metadata.yaml`` (as a person with an editor would)."""
    path = bag / 'metadata.yaml'
    doc = yaml.safe_load(path.read_text())
    edit(doc['rosbag2_bagfile_information'])
    path.write_text(yaml.safe_dump(doc, sort_keys=False))


def _topic_entry(info: dict, name: str) -> dict:
    return next(x for x in info['topics_with_message_count'] if x['topic_metadata']['name'] == name)


@pytest.mark.ros
def test_replay_reports_fewer_messages_than_the_bag_lists(ros, tmp_path):
    bag = tmp_path / 'goals'
    write_bag(bag, StoragePlugin.SQLITE3)

    def claim_more(info):
        _topic_entry(info, '/brace/pose_goal')['message_count'] = N + 2
        info['message_count'] += 2
    _edit_metadata(bag, claim_more)
    assert any(f'lists {N + 2} messages, the storage files index {N}' in w
               for w in bag_info(bag)['warnings'])
    stats = _run_replay(ros, ros.node('player'), bag, rate=8.0)
    assert stats.published == {'/brace/pose_goal': N, '/chatter': N}
    assert stats.problems == [f'/brace/pose_goal: published {N} of the {N + 2} messages the bag '
                              'lists (its storage holds other counts)']
    r = subprocess.run(_cli('replay', str(bag), '--rate', '8', '--delay', '0'),
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 1 and f'published {N} of the {N + 2}' in r.stderr


@pytest.mark.ros
def test_topic_filter_that_selects_no_message_is_a_problem(ros):
    stats = _run_replay(ros, ros.node('player'), REAL['mcap'], topics=['/parameter_events'])
    assert stats.total == 0
    assert stats.problems == ["nothing to replay: the topic filter ['/parameter_events'] "
                              'selects no message']
    with pytest.raises(BagError, match=r"topic\(s\) \['/nope'\] not in bag"):
        _run_replay(ros, ros.node('player2'), REAL['mcap'], topics=['/nope'])


@pytest.mark.ros
@pytest.mark.parametrize('change', ['drop', 'retype'])
def test_storage_connection_missing_from_metadata_is_said(ros, tmp_path, change):
    bag = tmp_path / 'goals'
    write_bag(bag, StoragePlugin.MCAP)

    def edit(info):
        entry = _topic_entry(info, '/chatter')
        if change == 'drop':
            info['topics_with_message_count'].remove(entry)
            info['message_count'] -= N
        else:
            entry['topic_metadata']['type'] = 'std_msgs/msg/Int32'
    _edit_metadata(bag, edit)
    said = ('metadata.yaml lacks it' if change == 'drop'
            else 'metadata.yaml lists it as std_msgs/msg/Int32')
    assert any(said in w and f'holds {N} message(s) of /chatter' in w
               for w in bag_info(bag)['warnings'])
    with pytest.raises(BagError, match=said):
        replay(ros.node('player'), bag)
    # leaving the topic out replays the rest
    stats = _run_replay(ros, ros.node('player2'), bag, topics=['/brace/pose_goal'], rate=8.0)
    assert stats.published == {'/brace/pose_goal': N} and stats.ok


# --------------------------------------------------------- metadata versions, split bags

QOS_T = Qos(QosHistory.KEEP_LAST, 7, QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL,
            QosTime(2147483647, 4294967295),      # deadline: Fast DDS's Foxy "infinite"
            QosTime(2, 500_000_000),              # lifespan 2.5 s
            QosLiveliness.AUTOMATIC, QosTime(0, 0), False)


def _write_versioned(path: Path, storage: StoragePlugin, version: int,
                     ks: range = range(N)) -> list[tuple[str, int, bytes]]:
    """A bag of metadata ``version``: rosbags writes 8 and 9; older versions drop the
    fields rosbag2 introduced after them (rosbag2_storage/yaml.hpp reads ``files`` from
    5, ``custom_data`` from 6, ``type_description_hash`` from 7, ``ros_distro`` from 8)."""
    written = []
    with Writer(path, version=9 if version >= 9 else 8, storage_plugin=storage) as w:
        c = w.add_connection('/brace/pose_goal', POSE_T, typestore=STORE,
                             offered_qos_profiles=[QOS_T])
        s = w.add_connection('/chatter', 'std_msgs/msg/String', typestore=STORE)
        for k in ks:
            t = 1_000_000_000 + k * SPACING_NS
            for conn, topic, data in ((c, '/brace/pose_goal', _pose_cdr(k)), (s, '/chatter', bytes(
                    STORE.serialize_cdr(STORE.types['std_msgs/msg/String'](data=f'm{k}'),
                                        'std_msgs/msg/String')))):
                w.write(conn, t, data)
                written.append((topic, t, data))
                t += 1

    def older(info):
        info['version'] = version
        for key, since in (('ros_distro', 8), ('custom_data', 6), ('files', 5)):
            if version < since:
                info.pop(key, None)
        if version < 7:
            for x in info['topics_with_message_count']:
                x['topic_metadata'].pop('type_description_hash', None)
    if version < 8:
        _edit_metadata(path, older)
    return written


@pytest.mark.parametrize('storage', [StoragePlugin.SQLITE3, StoragePlugin.MCAP], ids=['sqlite3', 'mcap'])
@pytest.mark.parametrize('version', [4, 5, 6, 7, 8, 9])
def test_reader_of_metadata_versions_4_to_9(tmp_path, storage, version):
    written = _write_versioned(tmp_path / 'bag', storage, version)
    text = (tmp_path / 'bag' / 'metadata.yaml').read_text()
    assert f'version: {version}' in text
    assert ('offered_qos_profiles: "' in text or "offered_qos_profiles: '" in text) == (version < 9)
    with open_bag(tmp_path / 'bag') as bag:
        assert bag.version == version
        assert {t.name: t.count for t in bag.topics.values()} == {'/brace/pose_goal': N,
                                                                  '/chatter': N}
        assert list(bag.messages()) == written
        qos = recorded_qos(bag.topics['/brace/pose_goal'].offered_qos)
        assert bag.warnings == []
    assert (qos.history, qos.depth) == (HistoryPolicy.KEEP_LAST, 7)   # transient local: as recorded
    assert qos.reliability == ReliabilityPolicy.RELIABLE
    assert qos.durability == DurabilityPolicy.TRANSIENT_LOCAL
    assert qos.deadline == Infinite
    assert qos.lifespan == Duration(seconds=2.5)


@pytest.mark.parametrize('storage, ext', [(StoragePlugin.SQLITE3, 'db3'), (StoragePlugin.MCAP, 'mcap')],
                         ids=['sqlite3', 'mcap'])
def test_split_bag_reads_its_files_in_order(tmp_path, storage, ext):
    """rosbags writes one file per bag; a split bag (ros2 bag record --max-bag-size) is two
    storage files in one directory, listed in metadata.yaml in recording order."""
    first = _write_versioned(tmp_path / 'a', storage, 9, range(0, 4))
    second = _write_versioned(tmp_path / 'b', storage, 9, range(4, 10))
    split = tmp_path / 'split'
    split.mkdir()
    (tmp_path / 'a' / f'a.{ext}').rename(split / f'split_0.{ext}')
    (tmp_path / 'b' / f'b.{ext}').rename(split / f'split_1.{ext}')
    info_a = yaml.safe_load((tmp_path / 'a' / 'metadata.yaml').read_text())
    info_b = yaml.safe_load((tmp_path / 'b' / 'metadata.yaml').read_text())
    a, b = info_a['rosbag2_bagfile_information'], info_b['rosbag2_bagfile_information']
    a['relative_file_paths'] = [f'split_0.{ext}', f'split_1.{ext}']
    a['files'] = [dict(a['files'][0], path=f'split_0.{ext}'), dict(b['files'][0], path=f'split_1.{ext}')]
    a['message_count'] += b['message_count']
    a['duration']['nanoseconds'] = (b['starting_time']['nanoseconds_since_epoch']
                                    + b['duration']['nanoseconds']
                                    - a['starting_time']['nanoseconds_since_epoch'])
    for x, y in zip(a['topics_with_message_count'], b['topics_with_message_count']):
        x['message_count'] += y['message_count']
    (split / 'metadata.yaml').write_text(yaml.safe_dump(info_a, sort_keys=False))
    with open_bag(split) as bag:
        assert [f.name for f in bag.files] == [f'split_0.{ext}', f'split_1.{ext}']
        assert bag.message_count == 20 and bag.warnings == []
        assert list(bag.messages()) == first + second
        assert list(bag.messages(['/chatter'])) == [m for m in first + second if m[0] == '/chatter']
    # a storage file the metadata does not list is said, not replayed
    (tmp_path / 'c.tmp').write_bytes((split / f'split_1.{ext}').read_bytes())
    (tmp_path / 'c.tmp').rename(split / f'split_2.{ext}')
    assert any(f"['split_2.{ext}']" in w and 'not listed' in w for w in bag_info(split)['warnings'])
    (split / f'split_1.{ext}').unlink()
    with pytest.raises(BagError, match=rf"\['split_1.{ext}'\] listed in .* are missing"):
        open_bag(split)


@pytest.mark.parametrize('mode', [CompressionMode.FILE, CompressionMode.MESSAGE], ids=['file', 'message'])
def test_zstd_compressed_bags(tmp_path, mode):
    payloads = []
    w = Writer(tmp_path / 'z', version=9, storage_plugin=StoragePlugin.MCAP)
    w.set_compression(mode, CompressionFormat.ZSTD)
    with w:
        c = w.add_connection('/brace/pose_goal', POSE_T, typestore=STORE)
        for k in range(N):
            payloads.append(_pose_cdr(k))
            w.write(c, 1_000_000_000 + k * SPACING_NS, payloads[-1])
    with open_bag(tmp_path / 'z') as bag:
        assert [d for _, _, d in bag.messages()] == payloads


def test_metadata_newer_than_version_9_is_a_clear_error(tmp_path):
    write_bag(tmp_path / 'b', StoragePlugin.MCAP)
    _edit_metadata(tmp_path / 'b', lambda info: info.update(version=10))
    with pytest.raises(BagError, match='metadata version 10 is newer than this reader knows'):
        open_bag(tmp_path / 'b')


# ------------------------------------------------------------------------------- QoS

def _offer(reliability=QosReliability.RELIABLE, durability=QosDurability.VOLATILE,
           history=QosHistory.UNKNOWN, depth=0, deadline=(0, 0), lifespan=(0, 0),
           liveliness=QosLiveliness.AUTOMATIC, lease=(0, 0)) -> Qos:
    return Qos(history, depth, reliability, durability, QosTime(*deadline), QosTime(*lifespan),
               liveliness, QosTime(*lease), False)


@pytest.mark.parametrize('sec, nsec, ns', [
    (0, 0, 0),                                   # unspecified: the RMW default
    (1, 500_000_000, 1_500_000_000),
    (2147483647, 4294967295, None),              # Fast DDS (Foxy) and DDS DURATION_INFINITE
    (2147483647, 2147483647, None),              # Connext (Foxy)
    (9223372036, 854775807, None),               # RMW_DURATION_INFINITE, Cyclone (Foxy)
])
def test_recorded_durations_and_infinite_sentinels(sec, nsec, ns):
    qos = recorded_qos([_offer(deadline=(sec, nsec), lifespan=(sec, nsec), lease=(sec, nsec))])
    want = Infinite if ns is None else Duration(nanoseconds=ns)
    assert qos.deadline == want and qos.lifespan == want and qos.liveliness_lease_duration == want


@pytest.mark.parametrize('sec, nsec, match', [(1, 1_000_000_000, 'nsec must be below 1e9'),
                                              (-1, 0, 'not negative')])
def test_invalid_recorded_duration_is_a_clear_error(sec, nsec, match):
    with pytest.raises(BagError, match=f'QoS deadline of topic /t is .*{match}'):
        recorded_qos([_offer(deadline=(sec, nsec))], topic='/t')


def test_recorded_history_and_depth():
    unknown = recorded_qos([_offer()])                                    # what ros2 bag record sees
    assert (unknown.history, unknown.depth) == (HistoryPolicy.KEEP_LAST, DEFAULT_DEPTH)
    latched = recorded_qos([_offer(durability=QosDurability.TRANSIENT_LOCAL,
                                   history=QosHistory.KEEP_LAST, depth=1)])
    assert (latched.history, latched.depth) == (HistoryPolicy.KEEP_LAST, 1)
    volatile = recorded_qos([_offer(history=QosHistory.KEEP_LAST, depth=1)])
    assert volatile.depth == DEFAULT_DEPTH
    assert recorded_qos([_offer(history=QosHistory.KEEP_ALL)]).history == HistoryPolicy.KEEP_ALL
    best = recorded_qos([_offer(reliability=QosReliability.BEST_EFFORT)])
    assert best.reliability == ReliabilityPolicy.BEST_EFFORT
    none = recorded_qos([])                                              # a bag without QoS
    assert (none.reliability, none.durability, none.depth) == (
        ReliabilityPolicy.RELIABLE, DurabilityPolicy.VOLATILE, DEFAULT_DEPTH)


def _request_like(offer: Qos) -> QoSProfile:
    """The strictest subscription that ``offer`` satisfies (what it matched when recorded)."""
    return QoSProfile(
        depth=10, reliability=ReliabilityPolicy[offer.reliability.name],
        durability=DurabilityPolicy[offer.durability.name],
        deadline=Duration(seconds=offer.deadline.sec, nanoseconds=offer.deadline.nsec),
        liveliness=LivelinessPolicy[offer.liveliness.name],
        liveliness_lease_duration=Duration(seconds=offer.liveliness_lease_duration.sec,
                                           nanoseconds=offer.liveliness_lease_duration.nsec))


def test_several_recorded_offers_merge_into_one_that_every_old_subscriber_matches():
    offers = [
        _offer(reliability=QosReliability.BEST_EFFORT, deadline=(1, 0), lease=(3, 0)),
        _offer(durability=QosDurability.TRANSIENT_LOCAL, deadline=(0, 500_000_000)),
        _offer(liveliness=QosLiveliness.MANUAL_BY_TOPIC, lease=(2, 0), lifespan=(4, 0)),
    ]
    merged = recorded_qos(offers)
    for offer in offers:
        request = _request_like(offer)
        original = recorded_qos([offer])
        assert qos_check_compatible(original, request)[0] != QoSCompatibility.ERROR
        assert qos_check_compatible(merged, request)[0] != QoSCompatibility.ERROR, (offer, merged)
    assert merged.lifespan == Duration(nanoseconds=0)      # two offers kept messages forever


def test_qos_overrides_replace_only_the_named_policies(tmp_path):
    base = recorded_qos([_offer(durability=QosDurability.TRANSIENT_LOCAL,
                                history=QosHistory.KEEP_LAST, depth=5, deadline=(1, 0))])
    new = qos_with_overrides(base, {'reliability': 'best_effort', 'lifespan': {'sec': 3, 'nsec': 0}})
    assert new.reliability == ReliabilityPolicy.BEST_EFFORT
    assert new.lifespan == Duration(seconds=3)
    for key in ('history', 'depth', 'durability', 'deadline', 'liveliness'):
        assert getattr(new, key) == getattr(base, key), key
    with pytest.raises(BagError, match=r"unknown policy \['reliablity'\]"):
        qos_with_overrides(base, {'reliablity': 'reliable'}, topic='/a')
    with pytest.raises(BagError, match="durability: 'sticky' is not one of"):
        qos_with_overrides(base, {'durability': 'sticky'})
    with pytest.raises(BagError, match='depth 0 is not a positive integer'):
        qos_with_overrides(base, {'depth': 0})
    path = tmp_path / 'qos.yaml'
    path.write_text('/a:\n  reliability: best_effort\n  deadline: {sec: 1, nsec: 0}\n')
    assert load_qos_overrides(path) == {'/a': {'reliability': 'best_effort',
                                               'deadline': {'sec': 1, 'nsec': 0}}}
    path.write_text('- reliability: best_effort\n')
    with pytest.raises(BagError, match='expected a mapping of topic names'):
        load_qos_overrides(path)


@pytest.mark.ros
def test_replay_with_a_qos_override(ros):
    got: list[bytes] = []
    best_effort = QoSProfile(history=HistoryPolicy.KEEP_ALL,
                             reliability=ReliabilityPolicy.BEST_EFFORT)
    ros.node('be_listener').create_subscription(String, '/topic', got.append, best_effort, raw=True)
    stats = _run_replay(ros, ros.node('player'), REAL['sqlite3'], topics=['/topic'], rate=20.0,
                        wait_subscribers=1, qos_overrides={'/topic': {'reliability': 'best_effort'}})
    assert stats.qos['/topic'].reliability == ReliabilityPolicy.BEST_EFFORT
    assert any('/topic is best effort' in w for w in stats.warnings)
    ros.spin_until(lambda: len(got) == 10, what='10 best-effort messages (same process)')
    assert got == _stored('sqlite3')['/topic']
    with pytest.raises(BagError, match=r"QoS override\(s\) for \['/nope'\]"):
        replay(ros.node('player2'), REAL['sqlite3'], qos_overrides={'/nope': {'depth': 1}})


# ------------------------------------------------------------------ layouts of a sweep (session 14)

def _metadata(bag: Path) -> dict:
    return yaml.safe_load((bag / 'metadata.yaml').read_text())


def _set_metadata(bag: Path, doc: dict) -> None:
    (bag / 'metadata.yaml').write_text(yaml.safe_dump(doc, sort_keys=False))


def test_a_file_compressed_storage_that_is_not_zstd_is_a_clear_error(tmp_path):
    """``compression_mode: FILE`` (zstd) over a storage file that is not zstd: a BagError
    naming the file (it was a zstd traceback), and the command exits 1 without one."""
    bag = tmp_path / 'fake_zstd'
    write_bag(bag, StoragePlugin.SQLITE3)
    doc = _metadata(bag)
    info = doc['rosbag2_bagfile_information']
    db3 = next(bag.glob('*.db3'))
    db3.rename(db3.with_name(db3.name + '.zstd'))
    info['compression_mode'], info['compression_format'] = 'FILE', 'zstd'
    info['relative_file_paths'] = [db3.name + '.zstd']
    for f in info.get('files', []):
        f['path'] = db3.name + '.zstd'
    _set_metadata(bag, doc)
    with pytest.raises(BagError, match=r'does not decompress as zstd'):
        open_bag(bag)
    r = subprocess.run([sys.executable, '-m', 'brace_control.bag', 'info', str(bag)],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 1 and 'does not decompress as zstd' in r.stderr and 'Traceback' not in r.stderr


def test_a_db3_with_messages_left_in_its_write_ahead_log_is_refused(tmp_path):
    """rosbag2's 'resilient' storage preset journals the .db3 in WAL mode: a recorder that did
    not close leaves its last messages in ``<file>-wal``, which a read-only open of the .db3
    alone never sees. The replay refuses it, saying how to merge them (a silent loss of the
    bag's end before)."""
    import shutil
    import sqlite3
    bag = tmp_path / 'wal'
    write_bag(bag, StoragePlugin.SQLITE3)
    db3 = next(bag.glob('*.db3'))
    work = tmp_path / 'work.db3'
    shutil.copy(db3, work)
    con = sqlite3.connect(work, isolation_level=None)
    con.execute('PRAGMA journal_mode=WAL')
    con.execute('PRAGMA wal_autocheckpoint=0')
    con.execute('INSERT INTO messages (topic_id, timestamp, data) '
                'SELECT topic_id, timestamp + 1000000000, data FROM messages')
    shutil.copy(work, db3)
    shutil.copy(f'{work}-wal', f'{db3}-wal')                 # while the writer still holds it
    con.close()
    assert Path(f'{db3}-wal').stat().st_size > 0
    with pytest.raises(BagError, match=r'-wal.*wal_checkpoint'):
        with open_bag(bag) as b:
            list(b.messages(b.topics))


def test_service_and_old_style_type_names_resolve_to_their_classes():
    """rosbag2 records service events (``pkg/srv/Name_Event``, Jazzy and later) and old bags
    name types ``pkg/Name``: both resolve to the Python classes rclpy publishes."""
    from std_srvs.srv import SetBool
    assert message_class('std_srvs/srv/SetBool_Event') is SetBool.Event
    assert message_class('std_msgs/String') is String
    with pytest.raises(BagError, match='not a ROS 2 message type name'):
        message_class('std_msgs/thing/String')


@pytest.mark.ros
def test_a_topic_of_a_type_not_installed_without_messages_is_skipped_with_a_warning(ros, tmp_path):
    """``ros2 bag record -a`` records ``/events/write_split`` (rosbag2_interfaces, not on PyPI)
    with no message: the replay skips it with a warning, as rosbag2 does, and replays the
    rest (it refused the whole bag before). A type not installed that does hold messages is
    still an error (test_message_type_this_python_lacks_is_a_clear_error)."""
    store = get_typestore(Stores.ROS2_HUMBLE)            # knows rosbag2_interfaces' types
    bag = tmp_path / 'with_events'
    payloads = [_pose_cdr(k) for k in range(N)]
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        c = w.add_connection('/brace/pose_goal', POSE_T, typestore=STORE)
        w.add_connection('/events/write_split', 'rosbag2_interfaces/msg/WriteSplitEvent', typestore=store)
        for k, data in enumerate(payloads):
            w.write(c, 1_000_000_000 + k * SPACING_NS, data)
    stats, raw, _, _ = _replay_into(ros, bag)
    assert [bytes(m) for m in raw] == payloads
    assert not stats.problems, stats.problems
    assert any('/events/write_split' in w and 'no publisher' in w for w in stats.warnings), stats.warnings


@pytest.mark.ros
def test_metadata_counts_that_are_not_the_storage_s_are_problems_and_every_message_is_replayed(ros, tmp_path):
    """metadata.yaml listing 0 messages per topic while the storage holds them: every stored
    message is replayed (the wait for subscribers too: it waited for none) and each topic's
    difference is a problem, not "nothing to replay". A total that is not the sum of the
    topics' counts is a problem as well."""
    bag = tmp_path / 'zero_counts'
    payloads = write_bag(bag, StoragePlugin.SQLITE3)
    doc = _metadata(bag)
    for t in doc['rosbag2_bagfile_information']['topics_with_message_count']:
        t['message_count'] = 0
    doc['rosbag2_bagfile_information']['message_count'] = 0
    _set_metadata(bag, doc)
    stats, raw, _, _ = _replay_into(ros, bag)
    assert [bytes(m) for m in raw] == payloads
    assert not any('nothing to replay' in p for p in stats.problems), stats.problems
    assert any('/brace/pose_goal' in p and f'published {N} of the 0' in p for p in stats.problems), stats.problems
    total = tmp_path / 'wrong_total'
    write_bag(total, StoragePlugin.MCAP)
    doc = _metadata(total)
    doc['rosbag2_bagfile_information']['message_count'] = 0
    _set_metadata(total, doc)
    stats, _, _, _ = _replay_into(ros, total)
    assert any('lists 0 messages in all' in p for p in stats.problems), stats.problems
