"""Unit scaling between SI and the drives' device units — the only place it happens.

The master and the simulated brace (:mod:`brace_control.sim.brace`) both take their
device units from :func:`scaling_from_config`. docs/can.md, "Units":

* linear actuators: counts per metre = ``encoder_counts_per_rev / screw_lead``
  (8192 / 0.001 m = 8 192 000 counts/m) for 6064h position actual, 607Ah target,
  6062h position demand, 607Ch home offset, 607Dh software limits, 6065h following
  error window; counts/s for 606Ch / 607Fh / 60B1h (velocity offset), counts/s² for
  6083h–6085h;
* rotary drives (``actuator.kind: rotary``): counts per radian =
  ``encoder_counts_per_rev / (2π) × gear_ratio`` (joint angle, motor encoder);
* load cell (2401h, INT16): N = counts × ``load_cell_n_per_count`` (push positive);
* torque actual (6077h, INT16, rotary drives): ‰ of the motor's rated torque (6076h) =
  ``rated_current × torque_constant``; joint N·m = counts / 1000 × that × ``gear_ratio``.
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from ..config import ConfigError, as_device_config

__all__ = ['AxisScaling', 'scaling_from_config', 'actuator_kind', 'rated_joint_torque', 'LoadInput',
           'per_actuator', 'encoder_counts', 'counts_ratios',
           'INT16_MIN', 'INT16_MAX', 'INT32_MIN', 'INT32_MAX']

INT16_MIN, INT16_MAX = -(1 << 15), (1 << 15) - 1
INT32_MIN, INT32_MAX = -(1 << 31), (1 << 31) - 1


def _clamp_int32(value: float, what: str) -> int:
    counts = round(value)
    if not INT32_MIN <= counts <= INT32_MAX:
        raise OverflowError(f'{what} = {value:.0f} counts does not fit a 32-bit object')
    return counts


@dataclass(frozen=True)
class AxisScaling:
    """Device units of one axis (all drives of a device share it).

    :param counts_per_unit: encoder counts per metre (linear) or per radian (rotary).
    :param newton_per_count: load-cell input 2401h scaling, N (or N·m) per count.
    :param rated_force: the load cell's full scale (N), for the saturation threshold.
    """

    counts_per_unit: float
    newton_per_count: float
    rated_force: float

    def __post_init__(self) -> None:
        for name in ('counts_per_unit', 'newton_per_count', 'rated_force'):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0.0):
                raise ConfigError(f'{name} must be a positive number, got {v!r}')

    @classmethod
    def linear(cls, *, encoder_counts_per_rev: int, screw_lead_m: float,
               newton_per_count: float, rated_force_n: float) -> AxisScaling:
        """Lead-screw actuator: ``counts/m = counts_per_rev / lead``."""
        return cls(encoder_counts_per_rev / screw_lead_m, newton_per_count, rated_force_n)

    @classmethod
    def rotary(cls, *, encoder_counts_per_rev: int, gear_ratio: float = 1.0,
               newton_metre_per_count: float, rated_torque_nm: float) -> AxisScaling:
        """Rotary joint: ``counts/rad = counts_per_rev / 2π × gear ratio``."""
        return cls(encoder_counts_per_rev / (2.0 * math.pi) * gear_ratio,
                   newton_metre_per_count, rated_torque_nm)

    # -- position (6064h, 607Ah, 607Ch, 607Dh, 6065h) -----------------------------
    def to_counts(self, position: float) -> int:
        """m (or rad) -> counts, rounded; :class:`OverflowError` outside INT32."""
        return _clamp_int32(position * self.counts_per_unit, 'position')

    def to_si(self, counts: int | float) -> float:
        """counts -> m (or rad)."""
        return counts / self.counts_per_unit

    # -- velocity (606Ch, 607Fh) and acceleration (6083h..6085h) ------------------
    def velocity_to_counts(self, velocity: float) -> int:
        """m/s -> counts/s."""
        return _clamp_int32(velocity * self.counts_per_unit, 'velocity')

    def velocity_to_si(self, counts_per_s: int | float) -> float:
        """counts/s -> m/s."""
        return counts_per_s / self.counts_per_unit

    def acceleration_to_counts(self, acceleration: float) -> int:
        """m/s² -> counts/s²."""
        return _clamp_int32(acceleration * self.counts_per_unit, 'acceleration')

    # -- load cell (2401h, or the object can.load_cell_object names) -----------------
    def force_to_si(self, counts: int | float) -> float:
        """Load-cell counts (from the input's zero, :class:`LoadInput`) -> N (push positive)."""
        return counts * self.newton_per_count

    def force_to_counts(self, force: float, load: 'LoadInput | None' = None) -> int | float:
        """N -> the reading of the load-cell input ``load`` (default INTEGER16 with zero at 0):
        its zero plus the counts, quantised and saturated to what the input can show (what a
        real amplifier does); a REAL32/64 input reads the unrounded value."""
        load = load or LoadInput.INT16
        value = force / self.newton_per_count
        if load.real:
            return load.zero + value
        return max(load.low, min(load.high, load.zero + round(value)))

    def saturation_counts(self, fraction: float, span: float = INT16_MAX) -> float:
        """|counts| from the zero at or above which the load cell counts as saturated.

        ``fraction`` of the rated full scale, never above ``span``, the most the input can show
        on either side of its zero (:attr:`LoadInput.span`; INTEGER16: 32767).
        """
        return min(span, math.floor(fraction * self.rated_force / self.newton_per_count))


@dataclass(frozen=True)
class LoadInput:
    """The object a load cell is read from, as a number: its range and its zero.

    A signed integer reads zero force at 0; an unsigned one (an ADC input of a bipolar
    amplifier) at mid-scale, 2^(bits-1); a REAL32/64 at 0.0. ``span`` is the most it shows
    on either side of its zero.
    """

    low: float
    high: float
    zero: float
    real: bool = False

    @classmethod
    def of(cls, code: str) -> LoadInput:
        """From the struct code of its data type (``'h'`` INTEGER16, ``'H'`` UNSIGNED16, ``'f'`` ...)."""
        if code in ('f', 'd'):
            return cls(-math.inf, math.inf, 0.0, True)
        import struct
        bits = 8 * struct.calcsize(code)
        if code.islower():
            return cls(-(1 << (bits - 1)), (1 << (bits - 1)) - 1, 0)
        return cls(0, (1 << bits) - 1, 1 << (bits - 1))

    @property
    def span(self) -> float:
        return min(self.high - self.zero, self.zero - self.low)


LoadInput.INT16 = LoadInput(INT16_MIN, INT16_MAX, 0)     # type: ignore[attr-defined]


def actuator_kind(cfg: Mapping[str, Any]) -> str:
    """``'linear'`` or ``'rotary'``: ``actuator.kind`` (schema default ``linear``)."""
    return str(as_device_config(cfg).get_path('actuator.kind'))


def scaling_from_config(cfg: Mapping[str, Any]) -> AxisScaling:
    """The device's :class:`AxisScaling` from its YAML (``actuator.*``).

    ``actuator.kind`` selects the axis. Linear: counts/m from
    ``encoder_counts_per_rev / screw_lead``, the load cell 2401h in N
    (``load_cell_n_per_count``, ``load_cell_rated_force``). Rotary: counts/rad from
    ``encoder_counts_per_rev × gear_ratio / 2π``, the torque actual 6077h in ‰ of the
    motor's rated torque ``rated_current × torque_constant``, so N·m per count at the
    joint = ``rated_current × torque_constant × gear_ratio / 1000`` and the full scale
    (saturation) is 1000 ‰; without ``rated_current`` and ``torque_constant`` the torque
    reading is scaled like a load cell. Types, ranges and defaults: :mod:`brace_control.schema`.

    :raises ConfigError: a missing, out-of-range or unknown parameter, naming it.
    """
    dc = as_device_config(cfg)
    act = dc.section('actuator')
    cpr = encoder_counts(dc)[0]      # the first actuator's; the others by their ratio (counts_ratios)
    if actuator_kind(dc) == 'linear':
        if 'screw_lead' not in act:
            raise ConfigError("parameter 'actuator.screw_lead' is missing (m per motor revolution of "
                              'a linear actuator)')
        return AxisScaling.linear(encoder_counts_per_rev=cpr, screw_lead_m=float(act['screw_lead']),
                                  newton_per_count=float(act['load_cell_n_per_count']),
                                  rated_force_n=float(act['load_cell_rated_force']))
    gear = float(act['gear_ratio'])
    if 'rated_current' in act or 'torque_constant' in act:
        rated = rated_joint_torque(dc)
        return AxisScaling.rotary(encoder_counts_per_rev=cpr, gear_ratio=gear,
                                  newton_metre_per_count=rated / 1000.0, rated_torque_nm=rated)
    # no motor data: the torque reading scaled like a load cell (N·m per count)
    return AxisScaling.rotary(encoder_counts_per_rev=cpr, gear_ratio=gear,
                              newton_metre_per_count=float(act['load_cell_n_per_count']),
                              rated_torque_nm=float(act['load_cell_rated_force']))


def per_actuator(value: Any, n: int, name: str) -> list:
    """A parameter given once for all actuators or once per actuator, as ``n`` values.

    :raises ConfigError: a list of another length, naming ``name``.
    """
    values = list(value) if isinstance(value, (list, tuple)) else [value]
    if len(values) == 1:
        return values * n
    if len(values) != n:
        raise ConfigError(f'parameter {name} = {values}: one value for all actuators or {n} (one per '
                          f'actuator), got {len(values)}')
    return values


def _n_actuators(dc: Any) -> int:
    ids = dc.get_path('can.node_ids', None)
    if ids is not None:
        return len(ids)
    names = dc.get_path('mechanism.actuator_names', None)
    return len(names) if names else 1


def encoder_counts(cfg: Mapping[str, Any], key: str = 'actuator.encoder_counts_per_rev') -> list[int]:
    """Each actuator's encoder counts per revolution (``actuator.encoder_counts_per_rev``,
    one for all or per actuator)."""
    dc = as_device_config(cfg)
    return [int(v) for v in per_actuator(dc.get_path(key), _n_actuators(dc), key)]


def counts_ratios(cfg: Mapping[str, Any]) -> list[float]:
    """Each drive's counts per the first drive's (the scaling's): 1.0 unless the encoders differ."""
    cprs = encoder_counts(cfg)
    return [c / cprs[0] for c in cprs]


def rated_joint_torque(cfg: Mapping[str, Any]) -> float:
    """Joint torque (N·m) at 1000 ‰ of 6077h: ``rated_current × torque_constant × gear_ratio``.

    :raises ConfigError: a missing or out-of-range value, naming the parameter.
    """
    act = as_device_config(cfg).section('actuator')
    for key in ('rated_current', 'torque_constant'):
        if key not in act:
            raise ConfigError(f'parameter {"actuator." + key!r} is missing (rotary drive: torque actual '
                              '6077h scaling)')
    return float(act['rated_current']) * float(act['torque_constant']) * float(act['gear_ratio'])
