"""The default PDO layouts of docs/can.md, the SDO write, and frame sizes on the wire.

The mapping a drive gets is planned against its own dictionary (:mod:`.plan`, from the
YAML's ``can.rpdo`` / ``can.tpdo``); these are the defaults:

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


def pdo_mapping_writes(node_id: int, *, force_object: int = LOAD_CELL_INPUT) -> list[SdoWrite]:
    """docs/can.md's default mapping (RPDO1, RPDO2, TPDO1; the other PDOs disabled) on a drive
    with 4 RPDOs and 4 TPDOs, ``config/lumbar_drive.eds``: what :func:`~.plan.plan_drive`
    plans for that dictionary (``force_object``: the load cell's index, sub-index 0)."""
    from .dictionary import Dictionary, ObjectRef
    from .plan import BootSettings, plan_drive
    from ..config import config_dir
    d = Dictionary(config_dir() / 'lumbar_drive.eds', node_id)
    plan = plan_drive(d, BootSettings(
        node_id=node_id, name=f'node {node_id}', master_node_id=127, master_heartbeat_ms=100,
        drive_heartbeat_ms=50, period_us=2000, interpolation=(2, -3), homing_method=0,
        following_error_counts=1, velocity_counts=1, acceleration_counts=1, soft_limits_counts=None,
        home_offset_counts=None, load_cell=ObjectRef(force_object)))
    return plan.mapping


def frame_bits(dlc: int, *, extended: bool = False) -> int:
    """Bits on the wire of a data frame, worst-case bit stuffing, with the 3-bit intermission.

    Classic CAN: 47 bits of overhead (standard id) + 8·dlc, stuffing over the
    34 + 8·dlc bits from SOF to the CRC: at most ⌊(34 + 8·dlc − 1)/4⌋ extra bits.
    """
    head = 54 if extended else 34
    overhead = 67 if extended else 47
    return overhead + 8 * dlc + (head + 8 * dlc - 1) // 4
