"""What :class:`~.cia402.Cia402Stage` watches on the bus: TPDO1, heartbeat and boot-up, other masters' NMT
commands, EMCY, CAN error frames, receive errors, and the consumer timeouts (heartbeat, TPDO staleness).

Everything here runs on canopen's notifier thread or the watchdog thread and only latches fault texts and
records state; the stage's own thread acts on them (``reset_fault``). NMT, as CiA 301 has it:

* a **boot-up** message (heartbeat state 0x00) means the drive was reset: its configuration is gone (the
  objects are back to their power-on values, the state machine is in SWITCH ON DISABLED), so it is a fault and
  the next fault reset re-configures the drive;
* an **NMT reset** (node or communication) sent by another master is the same, seen earlier;
* a heartbeat reporting a state other than OPERATIONAL is a fault only once the drive has reported OPERATIONAL
  since our last NMT start: a heartbeat the drive sent before that start reached it is still on its way when
  the first TPDO arrives, and is not a state change. A drive that does not report OPERATIONAL within the
  heartbeat timeout after our NMT start is a fault.

The consumer timeouts (heartbeat, NMT start, TPDO staleness) count *listening time*
(:meth:`Cia402Watch._listening_clock`): time this process was not scheduled does not count. A watchdog that
wakes later than twice its period was stalled with the rest of the process (a garbage collection holds the
GIL for its whole length, seconds on a loaded machine; a starved CPU; a debugger), and frames the drive sent
meanwhile wait unread in the socket. Judged on the wall clock, such a stall read as a lost heartbeat the drive
never missed (docs/hardware.md, the measurements). A drive that does fall silent is still found: its timeout
runs on as soon as the process runs again. The angle's freshness (``_pdo_at``) stays on the wall clock.
"""

from __future__ import annotations

import math
import threading
import time

import can
import canopen
from polarstripe.nodes.drivers import cia402_states as cia
from polarstripe.nodes.drivers.cia402_states import State

#: CAN error classes (linux/can/error.h) that are a fault for the stage; others are only counted.
FAULT_ERROR_CLASSES = {
    0x001: "TX timeout",
    0x020: "no ACK (no other node on the bus)",
    0x040: "bus-off",
    0x080: "bus error",
}
CAN_ERR_RESTARTED = 0x100
NMT_OPERATIONAL = 5
_NMT_COMMANDS = {0x02: "stop", 0x80: "enter PRE-OPERATIONAL", 0x81: "reset node", 0x82: "reset communication"}


class BusWatch(can.Listener):
    """Sees what canopen's listener drops: error frames, and receive errors (a Notifier without ``on_error``
    would die silently)."""

    def __init__(self, stage: Cia402Watch):
        self.stage = stage

    def on_message_received(self, msg: can.Message) -> None:
        if msg.is_error_frame:
            self.stage._on_error_frame(msg.arbitration_id)

    def on_error(self, exc: Exception) -> None:
        self.stage._latch_fault(f"CAN receive failed: {exc}")

    def stop(self) -> None:
        pass


class Cia402Watch:
    """The supervision half of :class:`~.cia402.Cia402Stage` (a mixin: the stage provides ``node``,
    ``name``, ``counts_per_deg``, the timeouts and ``_latch_fault``)."""

    def _init_watch(self) -> None:
        self.error_frames = 0
        self._lock = threading.RLock()
        self._sw: int | None = None
        self._pos: int | None = None
        self._pdo_at = -math.inf  # time.monotonic() of the last TPDO1: how fresh the angle is
        self._blind_s = 0.0  # time the watchdog was not scheduled beyond its period (module docstring)
        self._pdo_heard = -math.inf  # the last TPDO1 on the listening clock
        self._hb_at = self._listening_clock()  # the consumer timeout counts from the start of supervision
        self._nmt_state: int | None = None
        self._nmt_start_at: float | None = None  # our last NMT start, until the drive reports OPERATIONAL
        self._needs_config = False
        self._awaiting_ack = False
        self._acked = threading.Event()
        self._target_counts: int | None = None
        self._stop = threading.Event()

    def _listening_clock(self) -> float:
        """Seconds on a clock that stands still while this process did not run (the consumer timeouts)."""
        return time.monotonic() - self._blind_s

    def _start_watch(self) -> None:
        self.node.nmt.add_heartbeat_callback(self._on_heartbeat)
        self.node.emcy.add_callback(self._on_emcy)
        self.network.subscribe(0, self._on_nmt_command)
        self._watchdog = threading.Thread(target=self._watch, name=f"{self.name} watchdog", daemon=True)
        self._watchdog.start()

    def _nmt_start(self) -> None:
        """NMT start; a non-OPERATIONAL heartbeat is a state change again once OPERATIONAL is reported."""
        self._nmt_start_at = self._listening_clock()
        self._send(lambda: self.node.nmt.send_command(0x01), "NMT start")

    # -- callbacks (canopen's notifier thread) ------------------------------------------------------------
    def _on_tpdo(self, pdo_map) -> None:
        sw = pdo_map["Statusword"].raw
        with self._lock:
            self._sw, self._pos = sw, pdo_map["Position actual value"].raw
            self._pdo_at, self._pdo_heard = time.monotonic(), self._listening_clock()
            if self._awaiting_ack and sw & cia.SW_SETPOINT_ACK:
                self._acked.set()
        try:
            state = cia.decode_statusword(sw)
        except ValueError:
            self._latch_fault(f"statusword 0x{sw:04X} matches no CiA 402 state")
            return
        if state in (State.FAULT, State.FAULT_REACTION_ACTIVE):
            self._latch_fault(f"drive in {state.value} (statusword 0x{sw:04X})")
        if sw & cia.SW_INTERNAL_LIMIT and self._target_counts is not None:
            self._latch_fault(
                f"drive internal limit active: target {self._target_deg}° is beyond the drive's "
                "own position limit (0x607D)"
            )

    def _on_heartbeat(self, nmt_state: int) -> None:
        self._hb_at = self._listening_clock()
        self._nmt_state = nmt_state
        if nmt_state == 0:  # boot-up
            self._needs_config, self._nmt_start_at = True, None
            self._latch_fault(
                f"drive rebooted (boot-up message of node {self.node.id}): its configuration is back to "
                "power-on values until a fault reset configures it again"
            )
        elif nmt_state == NMT_OPERATIONAL:
            self._nmt_start_at = None
        elif self._nmt_start_at is None and self._pos is not None:
            name = canopen.nmt.NMT_STATES.get(nmt_state, str(nmt_state))
            self._latch_fault(f"drive left NMT OPERATIONAL (heartbeat reports {name})")

    def _on_nmt_command(self, can_id: int, data: bytearray, timestamp: float) -> None:
        """An NMT command on the bus: never ours (a bus does not receive its own frames), so another
        master's."""
        if len(data) < 2 or data[1] not in (0, self.node.id) or data[0] not in _NMT_COMMANDS:
            return
        if data[0] in (0x81, 0x82):
            self._needs_config = True
        self._latch_fault(
            f"another master sent NMT {_NMT_COMMANDS[data[0]]} (0x{data[0]:02X}) to node {self.node.id}"
        )

    def _on_emcy(self, emcy) -> None:
        if emcy.code & 0xFF00 == 0:
            return  # "error reset / no error"
        self._latch_fault(
            f"EMCY 0x{emcy.code:04X} ({emcy.get_desc() or 'no description'}), "
            f"error register 0x{emcy.register:02X}"
        )

    def _on_error_frame(self, error_class: int) -> None:
        self.error_frames += 1
        for bit, text in FAULT_ERROR_CLASSES.items():
            if error_class & bit:
                self._latch_fault(f"CAN {text} (error frame class 0x{error_class:03X})")

    def _watch(self) -> None:
        """Consumer heartbeat timeout, NMT start not taken, and TPDO staleness, checked every ``_watch_s``."""
        last = time.monotonic()
        while not self._stop.wait(self._watch_s):
            wall = time.monotonic()
            self._blind_s += max(0.0, wall - last - 2 * self._watch_s)  # woken late: the process stalled
            last, now = wall, self._listening_clock()
            if self._pos is None:
                continue
            if now - self._hb_at > self.heartbeat_timeout_s:
                self._latch_fault(
                    f"heartbeat of node {self.node.id} lost (none for more than "
                    f"{self.heartbeat_timeout_s:g} s)"
                )
            started = self._nmt_start_at
            if started is not None and now - started > self.heartbeat_timeout_s and self._hb_at > started:
                name = canopen.nmt.NMT_STATES.get(self._nmt_state, str(self._nmt_state))
                self._latch_fault(
                    f"drive did not enter NMT OPERATIONAL within {self.heartbeat_timeout_s:g} s of the NMT "
                    f"start (heartbeat reports {name})"
                )
            if now - self._pdo_heard > self.pdo_timeout_s:
                self._latch_fault(f"no TPDO1 from node {self.node.id} for more than {self.pdo_timeout_s:g} s")
