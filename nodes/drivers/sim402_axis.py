"""The drive side of the simulated CiA 402 drive: device control, profile position and homing, no CAN.

:class:`Axis402` is what :class:`~.simdrive.SimCia402Drive` runs behind its CANopen interface. It reads its
parameters from the object dictionary through a function (``od(index, subindex) -> int``), so the NMT resets
of the drive reset them too. What it does, against CiA 402-2 (IEC 61800-7-201):

* **Device control.** The controlword command (bits 0-3, 7) takes the numbered transitions of
  :mod:`.cia402_states`; FAULT is left only on the rising edge of bit 7 (15). Quick stop stops at once and
  stays in QUICK STOP ACTIVE (as quick stop option code 6 would), so 16 leads back to OPERATION ENABLED.
  Leaving OPERATION ENABLED drops every set-point.
* **Profile position (0x6060 = 1).** Bit 4 rising edge takes 0x607A as a new set-point; bit 6 makes it
  relative to the preceding (internal absolute) target, or to the actual position when there is none (after
  power-on, a disable or a mode change); the software position limit 0x607D clamps it and sets bit 11
  (internal limit active). Bit 5 = 1 starts it at once; bit 5 = 0 while a set-point is in progress buffers it
  (one deep, a later one overwrites it) and starts it when the current target is reached. Bit 12 (set-point
  acknowledge) is 1 from the accepted edge while bit 4 is high, and stays 1 while a buffered set-point waits.
  Bit 8 (halt) stops the axis; bit 10 is then 1 at standstill ("velocity 0"), and releasing halt resumes the
  set-point. Otherwise bit 10 (target reached) is 1 when the axis stood at the target for ``settle_s`` and
  nothing is buffered. Speed: 0x6081 [counts/s]; acceleration is not modelled (a halt stops at once).
* **Homing (0x6060 = 6).** Bit 4 rising edge starts the method in 0x6098. 35 and 37 ("home on the current
  position", 35 being the older number of 37) do not move: the position actual value becomes the home offset
  0x607C, and bits 12 + 10 say "homing completed". Method 0 ("no method assigned", the power-on value) ends in
  homing error (bit 13, with bit 10: velocity zero). Other methods are refused when 0x6098 is written.
"""

from __future__ import annotations

import time
from collections.abc import Callable

from polarstripe.nodes.drivers.cia402_states import (
    CW_CHANGE_SET_IMMEDIATELY,
    CW_HALT,
    CW_NEW_SETPOINT,
    CW_RELATIVE,
    SW_FOLLOWING_ERROR,
    SW_INTERNAL_LIMIT,
    SW_REMOTE,
    SW_SETPOINT_ACK,
    SW_TARGET_REACHED,
    State,
    statusword_for,
)

MODE_NONE, MODE_PROFILE_POSITION, MODE_HOMING = 0, 1, 6
#: 0x6502 bit of each mode this model runs (bit 0 profile position, bit 5 homing)
MODE_BITS = {MODE_PROFILE_POSITION: 1 << 0, MODE_HOMING: 1 << 5}
#: homing methods this model runs: 0 (none assigned: homing error), 35 and 37 (current position)
HOMING_METHODS = (0, 35, 37)


def decode_command(cw: int, state: State) -> State:
    """The state after controlword ``cw`` in ``state`` (FAULT is left by :meth:`Axis402.controlword` only)."""
    if cw & 0x82 == 0x00:  # disable voltage: 7, 9, 10, 12
        return State.SWITCH_ON_DISABLED
    if cw & 0x86 == 0x02:  # quick stop: 11 from OPERATION ENABLED, else 7 / 10
        return State.QUICK_STOP_ACTIVE if state is State.OPERATION_ENABLED else State.SWITCH_ON_DISABLED
    if cw & 0x87 == 0x06:  # shutdown: 2, 6, 8
        if state in (State.SWITCH_ON_DISABLED, State.SWITCHED_ON, State.OPERATION_ENABLED):
            return State.READY_TO_SWITCH_ON
    elif cw & 0x8F == 0x07:  # switch on 3 / disable operation 5
        if state in (State.READY_TO_SWITCH_ON, State.OPERATION_ENABLED):
            return State.SWITCHED_ON
    elif cw & 0x8F == 0x0F:  # enable operation: 4, 16 (3+4 from READY TO SWITCH ON)
        if state in (State.SWITCHED_ON, State.QUICK_STOP_ACTIVE, State.READY_TO_SWITCH_ON):
            return State.OPERATION_ENABLED
    return state


class Axis402:
    """One simulated axis (see the module docstring); not thread-safe: the drive holds its lock around it.

    :param od: the current value of an object dictionary entry, ``od(index, subindex)``.
    :param settle_s: how long the axis stands at the target before "target reached".
    """

    def __init__(self, od: Callable[[int, int], int], settle_s: float = 0.02):
        self._od = od
        self.settle_s = settle_s
        self.position = 0.0  # counts; kept through a power cycle (an absolute encoder)
        self.never_settle = False
        self.power_on()

    def power_on(self) -> None:
        """The state after power-on or NMT reset node: transitions 0 and 1, no mode, no set-point."""
        self.state = State.SWITCH_ON_DISABLED
        self.mode = MODE_NONE
        self.cw = 0
        self._drop_setpoints()
        self._homing = "idle"  # idle | done | error

    # -- inputs ---------------------------------------------------------------------------------------------
    def set_mode(self, mode: int) -> None:
        """0x6060 written (the drive checked it against 0x6502): the old mode's set-points are dropped."""
        if mode != self.mode:
            self.mode = mode
            self._drop_setpoints()
            self._homing = "idle"

    def fault(self) -> None:
        """Transitions 13 and 14: a fault in the drive."""
        self.state = State.FAULT
        self._drop_setpoints()

    def controlword(self, cw: int) -> bool:
        """Apply a controlword; True when it reset a fault (transition 15), so the drive clears its errors."""
        old, self.cw = self.cw, cw
        rising = cw & ~old
        if self.state is State.FAULT:
            if rising & 0x80:
                self.state = State.SWITCH_ON_DISABLED
                return True
            return False
        new = decode_command(cw, self.state)
        if new is not State.OPERATION_ENABLED:
            self._drop_setpoints()
        self.state = new
        if new is not State.OPERATION_ENABLED:
            return False
        if self.mode == MODE_PROFILE_POSITION:
            if rising & CW_NEW_SETPOINT:
                self._new_setpoint(cw)
            elif not cw & CW_NEW_SETPOINT:
                self._ack = self._buffered is not None
        elif self.mode == MODE_HOMING and rising & CW_NEW_SETPOINT:
            self._start_homing()
        return False

    # -- profile position -----------------------------------------------------------------------------------
    def _drop_setpoints(self) -> None:
        self._target: int | None = None  # the set-point in progress [counts]
        self._buffered: int | None = None  # the next one (bit 5 = 0)
        self._last_target: int | None = None  # the preceding internal absolute target (bit 6)
        self._ack = False
        self._limited = False
        self._reached = True
        self._reached_since: float | None = None

    def _new_setpoint(self, cw: int) -> None:
        value = self._od(0x607A, 0)
        if cw & CW_RELATIVE:
            base = self._last_target if self._last_target is not None else round(self.position)
            value += base
        lo, hi = self._od(0x607D, 1), self._od(0x607D, 2)
        target = min(max(value, lo), hi)
        self._limited = target != value
        self._last_target = target
        self._ack = True
        if cw & CW_CHANGE_SET_IMMEDIATELY or self._target is None:
            self._target, self._buffered = target, None
            self._reached, self._reached_since = False, None
        else:
            self._buffered = target

    def step(self, dt: float, now: float | None = None) -> None:
        """Advance the motion by ``dt`` seconds (OPERATION ENABLED, not halted, a set-point in progress)."""
        if self.state is not State.OPERATION_ENABLED or self._target is None or self.cw & CW_HALT:
            return
        target, here = self._target, self.position
        if self.never_settle:  # hunting: a few counts either side, never inside the window
            self.position = target + (25.0 if here <= target else -25.0)
            return
        step = self._od(0x6081, 0) * dt
        if abs(target - here) > step:
            self.position = here + (step if target > here else -step)
            return
        self.position = float(target)
        if self._buffered is not None:  # bit 5 = 0: the buffered set-point starts when this one is reached
            self._target, self._buffered = self._buffered, None
            self._ack = bool(self.cw & CW_NEW_SETPOINT)
            return
        now = time.monotonic() if now is None else now
        if self._reached_since is None:
            self._reached_since = now
        elif now - self._reached_since >= self.settle_s:
            self._reached, self._target = True, None

    # -- homing ---------------------------------------------------------------------------------------------
    def _start_homing(self) -> None:
        method = self._od(0x6098, 0)
        if method in (35, 37):
            self.position = float(self._od(0x607C, 0))
            self._homing = "done"
        else:
            self._homing = "error"

    # -- output ---------------------------------------------------------------------------------------------
    @property
    def moving(self) -> bool:
        return self.state is State.OPERATION_ENABLED and self._target is not None and not self.cw & CW_HALT

    def statusword(self) -> int:
        sw = statusword_for(self.state) | SW_REMOTE
        if self.mode == MODE_HOMING:
            if self._homing == "done":
                sw |= SW_SETPOINT_ACK | SW_TARGET_REACHED
            elif self._homing == "error":
                sw |= SW_FOLLOWING_ERROR | SW_TARGET_REACHED
            else:  # not started (or interrupted)
                sw |= SW_TARGET_REACHED
            return sw
        halted = self.cw & CW_HALT and self.state is State.OPERATION_ENABLED
        if self._reached or halted:
            sw |= SW_TARGET_REACHED
        if self._ack:
            sw |= SW_SETPOINT_ACK
        if self._limited:
            sw |= SW_INTERNAL_LIMIT
        return sw
