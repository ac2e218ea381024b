"""brace-bag: replay rosbag2 bags (sqlite3, mcap) into the graph; record topics to mcap.

Bags are written at test time with ``rosbags`` (its own CDR serializer, independent of
rclpy), replayed into a real subscriber, and recordings read back with ``rosbags``.
"""
from __future__ import annotations

import subprocess
import sys
import threading
import time

import pytest
from geometry_msgs.msg import PoseStamped
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from brace_control.bag import BagError, Recorder, bag_info, open_bag, replay
from brace_control.nodes.msgs import pose_msg, sec_to_stamp
from ros_helpers import RELIABLE_10, ros  # noqa: F401

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


def _replay_into(ros, bag, **kw):  # noqa: F811
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
def test_replay_publishes_recorded_bytes_unchanged(ros, tmp_path, storage, version):  # noqa: F811
    bag = tmp_path / 'goals'
    payloads = write_bag(bag, storage, version=version)
    stats, raw, parsed, _ = _replay_into(ros, bag)
    assert raw == payloads                                    # CDR bytes unchanged, in order
    assert [m.pose.position.x for m in parsed] == pytest.approx([k * 1e-3 for k in range(N)])
    assert [m.header.stamp.sec for m in parsed] == list(range(N))   # stamps as recorded
    assert stats.published == {'/brace/pose_goal': N, '/chatter': N}


@pytest.mark.ros
def test_replay_keeps_timing_scaled_by_rate_and_filters_topics(ros, tmp_path):  # noqa: F811
    bag = tmp_path / 'goals'
    write_bag(bag, StoragePlugin.MCAP)
    stats, *_ = _replay_into(ros, bag, rate=0.5, topics=['/brace/pose_goal'])
    recorded_span = (N - 1) * SPACING_NS * 1e-9
    assert stats.published == {'/brace/pose_goal': N}
    assert recorded_span / 0.5 <= stats.duration_s < recorded_span / 0.5 + 0.15


@pytest.mark.ros
def test_replay_of_a_single_mcap_file(ros, tmp_path):  # noqa: F811
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
def test_message_type_this_python_lacks_is_a_clear_error(ros, tmp_path):  # noqa: F811
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
def test_record_then_read_back(ros, tmp_path, out_name):  # noqa: F811
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
