"""CiA 402 drive profile and CiA 301 codes: statusword 6041h, controlword 6040h, NMT, EMCY.

Pure functions and enums, no bus: the master (:mod:`.master`) and the tests use them.
"""
from __future__ import annotations

import enum

__all__ = [
    'State402', 'Controlword', 'Statusword', 'NmtState', 'OpMode',
    'decode_state', 'controlword_towards', 'describe_statusword', 'emcy_description',
    'EMCY_CODES',
]


class State402(enum.Enum):
    """Power state machine of a CiA 402 drive (CiA 402-2 §6.3)."""

    NOT_READY_TO_SWITCH_ON = 'NOT READY TO SWITCH ON'
    SWITCH_ON_DISABLED = 'SWITCH ON DISABLED'
    READY_TO_SWITCH_ON = 'READY TO SWITCH ON'
    SWITCHED_ON = 'SWITCHED ON'
    OPERATION_ENABLED = 'OPERATION ENABLED'
    QUICK_STOP_ACTIVE = 'QUICK STOP ACTIVE'
    FAULT_REACTION_ACTIVE = 'FAULT REACTION ACTIVE'
    FAULT = 'FAULT'
    UNKNOWN = 'UNKNOWN'


class Statusword(enum.IntFlag):
    """Bits of 6041h (bits 12/13 depend on the mode: CSP / homing meaning given)."""

    READY_TO_SWITCH_ON = 1 << 0
    SWITCHED_ON = 1 << 1
    OPERATION_ENABLED = 1 << 2
    FAULT = 1 << 3
    VOLTAGE_ENABLED = 1 << 4
    QUICK_STOP = 1 << 5            # 0 = quick stop active
    SWITCH_ON_DISABLED = 1 << 6
    WARNING = 1 << 7
    REMOTE = 1 << 9
    TARGET_REACHED = 1 << 10
    INTERNAL_LIMIT = 1 << 11
    OP_SPECIFIC_12 = 1 << 12       # CSP: drive follows target; homing: homing attained
    OP_SPECIFIC_13 = 1 << 13       # CSP: following error; homing: homing error


HOMING_ATTAINED = Statusword.OP_SPECIFIC_12
HOMING_ERROR = Statusword.OP_SPECIFIC_13
FOLLOWING_ERROR = Statusword.OP_SPECIFIC_13


class Controlword(enum.IntEnum):
    """Commands of 6040h (bits 0..3, 7; bit 4 starts homing in homing mode)."""

    DISABLE_VOLTAGE = 0x0000
    QUICK_STOP = 0x0002
    SHUTDOWN = 0x0006
    SWITCH_ON = 0x0007          # also DISABLE OPERATION from OPERATION ENABLED
    ENABLE_OPERATION = 0x000F
    START_HOMING = 0x001F       # ENABLE OPERATION + bit 4 (homing operation start)
    FAULT_RESET = 0x0080        # acts on the rising edge of bit 7


class NmtState(enum.IntEnum):
    """NMT states as carried by the heartbeat (CiA 301 §7.2.8.3.2.1)."""

    BOOTUP = 0x00
    STOPPED = 0x04
    OPERATIONAL = 0x05
    PRE_OPERATIONAL = 0x7F


class OpMode(enum.IntEnum):
    """Modes of operation 6060h / 6061h used here."""

    HOMING = 6
    CYCLIC_SYNC_POSITION = 8


# (mask, value) -> state, CiA 402-2 table 30
_STATE_TABLE: tuple[tuple[int, int, State402], ...] = (
    (0x4F, 0x00, State402.NOT_READY_TO_SWITCH_ON),
    (0x4F, 0x40, State402.SWITCH_ON_DISABLED),
    (0x6F, 0x21, State402.READY_TO_SWITCH_ON),
    (0x6F, 0x23, State402.SWITCHED_ON),
    (0x6F, 0x27, State402.OPERATION_ENABLED),
    (0x6F, 0x07, State402.QUICK_STOP_ACTIVE),
    (0x4F, 0x0F, State402.FAULT_REACTION_ACTIVE),
    (0x4F, 0x08, State402.FAULT),
)


def decode_state(statusword: int) -> State402:
    """The 402 state a statusword 6041h shows."""
    for mask, value, state in _STATE_TABLE:
        if statusword & mask == value:
            return state
    return State402.UNKNOWN


def describe_statusword(statusword: int) -> str:
    """``'OPERATION ENABLED, warning, internal limit'``: state plus the flag bits that are set."""
    parts = [decode_state(statusword).value]
    for bit, text in ((Statusword.WARNING, 'warning'), (Statusword.INTERNAL_LIMIT, 'internal limit'),
                      (Statusword.TARGET_REACHED, 'target reached')):
        if statusword & bit:
            parts.append(text)
    return ', '.join(parts)


def controlword_towards(state: State402, target: State402) -> int | None:
    """The controlword that moves a drive in ``state`` one step towards ``target``.

    ``target`` is one of OPERATION ENABLED, SWITCH ON DISABLED (disable) or QUICK STOP
    ACTIVE (halt). When the drive is already there, the word that keeps it there.
    ``None`` when only a fault reset would help (FAULT: the master sends a fault reset
    only on ``recover``) or the drive cannot take commands yet.
    """
    if state is target:
        return {State402.OPERATION_ENABLED: int(Controlword.ENABLE_OPERATION),
                State402.SWITCH_ON_DISABLED: int(Controlword.DISABLE_VOLTAGE),
                State402.QUICK_STOP_ACTIVE: int(Controlword.QUICK_STOP)}.get(target)
    if state in (State402.FAULT, State402.FAULT_REACTION_ACTIVE, State402.NOT_READY_TO_SWITCH_ON,
                 State402.UNKNOWN):
        return None
    if target is State402.SWITCH_ON_DISABLED:
        return int(Controlword.DISABLE_VOLTAGE)
    if target is State402.QUICK_STOP_ACTIVE:
        # from OPERATION ENABLED: QUICK STOP ACTIVE; from the other powered states the
        # same word disables voltage (transitions 7, 10): the motor is not driving anyway
        return int(Controlword.QUICK_STOP)
    if target is State402.OPERATION_ENABLED:
        step = {
            State402.SWITCH_ON_DISABLED: Controlword.SHUTDOWN,
            State402.READY_TO_SWITCH_ON: Controlword.SWITCH_ON,
            State402.SWITCHED_ON: Controlword.ENABLE_OPERATION,
            State402.QUICK_STOP_ACTIVE: Controlword.DISABLE_VOLTAGE,
        }.get(state)
        return None if step is None else int(step)
    raise ValueError(f'no path to {target.value}')


#: Common EMCY error codes (CiA 301 table 21, CiA 402-2 table 6); longest prefix wins.
EMCY_CODES: dict[int, str] = {
    0x0000: 'error reset / no error',
    0x1000: 'generic error',
    0x2000: 'current',
    0x2310: 'continuous over-current',
    0x2320: 'short circuit at outputs',
    0x3000: 'voltage',
    0x3210: 'DC link over-voltage',
    0x3220: 'DC link under-voltage',
    0x4000: 'temperature',
    0x4210: 'excess temperature device',
    0x4310: 'excess temperature drive',
    0x5000: 'device hardware',
    0x5530: 'data storage (EEPROM) error',
    0x6000: 'device software',
    0x6100: 'internal software error',
    0x6320: 'parameter error',
    0x7000: 'additional modules',
    0x7121: 'motor blocked',
    0x7300: 'sensor',
    0x7305: 'incremental sensor 1 fault',
    0x7310: 'speed sensor',
    0x8000: 'monitoring',
    0x8110: 'CAN overrun (objects lost)',
    0x8120: 'CAN in error passive mode',
    0x8130: 'life guard or heartbeat error',
    0x8140: 'recovered from bus off',
    0x8210: 'PDO not processed due to length error',
    0x8400: 'velocity speed controller (over-speed)',
    0x8611: 'following error',
    0x8612: 'reference limit (software position limit)',
    0x9000: 'external error',
    0xF000: 'additional functions',
    0xFF00: 'device specific',
}


def emcy_description(code: int) -> str:
    """Text for an EMCY error code: exact entry, else its class (``0x23xx`` -> ``current``)."""
    if code in EMCY_CODES:
        return EMCY_CODES[code]
    for mask in (0xFFF0, 0xFF00, 0xF000):
        base = code & mask
        if base in EMCY_CODES and base != 0:
            return EMCY_CODES[base]
    return 'unknown'
