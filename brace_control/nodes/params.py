"""Device parameters for the nodes: declared with descriptors, range-checked at start-up.

Every node reads the same device YAML (``--ros-args --params-file config/<device>.yaml``).
:data:`SCHEMA` lists each parameter a node may use, with its default, its range and
whether it is read-only (the safety limits are). A node calls
:func:`declare_device_parameters` with the sections it needs and gets a
:class:`~brace_control.config.DeviceConfig` back, the same object the pure API builds
from the file, so ``mechanism_from_config(cfg)`` gives the node's model.

The ``mechanism.*`` geometry differs per mechanism type; those keys are taken from the
parameter file as given and declared read-only.
"""
from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.exceptions import (InvalidParameterTypeException,
                              InvalidParameterValueException)
from rclpy.node import Node

from ..config import ConfigError, DeviceConfig

__all__ = ['Param', 'SCHEMA', 'declare_device_parameters', 'ConfigError']


@dataclass(frozen=True)
class Param:
    """One parameter: default value (its type is the parameter's type), range, read-only."""

    default: Any
    description: str
    range: tuple[float, float] | None = None
    read_only: bool = False
    length: int | None = None          # exact length for an array, None = any
    choices: tuple[str, ...] | None = None


_F = float
SCHEMA: dict[str, Param] = {
    'device': Param('lumbar_brace', 'device name', read_only=True),
    'base_frame': Param('brace_base', 'frame of the fixed base', read_only=True),
    'platform_frame': Param('brace_platform', 'frame of the moving platform', read_only=True),
    # actuator (per actuator, SI)
    'actuator.max_velocity': Param(0.065, 'actuator speed limit (m/s or rad/s)', (1e-4, 100.0), True),
    'actuator.max_acceleration': Param(0.5, 'actuator acceleration limit', (1e-4, 1e4), True),
    'actuator.max_force': Param(250.0, 'actuator force (N) or torque (N·m) limit', (0.0, 1e4), True),
    'actuator.screw_lead': Param(0.001, 'm per motor revolution (linear actuators)', (1e-6, 1.0), True),
    'actuator.encoder_counts_per_rev': Param(8192, 'encoder counts per motor revolution', (1, 1 << 24), True),
    'actuator.load_cell_rated_force': Param(300.0, 'load-cell full scale (N)', (1.0, 1e5), True),
    'actuator.load_cell_n_per_count': Param(0.01, 'load-cell scaling (N per count)', (1e-9, 1e3), True),
    'actuator.kind': Param('linear', 'linear (m, load cell 2401h) or rotary (rad, torque actual 6077h)',
                           read_only=True, choices=('linear', 'rotary')),
    'actuator.gear_ratio': Param(1.0, 'motor turns per joint turn (rotary)', (1e-3, 1e5), True),
    'actuator.torque_constant': Param(0.0229, 'motor torque constant (N·m/A; rotary: 6077h scaling)', (1e-6, 100.0), True),
    'actuator.rated_current': Param(1.0, "motor rated current (A): 1000 ‰ of 6077h = rated_current × "
                                    "torque_constant × gear_ratio N·m at the joint", (1e-6, 1e4), True),
    'actuator.stiffness': Param(1.0e6, 'axial stiffness of each actuator with its load path in series '
                                '(N/m; rotary: N·m/rad): leg length = encoder - effort / stiffness',
                                (1.0, 1e12), True),
    # kinetics_node: the load-aware pose estimate (brace_control.mechanisms.pose_estimate)
    'kinetics.load_cell_noise': Param(0.05, 'standard deviation of one load-cell (N) or torque (N·m) '
                                      'reading, for the pose covariance', (0.0, 1e4), True),
    'kinetics.stiffness_rel_std': Param(0.05, 'relative standard deviation of actuator.stiffness, '
                                        'for the pose covariance', (0.0, 1.0), True),
    'kinetics.max_step': Param(0.02, 'longest solver step of the pose estimate (pose norm, m or rad): '
                               'longer ones are damped, the estimate never jumps', (1e-6, 10.0), True),
    'kinetics.max_iterations': Param(8, 'solver iterations per joint state', (1, 100), True),
    'kinetics.residual_sigmas': Param(3.0, 'the legs close (exact) when every leg-length residual is within '
                                      'this many standard deviations, else least squares', (0.1, 1e6), True),
    'kinetics.unobserved_variance': Param(1e6, 'variance (m^2, rad^2) on /brace/pose_with_covariance '
                                          'entries the device does not measure', (1.0, 1e12), True),
    'kinetics.ambiguity_distance': Param(0.02, 'another assembly mode closer than this (pose norm, m/rad) '
                                         '-> ambiguous forward solution', (0.0, 10.0), True),
    'kinetics.singularity_warn_fraction': Param(0.5, 'cond(J) above this fraction of '
                                                'singularity_condition_max -> warn', (1e-6, 1.0), True),
    'kinetics.ambiguity_check_period': Param(0.05, 'seconds between full forward solutions (all '
                                             'assembly modes)', (0.0, 10.0), True),
    # trajectory
    'trajectory.rate_hz': Param(200.0, 'setpoint rate (Hz)', (1.0, 2000.0)),
    'trajectory.profile': Param('minimum_jerk', 'motion profile',
                                choices=('minimum_jerk', 'scurve', 'logcosh')),
    'trajectory.max_velocity': Param([0.03, 0.03, 0.3], 'platform velocity limit per axis'),
    'trajectory.max_acceleration': Param([0.1, 0.1, 1.0], 'platform acceleration limit per axis'),
    'trajectory.max_jerk': Param([1.0, 1.0, 10.0], 'platform jerk limit per axis'),
    'trajectory.fitts_a': Param(0.2, "Fitts' law intercept a (s)", (0.0, 60.0)),
    'trajectory.fitts_b': Param(0.3, "Fitts' law slope b (s/bit)", (0.0, 60.0)),
    'trajectory.fitts_w': Param(0.01, "Fitts' law target width W (m)", (1e-6, 10.0)),
    'trajectory.path_check_samples': Param(200, 'samples of a path checked against the limits', (2, 100000)),
    'trajectory.min_wrench_capacity': Param([0.0], 'the smallest wrench capacity per wrench axis (the '
                                            "mechanism's wrench_axes: N or N·m) a planned path may pass; 0: "
                                            'not checked', read_only=True),
    'trajectory.limit_margin': Param(0.8, 'share of the actuator speed and acceleration limits a plan may '
                                     'use (the fastest axis never runs at saturation)', (0.05, 1.0), True),
    'trajectory.max_path_poses': Param(1000, 'most poses a nav_msgs/Path goal may have (larger ones are '
                                       'rejected)', (1, 1000000), True),
    'trajectory.planning_budget': Param(1.0, 'longest a goal may take to plan (s); longer: rejected',
                                        (0.01, 60.0), True),
    # CAN
    'can.interface': Param('virtual', 'python-can interface (virtual, socketcan, ...)', read_only=True),
    'can.channel': Param('brace0', 'python-can channel', read_only=True),
    'can.bitrate': Param(1000000, 'bit rate (bit/s)', (10000, 1000000), True),
    'can.node_ids': Param([1, 2, 3], 'CANopen node id per actuator, in actuator order', read_only=True),
    'can.eds': Param('lumbar_drive.eds', 'EDS file of the drives (relative to the YAML)', read_only=True),
    'can.sync_rate_hz': Param(500.0, 'SYNC / control rate (Hz)', (1.0, 2000.0), True),
    'can.joint_state_rate_hz': Param(100.0, 'joint_states publish rate (Hz)', (1.0, 2000.0)),
    'can.boot_timeout': Param(3.0, 'wait for boot-up / first heartbeat (s)', (0.05, 60.0), True),
    'can.drive_heartbeat_ms': Param(50, 'drive heartbeat producer time 1017h (ms)', (1, 10000), True),
    'can.heartbeat_consumer_ms': Param(150, "master's timeout on a drive's heartbeat (ms)", (1, 30000), True),
    'can.master_heartbeat_ms': Param(100, "master's heartbeat producer time (ms)", (1, 10000), True),
    'can.master_node_id': Param(127, "master's node id", (1, 127), True),
    'can.homing_method': Param(35, 'CiA 402 homing method 6098h', (-128, 127), True),
    'can.frame_log': Param('', 'python-can log of the bus (.asc/.blf/.log), empty = none', read_only=True),
    'can.sim': Param(True, 'start the simulated brace on the bus', read_only=True),
    'can.sync_spin_us': Param(300, 'SYNC thread: busy-wait before each deadline (us)', (0, 5000), True),
    'can.sync_thread_priority': Param(0, 'SCHED_FIFO priority of the SYNC thread, 0 = normal '
                                      'scheduling (needs CAP_SYS_NICE)', (0, 99), True),
    'can.gil_switch_interval_us': Param(200, "driver process: Python's GIL switch interval (us), "
                                        "0 = keep Python's 5000 us", (0, 100000), True),
    # safety (SAFETY.md): read-only at run time
    'safety.command_timeout': Param(0.015, 'no setpoint received for this long -> hold (s)', (0.001, 5.0), True),
    'safety.following_error_window': Param(0.003, 'following error window 6065h (m or rad)', (1e-6, 1.0), True),
    'safety.path_tolerance': Param(0.005, 'tracking error in actuator coordinates -> abort and hold (m or rad)', (1e-6, 1.0), True),
    'safety.step_margin': Param(0.0005, 'margin on |dq| per cycle (m or rad)', (0.0, 1.0), True),
    'safety.force_limit': Param(250.0, 'load-cell force / torque -> protective stop', (0.0, 1e5), True),
    'safety.saturation_fraction': Param(0.95, 'load-cell saturation threshold (of full scale)', (0.5, 1.0), True),
    'safety.stale_periods': Param(3, 'periods without sensor update -> fault', (1, 1000), True),
    'safety.max_wrench': Param([150.0, 150.0, 30.0], 'platform wrench limit per axis', read_only=True),
    'safety.soft_force_limit': Param(0.0, 'load-cell force / torque above which a motion that keeps '
                                     'pressing decelerates and holds, nothing latched (0: 0.8 x '
                                     'safety.force_limit)', (0.0, 1e5), True),
    'safety.release_force': Param(0.0, 'a relief (~/relieve) backs off until every force is below this '
                                  '(0: 0.2 x safety.force_limit)', (0.0, 1e5), True),
    'safety.pose_tolerance': Param([0.002, 0.002, 0.00524], 'a goal succeeds only when the estimated pose '
                                   'is this close to it, per pose coordinate (m or rad)', read_only=True),
    'safety.settle_time': Param(0.5, 'after a motion finished, how long the estimate may take to reach '
                                'the goal (s)', (0.0, 60.0), True),
    'safety.report_timeout': Param(1.0, 'silence of the driver (no start, no end) before a goal is '
                                   'aborted (s)', (0.05, 60.0), True),
    # simulation
    'sim.rest_pose': Param([0.0, 0.39, 0.0872664626], "body's rest pose", read_only=True),
    'sim.stiffness': Param([0.0] * 9, 'body stiffness (row-major dof x dof)', read_only=True),
    'sim.damping': Param([0.0] * 9, 'body damping (row-major dof x dof)', read_only=True),
    'sim.leg_stiffness': Param(1.0e6, 'axial stiffness of each actuator leg (N/m)', (1.0, 1e12), True),
    'sim.load_cell_noise': Param(0.05, 'load-cell noise std (N)', (0.0, 1e3), True),
    'sim.load_cell_offset': Param(0.0, 'load-cell offset (N)', (-1e3, 1e3), True),
    'sim.seed': Param(1, 'random seed of the simulator', (0, 2**31 - 1), True),
    'sim.drive_bandwidth_hz': Param(30.0, 'position-loop bandwidth of the simulated CSP drives (Hz), '
                                    'Kp = 2 pi x bandwidth', (1.0, 500.0), True),
    'sim.truth_rate_hz': Param(20.0, 'rate of the ground-truth topics /brace/sim/* (Hz)', (0.1, 1000.0), True),
    # the simulated patient (brace_control/sim/brace.py, docs/interaction.md)
    'sim.sway_amplitude': Param([0.0], "amplitude of the patient's sway per pose axis (m, rad; [0.0]: none)",
                                read_only=True),
    'sim.sway_frequency_hz': Param(0.0, "frequency of the patient's sway (Hz; 0: none)", (0.0, 20.0), True),
    'sim.sway_phase': Param([0.0], "phase of the sway per pose axis (rad; [0.0]: all zero)", read_only=True),
    'sim.patient_max_wrench': Param([0.0], "the patient's largest effort per pose axis (N, N·m; 0: no limit)",
                                    read_only=True),
    # interaction_node: admittance control (brace_control/interaction, docs/interaction.md)
    'interaction.force_axes': Param([False], 'per pose axis: force controlled (true) or held (false)',
                                    read_only=True),
    'interaction.mass': Param([1.0], 'virtual mass per pose axis (kg, kg·m²)', read_only=True),
    'interaction.damping': Param([100.0], 'virtual damping per pose axis (N·s/m, N·m·s/rad)', read_only=True),
    'interaction.rate_hz': Param(200.0, 'admittance update and setpoint rate (Hz)', (10.0, 2000.0), True),
    'interaction.max_goal_wrench': Param([0.0], 'largest |wrench goal| per pose axis (N, N·m; 0: the '
                                         "mechanism's wrench capacity alone)", read_only=True),
    'interaction.stop_deceleration': Param([0.1], 'deceleration to rest on ~/stop per pose axis '
                                           '(m/s², rad/s²)', read_only=True),
    'interaction.wrench_timeout': Param(0.1, 'no /brace/wrench for this long -> stop (s)', (0.005, 5.0), True),
}


def _descriptor(name: str, spec: Param) -> ParameterDescriptor:
    d = ParameterDescriptor(description=spec.description, read_only=spec.read_only)
    if spec.range is not None:
        lo, hi = spec.range
        if isinstance(spec.default, bool):
            pass
        elif isinstance(spec.default, int):
            d.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi), step=0)]
        elif isinstance(spec.default, float):
            d.floating_point_range = [FloatingPointRange(from_value=float(lo), to_value=float(hi), step=0.0)]
    if spec.choices:
        d.additional_constraints = f'one of {", ".join(spec.choices)}'
    return d


def _overrides(node: Node) -> dict[str, Any]:
    """Parameter values the node was started with (params file, -p, overrides)."""
    raw = getattr(node, '_parameter_overrides', {}) or {}
    return {name: p.value for name, p in raw.items()}


def _nest(cfg: dict[str, Any], dotted: str, value: Any) -> None:
    keys = dotted.split('.')
    node = cfg
    for k in keys[:-1]:
        node = node.setdefault(k, {})
    node[keys[-1]] = value


def declare_device_parameters(node: Node, sections: Iterable[str]) -> DeviceConfig:
    """Declare the device parameters of ``sections`` on ``node`` and return them nested.

    ``sections`` names top-level groups (``'mechanism'``, ``'trajectory'``, ``'can'``,
    ``'safety'``, ``'actuator'``, ``'sim'``); ``device`` and the frames are always declared.

    :raises ConfigError: a value of the wrong type, out of range, or not one of its
        choices; the message names the parameter and what was expected.
    """
    sections = set(sections)
    given = _overrides(node)
    cfg: dict[str, Any] = {}

    def declare(name: str, default: Any, descriptor: ParameterDescriptor) -> Any:
        try:
            value = node.declare_parameter(name, default, descriptor).value
        except InvalidParameterValueException as exc:
            raise ConfigError(
                f'parameter {name!r} = {given.get(name)!r} is out of range: {exc}') from exc
        except InvalidParameterTypeException as exc:
            raise ConfigError(
                f'parameter {name!r} = {given.get(name)!r} has the wrong type; expected '
                f'{type(default).__name__} like {default!r}') from exc
        return value

    for name, spec in SCHEMA.items():
        group = name.split('.', 1)[0] if '.' in name else None
        if group is not None and group not in sections:
            continue
        value = declare(name, spec.default, _descriptor(name, spec))
        if isinstance(value, (list, tuple)) or type(value).__name__ == 'array':
            value = list(value)
        if spec.choices and value not in spec.choices:
            raise ConfigError(f'parameter {name!r} = {value!r}; expected one of {list(spec.choices)}')
        if spec.length is not None and len(value) != spec.length:
            raise ConfigError(f'parameter {name!r} needs {spec.length} values, got {len(value)}')
        _nest(cfg, name, value)

    if 'mechanism' in sections:
        mech_keys = sorted(k for k in given if k.startswith('mechanism.'))
        if not mech_keys:
            raise ConfigError(
                'no mechanism.* parameters: start the node with the device file, '
                '--ros-args --params-file config/<device>.yaml')
        for name in mech_keys:
            value = declare(name, given[name], ParameterDescriptor(
                description='mechanism geometry (from the device file)', read_only=True))
            if isinstance(value, (list, tuple)) or type(value).__name__ == 'array':
                value = list(value)
            _nest(cfg, name, value)
    return DeviceConfig(cfg)
