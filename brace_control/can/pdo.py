"""The default PDO layouts of docs/can.md, the SDO write, and frame sizes on the wire.

The mapping a drive gets is planned against its own dictionary (:mod:`.plan`, from the
YAML's ``can.rpdo`` / ``can.tpdo``; :func:`.plan.pdo_mapping_writes` is the default one);
these are the defaults:

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
    'RPDO1', 'RPDO2', 'TPDO1', 'SdoWrite', 'frame_bits',
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


def frame_bits(dlc: int, *, extended: bool = False) -> int:
    """Bits on the wire of a data frame, worst-case bit stuffing, with the 3-bit intermission.

    Classic CAN: 47 bits of overhead (standard id) + 8·dlc, stuffing over the
    34 + 8·dlc bits from SOF to the CRC: at most ⌊(34 + 8·dlc − 1)/4⌋ extra bits.
    """
    head = 54 if extended else 34
    overhead = 67 if extended else 47
    return overhead + 8 * dlc + (head + 8 * dlc - 1) // 4
