"""Device parameters for the nodes: declared with descriptors, checked at start-up.

Every node reads the same device YAML (``--ros-args --params-file config/<device>.yaml``).
The table of parameters (default, range, unit, read-only) is :data:`brace_control.schema.SCHEMA`,
the one the pure Python API checks files against; this module turns its entries into ROS
``ParameterDescriptor`` s. A node calls :func:`declare_device_parameters` with the sections it
needs and gets a :class:`~brace_control.config.DeviceConfig` back, the same object the pure
API builds from the file, so ``mechanism_from_config(cfg)`` gives the node's model.

Before declaring anything, every parameter the node was given (the whole file, sections the
node does not use included) is checked against the schema: a misspelled key, a wrong type or
a value out of range stops the start-up with the message the pure API gives
(:class:`ConfigError`, exit code 2 from :func:`~.runner.run_node`).

The ``mechanism.*`` geometry differs per mechanism type (``schema.MECHANISM_SCHEMAS``); those
keys are taken from the parameter file as given and declared read-only.
"""
from __future__ import annotations

import array
import sys
from collections.abc import Iterable, Sequence
from typing import Any

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.exceptions import (InvalidParameterTypeException,
                              InvalidParameterValueException)
from rclpy.node import Node

from pathlib import Path

from ..checks import check_device
from ..config import ConfigError, DeviceConfig, load_device_config
from ..schema import ROS_BUILTIN_PREFIXES, SCHEMA, Param, lookup, nest, param_type

__all__ = ['Param', 'SCHEMA', 'declare_device_parameters', 'ConfigError', 'params_file_source']


def _descriptor(name: str, spec: Param) -> ParameterDescriptor:
    """The ROS descriptor of a schema entry: description (with the unit), read-only, range."""
    unit = f' [{spec.unit}]' if spec.unit else ''
    d = ParameterDescriptor(description=spec.description + unit, read_only=spec.read_only)
    t = param_type(spec)
    if spec.range is not None:
        lo, hi = spec.range
        if t == 'int':
            d.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi), step=0)]
        elif t == 'float':
            d.floating_point_range = [FloatingPointRange(from_value=float(lo), to_value=float(hi), step=0.0)]
        else:                       # lists: checked per element by brace_control.schema
            d.additional_constraints = f'each value in [{lo:g}, {hi:g}]'
    if spec.choices:
        d.additional_constraints = f'one of {", ".join(spec.choices)}'
    return d


def _overrides(node: Node) -> dict[str, Any]:
    """Parameter values the node was started with (params file, -p, overrides)."""
    raw = getattr(node, '_parameter_overrides', {}) or {}
    return {name: _plain(p.value) for name, p in raw.items()}


def _plain(value: Any) -> Any:
    """A ROS parameter value as plain Python (arrays -> lists)."""
    if isinstance(value, (list, tuple, array.array)):
        return list(value)
    return value


def params_files(argv: Sequence[str] | None = None) -> list[str]:
    """The ``--params-file`` (s) in ``argv`` (default ``sys.argv``) after ``--ros-args``."""
    argv = list(sys.argv if argv is None else argv)
    return [argv[i + 1] for i, a in enumerate(argv[:-1])
            if a == '--params-file' and '--ros-args' in argv[:i]]


def params_file_source(argv: Sequence[str] | None = None) -> str | None:
    """The ``--params-file`` (s) in ``argv`` (default ``sys.argv``) after ``--ros-args``, for
    messages; ``None`` when there is none."""
    return ', '.join(params_files(argv)) or None


def declare_device_parameters(node: Node, sections: Iterable[str], *,
                              source: str | None = None,
                              cli_args: Sequence[str] | None = None) -> DeviceConfig:
    """Check the node's parameters against the schema, declare those of ``sections`` on
    ``node`` and return them nested.

    ``sections`` names top-level groups (``'mechanism'``, ``'trajectory'``, ``'can'``,
    ``'safety'``, ``'actuator'``, ``'sim'``, ``'kinetics'``); ``device`` and the frames are
    always declared. Each is declared with the value the pure API computes (the file's, else
    the schema default), so node and API agree; optional parameters without a default
    (``sim.rest_pose``) are declared only when given.

    :param source: where the parameters came from, for messages (default: the
        ``--params-file`` of the command line).
    :param cli_args: the node's own command line (``cli_args`` of the node), searched for its
        ``--params-file`` before ``sys.argv``: the files the parameters name (``can.eds``)
        are relative to that file's directory, as in the pure API.
    :raises ConfigError: a parameter the schema does not know (naming the closest known
        one), a value of the wrong type, out of range, or not one of its choices; the
        message names the parameter and what was expected.
    """
    sections = set(sections)
    given = _overrides(node)
    files = params_files(cli_args or ()) or params_files()
    where = source or ', '.join(files) or f'the parameters of node {node.get_name()!r}'
    # the last parameter file wins in ROS; the files it names are relative to it
    path = Path(files[-1]).absolute() if files else None
    for f in files:
        load_device_config(f)       # what rcl's parser lets pass: a key given twice, not UTF-8
    device = {k: v for k, v in given.items() if not k.startswith(ROS_BUILTIN_PREFIXES)}
    nested: dict[str, Any] = {}
    for name, value in device.items():
        nest(nested, name, value)
    full = DeviceConfig(nested, path, source=where)   # the schema check of the whole file
    model = check_device(full)                         # and the checks across its keys
    cfg: dict[str, Any] = {}

    def declare(name: str, default: Any, descriptor: ParameterDescriptor) -> Any:
        try:
            value = node.declare_parameter(name, default, descriptor).value
        except InvalidParameterValueException as exc:
            raise ConfigError(
                f'parameter {name!r} = {given.get(name)!r} in {where} is out of range: {exc}') from exc
        except InvalidParameterTypeException as exc:
            raise ConfigError(
                f'parameter {name!r} = {given.get(name)!r} in {where} has the wrong type; expected '
                f'{type(default).__name__} like {default!r}') from exc
        return _plain(value)

    for name, spec in SCHEMA.items():
        group = name.split('.', 1)[0] if '.' in name else None
        if '*' in name or (group is not None and group not in sections):
            continue
        value = full.get_path(name, None)
        if value is None:            # optional, not given: absent, as in the pure API
            continue
        nest(cfg, name, declare(name, value, _descriptor(name, spec)))
    for name in sorted(given):       # wildcard entries (can.rpdo.<n>.mapping): as given
        spec = lookup(name)
        group = name.split('.', 1)[0]
        if spec is None or group not in sections or name in SCHEMA or name.startswith('mechanism.'):
            continue
        nest(cfg, name, declare(name, given[name], _descriptor(name, spec)))

    if 'mechanism' in sections:
        mech_keys = sorted(k for k in given if k.startswith('mechanism.'))
        if not mech_keys:
            raise ConfigError(
                'no mechanism.* parameters: start the node with the device file, '
                '--ros-args --params-file config/<device>.yaml')
        for name in mech_keys:
            nest(cfg, name, declare(name, given[name], ParameterDescriptor(
                description='mechanism geometry (from the device file)', read_only=True)))
    out = DeviceConfig(cfg, path, source=where)
    for key in [k for k, v in out.items() if isinstance(v, dict) and k not in sections]:
        del out[key]                 # only what the node declared, never silent defaults
    out.model = model if 'mechanism' in sections else None    # the same geometry: one model
    return out
