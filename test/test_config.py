"""The device YAML -> mechanism path: ``load_mechanism`` and the ``ConfigError`` it raises."""
from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest
import yaml

from brace_control.config import ConfigError, load_device_config
from brace_control.mechanisms import MECHANISM_TYPES, Rpr3, load_mechanism, mechanism_from_config

LUMBAR = Path(__file__).resolve().parent.parent / 'config' / 'lumbar_brace.yaml'


@pytest.fixture()
def section() -> dict:
    return copy.deepcopy(dict(load_device_config(LUMBAR)['mechanism']))


def write_device(tmp_path: Path, mechanism: dict) -> Path:
    path = tmp_path / 'device.yaml'
    path.write_text(yaml.safe_dump({'/**': {'ros__parameters': {'device': 'test', 'mechanism': mechanism}}}))
    return path


def test_rpr3_is_registered():
    assert 'rpr3' in MECHANISM_TYPES


def test_load_lumbar_brace_by_path_and_by_name():
    for ref in (LUMBAR, 'config/lumbar_brace.yaml', 'lumbar_brace'):
        mech = load_mechanism(ref)
        assert isinstance(mech, Rpr3)
        assert mech.actuator_names == ('a1', 'a2', 'a3')
        np.testing.assert_allclose(mech.base_anchors, [[-0.217, 0], [0, 0], [0.217, 0]])
        np.testing.assert_allclose(mech.platform_anchors, [[-0.195, 0], [0, 0], [0.195, 0]])
        lo, hi = mech.actuator_limits
        np.testing.assert_allclose(lo, [0.34] * 3)
        np.testing.assert_allclose(hi, [0.44] * 3)
        raw = yaml.safe_load(LUMBAR.read_text())['/**']['ros__parameters']['mechanism']
        np.testing.assert_allclose(mech.home_pose, raw['home_pose'])
        # PyYAML (YAML 1.1) reads "1.0e4" as a string; ROS reads it as a double, so do we
        assert mech.singularity_condition_max == float(raw['singularity_condition_max']) == 1e4


def test_lumbar_home_pose_is_reachable_and_not_singular():
    # theta = 0 is a singularity of the brace (leg lines concurrent): home must avoid it
    mech = load_mechanism(LUMBAR)
    assert mech.in_workspace(mech.home_pose)
    mech.check_singularity(mech.home_pose)


def test_nested_point_lists_and_per_actuator_strokes(tmp_path, section):
    section['base_anchors'] = [[-0.217, 0.0], [0.0, 0.0], [0.217, 0.0]]
    section['stroke_min'] = [0.33, 0.34, 0.35]
    section['stroke_max'] = [0.43, 0.44, 0.45]
    mech = load_mechanism(write_device(tmp_path, section))
    np.testing.assert_allclose(mech.actuator_limits[0], [0.33, 0.34, 0.35])
    np.testing.assert_allclose(mech.actuator_limits[1], [0.43, 0.44, 0.45])


def test_home_pose_optional(tmp_path, section):
    del section['home_pose']
    mech = load_mechanism(write_device(tmp_path, section))
    lo, hi = mech.actuator_limits
    q = mech.inverse(mech.home_pose)                   # within stroke
    assert np.all((q >= lo) & (q <= hi)) and mech.home_pose[1] > 0


@pytest.mark.parametrize('key, value, match', [
    ('base_anchors', [-0.217, 0.0, 0.0, 0.0, 0.217], 'base_anchors'),              # odd count
    ('base_anchors', [-0.217, 0.0, 0.0, 0.0], 'base_anchors.*3 points'),           # two points
    ('base_anchors', [-0.217, 0.0, 0.0, 0.0, 0.217, 0.0, 0.3, 0.0], 'base_anchors.*3 points'),
    ('platform_anchors', [-0.195, 0.0, 0.0, '.nan', 0.195, 0.0], 'platform_anchors.*non-finite'),
    ('platform_anchors', ['a', 'b', 'c', 'd', 'e', 'f'], 'platform_anchors'),
    ('platform_anchors', 0.195, 'platform_anchors'),
    ('stroke_min', 0.45, 'stroke'),                                                # lo > hi
    ('stroke_max', [0.44, 0.44], 'stroke'),
    ('stroke_min', -0.1, 'stroke'),
    ('actuator_names', ['a1', 'a2'], 'actuator_names'),
    ('home_pose', [0.0, 0.6, 0.0], 'a1 would need'),                               # outside stroke
    ('home_pose', [0.0, 0.39], 'home_pose'),
    ('singularity_condition_max', 0.5, 'singularity_condition_max'),
    ('type', 'rpr9', 'unknown'),
])
def test_bad_mechanism_section_raises_config_error(tmp_path, section, key, value, match):
    section[key] = float('nan') if value == '.nan' else value
    if isinstance(value, list):
        section[key] = [float('nan') if v == '.nan' else v for v in value]
    with pytest.raises(ConfigError, match=match):
        load_mechanism(write_device(tmp_path, section))


@pytest.mark.parametrize('key', ['base_anchors', 'platform_anchors', 'stroke_min', 'stroke_max'])
def test_missing_key_raises_config_error_naming_it(tmp_path, section, key):
    del section[key]
    with pytest.raises(ConfigError, match=f'mechanism.{key}'):
        load_mechanism(write_device(tmp_path, section))


def test_identical_legs_rejected(tmp_path, section):
    section['base_anchors'] = [0.0, 0.0, 0.0, 0.0, 0.217, 0.0]
    section['platform_anchors'] = [0.0, 0.0, 0.0, 0.0, 0.195, 0.0]
    with pytest.raises(ConfigError, match='same leg'):
        load_mechanism(write_device(tmp_path, section))


def test_missing_mechanism_section_and_missing_file(tmp_path):
    with pytest.raises(ConfigError, match='no "mechanism" section'):
        mechanism_from_config({'device': 'x'})
    with pytest.raises(ConfigError, match='not found'):
        load_mechanism(tmp_path / 'missing.yaml')


def test_from_config_rejects_wrong_type(section):
    section['type'] = 'rpr4'
    with pytest.raises(ConfigError, match='rpr3'):
        Rpr3.from_config(section)


def _python_parser_loader():
    """PyYAML's pure-Python safe loader with the device files' own rules (ROS-typed floats,
    keys given once): the oracle for the C-parsed loader."""
    from brace_control import config as c

    class PythonLoader(yaml.SafeLoader):
        pass
    PythonLoader.yaml_constructors = dict(c._RosYamlLoader.yaml_constructors)
    PythonLoader.yaml_implicit_resolvers = {k: list(v) for k, v in
                                            c._RosYamlLoader.yaml_implicit_resolvers.items()}
    return PythonLoader


_ROOT = Path(__file__).resolve().parents[1]
_YAML_FILES = sorted((_ROOT / 'config').glob('*.yaml')) + sorted((_ROOT / 'test' / 'data').glob('*.yaml'))


@pytest.mark.parametrize('path', _YAML_FILES, ids=lambda p: p.name)
def test_the_device_files_read_the_same_as_with_pyyamls_python_parser(path):
    """read_yaml parses with libyaml where PyYAML has it (10x faster at every node's start);
    every bundled file gives the same document as PyYAML's own Python parser."""
    from brace_control.config import read_yaml
    assert read_yaml(path) == yaml.load(path.read_text(encoding='utf-8'), Loader=_python_parser_loader())


@pytest.mark.parametrize('text, expected', [
    ('a: 1e4\nb: .5\nc: 1.0e-6\nd: -2.5E+3\ne: 7\nf: [1, 2.0, "x"]\ng: .inf\n',
     {'a': 1e4, 'b': 0.5, 'c': 1e-6, 'd': -2500.0, 'e': 7, 'f': [1, 2.0, 'x'], 'g': float('inf')}),
    ('n:\n  m: {k: true, j: null}\n', {'n': {'m': {'k': True, 'j': None}}}),
])
def test_ros_typed_numbers_as_ros_reads_them(tmp_path, text, expected):
    from brace_control.config import read_yaml
    f = tmp_path / 'x.yaml'
    f.write_text(text)
    assert read_yaml(f) == expected == yaml.load(text, Loader=_python_parser_loader())


@pytest.mark.parametrize('text, match', [
    ('a: 1\nb: 2\na: 3\n', r"key 'a' is given twice in one mapping \(lines 1 and 3\)"),
    ('x: [1, 2\n', r'(?s)not valid YAML: .*line 1'),
])
def test_a_key_given_twice_and_broken_yaml_are_named(tmp_path, text, match):
    from brace_control.config import read_yaml
    f = tmp_path / 'x.yaml'
    f.write_text(text)
    with pytest.raises(ConfigError, match=match):
        read_yaml(f)
