"""``load_mechanism``: build the mechanism model a device YAML describes."""
from __future__ import annotations

from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from ..config import ConfigError, DeviceConfig, as_device_config, load_device_config
from .base import Mechanism

__all__ = ['load_mechanism', 'mechanism_from_config', 'MECHANISM_TYPES', 'register']

# type name in the YAML (mechanism.type) -> factory(mechanism section) -> Mechanism
MECHANISM_TYPES: dict[str, Callable[[Mapping[str, Any]], Mechanism]] = {}


def register(type_name: str) -> Callable:
    """Class decorator: ``@register('rpr3')`` makes ``Cls.from_config(section)`` loadable."""
    def deco(cls):
        MECHANISM_TYPES[type_name] = cls.from_config
        return cls
    return deco


def mechanism_from_config(cfg: DeviceConfig | Mapping[str, Any]) -> Mechanism:
    """The mechanism of an already loaded device config (a nested dict is checked against
    :mod:`brace_control.schema` first, like a file)."""
    if not isinstance(cfg, Mapping):
        raise ConfigError(f'device config: expected a mapping, got {type(cfg).__name__}')
    cfg = as_device_config(cfg)
    section = cfg.get('mechanism')
    if not isinstance(section, Mapping):
        raise ConfigError('device config has no "mechanism" section')
    kind = section.get('type')
    if kind not in MECHANISM_TYPES:
        raise ConfigError(
            f'mechanism.type {kind!r} is unknown; expected one of {sorted(MECHANISM_TYPES)}')
    return MECHANISM_TYPES[kind](section)


def load_mechanism(path: str | Path) -> Mechanism:
    """Read a device YAML (the same file the nodes read) and build its mechanism."""
    return mechanism_from_config(load_device_config(path))
