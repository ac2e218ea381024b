"""One schema for every device parameter (brace_control/schema.py).

Oracles: the key names and values are read from the bundled YAML files themselves with plain
PyYAML (never from the schema); physically impossible values (a negative force limit, a
CANopen node id outside CiA 301's 1..127, a saturation beyond full scale) must be refused.
"""
from __future__ import annotations

import copy
import functools
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from brace_control.can.state import MasterConfig
from brace_control.can.supervision import Limits as CanLimits
from brace_control.can.units import scaling_from_config
from brace_control.config import ConfigError, DeviceConfig, load_device_config
from brace_control.mechanisms import MECHANISM_TYPES, Rpr3, mechanism_from_config
from brace_control.schema import MECHANISM_SCHEMAS, SCHEMA
from brace_control.trajectory import Limits as TrajectoryLimits

REPO = Path(__file__).resolve().parent.parent
CONFIGS = sorted((REPO / 'config').glob('*.yaml'))
LUMBAR = REPO / 'config' / 'lumbar_brace.yaml'


@functools.lru_cache(maxsize=None)
def _parsed(path: Path) -> dict[str, Any]:
    return yaml.safe_load(path.read_text())['/**']['ros__parameters']


def raw_params(path: Path) -> dict[str, Any]:
    """The ``ros__parameters`` of a device file, read with plain PyYAML (the oracle); each
    file parsed once, every caller given its own copy."""
    return copy.deepcopy(_parsed(path))


def leaf_keys(params: dict[str, Any], prefix: tuple[str, ...] = ()) -> list[tuple[str, ...]]:
    out: list[tuple[str, ...]] = []
    for key, value in params.items():
        if isinstance(value, dict):
            out += leaf_keys(value, prefix + (key,))
        else:
            out.append(prefix + (key,))
    return out


def misspell(word: str) -> str:
    """One character dropped (``force_limit`` -> ``force_limt``)."""
    i = max(1, len(word) - 2)
    return word[:i] + word[i + 1:]


def write(tmp_path: Path, params: dict[str, Any], name: str = 'device.yaml') -> Path:
    """The parameters as a device file in ``tmp_path``; the EDS it names stays the package's
    (files are relative to the YAML's own directory)."""
    eds = params.get('can', {}).get('eds') if isinstance(params.get('can'), dict) else None
    if isinstance(eds, str) and eds and not Path(eds).is_absolute():
        params = {**params, 'can': {**params['can'], 'eds': str(REPO / 'config' / eds)}}
    path = tmp_path / name
    path.write_text(yaml.safe_dump({'/**': {'ros__parameters': params}}, sort_keys=False))
    return path


def set_key(params: dict[str, Any], path: tuple[str, ...], value: Any) -> None:
    node = params
    for k in path[:-1]:
        node = node[k]
    node[path[-1]] = value


def rename_key(params: dict[str, Any], path: tuple[str, ...], new: str) -> None:
    node = params
    for k in path[:-1]:
        node = node[k]
    node[new] = node.pop(path[-1])


CASES = [(cfg, key) for cfg in CONFIGS for key in leaf_keys(raw_params(cfg))]


# ---------------------------------------------------------------------------- bundled files
@pytest.mark.parametrize('path', CONFIGS, ids=lambda p: p.stem)
def test_every_bundled_config_loads_unchanged(path):
    cfg = load_device_config(path)
    raw = raw_params(path)
    for key in leaf_keys(raw):
        value = cfg.get_path('.'.join(key))
        expected = raw
        for k in key:
            expected = expected[k]
        assert value == expected, key
    mechanism_from_config(cfg)
    if 'can' in raw:
        MasterConfig.from_device_config(cfg, channel='unused')


def test_every_mechanism_type_has_a_key_set():
    assert set(MECHANISM_SCHEMAS) == set(MECHANISM_TYPES)


@pytest.mark.parametrize('path, key', CASES, ids=[f'{c.stem}:{".".join(k)}' for c, k in CASES])
def test_a_misspelled_key_is_named_with_the_right_one(tmp_path, path, key):
    params = raw_params(path)
    wrong = misspell(key[-1])
    rename_key(params, key, wrong)
    bad = '.'.join(key[:-1] + (wrong,))
    right = '.'.join(key)
    file = write(tmp_path, params)
    with pytest.raises(ConfigError) as err:
        load_device_config(file)
    msg = str(err.value)
    assert f"unknown parameter '{bad}' in {file}" in msg, msg
    assert f"did you mean '{right}'?" in msg, msg


@pytest.mark.parametrize('path', CONFIGS, ids=lambda p: p.stem)
def test_a_misspelled_section_is_named(tmp_path, path):
    """Every section of the file, misspelled: the error names one of its keys and the section."""
    raw = raw_params(path)
    for section in (k for k, v in raw.items() if isinstance(v, dict)):
        params = copy.deepcopy(raw)
        wrong = misspell(section)
        params[wrong] = params.pop(section)
        with pytest.raises(ConfigError, match=rf"unknown parameter '{wrong}\..*did you mean '{section}\."):
            load_device_config(write(tmp_path, params))


def test_the_issues_examples(tmp_path):
    """issue 13: three misspellings that used to leave the default in force."""
    for section, wrong, right, value in (('actuator', 'max_velocty', 'max_velocity', 0.065),
                                         ('can', 'heartbeat_consumer_mss', 'heartbeat_consumer_ms', 150),
                                         ('safety', 'force_limt', 'force_limit', 100.0)):
        params = raw_params(LUMBAR)
        del params[section][right]
        params[section][wrong] = value
        file = write(tmp_path, params, 'x.yaml')
        with pytest.raises(ConfigError) as err:
            load_device_config(file)
        assert str(err.value) == (f"unknown parameter '{section}.{wrong}' in {file}; "
                                  f"did you mean '{section}.{right}'?")


def test_a_key_of_another_mechanism_type_is_unknown(tmp_path):
    params = raw_params(LUMBAR)
    params['mechanism']['link_lengths'] = [0.15, 0.12]          # rr2's, not rpr3's
    with pytest.raises(ConfigError, match=r"unknown parameter 'mechanism.link_lengths'.*'rpr3'"):
        load_device_config(write(tmp_path, params))


# ---------------------------------------------------------------------------- values
@pytest.mark.parametrize('key, value, words', [
    (('safety', 'force_limit'), -100.0, ['out of range', 'N']),
    (('can', 'master_node_id'), 200, ['out of range', '1 to 127']),          # CiA 301 node ids
    (('can', 'node_ids'), [1, 2, 128], ['out of range', '1 to 127']),
    (('safety', 'saturation_fraction'), 1.5, ['out of range']),              # beyond full scale
    (('actuator', 'max_velocity'), 0.0, ['out of range', 'm/s']),
    (('trajectory', 'rate_hz'), 0.0, ['out of range', 'Hz']),
    (('can', 'sync_rate_hz'), -500.0, ['out of range', 'Hz']),
    (('trajectory', 'max_velocity'), [0.03, -0.03, 0.3], ['out of range']),
    (('mechanism', 'stroke_min'), -0.1, ['out of range', 'm']),
    (('trajectory', 'profile'), 'linear', ['minimum_jerk']),
    (('safety', 'force_limit'), 'high', ['wrong type', 'float']),
    (('safety', 'force_limit'), 100, ['wrong type', '100.0']),                # ROS: typed
    (('can', 'bitrate'), 1e6, ['wrong type', 'integer']),
    (('sim', 'load_cell_noise'), float('nan'), ['non-finite']),
])
def test_a_bad_value_names_the_key_the_value_and_what_was_expected(tmp_path, key, value, words):
    params = raw_params(LUMBAR)
    set_key(params, key, value)
    with pytest.raises(ConfigError) as err:
        load_device_config(write(tmp_path, params))
    msg = str(err.value)
    assert f"parameter '{'.'.join(key)}' = {value!r}" in msg, msg
    for w in words:
        assert w in msg, msg


def test_ros_style_floats_are_floats(tmp_path):
    """ROS reads 1.0e4 and 1e-3 as doubles (PyYAML's YAML 1.1: strings)."""
    text = LUMBAR.read_text().replace('singularity_condition_max: 10000.0', 'singularity_condition_max: 1.0e4')
    text = text.replace('step_margin: 0.0005', 'step_margin: 5e-4')
    path = tmp_path / 'floats.yaml'
    path.write_text(text)
    cfg = load_device_config(path)
    assert cfg.get_path('mechanism.singularity_condition_max') == 10000.0
    assert cfg.get_path('safety.step_margin') == 0.0005


def test_a_removed_key_says_what_to_do(tmp_path):
    params = raw_params(LUMBAR)
    params['sim']['drive_acceleration_factor'] = 10.0
    with pytest.raises(ConfigError, match='drive_acceleration_factor.*was removed.*max_acceleration'):
        load_device_config(write(tmp_path, params))


# ---------------------------------------------------------------------------- defaults
def test_absent_keys_get_one_default_and_leg_stiffness_follows_the_actuator(tmp_path):
    params = raw_params(LUMBAR)
    del params['sim']['leg_stiffness']
    del params['can']['homing_method']
    params['actuator']['stiffness'] = 333333.0
    cfg = load_device_config(write(tmp_path, params))
    assert cfg.get_path('sim.leg_stiffness') == 333333.0
    assert cfg.get_path('can.homing_method') == 35            # CiA 402: homing on the current position
    assert MasterConfig.from_device_config(cfg, channel='unused').homing_method == 35


# ---------------------------------------------------------------------------- the Python API
@pytest.fixture
def params() -> dict[str, Any]:
    return raw_params(LUMBAR)


def test_master_config_from_a_dict_is_range_checked(params):
    params['safety']['force_limit'] = -5.0
    with pytest.raises(ConfigError, match=r"'safety.force_limit' = -5.0.*out of range"):
        MasterConfig.from_device_config(params, channel='unused')


def test_can_limits_from_a_dict_are_checked(params):
    params['can']['heartbeat_consumer_mss'] = 150
    with pytest.raises(ConfigError, match=r"did you mean 'can.heartbeat_consumer_ms'"):
        CanLimits.from_config(params, scaling_from_config(load_device_config(LUMBAR)))


def test_trajectory_limits_from_a_dict_are_checked(params):
    params['trajectory']['limit_margin'] = 2.0
    with pytest.raises(ConfigError, match=r"'trajectory.limit_margin' = 2.0.*out of range"):
        TrajectoryLimits.from_config(params)


def test_scaling_from_a_dict_is_checked(params):
    params['actuator']['screw_lead'] = 0.0
    with pytest.raises(ConfigError, match=r"'actuator.screw_lead' = 0.0.*out of range.*m"):
        scaling_from_config(params)


def test_device_config_from_a_dict_is_checked(params):
    params['actuator']['max_velocty'] = 0.065
    with pytest.raises(ConfigError, match=r"did you mean 'actuator.max_velocity'"):
        DeviceConfig(params)


def test_a_mechanism_section_built_in_python_is_checked(params):
    section = params['mechanism']
    with pytest.raises(ConfigError, match=r"unknown parameter 'mechanism.stroke_mn'.*'mechanism.stroke_min'"):
        mechanism_from_config({'mechanism': {**section, 'stroke_mn': 0.3}})
    with pytest.raises(ConfigError, match=r"'mechanism.stroke_max' = -0.44.*out of range"):
        Rpr3.from_config({**section, 'stroke_max': -0.44})
    with pytest.raises(ConfigError, match=r"unknown parameter 'mechanism.home_pos'"):
        Rpr3.from_config({**section, 'home_pos': [0.0, 0.39, 0.08]})
    np.testing.assert_allclose(Rpr3.from_config(section).home_pose, section['home_pose'])


# ---------------------------------------------------------------------------- the nodes
@pytest.mark.ros
def test_node_gets_the_same_defaults_as_the_api(tmp_path):
    """The schema default of sim.leg_stiffness no longer masks actuator.stiffness in a node."""
    import rclpy
    from rclpy.context import Context
    from rclpy.node import Node

    from brace_control.nodes.params import declare_device_parameters
    params = raw_params(LUMBAR)
    del params['sim']['leg_stiffness']
    params['actuator']['stiffness'] = 333333.0
    path = write(tmp_path, params)
    ctx = Context()
    rclpy.init(context=ctx)
    try:
        node = Node('schema_test', context=ctx, cli_args=['--ros-args', '--params-file', str(path)])
        try:
            cfg = declare_device_parameters(node, ('mechanism', 'actuator', 'sim', 'can', 'safety'))
            api = load_device_config(path)
            assert cfg.get_path('sim.leg_stiffness') == api.get_path('sim.leg_stiffness') == 333333.0
            assert node.get_parameter('sim.leg_stiffness').value == 333333.0
            assert cfg['safety'] == api['safety'] and cfg['can'] == api['can']
        finally:
            node.destroy_node()
    finally:
        rclpy.shutdown(context=ctx)


@pytest.mark.ros
def test_ik_node_with_a_misspelled_key_exits_at_start_up_naming_it(tmp_path):
    params = raw_params(LUMBAR)
    params['safety']['force_limt'] = params['safety'].pop('force_limit')
    path = write(tmp_path, params, 'misspelled.yaml')
    cmd = [sys.executable, '-c', 'import sys; from brace_control.nodes.ik_node import main; sys.exit(main())',
           '--ros-args', '--params-file', str(path)]
    t0 = time.monotonic()
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=60, env=dict(os.environ),
                          cwd=str(REPO))
    elapsed = time.monotonic() - t0
    assert proc.returncode == 2, (proc.returncode, proc.stderr)       # runner.EXIT_CONFIG
    assert (f"unknown parameter 'safety.force_limt' in {path}; did you mean 'safety.force_limit'?"
            in proc.stderr), proc.stderr
    print(f'ik_node refused the file after {elapsed:.2f} s')


def test_no_parameter_is_writable_at_run_time():
    """The nodes read the device file once; a parameter that ``ros2 param set`` could change
    would be accepted and ignored (issue 25): every entry is read-only, so the set is refused
    with ROS's own reason (test_can_driver_node, test_trajectory_node)."""
    writable = [name for name, spec in SCHEMA.items() if not spec.read_only]
    writable += [f'mechanism.{name} ({kind})' for kind, specs in MECHANISM_SCHEMAS.items()
                 for name, spec in specs.items() if not spec.read_only]
    assert not writable, writable
