"""PDO layouts of docs/can.md and the SDO writes that configure a drive at boot.

RPDO1 (0x200 + id, 6 bytes): 6040h controlword U16 + 607Ah target position I32.
RPDO2 (0x300 + id, 4 bytes): 60B1h velocity offset I32 (counts/s, the velocity
feed-forward of cyclic synchronous position mode).
TPDO1 (0x180 + id, 8 bytes): 6041h statusword U16 + 6064h position actual I32 +
2401h load-cell input I16 (or 6077h torque actual I16 on rotary devices).
All transmission type 1: the drive applies the RPDOs received before SYNC k at SYNC k
and answers every SYNC with the TPDO.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass

__all__ = [
    'RPDO1', 'RPDO2', 'TPDO1', 'SdoWrite', 'pdo_mapping_writes', 'frame_bits',
    'LOAD_CELL_INPUT', 'TORQUE_ACTUAL',
]

#: 6040h U16 + 607Ah I32
RPDO1 = struct.Struct('<Hi')
#: 60B1h I32 (velocity offset, counts/s)
RPDO2 = struct.Struct('<i')
#: 6041h U16 + 6064h I32 + 2401h/6077h I16
TPDO1 = struct.Struct('<Hih')

LOAD_CELL_INPUT = 0x2401
TORQUE_ACTUAL = 0x6077


@dataclass(frozen=True)
class SdoWrite:
    """One expedited SDO download: object, sub-index, struct format, value, and why."""

    index: int
    subindex: int
    fmt: str
    value: int
    what: str

    def data(self) -> bytes:
        return struct.pack('<' + self.fmt, self.value)


def _mapping_entry(index: int, subindex: int, bits: int) -> int:
    return (index << 16) | (subindex << 8) | bits


def pdo_mapping_writes(node_id: int, *, force_object: int = LOAD_CELL_INPUT,
                       n_pdos: int = 4) -> list[SdoWrite]:
    """CiA 301 §7.5.2.36 mapping procedure for RPDO1, RPDO2 and TPDO1; the other PDOs
    (RPDO3.., TPDO2..) disabled.

    Each PDO: COB-ID with bit 31 set (invalid) → sub0 = 0 → entries → sub0 = n →
    transmission type 1 → COB-ID valid.
    """
    invalid = 0x80000000
    out: list[SdoWrite] = []
    rx_cob, tx_cob = 0x200 + node_id, 0x180 + node_id
    # RPDO1: controlword + target position
    out += [
        SdoWrite(0x1400, 1, 'I', invalid | rx_cob, 'RPDO1 COB-ID (disabled for mapping)'),
        SdoWrite(0x1600, 0, 'B', 0, 'RPDO1 mapping count = 0'),
        SdoWrite(0x1600, 1, 'I', _mapping_entry(0x6040, 0, 16), 'RPDO1 entry 1: 6040h controlword'),
        SdoWrite(0x1600, 2, 'I', _mapping_entry(0x607A, 0, 32), 'RPDO1 entry 2: 607Ah target position'),
        SdoWrite(0x1600, 0, 'B', 2, 'RPDO1 mapping count = 2'),
        SdoWrite(0x1400, 2, 'B', 1, 'RPDO1 transmission type 1 (act on SYNC)'),
        SdoWrite(0x1400, 1, 'I', rx_cob, 'RPDO1 COB-ID (valid)'),
    ]
    # RPDO2: velocity offset (CSP velocity feed-forward)
    rx2_cob = 0x300 + node_id
    out += [
        SdoWrite(0x1401, 1, 'I', invalid | rx2_cob, 'RPDO2 COB-ID (disabled for mapping)'),
        SdoWrite(0x1601, 0, 'B', 0, 'RPDO2 mapping count = 0'),
        SdoWrite(0x1601, 1, 'I', _mapping_entry(0x60B1, 0, 32), 'RPDO2 entry 1: 60B1h velocity offset'),
        SdoWrite(0x1601, 0, 'B', 1, 'RPDO2 mapping count = 1'),
        SdoWrite(0x1401, 2, 'B', 1, 'RPDO2 transmission type 1 (act on SYNC)'),
        SdoWrite(0x1401, 1, 'I', rx2_cob, 'RPDO2 COB-ID (valid)'),
    ]
    # TPDO1: statusword + position actual + load cell (or torque)
    out += [
        SdoWrite(0x1800, 1, 'I', invalid | tx_cob, 'TPDO1 COB-ID (disabled for mapping)'),
        SdoWrite(0x1A00, 0, 'B', 0, 'TPDO1 mapping count = 0'),
        SdoWrite(0x1A00, 1, 'I', _mapping_entry(0x6041, 0, 16), 'TPDO1 entry 1: 6041h statusword'),
        SdoWrite(0x1A00, 2, 'I', _mapping_entry(0x6064, 0, 32), 'TPDO1 entry 2: 6064h position actual'),
        SdoWrite(0x1A00, 3, 'I', _mapping_entry(force_object, 0, 16),
                 f'TPDO1 entry 3: {force_object:04X}h force input'),
        SdoWrite(0x1A00, 0, 'B', 3, 'TPDO1 mapping count = 3'),
        SdoWrite(0x1800, 2, 'B', 1, 'TPDO1 transmission type 1 (every SYNC)'),
        SdoWrite(0x1800, 1, 'I', tx_cob, 'TPDO1 COB-ID (valid)'),
    ]
    for n in range(1, n_pdos):
        if n >= 2:
            out.append(SdoWrite(0x1400 + n, 1, 'I', invalid | (0x200 + 0x100 * n + node_id),
                                f'RPDO{n + 1} disabled'))
        out.append(SdoWrite(0x1800 + n, 1, 'I', invalid | (0x180 + 0x100 * n + node_id),
                            f'TPDO{n + 1} disabled'))
    return out


def frame_bits(dlc: int, *, extended: bool = False) -> int:
    """Bits on the wire of a data frame, worst-case bit stuffing, with the 3-bit intermission.

    Classic CAN: 47 bits of overhead (standard id) + 8·dlc, stuffing over the
    34 + 8·dlc bits from SOF to the CRC: at most ⌊(34 + 8·dlc − 1)/4⌋ extra bits.
    """
    head = 54 if extended else 34
    overhead = 67 if extended else 47
    return overhead + 8 * dlc + (head + 8 * dlc - 1) // 4
