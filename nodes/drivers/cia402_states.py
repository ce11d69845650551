"""The CiA 402 (IEC 61800-7-201) drive state machine: states, statusword patterns, controlword commands.

The transitions are numbered as in the standard's state diagram (and as in ``canopen.profiles.p402``)::

    0  START -> NOT READY TO SWITCH ON                 automatic
    1  NOT READY TO SWITCH ON -> SWITCH ON DISABLED    automatic
    2  SWITCH ON DISABLED -> READY TO SWITCH ON        Shutdown           cw xxxx xxxx 0xxx x110
    3  READY TO SWITCH ON -> SWITCHED ON               Switch on          cw 0xxx 0111
    4  SWITCHED ON -> OPERATION ENABLED                Enable operation   cw 0xxx 1111
    5  OPERATION ENABLED -> SWITCHED ON                Disable operation  cw 0xxx 0111
    6  SWITCHED ON -> READY TO SWITCH ON               Shutdown
    7  READY TO SWITCH ON -> SWITCH ON DISABLED        Disable voltage    cw 0xxx xx0x  (or Quick stop)
    8  OPERATION ENABLED -> READY TO SWITCH ON         Shutdown
    9  OPERATION ENABLED -> SWITCH ON DISABLED         Disable voltage
    10 SWITCHED ON -> SWITCH ON DISABLED               Disable voltage    (or Quick stop)
    11 OPERATION ENABLED -> QUICK STOP ACTIVE          Quick stop         cw 0xxx x01x
    12 QUICK STOP ACTIVE -> SWITCH ON DISABLED         Disable voltage (or quick stop completed)
    13 any -> FAULT REACTION ACTIVE                    a fault in the drive
    14 FAULT REACTION ACTIVE -> FAULT                  automatic
    15 FAULT -> SWITCH ON DISABLED                     Fault reset        cw bit 7 rising edge
    16 QUICK STOP ACTIVE -> OPERATION ENABLED          Enable operation

Statusword bits used in profile position mode: 10 target reached, 11 internal limit active, 12 set-point
acknowledge (in homing mode: homing attained), 13 following error (homing: homing error), 9 remote.
Controlword bits: 4 new set-point (homing: start), 5 change set immediately, 6 relative, 8 halt.
"""

from __future__ import annotations

import enum
import importlib.resources

#: the EDS of the simulated drive (also a fair minimal EDS for a real drive's profile-position objects)
EDS_PATH = str(importlib.resources.files("polarstripe.nodes.drivers") / "data" / "sim402.eds")


class State(enum.Enum):
    NOT_READY_TO_SWITCH_ON = "NOT READY TO SWITCH ON"
    SWITCH_ON_DISABLED = "SWITCH ON DISABLED"
    READY_TO_SWITCH_ON = "READY TO SWITCH ON"
    SWITCHED_ON = "SWITCHED ON"
    OPERATION_ENABLED = "OPERATION ENABLED"
    QUICK_STOP_ACTIVE = "QUICK STOP ACTIVE"
    FAULT_REACTION_ACTIVE = "FAULT REACTION ACTIVE"
    FAULT = "FAULT"


#: (mask, value) of the statusword for each state (the standard's table of statusword patterns).
STATUSWORD_PATTERNS: dict[State, tuple[int, int]] = {
    State.NOT_READY_TO_SWITCH_ON: (0x4F, 0x00),
    State.SWITCH_ON_DISABLED: (0x4F, 0x40),
    State.READY_TO_SWITCH_ON: (0x6F, 0x21),
    State.SWITCHED_ON: (0x6F, 0x23),
    State.OPERATION_ENABLED: (0x6F, 0x27),
    State.QUICK_STOP_ACTIVE: (0x6F, 0x07),
    State.FAULT_REACTION_ACTIVE: (0x4F, 0x0F),
    State.FAULT: (0x4F, 0x08),
}

SW_VOLTAGE_ENABLED = 1 << 4
SW_WARNING = 1 << 7
SW_REMOTE = 1 << 9
SW_TARGET_REACHED = 1 << 10
SW_INTERNAL_LIMIT = 1 << 11
SW_SETPOINT_ACK = 1 << 12  # homing mode: homing attained
SW_FOLLOWING_ERROR = 1 << 13  # homing mode: homing error

# Controlword commands (bits 0-3 and 7) and the profile-position bits.
CW_SHUTDOWN = 0x0006
CW_SWITCH_ON = 0x0007
CW_DISABLE_OPERATION = 0x0007
CW_ENABLE_OPERATION = 0x000F
CW_DISABLE_VOLTAGE = 0x0000
CW_QUICK_STOP = 0x0002
CW_FAULT_RESET = 0x0080
CW_NEW_SETPOINT = 1 << 4
CW_CHANGE_SET_IMMEDIATELY = 1 << 5
CW_RELATIVE = 1 << 6
CW_HALT = 1 << 8

#: transition number -> (from state, to state, controlword command or None when automatic / fault-driven)
TRANSITIONS: dict[int, tuple[State | None, State, int | None]] = {
    0: (None, State.NOT_READY_TO_SWITCH_ON, None),
    1: (State.NOT_READY_TO_SWITCH_ON, State.SWITCH_ON_DISABLED, None),
    2: (State.SWITCH_ON_DISABLED, State.READY_TO_SWITCH_ON, CW_SHUTDOWN),
    3: (State.READY_TO_SWITCH_ON, State.SWITCHED_ON, CW_SWITCH_ON),
    4: (State.SWITCHED_ON, State.OPERATION_ENABLED, CW_ENABLE_OPERATION),
    5: (State.OPERATION_ENABLED, State.SWITCHED_ON, CW_DISABLE_OPERATION),
    6: (State.SWITCHED_ON, State.READY_TO_SWITCH_ON, CW_SHUTDOWN),
    7: (State.READY_TO_SWITCH_ON, State.SWITCH_ON_DISABLED, CW_DISABLE_VOLTAGE),
    8: (State.OPERATION_ENABLED, State.READY_TO_SWITCH_ON, CW_SHUTDOWN),
    9: (State.OPERATION_ENABLED, State.SWITCH_ON_DISABLED, CW_DISABLE_VOLTAGE),
    10: (State.SWITCHED_ON, State.SWITCH_ON_DISABLED, CW_DISABLE_VOLTAGE),
    11: (State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE, CW_QUICK_STOP),
    12: (State.QUICK_STOP_ACTIVE, State.SWITCH_ON_DISABLED, CW_DISABLE_VOLTAGE),
    13: (None, State.FAULT_REACTION_ACTIVE, None),
    14: (State.FAULT_REACTION_ACTIVE, State.FAULT, None),
    15: (State.FAULT, State.SWITCH_ON_DISABLED, CW_FAULT_RESET),
    16: (State.QUICK_STOP_ACTIVE, State.OPERATION_ENABLED, CW_ENABLE_OPERATION),
}

#: the transition to take from each state on the way to OPERATION ENABLED (None: wait, it is automatic)
PATH_TO_OPERATION_ENABLED: dict[State, int | None] = {
    State.NOT_READY_TO_SWITCH_ON: None,  # 1 is automatic
    State.SWITCH_ON_DISABLED: 2,
    State.READY_TO_SWITCH_ON: 3,
    State.SWITCHED_ON: 4,
    State.QUICK_STOP_ACTIVE: 16,
    State.FAULT_REACTION_ACTIVE: None,  # 14 is automatic
    State.FAULT: 15,
}


def decode_statusword(statusword: int) -> State:
    """The drive state a statusword reports (bits 0-3, 5, 6).

    :raises ValueError: the bits match no state of the standard's table.
    """
    for state, (mask, value) in STATUSWORD_PATTERNS.items():
        if statusword & mask == value:
            return state
    raise ValueError(f"statusword 0x{statusword:04X} matches no CiA 402 state")


def statusword_for(state: State) -> int:
    """The statusword bits 0-6 that report ``state`` (bit 4, voltage enabled, set where the drive is
    powered)."""
    value = STATUSWORD_PATTERNS[state][1]
    if state in (
        State.READY_TO_SWITCH_ON,
        State.SWITCHED_ON,
        State.OPERATION_ENABLED,
        State.QUICK_STOP_ACTIVE,
    ):
        value |= SW_VOLTAGE_ENABLED
    return value
