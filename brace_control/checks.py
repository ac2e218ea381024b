"""The checks of a device file that span keys: what the schema's per-key ranges cannot see.

:func:`check_device` runs before anything starts (``brace-bringup`` in both modes, every
node as it reads its parameters): a file that passes it does not fail later for a reason
it holds. Each failure is one :class:`~brace_control.config.ConfigError` naming the keys,
the values and what was expected (exit code 2, no traceback).

* the mechanism builds, its home pose is reachable and not singular (a brace that homes and
  enables, then refuses every goal, is a configuration error);
* ``safety.force_limit`` within ``actuator.max_force`` and below the load cell's saturation
  (``safety.saturation_fraction`` x its full scale): a limit the actuator or the load cell
  can never show protects nothing;
* ``safety.max_wrench`` above 0 on every axis (0 latches a stop at the first sample);
* the SYNC period within ``safety.command_timeout`` and the drives' heartbeat: a control
  cycle slower than the time-outs it serves cannot keep them;
* the per-pose-axis lists (``sim.rest_pose``, ``interaction.*``) as long as the mechanism's
  pose;
* the CAN set-up the master reads (node ids, the EDS files, the load-cell wiring,
  heartbeats): :class:`~brace_control.can.state.MasterConfig`;
* the interaction mode's parameters (:class:`~brace_control.interaction.AdmittanceParams`).
"""
from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from .config import ConfigError, DeviceConfig

__all__ = ['check_device']


def check_device(cfg: DeviceConfig, *, mechanism: Any = None) -> Any:
    """Check ``cfg`` across keys (module docstring); returns the mechanism it built (or
    ``mechanism``), ``None`` when the file has no mechanism section.

    :raises ConfigError: the first inconsistency, naming the keys.
    """
    if not isinstance(cfg.get('mechanism'), Mapping) or 'type' not in cfg['mechanism']:
        return None
    mech = mechanism if mechanism is not None else _mechanism(cfg)
    home = np.asarray(mech.home_pose, dtype=float)
    try:
        mech.inverse(home)
    except ValueError as exc:
        raise ConfigError(f'mechanism.home_pose {np.round(home, 6).tolist()} is not reachable: {exc}') from None
    check = getattr(mech, 'check_singularity', None)
    if check is not None:
        try:
            check(home)
        except ValueError as exc:
            raise ConfigError(f'mechanism.home_pose {np.round(home, 6).tolist()}: {exc}; the brace would '
                              'home and enable there, then refuse every goal: park it off the singularity') from None
    dof = int(mech.dof)
    _check_forces(cfg)
    _check_lengths(cfg, dof)
    _check_timing(cfg)
    if isinstance(cfg.get('can'), Mapping) and isinstance(cfg.get('safety'), Mapping):
        from .can.state import MasterConfig
        try:
            MasterConfig.from_device_config(cfg, mechanism=mech)
        except ConfigError:
            raise
        except (ValueError, OverflowError) as exc:
            raise ConfigError(f'CAN set-up: {exc}') from None
    if isinstance(cfg.get('interaction'), Mapping) and 'force_axes' in cfg['interaction']:
        from .interaction import AdmittanceParams
        try:
            AdmittanceParams.from_config(cfg, mech)
        except ConfigError:
            raise
        except (ValueError, KeyError) as exc:
            raise ConfigError(f'interaction: {exc}') from None
    return mech


def _mechanism(cfg: DeviceConfig) -> Any:
    from .mechanisms import mechanism_from_config
    try:
        return mechanism_from_config(cfg)
    except ConfigError:
        raise
    except (ValueError, KeyError, TypeError) as exc:
        raise ConfigError(f'mechanism: {exc}') from None


def _get(cfg: DeviceConfig, name: str) -> Any:
    return cfg.get_path(name, None)


def _check_forces(cfg: DeviceConfig) -> None:
    limit, max_force = _get(cfg, 'safety.force_limit'), _get(cfg, 'actuator.max_force')
    if limit is None or max_force is None:
        return
    limit, max_force = float(limit), float(max_force)
    if max_force <= 0.0:
        raise ConfigError(f'parameter actuator.max_force = {max_force:g}: the actuator must be able to '
                          'push (a number above 0, N or N·m)')
    if limit <= 0.0:
        raise ConfigError(f'parameter safety.force_limit = {limit:g}: expected a limit above 0')
    if limit > max_force:
        raise ConfigError(f'parameter safety.force_limit = {limit:g} is above actuator.max_force = '
                          f'{max_force:g}: the actuator cannot reach it, so it protects nothing; '
                          'expected at most actuator.max_force')
    if isinstance(cfg.get('actuator'), Mapping) and _get(cfg, 'safety.saturation_fraction') is not None:
        from .can.units import scaling_from_config
        try:
            rated = scaling_from_config(cfg).rated_force
        except ConfigError:
            raise
        except (ValueError, KeyError):
            return
        saturates = float(_get(cfg, 'safety.saturation_fraction')) * rated
        if limit >= saturates:
            raise ConfigError(
                f'parameter safety.force_limit = {limit:g} is at or above the load cell\'s saturation '
                f'({float(_get(cfg, "safety.saturation_fraction")):g} x full scale {rated:g} = '
                f'{saturates:g}): the reading would saturate before the limit; lower the limit or '
                'give the real full scale (actuator.load_cell_rated_force)')
    wrench = _get(cfg, 'safety.max_wrench')
    if wrench is not None and any(float(w) <= 0.0 for w in wrench):
        raise ConfigError(f'parameter safety.max_wrench = {list(wrench)}: every axis needs a limit above 0 '
                          '(0 would latch a protective stop at the first sample)')


def _check_lengths(cfg: DeviceConfig, dof: int) -> None:
    rest = _get(cfg, 'sim.rest_pose')
    if rest is not None and len(rest) != dof:
        raise ConfigError(f'parameter sim.rest_pose = {list(rest)}: expected {dof} values (the '
                          f'mechanism\'s pose), got {len(rest)}')
    for key in ('sim.stiffness', 'sim.damping'):
        value = _get(cfg, key)
        if value is not None and len(value) != dof * dof:
            raise ConfigError(f'parameter {key}: expected {dof * dof} values ({dof} x {dof} row-major), '
                              f'got {len(value)}')
    tol = _get(cfg, 'safety.pose_tolerance')
    if tol is not None and len(tol) not in (1, dof):
        raise ConfigError(f'parameter safety.pose_tolerance = {list(tol)}: expected {dof} values (one per '
                          f'pose coordinate), got {len(tol)}')
    for key in ('interaction.force_axes', 'interaction.mass', 'interaction.damping',
                'interaction.max_goal_wrench', 'interaction.goal_rate', 'interaction.stop_deceleration'):
        value = _get(cfg, key)
        if value is not None and len(value) not in (1, dof):
            raise ConfigError(f'parameter {key} = {list(value)}: expected {dof} values (one per pose '
                              f'axis) or one for all, got {len(value)}')


def _check_timing(cfg: DeviceConfig) -> None:
    rate = _get(cfg, 'can.sync_rate_hz')
    if rate is None:
        return
    period = 1.0 / float(rate)
    timeout = _get(cfg, 'safety.command_timeout')
    if timeout is not None and period > float(timeout):
        raise ConfigError(
            f'parameter can.sync_rate_hz = {float(rate):g}: its {period * 1e3:g} ms period is longer than '
            f'safety.command_timeout = {float(timeout) * 1e3:g} ms, so every setpoint stream would be '
            f'stale at each cycle; expected at least {1.0 / float(timeout):.4g} Hz')
    hb = _get(cfg, 'can.drive_heartbeat_ms')
    if hb is not None and period > float(hb) * 1e-3:
        raise ConfigError(
            f'parameter can.sync_rate_hz = {float(rate):g}: a {period * 1e3:g} ms cycle cannot supervise '
            f'drives that beat every can.drive_heartbeat_ms = {int(hb)} ms; expected at least '
            f'{1000.0 / float(hb):.4g} Hz')
