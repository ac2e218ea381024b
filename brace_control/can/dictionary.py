"""A device's object dictionary as its EDS / DCF describes it: what exists, its type and access.

Read with ``canopen.import_od`` (CiA 306 electronic data sheets), shared by the master, which
plans every drive's boot against it (:mod:`.plan`), and by the simulated drives
(:mod:`brace_control.sim`), which answer as the dictionary's device would. Nothing here
opens a bus.

>>> d = Dictionary('test/data/eds/CL3-E-2-0F.eds', node_id=1)
>>> d.exists(ObjectRef.parse('0x3220:1')), d.supports_mode(8)
(True, (True, '6502h = 000003EFh: bit 7 (cyclic synchronous position) set'))
"""
from __future__ import annotations

import configparser
import io
import re
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import canopen
    from canopen import objectdictionary as odmod

__all__ = ['ObjectRef', 'Dictionary', 'DictionaryReadError', 'STRUCT_CODES', 'type_name',
           'type_range', 'MODE_BITS', 'MODE_NAMES', 'lookup', 'eds_files', 'DEFAULT_EDS']

#: the drive this project simulates (docs/can.md): ``can.eds`` when the YAML names none
DEFAULT_EDS = 'lumbar_drive.eds'

#: CiA 301 data type indices (table 44: the static data types, objects 0001h..001Bh), as
#: canopen's ``objectdictionary`` names them; here so that reading a device file's CAN
#: set-up (every node's start-up check) does not import canopen and python-can
BOOLEAN, INTEGER8, INTEGER16, INTEGER32 = 0x01, 0x02, 0x03, 0x04
UNSIGNED8, UNSIGNED16, UNSIGNED32, REAL32 = 0x05, 0x06, 0x07, 0x08
VISIBLE_STRING, DOMAIN, INTEGER24, REAL64 = 0x09, 0x0F, 0x10, 0x11
INTEGER64, UNSIGNED24, UNSIGNED64 = 0x15, 0x16, 0x1B

#: struct codes of the data types a PDO can carry (CiA 301 basic types of 8..64 bits)
STRUCT_CODES: dict[int, str] = {
    BOOLEAN: 'B', INTEGER8: 'b', UNSIGNED8: 'B', INTEGER16: 'h', UNSIGNED16: 'H',
    INTEGER32: 'i', UNSIGNED32: 'I', REAL32: 'f', INTEGER64: 'q', UNSIGNED64: 'Q', REAL64: 'd',
}

_TYPE_NAMES = {
    BOOLEAN: 'BOOLEAN', INTEGER8: 'INTEGER8', INTEGER16: 'INTEGER16', INTEGER24: 'INTEGER24',
    INTEGER32: 'INTEGER32', INTEGER64: 'INTEGER64', UNSIGNED8: 'UNSIGNED8',
    UNSIGNED16: 'UNSIGNED16', UNSIGNED24: 'UNSIGNED24', UNSIGNED32: 'UNSIGNED32',
    UNSIGNED64: 'UNSIGNED64', REAL32: 'REAL32', REAL64: 'REAL64',
    VISIBLE_STRING: 'VISIBLE_STRING', DOMAIN: 'DOMAIN',
}

#: CiA 402 modes of operation (6060h values) and their bit in 6502h (supported drive modes)
MODE_BITS: dict[int, int] = {1: 0, 2: 1, 3: 2, 4: 3, 6: 5, 7: 6, 8: 7, 9: 8, 10: 9}
MODE_NAMES: dict[int, str] = {
    1: 'profile position', 2: 'velocity', 3: 'profile velocity', 4: 'profile torque',
    6: 'homing', 7: 'interpolated position', 8: 'cyclic synchronous position',
    9: 'cyclic synchronous velocity', 10: 'cyclic synchronous torque',
}


def type_name(data_type: int) -> str:
    return _TYPE_NAMES.get(data_type, f'data type {data_type:04X}h')


def type_range(data_type: int) -> tuple[float, float]:
    """The values a data type can hold (``(-inf, inf)`` for REAL32/64)."""
    code = STRUCT_CODES.get(data_type)
    if code in ('f', 'd') or code is None:
        return float('-inf'), float('inf')
    bits = 8 * struct.calcsize(code)
    if data_type == BOOLEAN:
        return 0, 1
    if code.islower():
        return -(1 << (bits - 1)), (1 << (bits - 1)) - 1
    return 0, (1 << bits) - 1


@dataclass(frozen=True, order=True)
class ObjectRef:
    """An object of a dictionary: index and sub-index (``3220h:1``)."""

    index: int
    subindex: int = 0

    _PATTERN = re.compile(r'^\s*(?:0x)?([0-9a-f]{1,4})h?\s*(?::\s*(?:0x)?([0-9a-f]{1,2})h?)?\s*$', re.I)

    @classmethod
    def parse(cls, text: Any, *, what: str = 'object') -> ObjectRef:
        """``"0x3220:1"``, ``"0x3220:01"``, ``"3220h:1"`` or ``"0x6041"`` (sub-index 0).

        The index is hexadecimal (with or without ``0x`` / ``h``); the sub-index is decimal,
        or hexadecimal when written with ``0x`` or ``h`` (``"0x1A00:0x10"`` is sub-index 16).

        :raises ValueError: anything else, naming ``what`` and the expected form.
        """
        if isinstance(text, ObjectRef):
            return text
        m = cls._PATTERN.match(str(text)) if isinstance(text, str) else None
        if m is None:
            raise ValueError(f'{what} = {text!r} is not an object reference; expected '
                             '"0xIIII:SS" (index in hex, sub-index), e.g. "0x3220:1"')
        sub_text = m.group(2)
        raw = str(text).split(':', 1)[1].strip().lower() if ':' in str(text) else ''
        if sub_text is None:
            sub = 0
        elif raw.startswith('0x') or raw.endswith('h'):
            sub = int(sub_text, 16)
        else:
            if not sub_text.isdigit():
                raise ValueError(f'{what} = {text!r}: the sub-index {sub_text!r} is hexadecimal; '
                                 'write it "0x.." (e.g. "0x3220:0x0A") or in decimal')
            sub = int(sub_text, 10)
        return cls(int(m.group(1), 16), sub)

    def __str__(self) -> str:
        return f'{self.index:04X}h:{self.subindex}'


def eds_files(cfg: Any, n: int) -> tuple[Path, ...]:
    """``can.eds`` of a :class:`~brace_control.config.DeviceConfig`: one EDS/DCF for all ``n``
    drives, or a list of one per ``can.node_ids`` entry, each relative to the YAML
    (:meth:`~brace_control.config.DeviceConfig.resolve_file`); none named: the package's
    ``config/lumbar_drive.eds`` (:data:`DEFAULT_EDS`).

    :raises ConfigError: a list of another length, a file that does not exist (the path tried).
    """
    from ..config import ConfigError, config_dir
    value = cfg.get_path('can.eds', '') or ''
    if isinstance(value, str) and not value.strip():
        return (config_dir() / DEFAULT_EDS,) * n
    names = [value] * n if isinstance(value, str) else list(value)
    if len(names) != n:
        raise ConfigError(f'parameter can.eds lists {len(names)} files for {n} drives (can.node_ids); '
                          'give one file for all, or one per drive')
    if any(not str(name).strip() for name in names):
        raise ConfigError('parameter can.eds has an empty entry: name each drive\'s EDS or DCF')
    return tuple(cfg.resolve_file(str(name), 'can.eds') for name in names)


class DictionaryReadError(ValueError):
    """An EDS / DCF that cannot be read (missing, not an EDS, malformed)."""


def lookup(od: canopen.ObjectDictionary, index: int, subindex: int = 0) -> odmod.ODVariable | None:
    """The variable ``index:subindex`` when the dictionary defines it, else ``None``.

    An array's sub-indices are only those the file lists (canopen's ``ODArray`` would
    make up any sub-index 1..255 from its first entry).
    """
    from canopen.objectdictionary import ODVariable
    obj = od.get(index) if index in od else None
    if obj is None:
        return None
    if isinstance(obj, ODVariable):
        return obj if subindex == 0 else None
    return obj.subindices.get(subindex)


def _source(path: Path) -> tuple[str | io.StringIO, str | None]:
    """What ``canopen.import_od`` reads, and the file's text: an EDS/DCF decoded here,
    whatever the platform's default encoding. CiA 306 files are meant to be ASCII; vendors'
    tools write UTF-8 (with or without a byte-order mark), Windows-1252 or a DOS code page
    (Faulhaber's 605.3150.51 spells its town with a code-page-850 umlaut, byte 94h).
    ``canopen`` opens a path with the locale's encoding, which refuses one of those on every
    machine. Tried in that order: UTF-8, then Windows-1252, then Latin-1 (which decodes any
    byte). Other suffixes go to ``canopen`` as the path (its own error names them)."""
    if path.suffix.lower() not in ('.eds', '.dcf'):
        return str(path), None
    raw = path.read_bytes()
    for encoding in ('utf-8-sig', 'cp1252', 'latin-1'):
        try:
            text = raw.decode(encoding)
        except UnicodeDecodeError:
            continue
        break
    source = io.StringIO(text)
    source.name = str(path)
    return source, text


_DEVICE_INFO_NUMBERS = ('vendornumber', 'productnumber', 'revisionnumber', 'nrofrxpdo', 'nroftxpdo',
                        'simplebootupmaster', 'simplebootupslave', 'granularity', 'lss_supported',
                        'dynamicchannelssupported', 'groupmessaging', 'baudrate_')


def _lenient(text: str) -> str | None:
    """The file as ``canopen``'s strict reader takes it, where vendors' files trip it without an
    object being wrong: a section or key given twice (the last one counts, as in the vendors'
    tools), a [Comments] section whose ``Lines`` is not its ``LineN`` entries, a number in
    [DeviceInfo] left empty. ``None``: not even a lenient read parses it."""
    parser = configparser.RawConfigParser(inline_comment_prefixes=(';',), strict=False)
    parser.optionxform = str
    try:
        parser.read_string(text)
    except configparser.Error:
        return None
    parser.remove_section('Comments')
    if parser.has_section('DeviceInfo'):
        for key, value in list(parser.items('DeviceInfo')):
            if key.lower().startswith(_DEVICE_INFO_NUMBERS):
                try:
                    int(value, 0)
                except ValueError:
                    parser.remove_option('DeviceInfo', key)
    out = io.StringIO()
    parser.write(out, space_around_delimiters=False)
    return out.getvalue()


def _expand_compact_arrays(od: canopen.ObjectDictionary, text: str) -> None:
    """CiA 306 compact storage (``CompactSubObj=n`` in an array's section, no sub-index
    sections): ``canopen`` keeps only sub-index 1 as a template. Add sub-indices 2..n made from
    it, so the array has the n entries the file declares (a PDO mapping's capacity, what the
    boot may write)."""
    from canopen.objectdictionary import ODArray
    parser = configparser.RawConfigParser(inline_comment_prefixes=(';',), strict=False)
    parser.optionxform = str
    try:
        parser.read_string(text)
    except configparser.Error:
        return
    for section in parser.sections():
        if not re.fullmatch(r'[0-9A-Fa-f]{4}', section) or not parser.has_option(section, 'CompactSubObj'):
            continue
        try:
            n = int(parser.get(section, 'CompactSubObj'), 0)
        except ValueError:
            continue
        index = int(section, 16)
        obj = od.get(index) if index in od else None
        if not isinstance(obj, ODArray) or 1 not in obj.subindices:
            continue
        for sub in range(2, min(n, 254) + 1):
            if sub not in obj.subindices:
                obj.add_member(obj[sub])


class Dictionary:
    """One device's object dictionary (``canopen.import_od``) and what it says of the device.

    :param path: the EDS or DCF.
    :param node_id: the node id ``$NODEID`` expressions are evaluated with.
    :raises DictionaryReadError: the file does not exist or is not a readable EDS/DCF.
    """

    def __init__(self, path: str | Path, node_id: int) -> None:
        import canopen
        self.path = Path(path)
        if not self.path.is_file():
            raise DictionaryReadError(f'EDS/DCF {str(self.path)!r} does not exist')
        self.repaired = ''
        try:
            source, text = _source(self.path)
            try:
                self.od = canopen.import_od(source, node_id)
            except (configparser.Error, ValueError) as exc:
                lenient = _lenient(text) if text is not None else None
                if lenient is None or lenient == text:
                    raise
                retry = io.StringIO(lenient)
                retry.name = str(self.path)
                try:
                    self.od = canopen.import_od(retry, node_id)
                except Exception:  # noqa: BLE001 - the original error is the one to name
                    raise exc from None
                self.repaired = f'{type(exc).__name__}: {exc}'
            if text is not None and 'compactsubobj' in text.lower():
                _expand_compact_arrays(self.od, text)
        except Exception as exc:  # noqa: BLE001 - configparser, UnicodeDecodeError, KeyError ...
            raise DictionaryReadError(f'{self.path}: not a readable EDS/DCF ({type(exc).__name__}: '
                                      f'{exc})') from exc
        if len(self.od) == 0:
            raise DictionaryReadError(f'{self.path}: no object in it (not an EDS/DCF?)')
        self.node_id = node_id

    # -- identity -------------------------------------------------------------------------
    @property
    def product(self) -> str:
        """The device as the file names it: product name, vendor, file name."""
        info = self.od.device_information
        parts = [p for p in (info.product_name, info.vendor_name) if p]
        name = ' / '.join(str(p).strip() for p in parts) or 'unnamed device'
        return f'{name} ({self.path.name})'

    @property
    def vendor_number(self) -> int | None:
        return self.od.device_information.vendor_number

    @property
    def product_number(self) -> int | None:
        return self.od.device_information.product_number

    # -- objects --------------------------------------------------------------------------
    def var(self, ref: ObjectRef) -> odmod.ODVariable | None:
        return lookup(self.od, ref.index, ref.subindex)

    def exists(self, ref: ObjectRef) -> bool:
        return self.var(ref) is not None

    def compound(self, ref: ObjectRef) -> str | None:
        """When ``ref`` names sub-index 0 of an array or a record where one variable was
        expected (a drive of several axes that lists 6064h or 607Ah per axis, as the
        ZLAC8015D's file does): what the file has there, for the message; else ``None``."""
        from canopen.objectdictionary import ODArray, ODVariable
        obj = self.od.get(ref.index) if ref.index in self.od else None
        if ref.subindex != 0 or obj is None or isinstance(obj, ODVariable):
            return None
        kind = 'an array' if isinstance(obj, ODArray) else 'a record'
        subs = sorted(k for k in obj.subindices if k)
        names = ', '.join(f'{ref.index:04X}h:{k} {obj.subindices[k].name!r}' for k in subs[:3])
        return (f'{kind} of {len(subs)} entries ({names}{", ..." if len(subs) > 3 else ""}), '
                'not one variable: a drive of several axes? This master drives one axis per '
                'node id, with the objects of CiA 402 as single variables')

    def writable(self, ref: ObjectRef) -> bool:
        v = self.var(ref)
        return v is not None and v.writable

    def readable(self, ref: ObjectRef) -> bool:
        v = self.var(ref)
        return v is not None and v.readable

    def mappable(self, ref: ObjectRef) -> bool:
        v = self.var(ref)
        return v is not None and bool(v.pdo_mappable) and v.data_type in STRUCT_CODES

    def default(self, ref: ObjectRef) -> Any:
        """The value the device starts with (``ParameterValue`` of a DCF, else ``DefaultValue``)."""
        v = self.var(ref)
        if v is None:
            return None
        return v.value if v.value is not None else v.default

    def describe(self, ref: ObjectRef) -> str:
        v = self.var(ref)
        if v is None:
            return f'{ref} (absent)'
        return f'{ref} {v.name!r} ({type_name(v.data_type)}, {v.access_type})'

    def encode(self, ref: ObjectRef, value: int | float) -> bytes:
        """``value`` in the object's own data type.

        :raises ValueError: the object is absent, not a number, or ``value`` is outside the
            range its data type or the file's LowLimit/HighLimit allow (named).
        """
        v = self.var(ref)
        if v is None:
            raise ValueError(f'{ref} is not in {self.path.name}')
        if v.data_type not in STRUCT_CODES:
            raise ValueError(f'{self.describe(ref)} is not a number')
        lo, hi = type_range(v.data_type)
        if v.min is not None:
            lo = max(lo, v.min)
        if v.max is not None:
            hi = min(hi, v.max)
        if not lo <= value <= hi:
            raise ValueError(f'{value} is outside the range {lo:g}..{hi:g} of {self.describe(ref)} '
                             f'in {self.path.name}')
        return v.encode_raw(value if v.data_type in (REAL32, REAL64) else int(value))

    # -- PDOs ------------------------------------------------------------------------------
    def pdo_numbers(self, direction: str) -> list[int]:
        """The PDOs (1-based) whose communication and mapping objects both exist."""
        comm, mapping = (0x1400, 0x1600) if direction == 'rpdo' else (0x1800, 0x1A00)
        return [n + 1 for n in range(512) if comm + n in self.od and mapping + n in self.od]

    def mapping_capacity(self, direction: str, number: int) -> int:
        """How many entries the PDO's mapping object holds (its sub-indices 1..n, or sub 0's
        HighLimit when the file gives one and it is lower)."""
        base = 0x1600 if direction == 'rpdo' else 0x1A00
        from canopen.objectdictionary import ODVariable
        obj = self.od.get(base + number - 1) if base + number - 1 in self.od else None
        if obj is None or isinstance(obj, ODVariable):
            return 0
        subs = [s for s in obj.subindices if s > 0]
        n = max(subs, default=0)
        count = obj.subindices.get(0)
        if count is not None and count.max is not None:
            n = min(n, int(count.max))
        return n

    # -- CiA 402 ---------------------------------------------------------------------------
    def supports_mode(self, mode: int) -> tuple[bool | None, str]:
        """Whether the drive offers mode of operation ``mode`` (6060h value), and why we think so.

        6502h (supported drive modes) decides where it exists; otherwise 6060h's allowed range
        (LowLimit..HighLimit) does. ``None``: neither says (no 6502h, no range on 6060h).
        """
        sdm = self.var(ObjectRef(0x6502))
        bit = MODE_BITS.get(mode)
        if sdm is not None and bit is not None:
            value = self.default(ObjectRef(0x6502))
            if isinstance(value, int):
                on = bool(value >> bit & 1)
                return on, (f'6502h = {value:08X}h: bit {bit} ({MODE_NAMES[mode]}) '
                            f'{"set" if on else "not set"}')
        modes = self.var(ObjectRef(0x6060))
        if modes is not None and (modes.min is not None or modes.max is not None):
            lo = modes.min if modes.min is not None else -128
            hi = modes.max if modes.max is not None else 127
            on = lo <= mode <= hi
            return on, f'6060h allows {lo}..{hi}' + ('' if on else f', not {mode}')
        return None, 'neither 6502h nor a range on 6060h says which modes the drive has'

    def supported_modes(self) -> list[int]:
        """The modes 6502h lists ([] when the dictionary has no 6502h)."""
        value = self.default(ObjectRef(0x6502))
        if not isinstance(value, int):
            return []
        return [m for m, bit in MODE_BITS.items() if value >> bit & 1]
