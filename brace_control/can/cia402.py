"""CiA 402 drive profile and CiA 301 codes: statusword 6041h, controlword 6040h, NMT, EMCY.

Pure functions and enums, no bus. The one home of these codes: the master (:mod:`.master`)
decodes with them and the simulated drives (:mod:`brace_control.sim.drive`) encode with
them, so both sides of the bus share one table.
"""
from __future__ import annotations

import enum

__all__ = [
    'State402', 'Controlword', 'Statusword', 'NmtState', 'OpMode',
    'decode_state', 'controlword_towards', 'describe_statusword', 'emcy_description',
    'EMCY_CODES', 'STATE_STATUSWORD', 'EmcyCode', 'ErrorRegister', 'error_register_bits',
    'SdoAbortCode',
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
    """NMT states as carried by the heartbeat (CiA 301 §7.2.8.3.2.1).

    ``INITIALISING`` is an alias of ``BOOTUP``: a node in the NMT state *initialisation*
    (CiA 301 §7.3.2.2.1) sends the boot-up message, whose state byte is 0.
    """

    BOOTUP = 0x00
    INITIALISING = 0x00
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


#: The statusword bits 0-3, 5, 6 a drive shows in each state (the "value" column of
#: CiA 402-2 table 30 above): what a drive (the simulator) puts in 6041h.
STATE_STATUSWORD: dict[State402, int] = {state: value for _, value, state in _STATE_TABLE}


def _decode_state_by_table(statusword: int) -> State402:
    for mask, value, state in _STATE_TABLE:
        if statusword & mask == value:
            return state
    return State402.UNKNOWN


#: every table 30 mask is within bits 0-3, 5, 6 (0x6F): the state of each of their 0x70
#: combinations, so that decoding (every TPDO, every SYNC) is one index
_STATE_OF_BITS: tuple[State402, ...] = tuple(_decode_state_by_table(bits) for bits in range(0x70))
assert all(mask & ~0x6F == 0 for mask, _, _ in _STATE_TABLE)


def decode_state(statusword: int) -> State402:
    """The 402 state a statusword 6041h shows (CiA 402-2 table 30)."""
    return _STATE_OF_BITS[statusword & 0x6F]


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
        # the word that keeps it there (every SYNC while enabled: no table built per call)
        if target is State402.OPERATION_ENABLED:
            return _CW_ENABLE_OPERATION
        if target is State402.SWITCH_ON_DISABLED:
            return _CW_DISABLE_VOLTAGE
        if target is State402.QUICK_STOP_ACTIVE:
            return _CW_QUICK_STOP
        return None
    if state in (State402.FAULT, State402.FAULT_REACTION_ACTIVE, State402.NOT_READY_TO_SWITCH_ON,
                 State402.UNKNOWN):
        return None
    if target is State402.SWITCH_ON_DISABLED:
        return _CW_DISABLE_VOLTAGE
    if target is State402.QUICK_STOP_ACTIVE:
        # from OPERATION ENABLED: QUICK STOP ACTIVE; from the other powered states the
        # same word disables voltage (transitions 7, 10): the motor is not driving anyway
        return _CW_QUICK_STOP
    if target is State402.OPERATION_ENABLED:
        return _CW_TOWARDS_ENABLED.get(state)
    raise ValueError(f'no path to {target.value}')


_CW_ENABLE_OPERATION = int(Controlword.ENABLE_OPERATION)
_CW_DISABLE_VOLTAGE = int(Controlword.DISABLE_VOLTAGE)
_CW_QUICK_STOP = int(Controlword.QUICK_STOP)
# towards OPERATION ENABLED: one step of the CiA 402 state machine from each powered state
_CW_TOWARDS_ENABLED: dict[State402, int] = {
    State402.SWITCH_ON_DISABLED: int(Controlword.SHUTDOWN),
    State402.READY_TO_SWITCH_ON: int(Controlword.SWITCH_ON),
    State402.SWITCHED_ON: int(Controlword.ENABLE_OPERATION),
    State402.QUICK_STOP_ACTIVE: int(Controlword.DISABLE_VOLTAGE),
}


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


class EmcyCode(enum.IntEnum):
    """EMCY error codes (CiA 301 table 21, CiA 402-2 table 6) the devices here produce;
    :data:`EMCY_CODES` has the text of these and more."""

    NO_ERROR = 0x0000            # error reset / no error
    GENERIC = 0x1000
    LOAD_CELL = 0x7300           # sensor
    POSITION_SENSOR = 0x7305     # incremental sensor 1 fault
    HEARTBEAT = 0x8130           # life guard / heartbeat error
    BUS_OFF_RECOVERED = 0x8140
    PDO_LENGTH = 0x8210          # PDO not processed due to length error
    FOLLOWING_ERROR = 0x8611
    REFERENCE_LIMIT = 0x8612     # target outside the software position limits


class ErrorRegister(enum.IntFlag):
    """Bits of the error register 1001h (CiA 301 §7.5.2.2), also byte 2 of an EMCY."""

    GENERIC = 1 << 0
    CURRENT = 1 << 1
    VOLTAGE = 1 << 2
    TEMPERATURE = 1 << 3
    COMMUNICATION = 1 << 4       # overrun, error state, heartbeat
    DEVICE_PROFILE = 1 << 5
    MANUFACTURER = 1 << 7


def error_register_bits(code: int) -> ErrorRegister:
    """The 1001h bits an active EMCY error code sets (CiA 301 table 21 classes): 2xxxh
    current, 3xxxh voltage, 4xxxh temperature, 81xxh/82xxh communication, 86xxh/87xxh
    device profile (other classes: the generic bit alone); 0000h sets none."""
    if code == 0:
        return ErrorRegister(0)
    bits = ErrorRegister.GENERIC
    cls = code >> 12
    if cls == 0x2:
        bits |= ErrorRegister.CURRENT
    elif cls == 0x3:
        bits |= ErrorRegister.VOLTAGE
    elif cls == 0x4:
        bits |= ErrorRegister.TEMPERATURE
    elif code >> 8 in (0x81, 0x82):
        bits |= ErrorRegister.COMMUNICATION
    elif code >> 8 in (0x86, 0x87):
        bits |= ErrorRegister.DEVICE_PROFILE
    return bits


class SdoAbortCode(enum.IntEnum):
    """SDO abort codes (CiA 301 table 22) an SDO server here answers with."""

    READ_WRITE_ONLY = 0x06010001     # attempt to read a write-only object
    WRITE_READ_ONLY = 0x06010002     # attempt to write a read-only object
    NO_OBJECT = 0x06020000           # object does not exist in the object dictionary
    NOT_MAPPABLE = 0x06040041        # object cannot be mapped to the PDO
    PDO_LENGTH = 0x06040042          # mapped objects would exceed the PDO length
    LENGTH_MISMATCH = 0x06070010     # data type / length of service parameter does not match
    NO_SUBINDEX = 0x06090011         # sub-index does not exist
    VALUE_RANGE = 0x06090030         # invalid value for parameter (download only)
    VALUE_HIGH = 0x06090031          # value of parameter written too high
    VALUE_LOW = 0x06090032           # value of parameter written too low


def emcy_description(code: int) -> str:
    """Text for an EMCY error code: exact entry, else its class (``0x23xx`` -> ``current``)."""
    if code in EMCY_CODES:
        return EMCY_CODES[code]
    for mask in (0xFFF0, 0xFF00, 0xF000):
        base = code & mask
        if base in EMCY_CODES and base != 0:
            return EMCY_CODES[base]
    return 'unknown'
