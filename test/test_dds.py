"""brace_control's Fast DDS profiles (brace_control.dds): who sets them, and that Fast DDS
reads the packaged file.

A service server drops its answer when the caller's response reader is not matched within
the response writer's ``max_blocking_time`` (rmw_fastrtps ``rmw_send_response``); Fast
DDS's default is 100 ms (eProsima Fast DDS documentation, ReliabilityQosPolicy). The
packaged profile must give longer.
"""
from __future__ import annotations

import os
import subprocess
import sys
import xml.etree.ElementTree as ET

import pytest

from brace_control.dds import PROFILES_FILE, use_packaged_profiles

FAST_DDS_DEFAULT_MAX_BLOCKING_S = 0.1      # Fast DDS documentation, ReliabilityQosPolicy
NS = {'d': 'http://www.eprosima.com'}


def test_the_packaged_default_writer_waits_longer_than_fast_dds_default():
    root = ET.parse(PROFILES_FILE).getroot()
    writers = root.findall('d:profiles/d:data_writer', NS)
    assert [w.get('is_default_profile') for w in writers] == ['true']
    mbt = writers[0].find('d:qos/d:reliability/d:max_blocking_time', NS)
    seconds = int(mbt.find('d:sec', NS).text) + int(mbt.find('d:nanosec', NS).text) * 1e-9
    assert seconds >= 10 * FAST_DDS_DEFAULT_MAX_BLOCKING_S
    # nothing else: every other QoS stays the node's own
    assert [e.tag.split('}')[1] for e in writers[0].iter()] == [
        'data_writer', 'qos', 'reliability', 'max_blocking_time', 'sec', 'nanosec']


@pytest.mark.parametrize('distro, expected', [
    (None, {'FASTDDS_DEFAULT_PROFILES_FILE'}),
    ('kilted', {'FASTDDS_DEFAULT_PROFILES_FILE'}),
    ('jazzy', {'FASTDDS_DEFAULT_PROFILES_FILE', 'FASTRTPS_DEFAULT_PROFILES_FILE'}),
    ('humble', {'FASTDDS_DEFAULT_PROFILES_FILE', 'FASTRTPS_DEFAULT_PROFILES_FILE'}),
])
def test_profiles_are_set_for_the_fast_dds_of_the_distribution(distro, expected):
    env = {} if distro is None else {'ROS_DISTRO': distro}
    assert use_packaged_profiles(env)
    assert {k for k in env if k != 'ROS_DISTRO'} == expected
    assert all(env[k] == str(PROFILES_FILE) for k in expected)


@pytest.mark.parametrize('variable', ['FASTDDS_DEFAULT_PROFILES_FILE', 'FASTRTPS_DEFAULT_PROFILES_FILE'])
def test_a_users_own_profiles_file_is_left_alone(variable):
    env = {variable: '/etc/my_lab/fastdds.xml', 'ROS_DISTRO': 'jazzy'}
    assert not use_packaged_profiles(env)
    assert env == {variable: '/etc/my_lab/fastdds.xml', 'ROS_DISTRO': 'jazzy'}


def _start_a_node(profiles: str) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if 'PROFILES_FILE' not in k}
    env['FASTDDS_DEFAULT_PROFILES_FILE'] = profiles
    code = ('import rclpy; rclpy.init(); n = rclpy.create_node("dds_profiles_probe"); '
            'n.create_service(__import__("std_srvs.srv", fromlist=["Trigger"]).Trigger, "t", '
            'lambda q, r: r); n.destroy_node(); rclpy.shutdown(); print("up")')
    return subprocess.run([sys.executable, '-c', code], env=env, capture_output=True, text=True,
                          timeout=60)


@pytest.mark.ros
def test_fast_dds_reads_the_packaged_file_without_complaint(tmp_path):
    r = _start_a_node(str(PROFILES_FILE))
    assert r.returncode == 0 and r.stdout.strip() == 'up', r.stderr
    assert 'XMLPARSER' not in r.stderr and 'Error' not in r.stderr, r.stderr
    # the same check sees a file Fast DDS cannot read: the variable reaches Fast DDS
    broken = tmp_path / 'broken.xml'
    broken.write_text(PROFILES_FILE.read_text().replace('<sec>', '<seconds>').replace('</sec>', '</seconds>'))
    r = _start_a_node(str(broken))
    assert 'XMLPARSER' in r.stderr, r.stderr
