"""The one schema of the device parameters: name, type, range, unit, default, read-only.

Every device YAML (``config/<device>.yaml``) is checked against this table, by the pure
Python API (:class:`~brace_control.config.DeviceConfig`, built by
:func:`~brace_control.config.load_device_config` and by every ``from_config`` reader) and by
the nodes (:func:`brace_control.nodes.params.declare_device_parameters`, which also builds
the ROS ``ParameterDescriptor`` of each entry). A key the schema does not know is an error
naming the closest known one, so a misspelled ``safety.force_limt: 100`` stops the start-up
instead of leaving the 250 N default in force. Defaults live here and nowhere else.

This module imports neither rclpy nor the mechanism models.

* :data:`SCHEMA`: the sections every device shares (``device``, the frames, ``actuator.*``,
  ``kinetics.*``, ``trajectory.*``, ``can.*``, ``safety.*``, ``sim.*``) and the
  ``exercises.*`` of the trainer's report tool (``*`` matches one name segment).
* :data:`MECHANISM_SCHEMAS`: the ``mechanism.*`` geometry, one key set per
  ``mechanism.type`` (what that model's ``from_config`` reads).

A new section (e.g. ``interaction.*`` of a new node) is added as entries of :data:`SCHEMA`
here, not in its consumer: every node validates the whole parameter file, including
sections it does not use, so the table must be complete whichever module is imported.
"""
from __future__ import annotations

import difflib
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

__all__ = ['Param', 'SCHEMA', 'MECHANISM_SCHEMAS', 'MECHANISM_COMMON', 'REMOVED', 'ROS_BUILTIN_PREFIXES',
           'ConfigError', 'param_type', 'mechanism_params', 'lookup', 'validate', 'validate_flat',
           'check_value', 'with_defaults', 'flatten', 'known_names', 'SOFT_LIMIT_FRACTION',
           'RELEASE_FRACTION', 'soft_force_limit', 'release_force']


class ConfigError(ValueError):
    """A device file is missing, malformed, or holds a value out of its range (re-exported
    as :class:`brace_control.config.ConfigError`)."""


@dataclass(frozen=True)
class Param:
    """One parameter.

    :param default: value when the file does not give one; its Python type is the
        parameter's type (``float``, ``int``, ``bool``, ``str``, or a list of one of them).
        ``None``: optional without a default (the description says what absence means).
    :param description: one line for the ROS descriptor and the docs.
    :param range: ``(lo, hi)`` inclusive, for a number or for every element of a list.
    :param read_only: the node refuses to change it at run time.
    :param length: exact length of a list, ``None`` = any.
    :param choices: the allowed strings.
    :param unit: SI unit of the value (``'N'``, ``'m/s'``, ``'m or rad'`` ...), ``''`` if none.
    :param type: explicit type when ``default`` is ``None`` or cannot show it: ``'float'``,
        ``'int'``, ``'bool'``, ``'str'``, ``'float[]'``, ``'int[]'``, ``'str[]'``,
        ``'number'`` (a float or a list of floats: scalar or per actuator), ``'points'`` (a
        flat or nested list of floats), ``'int|str'``.
    :param int_ok: an integer is accepted for a float (geometry keys that ROS declares with
        the file's own value, so its type does not matter); the shared keys are typed like
        ROS parameters, where ``100`` for a double is an error (write ``100.0``).
    :param default_from: when absent, the value of this other parameter (one place for the
        fallback, e.g. ``sim.leg_stiffness`` from ``actuator.stiffness``).
    """

    default: Any
    description: str
    range: tuple[float, float] | None = None
    read_only: bool = False
    length: int | None = None
    choices: tuple[str, ...] | None = None
    unit: str = ''
    type: str = ''
    int_ok: bool = False
    default_from: str | None = None


def param_type(spec: Param) -> str:
    """The parameter's type name (see :class:`Param`)."""
    if spec.type:
        return spec.type
    d = spec.default
    if isinstance(d, bool):
        return 'bool'
    if isinstance(d, int):
        return 'int'
    if isinstance(d, float):
        return 'float'
    if isinstance(d, str):
        return 'str'
    if isinstance(d, (list, tuple)) and d:
        return param_type(Param(d[0], '')) + '[]'
    raise TypeError(f'schema entry with default {d!r} needs an explicit type')


def _ro(default: Any, description: str, range: tuple[float, float] | None = None, unit: str = '',
        **kw: Any) -> Param:
    return Param(default, description, range, True, unit=unit, **kw)


_INF = math.inf
SCHEMA: dict[str, Param] = {
    'device': _ro('lumbar_brace', 'device name'),
    'base_frame': _ro('brace_base', 'frame of the fixed base'),
    'platform_frame': _ro('brace_platform', 'frame of the moving platform'),
    # actuator (per actuator, SI)
    'actuator.kind': _ro('linear', 'linear (m, load cell 2401h) or rotary (rad, torque actual 6077h)',
                         choices=('linear', 'rotary')),
    'actuator.max_velocity': _ro(0.065, 'actuator speed limit', (1e-4, 100.0), 'm/s or rad/s'),
    'actuator.max_acceleration': _ro(0.5, 'actuator acceleration limit', (1e-4, 1e4), 'm/s^2 or rad/s^2'),
    'actuator.max_force': _ro(250.0, 'actuator force or torque limit', (0.0, 1e4), 'N or N·m'),
    'actuator.screw_lead': _ro(None, 'travel per motor revolution (linear actuators; a cable drum: '
                               '2 pi r); required when actuator.kind is linear', (1e-6, 1.0), 'm',
                               type='float'),
    'actuator.encoder_counts_per_rev': _ro(8192, 'encoder counts per motor revolution, one for all or per '
                                           'actuator', (1, 1 << 24), 'counts', type='int|int[]'),
    'actuator.polarity': _ro(1, '+1 or -1, one for all or per actuator: -1 turns the drive\'s counts around '
                             '(its position grows as the actuator shortens)', (-1, 1), type='int|int[]'),
    'actuator.load_cell_gain': _ro(1.0, 'load-cell reading per N of force, one for all or per actuator '
                                   '(brace-commission calibrate-load-cell)', (1e-6, 1e6), type='number'),
    'actuator.load_cell_offset': _ro(0.0, 'load-cell reading with no force, one for all or per actuator '
                                     '(the tare)', (-1e5, 1e5), 'N or N·m', type='number'),
    'actuator.load_cell_rated_force': _ro(300.0, 'load-cell full scale (rotary drives without motor data: '
                                          'torque full scale)', (1.0, 1e5), 'N or N·m'),
    'actuator.load_cell_n_per_count': _ro(0.01, 'load-cell scaling', (1e-9, 1e3), 'N/count or N·m/count'),
    'actuator.gear_ratio': _ro(1.0, 'motor turns per joint turn (rotary)', (1e-3, 1e5)),
    'actuator.torque_constant': _ro(None, 'motor torque constant (rotary: 6077h scaling); absent with '
                                    'rated_current: the torque reading is scaled like a load cell',
                                    (1e-6, 100.0), 'N·m/A', type='float'),
    'actuator.rated_current': _ro(None, 'motor rated current: 1000 ‰ of 6077h = rated_current × '
                                  'torque_constant × gear_ratio N·m at the joint', (1e-6, 1e4), 'A',
                                  type='float'),
    'actuator.stiffness': _ro(1.0e6, 'axial stiffness of each actuator with its load path in series: '
                              'leg length = encoder - effort / stiffness', (1.0, 1e12), 'N/m or N·m/rad'),
    # kinetics_node: the load-aware pose estimate (brace_control.mechanisms.pose_estimate)
    'kinetics.load_cell_noise': _ro(0.05, 'standard deviation of one load-cell or torque reading, for '
                                    'the pose covariance', (0.0, 1e4), 'N or N·m'),
    'kinetics.stiffness_rel_std': _ro(0.05, 'relative standard deviation of actuator.stiffness, for the '
                                      'pose covariance', (0.0, 1.0)),
    'kinetics.max_step': _ro(0.02, 'longest solver step of the pose estimate (pose norm): longer ones '
                             'are damped, the estimate never jumps', (1e-6, 10.0), 'm or rad'),
    'kinetics.max_iterations': _ro(8, 'solver iterations per joint state', (1, 100)),
    'kinetics.residual_sigmas': _ro(3.0, 'the legs close (exact) when every leg-length residual is within '
                                    'this many standard deviations, else least squares', (0.1, 1e6)),
    'kinetics.unobserved_variance': _ro(1e6, 'variance on /brace/pose_with_covariance entries the device '
                                        'does not measure', (1.0, 1e12), 'm^2 or rad^2'),
    'kinetics.ambiguity_distance': _ro(0.02, 'another assembly mode closer than this (pose norm) -> '
                                       'ambiguous forward solution', (0.0, 10.0), 'm or rad'),
    'kinetics.singularity_warn_fraction': _ro(0.5, 'cond(J) above this fraction of '
                                              'mechanism.singularity_condition_max -> warn', (1e-6, 1.0)),
    'kinetics.ambiguity_check_period': _ro(0.05, 'time between full forward solutions (all assembly '
                                           'modes)', (0.0, 10.0), 's'),
    'kinetics.rest_period': _ro(0.05, 'at rest (no reading moved beyond kinetics.rest_band_sigmas of '
                                'its noise since the last estimate) the estimate and its topics are '
                                'renewed at this period, not on every joint state (0: every joint '
                                'state)', (0.0, 0.1), 's'),
    'kinetics.rest_band_sigmas': _ro(5.0, 'a reading has moved when it differs from the one of the last '
                                     'estimate by more than this many of its standard deviations '
                                     '(encoder: quantum / sqrt(12); load cell: kinetics.load_cell_noise '
                                     'with its quantum)', (0.0, 1e3)),
    # trajectory
    'trajectory.rate_hz': _ro(200.0, 'setpoint rate', (1.0, 2000.0), unit='Hz'),
    'trajectory.profile': _ro('minimum_jerk', 'motion profile',
                                choices=('minimum_jerk', 'scurve', 'logcosh')),
    'trajectory.max_velocity': _ro([0.03, 0.03, 0.3], 'platform velocity limit per pose coordinate',
                                     (1e-9, _INF), unit='m/s or rad/s'),
    'trajectory.max_acceleration': _ro([0.1, 0.1, 1.0], 'platform acceleration limit per pose coordinate',
                                         (1e-9, _INF), unit='m/s^2 or rad/s^2'),
    'trajectory.max_jerk': _ro([1.0, 1.0, 10.0], 'platform jerk limit per pose coordinate',
                                 (1e-9, _INF), unit='m/s^3 or rad/s^3'),
    'trajectory.fitts_a': _ro(0.2, "Fitts' law intercept a", (0.0, 60.0), unit='s'),
    'trajectory.fitts_b': _ro(0.3, "Fitts' law slope b", (0.0, 60.0), unit='s/bit'),
    'trajectory.fitts_w': _ro(0.01, "Fitts' law target width W", (1e-6, 10.0), unit='m or rad'),
    'trajectory.path_check_samples': _ro(200, 'samples of a path checked for stroke, workspace and singularity (its '
                                           'actuator speed and acceleration are checked on the knots the driver runs)',
                                           (2, 100000)),
    'trajectory.min_wrench_capacity': _ro([0.0], 'the smallest wrench capacity per wrench axis (the '
                                          "mechanism's wrench_axes) a planned path may pass; 0: not checked",
                                          (0.0, _INF), 'N or N·m'),
    'trajectory.limit_margin': _ro(0.8, 'share of the actuator speed and acceleration limits a plan may '
                                   'use (the fastest axis never runs at saturation)', (0.05, 1.0)),
    'trajectory.max_path_poses': _ro(1000, 'most poses a nav_msgs/Path goal may have (larger ones are '
                                     'rejected)', (1, 1000000)),
    'trajectory.planning_budget': _ro(1.0, 'longest a goal may take to plan; longer: rejected',
                                      (0.01, 60.0), 's'),
    'trajectory.plan_lookahead': _ro(0.15, 'a plan takes over this long after its planning began: '
                                     'planning, IK and two DDS hops must fit in it, else the '
                                     'driver blends a late start in, or rejects it beyond '
                                     'safety.path_tolerance (raise it on a slow or busy host)',
                                     (0.02, 5.0), 's'),
    # CAN
    'can.interface': _ro('virtual', 'python-can interface (virtual, socketcan, ...)'),
    'can.channel': _ro('brace0', 'python-can channel'),
    'can.bitrate': _ro(1000000, 'bit rate', (10000, 1000000), 'bit/s'),
    'can.node_ids': _ro([1, 2, 3], 'CANopen node id per actuator, in actuator order', (1, 127)),
    'can.eds': _ro('', "the drives' EDS or DCF, relative to the YAML: one file for every drive, or a "
                   "list of one per can.node_ids entry; empty: the package's config/lumbar_drive.eds",
                   type='str|str[]'),
    'can.load_cell_object': _ro('', "the object carrying each actuator's load cell on its drive, "
                                '"0xIIII:SS" (e.g. a drive\'s analog input "0x3220:1"); empty: 2401h:0, '
                                'or 6077h:0 (torque actual) for rotary drives'),
    'can.load_cell_node.node_id': _ro(0, 'node id of a CiA 401 analog-input module carrying the load '
                                      'cells (0: the drives carry them, can.load_cell_object)', (0, 127)),
    'can.load_cell_node.eds': _ro('', "the load-cell module's EDS or DCF (relative to the YAML)"),
    'can.load_cell_node.objects': _ro(None, "the module's object per actuator, in actuator order; absent: "
                                      '6401h:1, 6401h:2, ... (CiA 401 analog inputs)', type='str[]'),
    'can.load_cell_node.tpdo': _ro(1, "the module's TPDO that carries them", (1, 512)),
    'can.rpdo.*.mapping': _ro(None, 'objects the RPDO carries, "0xIIII:SS" each (ros2_canopen bus.yml '
                              'shape); the master fills 6040h, 607Ah, 60B1h and 6060h', type='str[]'),
    'can.rpdo.*.transmission': _ro(1, 'RPDO transmission type (0-240: applied at the next SYNC)', (0, 255)),
    'can.rpdo.*.cob_id': _ro(0, 'RPDO COB-ID (0: the CiA 301 pre-defined one, RPDOs 1-4)', (0, 0x7FF)),
    'can.rpdo.*.enabled': _ro(True, 'the RPDO is used (false: disabled on the drive)'),
    'can.tpdo.*.mapping': _ro(None, 'objects the TPDO carries, "0xIIII:SS" each; the one with 6041h '
                              'must also carry 6064h and the load cell', type='str[]'),
    'can.tpdo.*.transmission': _ro(1, 'TPDO transmission type (1: every SYNC)', (0, 255)),
    'can.tpdo.*.cob_id': _ro(0, 'TPDO COB-ID (0: the CiA 301 pre-defined one, TPDOs 1-4)', (0, 0x7FF)),
    'can.tpdo.*.enabled': _ro(True, 'the TPDO is used (false: disabled on the drive)'),
    'can.sdo_timeout': _ro(0.1, 'longest an SDO answer may take before the request is sent again '
                           '(can.sdo_retries) or the boot fails', (0.001, 10.0), 's'),
    'can.sdo_retries': _ro(1, 'times an unanswered SDO request is sent again', (0, 10)),
    'can.sync_rate_hz': _ro(500.0, 'SYNC / control rate', (1.0, 2000.0), 'Hz'),
    'can.joint_state_rate_hz': _ro(100.0, 'joint_states publish rate', (1.0, 2000.0), unit='Hz'),
    'can.boot_timeout': _ro(3.0, 'wait for boot-up / first heartbeat', (0.05, 60.0), 's'),
    'can.drive_heartbeat_ms': _ro(50, 'drive heartbeat producer time 1017h', (1, 10000), 'ms'),
    'can.heartbeat_consumer_ms': _ro(150, "master's timeout on a drive's heartbeat", (1, 30000), 'ms'),
    'can.master_heartbeat_ms': _ro(100, "master's heartbeat producer time", (1, 10000), 'ms'),
    'can.master_node_id': _ro(127, "master's node id", (1, 127)),
    'can.homing_method': _ro(35, 'CiA 402 homing method 6098h', (-128, 127)),
    'can.frame_log': _ro('', 'python-can log of the bus (.asc/.blf/.log), empty = none'),
    'can.sim': _ro(True, 'start the simulated brace on the bus'),
    'can.cycle_process': _ro(True, 'run the control cycle (CAN I/O, SYNC, execution, the safety tiers, '
                             'the simulated brace) in a process of its own, where rclpy never runs '
                             "(false: in the driver node's process)"),
    'can.cycle_priority': _ro(50, "SCHED_FIFO priority of the control cycle's process, all its threads "
                              '(can.cycle_process; needs CAP_SYS_NICE or an rtprio allowance, else '
                              'can.cycle_nice applies and the log says so); 0: normal scheduling',
                              (0, 99)),
    'can.cycle_nice': _ro(-10, "niceness of the control cycle's process when it runs without "
                          'can.cycle_priority: below 0 the kernel runs it before the nodes when the '
                          'cores are busy (needs CAP_SYS_NICE or an RLIMIT_NICE allowance, else it '
                          'keeps 0 and says so); 0: unchanged', (-20, 19)),
    'can.sync_spin_us': _ro(0, 'SYNC thread: busy-wait before each deadline (0: sleep only)', (0, 5000), 'us'),
    'can.sync_thread_priority': _ro(0, 'SCHED_FIFO priority of the SYNC thread, 0 = normal scheduling '
                                    '(needs CAP_SYS_NICE)', (0, 99)),
    'can.gil_switch_interval_us': _ro(200, "the cycle's process: Python's GIL switch interval, 0 = keep "
                                      "Python's 5000 us", (0, 100000), 'us'),
    # safety (docs/safety.md): read-only at run time
    'safety.command_timeout': _ro(0.015, 'no setpoint received for this long -> hold', (0.001, 5.0), 's'),
    'safety.following_error_window': _ro(0.003, 'following error window 6065h', (1e-6, 1.0), 'm or rad'),
    'safety.path_tolerance': _ro(0.005, 'tracking error in actuator coordinates -> abort and hold',
                                 (1e-6, 1.0), 'm or rad'),
    'safety.step_margin': _ro(0.0005, 'margin on |dq| per cycle', (0.0, 1.0), 'm or rad'),
    'safety.force_limit': _ro(250.0, 'load-cell force / torque -> protective stop', (0.0, 1e5), 'N or N·m'),
    'safety.saturation_fraction': _ro(0.95, 'load-cell saturation threshold (of full scale)', (0.5, 1.0)),
    'safety.stale_periods': _ro(3, 'periods without sensor update -> fault', (1, 1000)),
    'safety.max_wrench': _ro([150.0, 150.0, 30.0], 'platform wrench limit per axis', (0.0, _INF), 'N or N·m'),
    'safety.soft_force_limit': _ro(0.0, 'load-cell force / torque above which a motion that keeps pressing '
                                   'decelerates and holds, nothing latched (0: SOFT_LIMIT_FRACTION = 0.8 x '
                                   'safety.force_limit)',
                                   (0.0, 1e5), 'N or N·m'),
    'safety.release_force': _ro(0.0, 'a relief (~/relieve) backs off until every force is below this '
                                '(0: RELEASE_FRACTION = 0.2 x safety.force_limit)', (0.0, 1e5), 'N or N·m'),
    'safety.pose_tolerance': _ro([0.002, 0.002, 0.00524], 'a goal succeeds only when the estimated pose '
                                 'is this close to it, per pose coordinate', (0.0, _INF), 'm or rad'),
    'safety.settle_time': _ro(0.5, 'after a motion finished, how long the estimate may take to reach '
                              'the goal', (0.0, 60.0), 's'),
    'safety.report_timeout': _ro(1.0, 'silence of the driver (no start, no end) before a goal is '
                                 'aborted', (0.05, 60.0), 's'),
    # simulation
    'sim.rest_pose': _ro(None, "body's rest pose; absent: mechanism's home pose", unit='m or rad',
                         type='float[]'),
    'sim.stiffness': _ro(None, 'body stiffness (row-major dof x dof); absent: none (a free body)',
                         unit='N/m or N·m/rad', type='float[]'),
    'sim.damping': _ro(None, 'body damping (row-major dof x dof); absent: none', unit='N·s/m or N·m·s/rad',
                       type='float[]'),
    'sim.leg_stiffness': _ro(None, 'axial stiffness of each simulated actuator leg in series; absent: '
                             'actuator.stiffness', (1.0, 1e12), 'N/m or N·m/rad', type='float',
                             default_from='actuator.stiffness'),
    'sim.load_cell_noise': _ro(0.05, 'load-cell noise standard deviation', (0.0, 1e3), 'N or N·m'),
    'sim.load_cell_offset': _ro(0.0, "load-cell offset, one for all or per actuator (the hardware's "
                                'truth; actuator.load_cell_offset is what the user believes)', (-1e3, 1e3),
                                'N or N·m', type='number'),
    'sim.load_cell_gain': _ro(1.0, 'load-cell gain (reading per N of force), one for all or per actuator',
                              (1e-6, 1e6), type='number'),
    'sim.node_ids': _ro(None, 'the node ids the simulated drives really have, in actuator order (0: that '
                        'drive does not answer); absent: can.node_ids', (0, 127), type='int[]'),
    'sim.polarity': _ro(None, 'the simulated drives\' real polarity, +1 or -1 per actuator; absent: all +1',
                        (-1, 1), type='int|int[]'),
    'sim.encoder_counts_per_rev': _ro(None, 'the simulated encoders\' real counts per revolution, one for '
                                      'all or per actuator; absent: actuator.encoder_counts_per_rev',
                                      (1, 1 << 24), 'counts', type='int|int[]'),
    'sim.extra_node_ids': _ro(None, 'foreign nodes on the simulated bus (CiA 401 I/O modules) besides the '
                              'brace\'s', (1, 127), type='int[]'),
    'sim.seed': _ro(1, 'random seed of the simulator', (0, 2**31 - 1)),
    'sim.drive_bandwidth_hz': _ro(30.0, 'position-loop bandwidth of the simulated CSP drives, '
                                  'Kp = 2 pi x bandwidth', (1.0, 500.0), 'Hz'),
    'sim.truth_rate_hz': _ro(20.0, 'rate of the ground-truth topics /brace/sim/*', (0.1, 1000.0), 'Hz'),
    # the simulated patient (brace_control/sim/brace.py, docs/interaction.md)
    'sim.sway_amplitude': _ro([0.0], "amplitude of the patient's sway per pose axis ([0.0]: none)",
                              (0.0, 10.0), 'm or rad'),
    'sim.sway_frequency_hz': _ro(0.0, "frequency of the patient's sway (0: none)", (0.0, 20.0), 'Hz'),
    'sim.sway_phase': _ro([0.0], 'phase of the sway per pose axis ([0.0]: all zero)',
                          (-2 * math.pi, 2 * math.pi), 'rad'),
    'sim.patient_max_wrench': _ro([0.0], "the patient's largest effort per pose axis (0: no limit)",
                                  (0.0, 1e5), 'N or N·m'),
    # interaction_node and the driver's in-cycle admittance (brace_control/interaction)
    'interaction.force_axes': _ro([False], 'per pose axis: force controlled (true) or held (false)'),
    'interaction.mass': _ro([1.0], 'virtual mass per pose axis', (1e-9, 1e6), 'kg or kg·m²'),
    'interaction.damping': _ro([100.0], 'virtual damping per pose axis', (1e-9, 1e8),
                               'N·s/m or N·m·s/rad'),
    'interaction.rate_hz': _ro(200.0, 'admittance update rate', (10.0, 2000.0), 'Hz'),
    'interaction.max_goal_wrench': _ro([0.0], "largest |wrench goal| per pose axis (0: the mechanism's "
                                       'wrench capacity alone)', (0.0, 1e5), 'N or N·m'),
    'interaction.stop_deceleration': _ro([0.1], 'deceleration to rest on ~/stop and at a limit, per pose '
                                         'axis', (1e-6, 1e4), 'm/s² or rad/s²'),
    'interaction.goal_rate': _ro([0.0], 'a new wrench goal is tracked as a ramp at this rate per pose axis '
                                 '(0: a step)', (0.0, 1e6), 'N/s or N·m/s'),
    'interaction.wrench_timeout': _ro(0.1, 'no effect (kept for older device files): the admittance '
                                      "reads the drives' load cells in the cycle, a silent one is "
                                      'stale feedback (docs/interaction.md)', (0.005, 5.0), 's'),
}


def _ex(type_: str, description: str, range: tuple[float, float] | None = None, unit: str = '') -> Param:
    """An ``exercises.*`` entry of the trainer's report tool (no default: the tool's own)."""
    return Param(None, description, range, True, unit=unit, type=type_, int_ok=True)


# brace-fourbar-report (brace_control/tools/fourbar_report.py): thesis 002 ch. 4 exercises
SCHEMA.update({
    'exercises.names': _ex('str[]', 'exercises the report runs'),
    'exercises.dead_point_margin': _ex('float', 'springs are fitted where |sin(theta2 - theta3)| >= this',
                                       (0.0, 1.0)),
    'exercises.optimiser.seed': _ex('int', 'differential evolution seed', (0, 2**31 - 1)),
    'exercises.optimiser.maxiter': _ex('int', 'differential evolution generations', (1, 1000000)),
    'exercises.optimiser.popsize': _ex('int', 'differential evolution population factor', (1, 10000)),
    'exercises.optimiser.unilateral': _ex('bool', 'contact springs push only while compressed'),
    'exercises.*.start': _ex('float[]', 'start point of the hand path', unit='m'),
    'exercises.*.goal': _ex('float[]', 'end point of the hand path', unit='m'),
    'exercises.*.via': _ex('float[]', 'via point of the hand path', unit='m'),
    'exercises.*.t_via': _ex('float', 'time of the via point', (0.0, 1e4), 's'),
    'exercises.*.duration': _ex('float', 'duration of the exercise', (1e-3, 1e4), 's'),
    'exercises.*.samples': _ex('int', 'samples of the exercise', (2, 10**7)),
    'exercises.*.follow': Param(None, 'crank law: x (P follows the path x) or nearest', read_only=True,
                                choices=('x', 'nearest'), type='str'),
    'exercises.*.hand_t': _ex('float[]', "times of the impaired user's hand samples", unit='s'),
    'exercises.*.hand_x': _ex('float[]', "x of the impaired user's hand samples", unit='m'),
    'exercises.*.max_patient_force': _ex('float', 'F_PUmax (eq. 3.20)', (0.0, 1e5), 'N'),
    'exercises.*.thesis_links': _ex('float[]', "L1, L2, L3 of the thesis's replica", (0.0, 10.0), 'm'),
    'exercises.*.spring_bounds': _ex('float[]', 'eq. 4.1 bounds, flattened (lo, hi) pairs'),
    'exercises.*.thesis_springs': _ex('float[]', 'Table 4.1 springs, for comparison'),
})

#: keys that were removed, with what to do instead
REMOVED: dict[str, str] = {
    'sim.drive_acceleration_factor': (
        'was removed: the simulated drives are CSP servo drives (interpolated 607Ah, 60B1h velocity '
        'feed-forward, a position loop of sim.drive_bandwidth_hz) and accelerate at '
        "actuator.max_acceleration, the actuator's real limit; delete the key from the device file "
        '(docs/can.md)'),
}

#: parameters rclpy itself may be given in a parameter file (not device parameters)
ROS_BUILTIN_PREFIXES: tuple[str, ...] = ('use_sim_time', 'start_type_description_service',
                                         'start_parameter_event_publisher', 'qos_overrides.')


# ---------------------------------------------------------------------- mechanism.* per type
def _m(type_: str, description: str, range: tuple[float, float] | None = None, unit: str = '',
       default: Any = None, choices: tuple[str, ...] | None = None) -> Param:
    """A ``mechanism.*`` geometry entry: read-only, integers accepted for floats (the node
    declares it with the file's own value); no default unless given (the model's own)."""
    return Param(default, description, range, True, choices=choices, unit=unit, type=type_, int_ok=True)


_LEN = (0.0, 100.0)
_ANGLE = (-100.0, 100.0)
#: keys every mechanism type reads
MECHANISM_COMMON: dict[str, Param] = {
    'type': _m('str', 'mechanism model (mechanism_from_config)'),
    'actuator_names': _m('str[]', 'actuator (joint) names, in actuator order'),
    'home_pose': _m('float[]', 'pose the device parks at (absent: the model picks one)', unit='m or rad'),
}


def _cond(default: float) -> Param:
    return _m('float', 'cond(J) above this: treated as singular', (1.0, 1e15), default=default)


_STROKE_MIN = _m('number', 'shortest actuator length, scalar or per actuator', _LEN, 'm')
_STROKE_MAX = _m('number', 'longest actuator length, scalar or per actuator', _LEN, 'm')
_JOINT_MIN = _m('number', 'lowest joint angle, scalar or per joint', _ANGLE, 'rad')
_JOINT_MAX = _m('number', 'highest joint angle, scalar or per joint', _ANGLE, 'rad')

#: ``mechanism.type`` -> the keys its ``from_config`` reads (besides :data:`MECHANISM_COMMON`)
MECHANISM_SCHEMAS: dict[str, dict[str, Param]] = {
    'rpr3': {   # brace_control/mechanisms/rpr3.py, planar 3-RPR (seed 001)
        'base_anchors': _m('points', 'A_i in the base frame, flattened [x0, y0, ...]', unit='m'),
        'platform_anchors': _m('points', 'B_i in the platform frame, flattened', unit='m'),
        'stroke_min': _STROKE_MIN, 'stroke_max': _STROKE_MAX,
        'singularity_condition_max': _cond(1e4),
    },
    'rpr4': {   # brace_control/mechanisms/rpr4.py, planar 4-RPR / cable neck brace
        'base_anchors': _m('points', 'A_i in the base frame, flattened', unit='m'),
        'platform_anchors': _m('points', 'B_i in the platform frame, flattened (or platform_radius and '
                               'anchor_angles)', unit='m'),
        'platform_radius': _m('float', 'radius of the platform anchors', _LEN, 'm'),
        'anchor_angles': _m('float[]', 'angles of the platform anchors (delta_n)', _ANGLE, 'rad'),
        'stroke_min': _STROKE_MIN, 'stroke_max': _STROKE_MAX,
        'actuation': _m('str', 'cable (pull only) or rod (push/pull)'),
        'tension_min': _m('float', 'least cable tension', (0.0, 1e6), 'N'),
        'tension_max': _m('float', 'largest cable tension', (0.0, _INF), 'N'),
        'force_max': _m('float', 'largest rod force', (0.0, _INF), 'N'),
        'distribution': _m('str', 'tension distribution: centre or min_norm'),
        'residual_max': _m('float', 'largest leg-length residual of the forward solution', (0.0, 1.0), 'm'),
        'singularity_condition_max': _cond(1e4),
    },
    'rr2': {    # brace_control/mechanisms/rr2.py, serial 2R neck brace
        'link_lengths': _m('float[]', 'l1, l2', _LEN, 'm'),
        'joint_min': _JOINT_MIN, 'joint_max': _JOINT_MAX,
        'base': _m('float[]', 'base joint position (x0, y0)', (-100.0, 100.0), 'm'),
        'elbow': _m('str', 'elbow up or down'),
        'singularity_condition_max': _cond(1e4),
    },
    'rrr3': {   # brace_control/mechanisms/rrr3.py, planar 3-RRR
        'base_pivots': _m('points', 'base pivots, flattened', unit='m'),
        'platform_anchors': _m('points', 'platform anchors in the platform frame, flattened', unit='m'),
        'proximal_lengths': _m('number', 'proximal link lengths, scalar or three', _LEN, 'm'),
        'distal_lengths': _m('number', 'distal link lengths, scalar or three', _LEN, 'm'),
        'joint_min': _JOINT_MIN, 'joint_max': _JOINT_MAX,
        'working_mode': _m('int[]', 'sign (+1/-1) of each leg', (-1, 1)),
        'singularity_condition_max': _cond(1e4),
    },
    'spherical_3rrr': {   # brace_control/mechanisms/spherical.py, spherical 3-RRR shoulder
        'gamma': _m('float', 'base cone half-angle', _ANGLE, 'rad'),
        'beta': _m('float', 'platform cone half-angle', _ANGLE, 'rad'),
        'alpha1': _m('float[]', 'proximal arc angles', _ANGLE, 'rad'),
        'alpha2': _m('float[]', 'distal arc angles', _ANGLE, 'rad'),
        'delta': _m('float[]', 'leg placement angles', _ANGLE, 'rad'),
        'working_mode': _m('int|str', 'working mode, e.g. "++-"'),
        'joint_min': _JOINT_MIN, 'joint_max': _JOINT_MAX,
        'singularity_condition_max': _cond(100.0),
        'load_forces': _m('float[]', 'design loads of the study (brace-spm-study)', (0.0, 1e6), 'N'),
        'load_lever_arms': _m('float[]', 'lever arms of the design loads', _LEN, 'm'),
    },
    'hoeken_fourbar': {   # brace_control/mechanisms/fourbar.py, Hoeken's four-bar trainer
        'ground': _m('float', 'L1, O2 O4', _LEN, 'm'),
        'crank': _m('float', 'L2, O2 A', _LEN, 'm'),
        'coupler': _m('float', 'L3, A B', _LEN, 'm'),
        'rocker': _m('float', 'L4, O4 B', _LEN, 'm'),
        'coupler_extension': _m('float', 'B P on A B extended', _LEN, 'm'),
        'branch': _m('str', 'assembly branch: open or crossed'),
        'crank_range': _m('float[]', 'crank angle range [lo, hi]', _ANGLE, 'rad'),
        'curve_tolerance': _m('float', 'a pose this close to the coupler curve is projected onto it',
                              (0.0, 1.0), 'm'),
        'masses': _m('float[]', 'link masses m2, m3, m4', (0.0, 1e4), 'kg'),
        'cg_fractions': _m('float[]', 'centre of gravity along each link (fraction)', (-10.0, 10.0)),
        'inertias': _m('float[]', 'moments of inertia about each centre of gravity', (0.0, 1e4), 'kg m^2'),
        'bar_width': _m('float', 'bar width', _LEN, 'm'),
        'flywheel_mass': _m('float', 'flywheel mass on the crank axis', (0.0, 1e4), 'kg'),
        'flywheel_inertia': _m('float', 'flywheel moment of inertia', (0.0, 1e4), 'kg m^2'),
        'gravity': _m('float[]', 'gravity in the plane', (-100.0, 100.0), 'm/s^2'),
    },
    'continuum2': {   # brace_control/mechanisms/continuum.py, planar continuum robot (seed 003)
        'bar_length': _m('float', 'length of each bar', _LEN, 'm'),
        'youngs_modulus': _m('float', "Young's modulus of the bars", (1.0, 1e13), 'Pa'),
        'width': _m('float', 'bar cross-section width', _LEN, 'm'),
        'thickness': _m('float', 'bar thickness in the bending plane', _LEN, 'm'),
        'stroke_min': _m('number', 'slider positions, lowest', (-100.0, 100.0), 'm'),
        'stroke_max': _m('number', 'slider positions, highest', (-100.0, 100.0), 'm'),
        'k_max': _m('float', 'largest elliptic modulus used', (0.0, 1.0)),
        'min_half_distance': _m('float', 'the carriages touch at 2 x this', (0.0, 100.0), 'm'),
    },
}


def mechanism_params(kind: Any) -> dict[str, Param] | None:
    """``mechanism.*`` entries (without the prefix) of mechanism type ``kind``; every type's
    keys when ``kind`` is ``None``; ``None`` for an unknown type."""
    if kind is None:
        merged = dict(MECHANISM_COMMON)
        for keys in MECHANISM_SCHEMAS.values():
            for k, v in keys.items():
                merged.setdefault(k, v)
        return merged
    if not isinstance(kind, str) or kind not in MECHANISM_SCHEMAS:
        return None
    return {**MECHANISM_COMMON, **MECHANISM_SCHEMAS[kind]}


def default(name: str) -> Any:
    """The schema's default of the shared parameter ``name`` (dotted): where a reader of a
    plain mapping (not a :class:`~brace_control.config.DeviceConfig`, which has them filled
    in) needs a fallback, it takes it from here, not from a literal of its own."""
    spec = lookup(name)
    if spec is None:
        raise KeyError(f'no parameter {name!r} in the schema')
    return spec.default


def mechanism_default(kind: Any, key: str) -> Any:
    """The default of ``mechanism.<key>`` for mechanism type ``kind`` (a type without the
    key, an unknown or absent type: the first type's that has it)."""
    params = mechanism_params(kind)
    if not params or key not in params:
        params = mechanism_params(None)
    return params[key].default


# ---------------------------------------------------------------------------------- checking
def flatten(params: Mapping[str, Any], prefix: str = '') -> dict[str, Any]:
    """Nested mapping -> ``{'mechanism.type': 'rpr3', ...}`` as ROS names its parameters."""
    out: dict[str, Any] = {}
    for key, value in params.items():
        name = f'{prefix}{key}'
        if isinstance(value, Mapping):
            out.update(flatten(value, f'{name}.'))
        else:
            out[name] = value
    return out


def _matches(pattern: str, name: str) -> bool:
    a, b = pattern.split('.'), name.split('.')
    return len(a) == len(b) and all(p == '*' or p == n for p, n in zip(a, b))


def lookup(name: str, mechanism_type: Any = None) -> Param | None:
    """The schema entry of the dotted ``name`` (``mechanism.*`` of ``mechanism_type``)."""
    if name.startswith('mechanism.'):
        keys = mechanism_params(mechanism_type)
        return None if keys is None else keys.get(name[len('mechanism.'):])
    if name in SCHEMA:
        return SCHEMA[name]
    for pattern, spec in SCHEMA.items():
        if '*' in pattern and _matches(pattern, name):
            return spec
    return None


def known_names(mechanism_type: Any = None) -> list[str]:
    """Every parameter name the schema knows (``mechanism.*`` of ``mechanism_type``)."""
    names = [n for n in SCHEMA if '*' not in n]
    names += [f'mechanism.{k}' for k in (mechanism_params(mechanism_type) or {})]
    return names


def _suggest(name: str, mechanism_type: Any) -> str | None:
    candidates = known_names(mechanism_type)
    parts = name.split('.')
    for pattern in SCHEMA:        # wildcard entries, with the name's own segment in the '*'
        p = pattern.split('.')
        if '*' in p and len(p) == len(parts):
            candidates.append('.'.join(n if q == '*' else q for q, n in zip(p, parts)))
    best = difflib.get_close_matches(name, candidates, n=1, cutoff=0.6)
    return best[0] if best else None


def _where(source: str | None) -> str:
    return f' in {source}' if source else ''


def _fmt(x: float) -> str:
    return f'{x:g}' if math.isfinite(x) else ('inf' if x > 0 else '-inf')


def _expected(spec: Param) -> str:
    t = param_type(spec)
    words = {'float': 'a float', 'int': 'an integer', 'bool': 'true or false', 'str': 'a string',
             'float[]': 'a list of floats', 'int[]': 'a list of integers', 'str[]': 'a list of strings', 'bool[]': 'a list of booleans',
             'number': 'a float or a list of floats', 'points': 'a list of point coordinates (floats)',
             'int|str': 'an integer or a string', 'str|str[]': 'a string or a list of strings',
             'int|int[]': 'an integer or a list of integers'}[t]
    if spec.default is not None:
        words += f' like {spec.default!r}'
    if spec.unit:
        words += f' ({spec.unit})'
    return words


def _is_float(v: Any, int_ok: bool) -> bool:
    if isinstance(v, bool):
        return False
    return isinstance(v, float) or (int_ok and isinstance(v, int))


def _numbers(value: Any, int_ok: bool, nested: bool) -> list[float] | None:
    """The floats of a list (nested lists too when ``nested``), else ``None``."""
    if not isinstance(value, (list, tuple)):
        return None
    out: list[float] = []
    for v in value:
        if nested and isinstance(v, (list, tuple)):
            inner = _numbers(v, int_ok, False)
            if inner is None:
                return None
            out += inner
        elif _is_float(v, int_ok):
            out.append(float(v))
        else:
            return None
    return out


def check_value(name: str, value: Any, spec: Param, source: str | None = None) -> None:
    """Type, finiteness, range, length and choices of one value.

    :raises ConfigError: naming ``name``, the value, what was expected and the unit.
    """
    t = param_type(spec)
    head = f'parameter {name!r} = {value!r}{_where(source)}'
    numbers: list[float] | None = None
    ok: bool
    if t == 'float':
        ok = _is_float(value, spec.int_ok)
        numbers = [float(value)] if ok else None
    elif t == 'int':
        ok = isinstance(value, int) and not isinstance(value, bool)
        numbers = [value] if ok else None
    elif t == 'bool':
        ok = isinstance(value, bool)
    elif t == 'str':
        ok = isinstance(value, str)
    elif t == 'int|int[]':
        one = lambda v: isinstance(v, int) and not isinstance(v, bool)
        ok = one(value) or (isinstance(value, (list, tuple)) and bool(value) and all(one(v) for v in value))
        numbers = ([value] if one(value) else list(value)) if ok else None
    elif t == 'str|str[]':
        ok = isinstance(value, str) or (isinstance(value, (list, tuple)) and bool(value)
                                        and all(isinstance(v, str) for v in value))
    elif t == 'int|str':
        ok = isinstance(value, str) or (isinstance(value, int) and not isinstance(value, bool)) or (
            isinstance(value, (list, tuple)) and all(isinstance(v, int) and not isinstance(v, bool) for v in value))
    elif t in ('float[]', 'points'):
        numbers = _numbers(value, spec.int_ok, t == 'points')
        ok = numbers is not None
    elif t == 'number':
        if _is_float(value, spec.int_ok):
            numbers = [float(value)]
        else:
            numbers = _numbers(value, spec.int_ok, False)
        ok = numbers is not None
    elif t == 'int[]':
        ok = isinstance(value, (list, tuple)) and all(isinstance(v, int) and not isinstance(v, bool)
                                                      for v in value)
        numbers = list(value) if ok else None
    elif t == 'str[]':
        ok = isinstance(value, (list, tuple)) and all(isinstance(v, str) for v in value)
    elif t == 'bool[]':
        ok = isinstance(value, (list, tuple)) and all(isinstance(v, bool) for v in value)
    else:  # pragma: no cover - a schema typo
        raise TypeError(f'schema type {t!r} of {name!r}')
    if not ok:
        hint = ''
        if t in ('float', 'float[]') and not spec.int_ok and isinstance(value, (int, list, tuple)) \
                and not isinstance(value, bool):
            hint = ' (ROS parameters are typed: write 100.0, not 100)'
        raise ConfigError(f'{head} has the wrong type: expected {_expected(spec)}{hint}')
    if numbers is not None and not all(math.isfinite(x) for x in numbers):
        raise ConfigError(f'{head} contains a non-finite value; expected {_expected(spec)}')
    if spec.range is not None and numbers is not None:
        lo, hi = spec.range
        bad = [x for x in numbers if not lo <= x <= hi]
        if bad:
            unit = f' {spec.unit}' if spec.unit else ''
            each = ' (each value)' if isinstance(value, (list, tuple)) else ''
            raise ConfigError(f'{head} is out of range: expected {_fmt(lo)} to {_fmt(hi)}{unit}{each}')
    if spec.length is not None and isinstance(value, (list, tuple)) and len(value) != spec.length:
        raise ConfigError(f'{head} needs {spec.length} values, got {len(value)}')
    if spec.choices is not None and value not in spec.choices:
        raise ConfigError(f'{head} is not allowed: expected one of {list(spec.choices)}')


def validate_flat(flat: Mapping[str, Any], source: str | None = None) -> None:
    """Check flattened parameters (``{'safety.force_limit': 100.0, ...}``) against the schema.

    :param source: where they came from, for the message (``config/x.yaml``).
    :raises ConfigError: the first unknown key (with the closest known name), wrong type or
        out-of-range value, naming the key.
    """
    kind = flat.get('mechanism.type')
    if 'mechanism.type' in flat and (not isinstance(kind, str) or kind not in MECHANISM_SCHEMAS):
        raise ConfigError(f'parameter {"mechanism.type"!r} = {kind!r}{_where(source)} is unknown; '
                          f'expected one of {sorted(MECHANISM_SCHEMAS)}')
    names = sorted(flat)
    specs: dict[str, Param] = {}
    for name in names:                 # unknown keys first: the likeliest cause of the rest
        if name in REMOVED:
            raise ConfigError(f'{name} {REMOVED[name]}' + (f' (in {source})' if source else ''))
        spec = lookup(name, kind)
        if spec is None:
            guess = _suggest(name, kind)
            hint = f"; did you mean {guess!r}?" if guess else ''
            what = f' for mechanism.type {kind!r}' if name.startswith('mechanism.') and kind else ''
            raise ConfigError(f'unknown parameter {name!r}{_where(source)}{what}{hint}')
        specs[name] = spec
    for name in names:
        if name.startswith('mechanism.') and kind is None:
            continue                   # no type: the keys of every type; values checked by from_config
        check_value(name, flat[name], specs[name], source)


def validate(params: Mapping[str, Any], source: str | None = None) -> None:
    """:func:`validate_flat` of a nested mapping (the ``ros__parameters`` of a device file)."""
    validate_flat(flatten(params), source)


def nest(cfg: dict[str, Any], dotted: str, value: Any) -> None:
    """Set ``cfg['a']['b']['c'] = value`` for ``dotted`` = ``'a.b.c'`` (creating the levels)."""
    keys = dotted.split('.')
    node = cfg
    for k in keys[:-1]:
        node = node.setdefault(k, {})
    node[keys[-1]] = value


def _get(cfg: Mapping[str, Any], dotted: str) -> Any:
    node: Any = cfg
    for k in dotted.split('.'):
        if not isinstance(node, Mapping) or k not in node:
            return None
        node = node[k]
    return node


#: ``safety.soft_force_limit = 0`` means this share of ``safety.force_limit`` (docs/safety.md §14)
SOFT_LIMIT_FRACTION = 0.8
#: ``safety.release_force = 0`` means this share of ``safety.force_limit`` (docs/safety.md §15)
RELEASE_FRACTION = 0.2


def soft_force_limit(cfg: Mapping[str, Any]) -> float:
    """The soft force tier's threshold of a device file (docs/safety.md §14): its
    ``safety.soft_force_limit``, or :data:`SOFT_LIMIT_FRACTION` of ``safety.force_limit``
    when that is 0."""
    return float(_get(cfg, 'safety.soft_force_limit') or
                 SOFT_LIMIT_FRACTION * float(_get(cfg, 'safety.force_limit')))


def release_force(cfg: Mapping[str, Any]) -> float:
    """A relief's release threshold (docs/safety.md §15): ``safety.release_force``, or
    :data:`RELEASE_FRACTION` of ``safety.force_limit`` when that is 0."""
    return float(_get(cfg, 'safety.release_force') or
                 RELEASE_FRACTION * float(_get(cfg, 'safety.force_limit')))


def with_defaults(params: Mapping[str, Any], sections: Iterable[str] | None = None) -> dict[str, Any]:
    """A deep copy of ``params`` with every absent parameter that has a default filled in
    (``default_from`` ones after the rest), ``mechanism.*`` defaults of its type included.

    :param sections: only these top-level groups (``None``: all); ``device`` and the frames
        are always filled.
    """
    out = _deepcopy(params)
    wanted = None if sections is None else set(sections)
    entries = [(n, s) for n, s in SCHEMA.items() if '*' not in n]
    mech = out.get('mechanism')
    if isinstance(mech, Mapping) and isinstance(mech.get('type'), str) and mech['type'] in MECHANISM_SCHEMAS:
        entries += [(f'mechanism.{k}', s) for k, s in MECHANISM_SCHEMAS[mech['type']].items()]
    for pass_ in (0, 1):
        for name, spec in entries:
            group = name.split('.', 1)[0] if '.' in name else None
            if group is not None and wanted is not None and group not in wanted:
                continue
            if _get(out, name) is not None:
                continue
            if pass_ == 0 and spec.default is not None:
                nest(out, name, list(spec.default) if isinstance(spec.default, list) else spec.default)
            elif pass_ == 1 and spec.default_from is not None:
                value = _get(out, spec.default_from)
                if value is not None:
                    nest(out, name, value)
    return out


def _deepcopy(value: Any) -> Any:
    if isinstance(value, Mapping):
        return {k: _deepcopy(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_deepcopy(v) for v in value]
    return value
