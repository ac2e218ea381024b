"""The boot of each drive, planned against its own object dictionary before a frame is sent.

At configure time the master reads each drive's EDS/DCF (:class:`~.dictionary.Dictionary`) and
plans (:func:`plan_drive`):

* **required** objects: 6040h, 6041h, 6060h, 6061h, 6064h, 607Ah and the load-cell source
  (``can.load_cell_object``, unless a separate module carries the load cells), and cyclic
  synchronous position itself (6502h bit 7 where 6502h exists, else 6060h's range), and the
  homing method ``can.homing_method`` when one is asked for. Anything missing: one
  :class:`DictionaryError` that lists every missing object with the drive; nothing is sent.
* **optional** objects, written only where they exist, are writable and the value fits
  their range: 1006h, 1016h, 1017h, 6007h, 605Ah, 6065h, 607Ch, 607Dh, 607Fh, 6083h-6085h,
  60C2h, and 60B1h in a PDO (the velocity feed-forward). Each one skipped is reported once
  (:attr:`BootPlan.notes`, :attr:`BootPlan.warnings`) with what the master does instead.
* **PDOs** from the YAML in the shape of ros2_canopen's ``bus.yml`` (``can.rpdo.<n>.mapping:
  ["0x6040:0", "0x607A:0"]``, ``transmission``, ``cob_id``, ``enabled``), by default
  docs/can.md's mapping; validated against the dictionary (the PDO exists, each entry
  exists, is PDO-mappable, readable / writable as its direction needs, at most the mapping
  object's entries and 64 bits) and written by the CiA 301 procedure (COB-ID invalid,
  sub 0 = 0, the entries, sub 0 = n, transmission type, COB-ID valid). PDOs not used are
  disabled where the drive has them; a PDO the drive does not have is never written.

:func:`plan_module` plans a CiA 401 analog-input module that carries the load cells
(``can.load_cell_node``) the same way.
"""
from __future__ import annotations

import functools
import math
import re
import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from .dictionary import STRUCT_CODES, Dictionary, ObjectRef, type_name
from .pdo import LOAD_CELL_INPUT, SdoWrite

__all__ = ['DictionaryError', 'PdoEntry', 'PdoLayout', 'PdoSpec', 'BootSettings', 'BootPlan',
           'ModulePlan', 'plan_drive', 'plan_module', 'pdo_specs', 'default_cob_id',
           'RPDO_ROLES', 'TPDO_ROLES', 'pdo_mapping_writes']

#: objects the master fills in the RPDOs it sends, by role
RPDO_ROLES: dict[ObjectRef, str] = {
    ObjectRef(0x6040): 'controlword', ObjectRef(0x607A): 'target',
    ObjectRef(0x60B1): 'velocity_offset', ObjectRef(0x6060): 'mode',
}
#: objects the master reads from the TPDOs, by role (the load cell is added per drive)
TPDO_ROLES: dict[ObjectRef, str] = {ObjectRef(0x6041): 'statusword', ObjectRef(0x6064): 'position'}

_INVALID = 0x80000000
_FLAGS = 0x60000000          # bit 30 (no RTR) and bit 29 (29-bit id) of a PDO COB-ID


def __getattr__(name: str) -> Any:
    # DictionaryError lives with the layer's other errors (python-can's classes are its
    # bases); loaded on first use, so that a node reading a device file's CAN set-up
    # (every node's start-up check) does not import python-can
    if name == 'DictionaryError':
        from .errors import DictionaryError
        return DictionaryError
    raise AttributeError(f'module {__name__!r} has no attribute {name!r}')


@dataclass(frozen=True)
class PdoEntry:
    """One mapped object: where it is, its struct code and size, and what the master does with it."""

    ref: ObjectRef
    code: str
    bits: int
    role: str = ''            # '' : carried, not used by the master

    @property
    def mapping_value(self) -> int:
        """The 32-bit mapping entry (index << 16 | sub-index << 8 | bits)."""
        return (self.ref.index << 16) | (self.ref.subindex << 8) | self.bits


@dataclass(frozen=True)
class PdoLayout:
    """One PDO as planned: direction, number (1-based), COB-ID, transmission type, entries."""

    direction: str            # 'rpdo' | 'tpdo'
    number: int
    cob_id: int
    transmission: int
    entries: tuple[PdoEntry, ...]
    flags: int = 0            # bits 29/30 of the COB-ID as the dictionary has them
    #: what the dictionary fixes (read-only) and the boot therefore leaves as the drive has it:
    #: the mapping (it already is ``entries``), the transmission type, the COB-ID
    fixed: frozenset[str] = frozenset()

    @property
    def name(self) -> str:
        return f'{self.direction.upper()}{self.number}'

    @property
    def comm_index(self) -> int:
        return (0x1400 if self.direction == 'rpdo' else 0x1800) + self.number - 1

    @property
    def map_index(self) -> int:
        return (0x1600 if self.direction == 'rpdo' else 0x1A00) + self.number - 1

    @functools.cached_property
    def codec(self) -> struct.Struct:
        return struct.Struct('<' + ''.join(e.code for e in self.entries))

    @functools.cached_property
    def roles(self) -> tuple[str, ...]:
        return tuple(e.role for e in self.entries)

    def position_of(self, role: str) -> int | None:
        """Where ``role`` is in the unpacked tuple, ``None`` if not carried."""
        roles = self.roles
        return roles.index(role) if role in roles else None

    def writes(self) -> list[SdoWrite]:
        """The CiA 301 mapping procedure for this PDO, without what the dictionary fixes
        (:attr:`fixed`: a read-only mapping already carries the entries, a read-only
        transmission type or COB-ID already has the value planned)."""
        c, m, n = self.comm_index, self.map_index, self.name
        cob, remap = 'cob_id' not in self.fixed, 'mapping' not in self.fixed
        out = []
        if remap:
            if cob:
                out.append(SdoWrite(c, 1, 'I', _INVALID | self.flags | self.cob_id,
                                    f'{n} COB-ID (disabled for mapping)'))
            out.append(SdoWrite(m, 0, 'B', 0, f'{n} mapping count = 0'))
            for i, e in enumerate(self.entries, 1):
                out.append(SdoWrite(m, i, 'I', e.mapping_value, f'{n} entry {i}: {e.ref}'
                                    + (f' ({e.role})' if e.role else '')))
            out.append(SdoWrite(m, 0, 'B', len(self.entries), f'{n} mapping count = {len(self.entries)}'))
        if 'transmission' not in self.fixed:
            out.append(SdoWrite(c, 2, 'B', self.transmission, f'{n} transmission type {self.transmission}'
                                + (' (SYNC)' if 1 <= self.transmission <= 240 or self.transmission == 0 else '')))
        if cob:
            out.append(SdoWrite(c, 1, 'I', self.flags | self.cob_id, f'{n} COB-ID (valid)'))
        return out


@dataclass(frozen=True)
class PdoSpec:
    """A PDO as the YAML asks for it (``can.rpdo.<n>.*`` / ``can.tpdo.<n>.*``)."""

    direction: str
    number: int
    mapping: tuple[ObjectRef, ...]
    transmission: int = 1
    cob_id: int = 0           # 0: the CiA 301 pre-defined connection set (PDOs 1-4)
    enabled: bool = True

    @property
    def key(self) -> str:
        return f'can.{self.direction}.{self.number}'


def default_cob_id(direction: str, number: int, node_id: int) -> int | None:
    """CiA 301 pre-defined connection set: RPDO n at 100h (n + 1) + id, TPDO n at
    100h n + 80h + id, for n = 1..4; ``None`` beyond."""
    if not 1 <= number <= 4:
        return None
    return (0x100 * (number + 1) if direction == 'rpdo' else 0x100 * number + 0x80) + node_id


def pdo_specs(section: Any, direction: str) -> dict[int, PdoSpec] | None:
    """The PDOs of ``can.rpdo`` / ``can.tpdo`` (``None`` when the YAML gives none: the default
    mapping applies).

    :raises ValueError: a PDO number that is not 1..512, an object reference that cannot be
        read, a transmission type outside 0..255 (named).
    """
    if not section:
        return None
    if not isinstance(section, Mapping):
        raise ValueError(f'can.{direction}: expected PDO numbers with mapping and transmission, '
                         f'got {section!r}')
    out: dict[int, PdoSpec] = {}
    for key, body in section.items():
        try:
            number = int(str(key))
        except ValueError:
            raise ValueError(f'can.{direction}.{key}: the PDO number must be 1..512') from None
        if not 1 <= number <= 512:
            raise ValueError(f'can.{direction}.{key}: the PDO number must be 1..512')
        body = body if isinstance(body, Mapping) else {}
        where = f'can.{direction}.{number}'
        mapping = tuple(ObjectRef.parse(t, what=f'{where}.mapping entry')
                        for t in body.get('mapping', []) or [])
        transmission = int(body.get('transmission', 1))
        if not 0 <= transmission <= 255:
            raise ValueError(f'{where}.transmission = {transmission}: expected 0..255 (1: every SYNC)')
        enabled = bool(body.get('enabled', True)) and bool(mapping)
        out[number] = PdoSpec(direction, number, mapping, transmission,
                              int(body.get('cob_id', 0) or 0), enabled)
    return out


@dataclass(frozen=True)
class BootSettings:
    """What the master wants of one drive, in the drive's units (built by the master from the
    device YAML). ``None`` values are not written."""

    node_id: int
    name: str
    master_node_id: int
    master_heartbeat_ms: int
    drive_heartbeat_ms: int
    period_us: int
    interpolation: tuple[int, int]          # 60C2h value, index
    homing_method: int
    following_error_counts: int
    velocity_counts: int
    acceleration_counts: int
    soft_limits_counts: tuple[int, int] | None
    home_offset_counts: int | None
    load_cell: ObjectRef | None             # None: a separate module carries the load cell
    rpdo: Mapping[int, PdoSpec] | None = None
    tpdo: Mapping[int, PdoSpec] | None = None
    counts_per_rev: int | None = None       # actuator.encoder_counts_per_rev (60A8h check)


@dataclass
class BootPlan:
    """One drive's boot as planned against its dictionary (see the module docstring)."""

    name: str
    node_id: int
    dictionary: Dictionary
    writes: list[SdoWrite]                  # configuration, in order, before the PDO mapping
    mapping: list[SdoWrite]                 # the PDO mapping procedure
    rpdos: tuple[PdoLayout, ...]
    feedback: PdoLayout                     # the TPDO with statusword, position (and load cell)
    feedforward: bool                       # 60B1h carried in an RPDO
    home_offset_on_drive: bool              # 607Ch written (else the master keeps the offset)
    soft_limits_on_drive: bool              # 607Dh written
    heartbeat: bool                         # 1017h: the drive produces a heartbeat
    load_type: int | None                   # data type of the load-cell object on the drive
    notes: list[str] = field(default_factory=list)      # skipped optional objects, and why
    warnings: list[str] = field(default_factory=list)   # skipped objects a user must act on

    def describe(self) -> str:
        """One line per skipped object (what the master does instead)."""
        return '\n'.join([f'warning: {w}' for w in self.warnings] + self.notes)


class _Planner:
    """Collects what is missing (errors), skipped (notes, warnings) and what to write."""

    def __init__(self, d: Dictionary, who: str) -> None:
        self.d = d
        self.who = who
        self.missing: list[str] = []
        self.notes: list[str] = []
        self.warnings: list[str] = []
        self.writes: list[SdoWrite] = []

    def require(self, ref: ObjectRef, what: str, *, write: bool = False) -> bool:
        v = self.d.var(ref)
        if v is None:
            self.missing.append(f'{ref} ({what})')
            return False
        compound = self.d.compound(ref)
        if compound:
            self.missing.append(f'{ref} ({what}) is {compound}')
            return False
        if write and not v.writable:
            self.missing.append(f'{ref} ({what}) is {v.access_type}, not writable')
            return False
        return True

    def optional(self, ref: ObjectRef, value: int, what: str, instead: str, *,
                 warn: bool = False, alternatives: Sequence[int] = ()) -> bool:
        """Write ``value`` (else the first of ``alternatives`` the object takes) where the
        object exists and is writable; else note (or warn) ``instead`` once."""
        v = self.d.var(ref)
        if v is None or not v.writable or v.data_type not in STRUCT_CODES:
            why = 'absent' if v is None else (f'{v.access_type}' if not v.writable
                                              else f'{type_name(v.data_type)}')
            (self.warnings if warn else self.notes).append(f'{ref} {what}: {why} in the dictionary; '
                                                            f'{instead}')
            return False
        errors = []
        for candidate in (value, *alternatives):
            try:
                self.d.encode(ref, candidate)
            except ValueError as exc:
                errors.append(str(exc))
                continue
            self.writes.append(SdoWrite(ref.index, ref.subindex, STRUCT_CODES[v.data_type],
                                        candidate, what))
            if candidate != value:
                self.notes.append(f'{ref} {what}: {value} is outside the dictionary\'s range, '
                                  f'{candidate} written instead')
            return True
        (self.warnings if warn else self.notes).append(
            f'{ref} {what}: not written ({errors[0]}); {instead}')
        return False


def _layout(p: _Planner, spec: PdoSpec, node_id: int, roles: Mapping[ObjectRef, str],
            available: Sequence[int]) -> PdoLayout | None:
    """Validate one PDO of the YAML (or the default) against the dictionary; errors go to
    ``p.missing`` (each naming the PDO and the entry)."""
    d, where = p.d, spec.key
    if spec.number not in available:
        have = f'{spec.direction.upper()}s {", ".join(map(str, available))}' if available \
            else f'no {spec.direction.upper()}'
        declared = getattr(d.od.device_information,
                           'nr_of_RXPDO' if spec.direction == 'rpdo' else 'nr_of_TXPDO', None)
        if not available and declared:
            have = (f'{declared} {spec.direction.upper()}s by [DeviceInfo] but the file lists none of '
                    'their communication / mapping objects (compact PDO storage, CompactPDO): expand '
                    'them with the vendor\'s EDS tool or a DCF')
        p.missing.append(f'{spec.direction.upper()}{spec.number} ({where}): the drive has {have}')
        return None
    capacity = d.mapping_capacity(spec.direction, spec.number)
    entries, ok = [], True
    if len(spec.mapping) > capacity:
        p.missing.append(f'{where}: {len(spec.mapping)} entries, the drive\'s '
                         f'{spec.direction.upper()}{spec.number} maps at most {capacity}')
        ok = False      # not also "fixed (read-only)": the entries beyond are absent, not read-only
    for ref in spec.mapping:
        v = d.var(ref)
        if v is None:
            p.missing.append(f'{ref} ({where}.mapping): absent'); ok = False; continue
        if d.compound(ref):
            p.missing.append(f'{ref} ({where}.mapping): {ref.index:04X}h is an array or a record '
                             'in the dictionary, not one variable'); ok = False
            continue
        if not v.pdo_mappable or v.data_type not in STRUCT_CODES:
            p.missing.append(f'{ref} ({where}.mapping): not PDO-mappable in the dictionary'); ok = False
            continue
        if spec.direction == 'rpdo' and not v.writable:
            p.missing.append(f'{ref} ({where}.mapping): {v.access_type}, an RPDO entry must be '
                             'writable'); ok = False; continue
        if spec.direction == 'tpdo' and not v.readable:
            p.missing.append(f'{ref} ({where}.mapping): not readable'); ok = False; continue
        role = roles.get(ref, '')
        if spec.direction == 'rpdo' and not role:
            p.missing.append(f'{ref} ({where}.mapping): the master has no value to send for it '
                             f'(it fills {", ".join(str(r) for r in RPDO_ROLES)})'); ok = False
            continue
        code = STRUCT_CODES[v.data_type]
        entries.append(PdoEntry(ref, code, 8 * struct.calcsize(code), role))
    bits = sum(e.bits for e in entries)
    if bits > 64:
        p.missing.append(f'{where}: {bits} bits mapped, a PDO holds at most 64'); ok = False
    if not 0 <= spec.transmission <= 240 and spec.transmission not in (254, 255):
        p.missing.append(f'{where}.transmission = {spec.transmission}: 0..240 (SYNC), 254 or 255')
        ok = False
    comm = 0x1400 if spec.direction == 'rpdo' else 0x1800
    default = d.default(ObjectRef(comm + spec.number - 1, 1))
    flags = (default & _FLAGS) if isinstance(default, int) else 0
    cob = spec.cob_id or default_cob_id(spec.direction, spec.number, node_id)
    if cob is None:
        eds_cob = default & 0x7FF if isinstance(default, int) and not default & _INVALID else 0
        cob = eds_cob or None
    if cob is None:
        p.missing.append(f'{where}.cob_id: PDO {spec.number} has no pre-defined COB-ID and the '
                         'dictionary gives none; set it')
        ok = False
    fixed: set[str] = set()
    if ok:
        ok, entries, cob = _fixed_parts(p, spec, entries, int(cob), fixed)
    if not ok:
        return None
    return PdoLayout(spec.direction, spec.number, int(cob), spec.transmission, tuple(entries), flags,
                     frozenset(fixed))


def _fixed_parts(p: _Planner, spec: PdoSpec, entries: list[PdoEntry], cob: int,
                 fixed: set[str]) -> tuple[bool, list[PdoEntry], int]:
    """What the dictionary fixes of this PDO (read-only objects), checked against the plan:
    a fixed mapping must carry the planned objects (in its own order, which the decoding then
    follows), a fixed transmission type must be the planned one, a fixed COB-ID must be valid
    (and is the one used). Adds to ``fixed`` what the boot leaves alone; errors go to
    ``p.missing``. Returns (ok, the entries in the drive's order, the COB-ID)."""
    d, where, name = p.d, spec.key, f'{spec.direction.upper()}{spec.number}'
    comm = (0x1400 if spec.direction == 'rpdo' else 0x1800) + spec.number - 1
    mapping = (0x1600 if spec.direction == 'rpdo' else 0x1A00) + spec.number - 1
    ok = True
    subs = [ObjectRef(mapping, i) for i in range(len(entries) + 1)]
    if not all(d.writable(r) for r in subs):
        count = d.default(ObjectRef(mapping, 0))
        count = count if isinstance(count, int) else 0
        have = [d.default(ObjectRef(mapping, i)) for i in range(1, count + 1)]
        by_value = {e.mapping_value: e for e in entries}
        text = ', '.join(f'{v:08X}h' if isinstance(v, int) else '?' for v in have) or 'nothing'
        if sorted(by_value) == sorted(v for v in have if isinstance(v, int)) and len(have) == len(entries):
            entries = [by_value[v] for v in have]
            fixed.add('mapping')
            p.notes.append(f'{mapping:04X}h {name} mapping: read-only in the dictionary, fixed at '
                           f'{text}: used as the drive has it')
        else:
            want = ', '.join(f'{e.mapping_value:08X}h' for e in entries)
            p.missing.append(f'{where}: the drive\'s {name} mapping is fixed ({mapping:04X}h read-only) at '
                             f'{text}, not {want}; map what it carries ({where}.mapping), or use '
                             'another PDO')
            ok = False
    tx_ref = ObjectRef(comm, 2)
    if d.exists(tx_ref) and not d.writable(tx_ref):
        have = d.default(tx_ref)
        if have == spec.transmission:
            fixed.add('transmission')
        else:
            p.missing.append(f'{where}.transmission = {spec.transmission}: {comm:04X}h:2 is read-only at '
                             f'{have} in the dictionary')
            ok = False
    cob_ref = ObjectRef(comm, 1)
    if d.exists(cob_ref) and not d.writable(cob_ref):
        have = d.default(cob_ref)
        if not isinstance(have, int) or have & _INVALID:
            p.missing.append(f'{name}: its COB-ID {comm:04X}h:1 is read-only and '
                             + ('not given' if not isinstance(have, int) else f'invalid ({have:08X}h)')
                             + ' in the dictionary: the PDO cannot be used')
            ok = False
        elif spec.cob_id and spec.cob_id != have & 0x7FF:
            p.missing.append(f'{where}.cob_id = {spec.cob_id:03X}h: {comm:04X}h:1 is read-only at '
                             f'{have & 0x7FF:03X}h in the dictionary')
            ok = False
        else:
            fixed.add('cob_id')
            cob = have & 0x7FF
    return ok, entries, cob


def _mapping_writes(d: Dictionary, layouts: Sequence[PdoLayout], direction: str,
                    node_id: int) -> list[SdoWrite]:
    """The used PDOs mapped, every other PDO the drive has disabled (COB-ID invalid)."""
    used = {lay.number: lay for lay in layouts}
    out: list[SdoWrite] = []
    comm = 0x1400 if direction == 'rpdo' else 0x1800
    for number in d.pdo_numbers(direction):
        lay = used.get(number)
        if lay is not None:
            out += lay.writes()
            if direction == 'tpdo':
                # a synchronous TPDO has no inhibit time / event timer (CiA 301); some drives
                # apply them anyway: off where the drive has them writable
                for sub, what in ((3, 'inhibit time'), (5, 'event timer')):
                    ref = ObjectRef(comm + number - 1, sub)
                    v = d.var(ref)
                    if v is not None and v.writable and v.data_type in STRUCT_CODES and d.default(ref):
                        out.insert(len(out) - 1, SdoWrite(ref.index, sub, STRUCT_CODES[v.data_type], 0,
                                                          f'{lay.name} {what} 0'))
            continue
        ref = ObjectRef(comm + number - 1, 1)
        v = d.var(ref)
        if v is None or not v.writable:
            continue
        default = d.default(ref)
        flags = (default & _FLAGS) if isinstance(default, int) else 0
        cob = default_cob_id(direction, number, node_id)
        if cob is None:
            cob = default & 0x7FF if isinstance(default, int) else 0
        out.append(SdoWrite(ref.index, 1, 'I', _INVALID | flags | cob,
                            f'{direction.upper()}{number} disabled'))
    return out


#: CiA 402 unit codes in 60A8h / 60A9h (bits 16-23: the unit; bits 8-15: the time base; bits
#: 24-31: a power of ten), as the drive makers' manuals list them (Nanotec, Synapticon:
#: 00B44700h is revolutions per minute, FF410000h tenths of a degree)
SI_UNITS = {0x01: 'm', 0x10: 'rad', 0x41: 'degree', 0xB4: 'revolution'}
SI_TIMES = {0x03: 's', 0x47: 'min', 0x48: 'h'}


def _unit_text(code: int, *, time: bool) -> str:
    exp = ((code >> 24) & 0xFF) - 256 if (code >> 24) & 0x80 else (code >> 24) & 0xFF
    unit = (code >> 16) & 0xFF
    text = SI_UNITS.get(unit, f'unit {unit:02X}h')
    if time:
        base = (code >> 8) & 0xFF
        text += f'/{SI_TIMES.get(base, f"time {base:02X}h")}'
    return text if exp == 0 else f'10^{exp} {text}'


def _unit_allowed(v: Any, value: int) -> bool:
    """Whether a unit code (60A8h / 60A9h) is one the file's LowLimit..HighLimit encode: limits
    that agree in bits 8..23 (unit and time base) fix them, only the prefix (bits 24..31) varies
    (maxon EPOS4: 60A9h 00B44700h..FFB44700h, rpm with a prefix). A numeric range check alone
    lets 00B50300h through, which the drive aborts."""
    if v is None or v.min is None or v.max is None:
        return True
    unit = 0x00FFFF00
    return (int(v.min) & unit) != (int(v.max) & unit) or (value & unit) == (int(v.min) & unit)


def _drive_units(p: '_Planner', counts_per_rev: int | None = None) -> str | None:
    """Match the drive's units (60A8h SI unit position, 60A9h SI unit velocity, as the
    dictionary says it starts) to the master's: positions in encoder increments, velocities in
    those increments per second (docs/can.md, "Units").

    * A position unit that is an angle or a revolution (Nanotec: FF410000h, tenths of a
      degree): ``actuator.encoder_counts_per_rev`` must be the drive's units per revolution
      (3600); a warning where it is not, or cannot be told (radians).
    * A velocity unit that is not the position unit per second (00B44700h, revolutions per
      minute, is common) is set to it where 60A9h is writable (60A9h = the position unit with
      the time base 03h, seconds): 607Fh, 6083h..6085h and the feed-forward 60B1h then mean
      what the master writes.

    Returns why velocities stay in another unit (60A9h read-only, or no 60A8h to take the
    position unit from), ``None`` if they do not."""
    d = p.d
    pos, vel = d.default(ObjectRef(0x60A8)), d.default(ObjectRef(0x60A9))
    pos_unit = (pos >> 16) & 0xFF if isinstance(pos, int) else None
    if pos_unit in SI_UNITS:
        exp = ((pos >> 24) & 0xFF) - 256 if (pos >> 24) & 0x80 else (pos >> 24) & 0xFF
        per_rev = {0x41: 360.0, 0xB4: 1.0}.get(pos_unit)
        per_rev = None if per_rev is None else per_rev / 10 ** exp
        hint = (f' ({per_rev:g} for this unit)' if per_rev is not None else '')
        if per_rev is not None and counts_per_rev is not None and math.isclose(counts_per_rev, per_rev):
            p.notes.append(f'60A8h SI unit position = {pos:08X}h ({_unit_text(pos, time=False)}): '
                           f'{counts_per_rev} per revolution, as actuator.encoder_counts_per_rev says')
        else:
            p.warnings.append(
                f'60A8h SI unit position = {pos:08X}h ({_unit_text(pos, time=False)}) in the dictionary: '
                'the master writes and reads positions (607Ah, 6064h, 607Ch, 607Dh, 6065h) as '
                'actuator.encoder_counts_per_rev units per revolution: that must be the drive\'s units '
                f'per revolution{hint}, or the drive\'s position unit set to encoder increments (its '
                'tool, or a DCF)')
    if not isinstance(vel, int):
        return None
    vel_unit, base = (vel >> 16) & 0xFF, (vel >> 8) & 0xFF
    if base in (0x00, 0x03) and (vel_unit not in SI_UNITS or vel_unit == pos_unit):
        return None
    why = (f'60A9h SI unit velocity = {vel:08X}h ({_unit_text(vel, time=True)}) in the dictionary, '
           'not position units per second')
    if isinstance(pos, int):
        value = (pos & 0xFFFF0000) | 0x0300
        if not _unit_allowed(d.var(ObjectRef(0x60A9)), value):
            v = d.var(ObjectRef(0x60A9))
            why += (f'; 60A9h cannot be {value:08X}h: its limits {v.min:08X}h..{v.max:08X}h in the '
                    'dictionary fix the unit and the time base (only the prefix may change)')
        elif p.optional(ObjectRef(0x60A9), value,
                      f'SI unit velocity = {_unit_text(value, time=True)} (the position unit per second; '
                      f'the dictionary starts at {vel:08X}h, {_unit_text(vel, time=True)})',
                      'velocities stay in the drive\'s unit'):
            p.notes.append(f'60A9h SI unit velocity: {value:08X}h written ({_unit_text(value, time=True)}; '
                           f'the dictionary starts at {vel:08X}h, {_unit_text(vel, time=True)}): 607Fh, '
                           '6083h..6085h and the feed-forward 60B1h in position units per second')
            return None
    p.warnings.append(
        f'{why}: the master writes 607Fh and 6083h..6085h in increments per second (s^2), which the '
        'drive reads in its own unit; set 60A9h to the position unit per second (its tool, or a DCF)')
    return why


def plan_drive(d: Dictionary, s: BootSettings) -> BootPlan:
    """Plan one drive's boot (see the module docstring).

    :raises DictionaryError: every required object the dictionary lacks, and every PDO entry
        it refuses, in one message naming the drive.
    """
    who = f'{s.name} (node {s.node_id}, {d.product})'
    p = _Planner(d, who)
    if d.repaired:
        p.warnings.append(f'{d.path.name} is not a well-formed EDS/DCF ({d.repaired}); read leniently '
                          '(a key given twice: its last value; [Comments] and empty [DeviceInfo] '
                          'numbers left out): check the objects against the drive\'s manual')
    # ---- required
    for ref, what, write in ((ObjectRef(0x6040), 'controlword', True), (ObjectRef(0x6041), 'statusword', False),
                             (ObjectRef(0x6060), 'modes of operation', True),
                             (ObjectRef(0x6061), 'modes of operation display', False),
                             (ObjectRef(0x6064), 'position actual value', False),
                             (ObjectRef(0x607A), 'target position', True)):
        p.require(ref, what, write=write)
    load_type = None
    if s.load_cell is not None:
        v = d.var(s.load_cell)
        if v is None:
            found = _analog_inputs(d)
            p.missing.append(f'{s.load_cell} (the load cell, can.load_cell_object): set can.load_cell_object '
                             'to the object the load cell is wired to'
                             + (f' (analog inputs in this dictionary: {", ".join(found)})' if found
                                else ' or carry the load cells on a CiA 401 module (can.load_cell_node)'))
        elif d.compound(s.load_cell):
            obj = d.od[s.load_cell.index]
            subs = ', '.join(f'{s.load_cell.index:04X}h:{k} {obj.subindices[k].name!r}'
                             for k in sorted(obj.subindices)[1:4])
            p.missing.append(f'{s.load_cell} (the load cell, can.load_cell_object) is sub-index 0 (the '
                             f'entry count) of {s.load_cell.index:04X}h {obj.name!r}: name the input, '
                             f'e.g. "0x{s.load_cell.index:04X}:1" ({subs})')
        else:
            load_type = v.data_type
            if v.data_type not in STRUCT_CODES:
                p.missing.append(f'{s.load_cell} (load cell) is {type_name(v.data_type)}, not a number')
    csp, why = d.supports_mode(8)
    if csp is False:
        p.missing.insert(0, f'cyclic synchronous position mode ({why})')
    elif csp is None:
        p.notes.append(f'6502h / 6060h: {why}; cyclic synchronous position is assumed (6060h = 8 '
                       'is written: a drive without it aborts that write)')
    mode = d.var(ObjectRef(0x6060))
    if mode is not None and mode.writable and mode.data_type in STRUCT_CODES:
        p.writes.append(SdoWrite(0x6060, 0, STRUCT_CODES[mode.data_type], 8,
                                 'mode: cyclic synchronous position'))
    # ---- optional configuration (docs/can.md "Bring your own drive"); the units first: the
    # velocity objects below are written in them
    foreign_velocity = _drive_units(p, s.counts_per_rev)
    heartbeat = p.optional(ObjectRef(0x1017), s.drive_heartbeat_ms, 'producer heartbeat time (ms)',
                           'the drive sends no heartbeat the master sets; it is supervised by its '
                           'TPDOs (safety.stale_periods)')
    if not heartbeat:
        hb = d.default(ObjectRef(0x1017))
        heartbeat = isinstance(hb, int) and hb > 0
    p.optional(ObjectRef(0x1016, 1), (s.master_node_id << 16) | (2 * s.master_heartbeat_ms),
               "consumer heartbeat time of the master's heartbeat",
               'the drive cannot stop itself when the master dies: a hardware stop (STO or an '
               'emergency-stop circuit) is needed', warn=True)
    p.optional(ObjectRef(0x6007), 3, 'abort connection option: quick stop',
               "on losing the master's heartbeat the drive reacts as its firmware does",
               alternatives=(2, 1))
    p.optional(ObjectRef(0x605A), 6, 'quick stop option: ramp, stay in QUICK STOP ACTIVE',
               'a quick stop ends as the drive\'s default option says (the halt and protective '
               'stop accept SWITCH ON DISABLED)', alternatives=(5, 2, 1))
    p.optional(ObjectRef(0x6065), s.following_error_counts, 'following error window (counts)',
               "the master's own following-error check (safety.path_tolerance) supervises tracking")
    _plan_interpolation(p, s.interpolation)
    p.optional(ObjectRef(0x1006), s.period_us, 'communication cycle period (us)',
               'the drive times the SYNC interval itself')
    for ref, value, what in ((ObjectRef(0x607F), s.velocity_counts, 'max profile velocity'),
                             (ObjectRef(0x6083), s.acceleration_counts, 'profile acceleration'),
                             (ObjectRef(0x6084), s.acceleration_counts, 'profile deceleration'),
                             (ObjectRef(0x6085), s.acceleration_counts, 'quick stop deceleration')):
        if p.optional(ref, value, what, "the drive's own value applies") or ref.index != 0x607F:
            continue
        own = d.default(ref)
        if isinstance(own, int) and 0 < own < value:
            # in CSP many drives clamp their targets' speed to 607Fh: motions faster than the
            # drive's own value lag the plan until the following-error check stops them
            p.warnings.append(
                f'607Fh max profile velocity: the drive keeps its own {own} (the dictionary\'s value), '
                f'below the {value} the plans may use (actuator.max_velocity in position units per '
                'second, if that is the drive\'s velocity unit): a drive that limits its targets with '
                'it lags faster motions, and the following-error check stops them; set 607Fh with the '
                "drive's tool, or lower actuator.max_velocity")
    if s.homing_method:
        _plan_homing(p, s.homing_method)
    soft_limits = False
    home_on_drive = s.home_offset_counts is not None and d.writable(ObjectRef(0x607C))
    if s.soft_limits_counts is not None:
        if home_on_drive or not s.homing_method:
            lo, hi = s.soft_limits_counts
            soft_limits = (p.optional(ObjectRef(0x607D, 1), lo, 'software position limit min',
                                      'no software position limit in the drive: the master\'s stroke '
                                      'check is the only one')
                           & p.optional(ObjectRef(0x607D, 2), hi, 'software position limit max',
                                        'no software position limit in the drive: the master\'s '
                                        'stroke check is the only one'))
        elif d.writable(ObjectRef(0x607D, 1)):
            p.notes.append('607Dh software position limits: written after homing (the master keeps '
                           'the home offset)')
    if s.home_offset_counts is not None:
        if home_on_drive:
            p.optional(ObjectRef(0x607C), s.home_offset_counts, 'home offset = IK(home_pose) length',
                       'the master keeps the home offset')
        elif s.homing_method:
            p.notes.append('607Ch home offset: absent or read-only in the dictionary; the master keeps '
                           'the home offset itself (position = drive counts + offset)')
    # ---- PDOs
    rpdos, feedback, feedforward = _plan_pdos(p, s, foreign_velocity)
    if p.missing:
        optional = [f'{r:04X}h' for r in OPTIONAL if not d.exists(ObjectRef(r, 1 if r in (0x1016, 0x60C2) else 0))]
        from .errors import DictionaryError
        raise DictionaryError(
            f'{who} cannot drive the brace: ' + '; '.join(p.missing)
            + (f' (optional objects it lacks as well: {", ".join(optional)})' if optional else '')
            + '. Nothing was sent to the drives (docs/can.md, "Bring your own drive")')
    mapping = (_mapping_writes(d, rpdos, 'rpdo', s.node_id)
               + _mapping_writes(d, [feedback], 'tpdo', s.node_id))
    return BootPlan(s.name, s.node_id, d, p.writes, mapping, tuple(rpdos), feedback, feedforward,
                    home_on_drive, soft_limits, heartbeat, load_type, p.notes, p.warnings)


def _plan_interpolation(p: _Planner, period: tuple[int, int]) -> None:
    """60C2h:1 (value) and :2 (index, 10^index s) as one setting: both written (or a read-only
    one already at the value wanted), or neither; one alone gives the drive a period that is
    neither the SYNC's nor its own."""
    d, writes, why = p.d, [], ''
    for sub, value in ((1, period[0]), (2, period[1])):
        ref = ObjectRef(0x60C2, sub)
        v = d.var(ref)
        if v is not None and not v.writable and d.default(ref) == value:
            continue
        try:
            if v is None or not v.writable or v.data_type not in STRUCT_CODES:
                raise ValueError(f'{ref} is {"absent" if v is None else v.access_type}')
            d.encode(ref, value)
        except ValueError as exc:
            why = str(exc)
            break
        writes.append(SdoWrite(0x60C2, sub, STRUCT_CODES[v.data_type], value,
                               'interpolation time ' + ('period value' if sub == 1 else 'index (10^index s)')))
    if why:
        p.notes.append(f'60C2h interpolation time period {period[0]} x 10^{period[1]} s: not written '
                       f'({why}); the drive interpolates each target over its own period')
    else:
        p.writes += writes


#: the optional objects the boot writes where they exist
OPTIONAL = (0x1006, 0x1016, 0x6007, 0x605A, 0x6065, 0x607C, 0x607D, 0x607F, 0x6083, 0x6084,
            0x6085, 0x60B1, 0x60C2)


def _analog_inputs(d: Dictionary) -> list[str]:
    """PDO-mappable numeric objects whose name says analog input (candidates for the load cell):
    "analog" or "AI" (CiA 404's 7130h "AI Input PV", a vendor's "AI0_Input_PV") with "input",
    or CiA 401's 6401h "Read Analog Input 16-bit"."""
    out = []
    for index in sorted(d.od.keys()):
        obj = d.od[index]
        subs = [obj] if not hasattr(obj, 'subindices') else [v for k, v in obj.subindices.items() if k > 0]
        for v in subs:
            name = f'{getattr(obj, "name", "")} {v.name}'.lower()
            words = set(re.split(r'[^a-z0-9]+', name))
            analog = 'analog' in name or any(re.fullmatch(r'ai\d*', w) for w in words)
            if analog and 'input' in name and v.pdo_mappable and v.data_type in STRUCT_CODES:
                out.append(f'{v.index:04X}h:{v.subindex} {v.name!r}')
    return out[:6]


def _plan_homing(p: _Planner, method: int) -> None:
    d = p.d
    homing, why = d.supports_mode(6)
    if homing is False:
        p.missing.append(f'homing mode for can.homing_method = {method} ({why}); set '
                         'can.homing_method: 0 for absolute encoders')
        return
    v = d.var(ObjectRef(0x6098))
    if v is None or not v.writable:
        p.missing.append('6098h (homing method, for can.homing_method) '
                         + ('absent' if v is None else 'not writable')
                         + ': the drive cannot home itself; set can.homing_method: 0 for absolute '
                         'encoders (or home it with its own tool, then 0)')
        return
    offered = _homing_methods(d)
    lo = v.min if v.min is not None else -128
    hi = v.max if v.max is not None else 127
    if (offered and method not in offered) or not lo <= method <= hi:
        alternatives = [m for m in (35, 37) if m != method and (not offered or m in offered)
                        and lo <= m <= hi]
        have = f'60E3h lists {offered}' if offered else f'6098h allows {lo}..{hi}'
        hint = f'; homing on the current position is method {alternatives[0]} on this drive' \
            if alternatives else ''
        p.missing.append(f'homing method {method} (can.homing_method): {have}{hint}')
        return
    p.writes.append(SdoWrite(0x6098, 0, STRUCT_CODES.get(v.data_type, 'b'), method, 'homing method'))


def _homing_methods(d: Dictionary) -> list[int]:
    """The methods 60E3h (supported homing methods) lists, [] without it."""
    if 0x60E3 not in d.od:
        return []
    obj = d.od[0x60E3]
    subs = [obj] if not hasattr(obj, 'subindices') else [v for s, v in obj.subindices.items() if s > 0]
    out = []
    for v in subs:
        val = v.value if v.value is not None else v.default
        if isinstance(val, int):
            out.append(val - 256 if val > 127 else val)
    return out


def _plan_pdos(p: _Planner, s: BootSettings,
               foreign_velocity: str | None = None) -> tuple[list[PdoLayout], PdoLayout, bool]:
    """The PDO layouts and whether the velocity feed-forward (60B1h) is carried.
    ``foreign_velocity``: why the drive's velocity unit is not increments per second; then no
    feed-forward (a velocity offset in counts/s read as rpm is a runaway), and a YAML mapping
    60B1h is refused."""
    d = p.d
    ff_ref = ObjectRef(0x60B1)
    rx = d.pdo_numbers('rpdo')
    tx = d.pdo_numbers('tpdo')
    rspecs = dict(s.rpdo) if s.rpdo else None
    if rspecs is not None and foreign_velocity and any(ff_ref in spec.mapping for spec in rspecs.values()):
        p.missing.append(f'60B1h velocity offset in can.rpdo: {foreign_velocity}; the master\'s '
                         'feed-forward is in increments per second')
    if rspecs is None:
        rspecs = {1: PdoSpec('rpdo', 1, (ObjectRef(0x6040), ObjectRef(0x607A)))}
        if (not foreign_velocity and d.mappable(ff_ref) and d.writable(ff_ref) and 2 in rx
                and d.mapping_capacity('rpdo', 2) >= 1):
            rspecs[2] = PdoSpec('rpdo', 2, (ff_ref,))
        else:
            why = (foreign_velocity if foreign_velocity and d.exists(ff_ref)
                   else 'absent' if not d.exists(ff_ref) else 'not PDO-mappable' if not d.mappable(ff_ref)
                   else 'read-only' if not d.writable(ff_ref) else 'no RPDO2 to carry it')
            p.notes.append(f'60B1h velocity offset: {why}; no velocity feed-forward: the drive\'s '
                           'position loop lags the plan, and the master\'s following-error check '
                           'allows for that lag')
    tspecs = dict(s.tpdo) if s.tpdo else None
    if tspecs is None:
        entries = [ObjectRef(0x6041), ObjectRef(0x6064)]
        if s.load_cell is not None and d.exists(s.load_cell) and not d.compound(s.load_cell):
            entries.append(s.load_cell)
        tspecs = {1: PdoSpec('tpdo', 1, tuple(entries))}
    tpdo_roles = dict(TPDO_ROLES)
    if s.load_cell is not None:
        tpdo_roles[s.load_cell] = 'load'
    rpdos = [lay for spec in rspecs.values() if spec.enabled
             for lay in [_layout(p, spec, s.node_id, RPDO_ROLES, rx)] if lay is not None]
    tpdos = [lay for spec in tspecs.values() if spec.enabled
             for lay in [_layout(p, spec, s.node_id, tpdo_roles, tx)] if lay is not None]
    carried = [r for lay in rpdos for r in lay.roles]
    for role, ref in (('controlword', 0x6040), ('target', 0x607A)):
        if role not in carried and not any(ObjectRef(ref) in spec.mapping for spec in rspecs.values()):
            p.missing.append(f'{ObjectRef(ref)} ({role}) is in no RPDO of can.rpdo')
    feedback = None
    for lay in tpdos:
        if 'statusword' in lay.roles:
            feedback = lay
            break
    needed = ['statusword', 'position'] + (['load'] if s.load_cell is not None and d.exists(s.load_cell)
                                           and not d.compound(s.load_cell) else [])
    if feedback is None:
        if not p.missing:
            p.missing.append('6041h (statusword) is in no TPDO of can.tpdo')
        feedback = PdoLayout('tpdo', 1, 0, 1, ())
    else:
        absent = [r for r in needed if r not in feedback.roles]
        if absent:
            p.missing.append(f'{feedback.name} carries the statusword but not the '
                             f'{" and ".join(absent)} (6041h, 6064h and the load cell must be in '
                             'one TPDO: a SYNC\'s sample is one frame)')
        if feedback.transmission != 1:
            p.missing.append(f'can.tpdo.{feedback.number}.transmission = {feedback.transmission}: the '
                             'feedback TPDO must answer every SYNC (1)')
    if len(tpdos) > 1:
        p.notes.append(f'TPDOs {[lay.number for lay in tpdos if lay is not feedback]}: mapped as asked; '
                       'the master reads only the feedback TPDO')
    feedforward = any('velocity_offset' in lay.roles for lay in rpdos)
    return rpdos, feedback, feedforward


@dataclass
class ModulePlan:
    """A CiA 401 analog-input module that carries the load cells (``can.load_cell_node``)."""

    node_id: int
    dictionary: Dictionary
    writes: list[SdoWrite]
    mapping: list[SdoWrite]
    tpdo: PdoLayout
    heartbeat: bool
    notes: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)

    @property
    def load_types(self) -> tuple[int, ...]:
        return tuple(self.dictionary.var(e.ref).data_type for e in self.tpdo.entries)


def plan_module(d: Dictionary, *, node_id: int, objects: Sequence[ObjectRef], tpdo: int,
                master_node_id: int, master_heartbeat_ms: int, drive_heartbeat_ms: int) -> ModulePlan:
    """Plan the load-cell module's boot: its heartbeat, one TPDO carrying ``objects`` (one per
    actuator, in actuator order) on every SYNC, its other TPDOs and its RPDOs disabled.

    :raises DictionaryError: an object absent or not mappable, more than 64 bits, no such TPDO.
    """
    who = f'load-cell module (node {node_id}, {d.product})'
    p = _Planner(d, who)
    heartbeat = p.optional(ObjectRef(0x1017), drive_heartbeat_ms, 'producer heartbeat time (ms)',
                           'the module sends no heartbeat the master sets; it is supervised by its TPDO')
    p.optional(ObjectRef(0x1016, 1), (master_node_id << 16) | (2 * master_heartbeat_ms),
               "consumer heartbeat time of the master's heartbeat", 'the module does not watch the master')
    roles = {ref: f'load{i}' for i, ref in enumerate(objects)}
    spec = PdoSpec('tpdo', tpdo, tuple(objects))
    lay = _layout(p, spec, node_id, roles, d.pdo_numbers('tpdo'))
    if len(set(objects)) != len(objects):
        p.missing.append(f'can.load_cell_node.objects {[str(o) for o in objects]}: an object twice')
    if p.missing or lay is None:
        absent = [o for o in objects if not d.exists(o)]
        found = _analog_inputs(d) if absent else []
        from .errors import DictionaryError
        raise DictionaryError(f'{who} cannot carry the load cells: ' + '; '.join(
            m.replace(f'can.tpdo.{tpdo}', 'can.load_cell_node') for m in p.missing)
            + (f' (set can.load_cell_node.objects; analog inputs in this dictionary: {", ".join(found)})'
               if found else '')
            + '. Nothing was sent')
    mapping = _mapping_writes(d, [], 'rpdo', node_id) + _mapping_writes(d, [lay], 'tpdo', node_id)
    return ModulePlan(node_id, d, p.writes, mapping, lay, heartbeat, p.notes, p.warnings)


def pdo_mapping_writes(node_id: int, *, force_object: int = LOAD_CELL_INPUT) -> list[SdoWrite]:
    """docs/can.md's default mapping (RPDO1, RPDO2, TPDO1; the other PDOs disabled) on a drive
    with 4 RPDOs and 4 TPDOs, ``config/lumbar_drive.eds``: what :func:`plan_drive`
    plans for that dictionary (``force_object``: the load cell's index, sub-index 0)."""
    from ..config import config_dir
    d = Dictionary(config_dir() / 'lumbar_drive.eds', node_id)
    plan = plan_drive(d, BootSettings(
        node_id=node_id, name=f'node {node_id}', master_node_id=127, master_heartbeat_ms=100,
        drive_heartbeat_ms=50, period_us=2000, interpolation=(2, -3), homing_method=0,
        following_error_counts=1, velocity_counts=1, acceleration_counts=1, soft_limits_counts=None,
        home_offset_counts=None, load_cell=ObjectRef(force_object)))
    return plan.mapping
