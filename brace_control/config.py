"""The device YAML: one ROS 2 parameter file read by the nodes and by the pure-Python API.

A device file looks like::

    /**:
      ros__parameters:
        device: lumbar_brace
        mechanism: {type: rpr3, ...}
        can: {...}

Nested mappings are ROS parameter namespaces (``mechanism.type``); lists of points are
flattened ``[x0, y0, x1, y1, ...]`` because ROS parameters cannot hold nested lists.

Every :class:`DeviceConfig` is checked against :mod:`brace_control.schema` when it is built
(from a file or from a dict in Python): an unknown key, a wrong type or a value out of range
is a :class:`ConfigError` naming the key; absent parameters get the schema's defaults.
"""
from __future__ import annotations

import os
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from . import schema
from .schema import ConfigError

__all__ = [
    'DeviceConfig', 'ConfigError', 'load_device_config', 'flatten_parameters',
    'points', 'config_dir', 'resolve_device_file', 'as_device_config', 'read_yaml',
]


class _RosYamlLoader(getattr(yaml, 'CSafeLoader', yaml.SafeLoader)):  # type: ignore[misc]
    """PyYAML's safe loader reading numbers as ROS 2's parameter parser does: ``1e4``,
    ``1.0e-6`` and ``.5`` are floats (YAML 1.1 makes them strings).

    Parsed by libyaml where PyYAML was built with it (``CSafeLoader``: the same safe
    constructor and resolver over a C parser; lumbar_brace.yaml in 0.9 ms instead of 8.3, at
    every node's start and every configuration check), else by PyYAML's Python parser."""


def _unique_mapping(loader: yaml.SafeLoader, node: yaml.MappingNode, deep: bool = False) -> dict:
    """A YAML mapping whose keys are each given once (PyYAML keeps the last silently: a
    ``force_limit`` written twice would leave the second in force, unseen)."""
    seen: dict[Any, int] = {}
    for key_node, _ in node.value:
        key = loader.construct_object(key_node, deep=deep)
        line = key_node.start_mark.line + 1
        if key in seen:
            raise ConfigError(f'key {key!r} is given twice in one mapping (lines {seen[key]} and '
                              f'{line}); keep one')
        seen[key] = line
    return loader.construct_mapping(node, deep=deep)


_RosYamlLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _unique_mapping)
_RosYamlLoader.add_implicit_resolver(
    'tag:yaml.org,2002:float',
    re.compile(r'''^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
                  |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
                  |\.[0-9_]+(?:[eE][-+]?[0-9]+)?
                  |[-+]?\.(?:inf|Inf|INF)
                  |\.(?:nan|NaN|NAN))$''', re.X),
    list('-+0123456789.'))


class DeviceConfig(dict):
    """Parameters of one device (the ``ros__parameters`` mapping), plus where it came from.

    Behaves as the nested dict of the YAML; :meth:`get_path` reads dotted names the way a
    ROS parameter is named (``cfg.get_path('can.sync_rate_hz')``). Building one checks
    ``params`` against :mod:`brace_control.schema` and fills in the schema's defaults, so
    every reader sees the same values whether the config came from a file, from a dict
    built in Python or from a node's parameters.

    :param params: the nested parameters.
    :param path: the YAML it was read from (files it names are relative to it).
    :param source: where the parameters came from, for messages (default: ``path``).
    :raises ConfigError: an unknown key (naming the closest known one), a wrong type or a
        value out of range, naming the key, the value, what was expected and the unit.
    """

    def __init__(self, params: Mapping[str, Any], path: Path | None = None, *,
                 source: str | None = None) -> None:
        if not isinstance(params, Mapping):
            raise ConfigError(f'device parameters: expected a mapping, got {type(params).__name__}')
        params = _string_keys(params)
        self.source = source if source is not None else (str(path) if path is not None else None)
        schema.validate(params, self.source)
        super().__init__(schema.with_defaults(params))
        self.path = path
        #: the mechanism model built from these parameters, when one was (the checks at
        #: start-up build it; a node takes it instead of building a second)
        self.model: Any = None

    def get_path(self, dotted: str, default: Any = ...) -> Any:
        node: Any = self
        for key in dotted.split('.'):
            if not isinstance(node, Mapping) or key not in node:
                if default is ...:
                    where = f' in {self.path}' if self.path else ''
                    raise ConfigError(f'parameter {dotted!r} is missing{where}')
                return default
            node = node[key]
        return node

    def section(self, name: str) -> dict[str, Any]:
        """The sub-mapping ``name`` (empty dict if absent)."""
        value = self.get(name, {})
        if not isinstance(value, Mapping):
            raise ConfigError(f'parameter {name!r} must be a mapping, got {type(value).__name__}')
        return dict(value)

    def relative_file(self, name: str) -> Path:
        """A file named in the YAML, relative to the YAML's own directory."""
        p = Path(name)
        if not p.is_absolute() and self.path is not None:
            p = self.path.parent / p
        return p

    def resolve_file(self, name: str, key: str) -> Path:
        """The file a parameter ``key`` names, as an absolute path: relative to the YAML's
        directory (:meth:`relative_file`). Parameters built in Python without a file
        (``path`` is ``None``) look in the working directory, then in the package's
        ``config/``.

        :raises ConfigError: the file does not exist (naming the path tried).
        """
        p = self.relative_file(name)
        if p.is_file():
            return Path(os.path.abspath(p))
        if self.path is None and not Path(name).is_absolute():
            alt = config_dir() / name
            if alt.is_file():
                return Path(os.path.abspath(alt))
            raise ConfigError(f'parameter {key} = {name!r}: no such file (looked at {p.resolve()} and '
                              f'{alt}){_where_from(self.source)}')
        raise ConfigError(f'parameter {key} = {name!r}: no such file {p.resolve()} (relative to the '
                          f'parameter file\'s directory){_where_from(self.source)}')


def _where_from(source: str | None) -> str:
    return f' in {source}' if source else ''


def _string_keys(value: Any) -> Any:
    """Every mapping key as a string (YAML reads ``rpdo: {1: ...}`` with an integer key; ROS
    names that parameter ``can.rpdo.1.mapping``)."""
    if isinstance(value, Mapping):
        return {str(k): _string_keys(v) for k, v in value.items()}
    return value


def as_device_config(cfg: Mapping[str, Any]) -> DeviceConfig:
    """``cfg`` itself when it is a :class:`DeviceConfig`, else one built (and so checked
    against the schema) from the nested mapping: the one entry point of every reader."""
    return cfg if isinstance(cfg, DeviceConfig) else DeviceConfig(cfg)


def config_dir() -> Path:
    """The package's config directory: the source tree's, else the installed share/ one."""
    src = Path(__file__).resolve().parent.parent / 'config'
    if src.is_dir():
        return src
    try:
        from ament_index_python.packages import get_package_share_directory
        return Path(get_package_share_directory('brace_control')) / 'config'
    except Exception:  # noqa: BLE001 - no ament index: only the source layout is left
        return src


def resolve_device_file(name_or_path: str | Path) -> Path:
    """A device YAML by path, or by bare device name (``lumbar_brace``) from :func:`config_dir`."""
    p = Path(name_or_path)
    if p.is_file():
        return p
    candidate = config_dir() / (p.name if p.suffix else f'{p.name}.yaml')
    if candidate.is_file():
        return candidate
    raise ConfigError(f'device file {str(name_or_path)!r} not found (looked at {p} and {candidate})')


def load_device_config(path: str | Path) -> DeviceConfig:
    """Read a device YAML (ROS 2 parameter file) into a :class:`DeviceConfig`.

    Accepts the ``/**: ros__parameters:`` layout, a single node-name key with
    ``ros__parameters``, or a bare mapping of parameters.

    :raises ConfigError: missing file, YAML syntax error, no parameter mapping, or a
        parameter the schema does not know, of the wrong type or out of range (naming it,
        with the closest known name for an unknown one).
    """
    p = resolve_device_file(path)
    doc = read_yaml(p)
    if not isinstance(doc, Mapping):
        raise ConfigError(f'{p}: expected a mapping at the top level, got {type(doc).__name__}')
    params: Any = None
    if '/**' in doc:
        section = doc['/**'] or {}
        if not isinstance(section, Mapping):
            raise ConfigError(f'{p}: "/**" must hold "ros__parameters:", got {type(section).__name__}')
        params = section.get('ros__parameters')
    else:
        for value in doc.values():
            if isinstance(value, Mapping) and 'ros__parameters' in value:
                params = value['ros__parameters']
                break
        else:
            params = doc
    if not isinstance(params, Mapping):
        raise ConfigError(f'{p}: no "ros__parameters" mapping found')
    return DeviceConfig(params, p.resolve(), source=str(p))


def read_yaml(path: str | Path) -> Any:
    """A YAML file as ROS 2 reads parameter files: UTF-8, numbers typed as ROS types them,
    every key given once in its mapping.

    :raises ConfigError: unreadable, not UTF-8, not YAML, or a key given twice (with where).
    """
    p = Path(path)
    try:
        text = p.read_bytes().decode('utf-8')
    except OSError as exc:
        raise ConfigError(f'{p}: cannot read: {exc.strerror or exc}') from None
    except UnicodeDecodeError as exc:
        line = p.read_bytes()[:exc.start].count(b'\n') + 1
        raise ConfigError(f'{p}: not UTF-8 text (byte {exc.object[exc.start]:#04x} at line {line}); '
                          'save the file as UTF-8') from None
    try:
        return yaml.load(text, Loader=_RosYamlLoader)  # noqa: S506 - a SafeLoader
    except ConfigError as exc:
        raise ConfigError(f'{p}: {exc}') from None
    except yaml.YAMLError as exc:
        raise ConfigError(f'{p}: not valid YAML: {exc}') from None


def flatten_parameters(params: Mapping[str, Any], prefix: str = '') -> dict[str, Any]:
    """Nested mapping -> ``{'mechanism.type': 'rpr3', ...}`` as ROS names its parameters."""
    return schema.flatten(params, prefix)


def points(flat: Any, name: str, *, dim: int = 2) -> np.ndarray:
    """A flattened point list ``[x0, y0, x1, y1, ...]`` (or already nested) -> (n, dim) array.

    :raises ConfigError: non-numeric, non-finite, or a length not a multiple of ``dim``.
    """
    try:
        arr = np.asarray(flat, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f'{name}: expected numbers, got {flat!r}') from exc
    if arr.ndim == 2 and arr.shape[1] == dim:
        pass
    elif arr.ndim == 1 and arr.size % dim == 0 and arr.size > 0:
        arr = arr.reshape(-1, dim)
    else:
        raise ConfigError(f'{name}: expected a flat list of {dim}-D points, got shape {arr.shape}')
    if not np.all(np.isfinite(arr)):
        raise ConfigError(f'{name}: contains a non-finite value')
    return arr
