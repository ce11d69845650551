"""A simulated CiA 402 drive that speaks real CANopen: the polarizer stage when there is no hardware.

Its object dictionary is the shipped EDS (``data/sim402.eds``), served by canopen's SDO server of a
:class:`canopen.LocalNode`; the drive behind it is :class:`~.sim402_axis.Axis402` (device control, profile
position, homing). The CiA 301 communication is this module's own, because the standard's NMT slave is more
than canopen's ``NmtSlave`` does:

* **NMT** (COB-ID 0x000, node id or 0). Start (0x01), stop (0x02), enter PRE-OPERATIONAL (0x80). Reset node
  (0x81): every object back to its power-on value and the drive state machine to SWITCH ON DISABLED
  (transitions 0, 1), then reset communication. Reset communication (0x82): the communication objects
  0x1000-0x1FFF back to their power-on values. Both end in one boot-up message (0x700 + id, 0x00) and
  PRE-OPERATIONAL. The power-on values are the EDS defaults (0x6081 from ``speed_counts_s``); the position is
  kept (an absolute encoder).
* **Services per NMT state.** PRE-OPERATIONAL: SDO, EMCY, heartbeat. OPERATIONAL: also the PDOs. STOPPED:
  only NMT and heartbeat (an SDO request gets no answer, an RPDO is ignored, no EMCY). The drive state machine
  does not react to the NMT state (0x6007, abort connection option, is not modelled: "no action").
* **Heartbeat** (0x1017 [ms], 0 = off): one producer, the drive's own clock thread; composed when it is sent,
  under the same lock as the NMT state changes, so no heartbeat reports a state the drive already left.
  Nothing is served before the boot-up (INITIALISING).
* **TPDO1** (statusword, position actual value, mode display; COB-ID 0x1800:01, bit 31 = not valid): in
  OPERATIONAL only, on every change of its data (no more often than the inhibit time 0x1800:03 [100 µs]) and
  every event timer 0x1800:05 [ms] (0 = off; 10 ms at power-on); transmission types 254/255 only (no SYNC).
  One is sent on entering OPERATIONAL.
* **RPDO1** (controlword, target position; COB-ID 0x1400:01): in OPERATIONAL only; shorter frames are dropped.
* **EMCY** (0x80 + id) and the error register 0x1001 (bit 0, generic error, set with any error): a fault sends
  the error code with the register; the fault reset (transition 15) clears 0x603F and 0x1001 and sends the
  "error reset" EMCY (code 0x0000) with register 0x00.
* **Modes.** 0x6060 accepts 0 and the modes 0x6502 lists (1 profile position, 6 homing), else SDO abort
  0x06090030 and 0x6061 keeps the current mode. 0x6098 accepts 0, 35 and 37.

Injectable faults: :meth:`inject_emcy` (FAULT state plus an EMCY), :meth:`inject_reboot` (a power cycle:
reset node without an NMT command), :meth:`inject_heartbeat_stop`,
:meth:`inject_bus_off` (an error frame 0x040, silence, then 0x100 "restarted"), :meth:`inject_never_settle`,
:meth:`inject_position_limit`. Not modelled: following error, acceleration and quick-stop ramps, SYNC, PDO
remapping and COB-ID changes, LSS, the drive's own bus-off counters, storing parameters (0x1010).

Embedded: ``SimCia402Drive(channel=…, node_id=5).start()`` … ``.stop()``. As a process::

    python -m polarstripe.nodes.drivers.simdrive --channel ipc:///tmp/rig-can --node-id 5

prints ``ready`` and then reads commands on stdin, one a line, answering ``ok <command>``: ``emcy [CODE]``,
``reboot``, ``heartbeat_stop [SECONDS]``, ``heartbeat_resume``, ``bus_off SECONDS``, ``never_settle on|off``,
``position_limit MIN MAX`` (counts), ``quit``.
"""

from __future__ import annotations

import argparse
import struct
import sys
import threading
import time

import can
import canopen
from canopen.sdo.exceptions import SdoAbortedError
from polarstripe.nodes.drivers.cia402_states import EDS_PATH
from polarstripe.nodes.drivers.sim402_axis import HOMING_METHODS, MODE_BITS, Axis402
from polarstripe.nodes.drivers.zmqcan import CAN_ERR_BUSOFF, CAN_ERR_RESTARTED, GatedBus

NMT_INITIALISING, NMT_STOPPED, NMT_OPERATIONAL, NMT_PRE_OPERATIONAL = 0x00, 0x04, 0x05, 0x7F
ABORT_VALUE_RANGE = 0x06090030  # "value range of parameter exceeded" (CiA 301)
_COB_INVALID = 1 << 31


class SimCia402Drive:
    """A simulated CiA 402 rotation drive on a python-can bus (see the module docstring).

    :param channel, interface: the python-can bus (``zmq`` crosses processes; ``virtual`` stays in one).
    :param node_id: CANopen node id, 1-127.
    :param speed_counts_s: the power-on profile velocity 0x6081 [counts/s].
    :param settle_s: time [s] the drive stands at the target before it reports "target reached".
    :param tick_s: period [s] of the motion model.
    """

    def __init__(
        self,
        channel: str = "polarstripe",
        node_id: int = 5,
        *,
        interface: str = "zmq",
        speed_counts_s: float = 200_000.0,
        settle_s: float = 0.02,
        tick_s: float = 0.005,
        eds: str = EDS_PATH,
        **bus_kwargs,
    ):
        if not 1 <= node_id <= 127:
            raise ValueError(f"node_id={node_id} outside 1..127")
        self.channel, self.node_id, self.interface = channel, node_id, interface
        self.tick_s = tick_s
        self._bus_kwargs = bus_kwargs
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.network: canopen.Network | None = None
        self._gate: GatedBus | None = None
        self.node = canopen.LocalNode(node_id, eds)
        self._power_on_values = {(0x6081, 0): struct.pack("<I", int(speed_counts_s))}
        self.axis = Axis402(self.od, settle_s)
        self.nmt_state = NMT_INITIALISING
        self.error_register = self.error_code = 0
        self._hb_muted = False
        self._hb_next: float | None = None
        self._tpdo_at, self._tpdo_data = -1e9, b""

    # -- life cycle ----------------------------------------------------------------------------------------
    def start(self) -> SimCia402Drive:
        inner = can.Bus(interface=self.interface, channel=self.channel, **self._bus_kwargs)
        try:
            self._start(inner)
        except BaseException:  # a stop signal mid-start: leave the bus (and the hub it may host)
            self.stop()
            inner.shutdown()
            raise
        return self

    def _start(self, inner) -> None:
        self._gate = GatedBus(inner)
        self.network = canopen.Network(self._gate)
        self.network.NOTIFIER_CYCLE = 0.05
        self.network.add_node(self.node)
        node, net = self.node, self.network
        # this module is the NMT slave and gates the SDO server by NMT state (canopen's LocalNode does not)
        net.unsubscribe(0, node.nmt.on_command)
        net.unsubscribe(node.sdo.rx_cobid, node.sdo.on_request)
        node._write_callbacks.remove(node.nmt.on_write)
        net.subscribe(0, self._on_nmt)
        net.subscribe(node.sdo.rx_cobid, self._on_sdo)
        net.subscribe(0x200 + self.node_id, self._on_rpdo)
        node.add_write_callback(self._on_write)
        node.add_read_callback(self._on_read)
        net.connect()
        with self._lock:
            self._reset(application=True)  # power on
        self._thread = threading.Thread(target=self._run, name=f"simdrive {self.node_id}", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop the drive and leave the bus; idempotent."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)
            self._thread = None
        if self.network is not None:
            self.network.disconnect()
            self.network = None

    def __enter__(self) -> SimCia402Drive:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    # -- the object dictionary ------------------------------------------------------------------------------
    def od(self, index: int, subindex: int = 0) -> int:
        """The current value of an object (what an SDO upload would read)."""
        obj = self.node._find_object(index, subindex)
        return obj.decode_raw(self.node.get_data(index, subindex))

    def _on_read(self, index: int, subindex: int, od) -> int | None:
        with self._lock:
            live = {
                0x6041: self.axis.statusword,
                0x6064: lambda: int(round(self.axis.position)),
                0x6061: lambda: self.axis.mode,
                0x1001: lambda: self.error_register,
                0x603F: lambda: self.error_code,
            }.get(index)
            return None if live is None else live()

    def _on_write(self, index: int, subindex: int, od, data: bytes) -> None:
        # Called BEFORE the value is stored; an SdoAbortedError refuses the value.
        value = od.decode_raw(data)
        with self._lock:
            if index == 0x6040:
                self._controlword(value)
            elif index == 0x6060:
                if value != 0 and not self.od(0x6502) & MODE_BITS.get(value, 0):
                    raise SdoAbortedError(ABORT_VALUE_RANGE)
                self.axis.set_mode(value)
            elif index == 0x6098 and value not in HOMING_METHODS:
                raise SdoAbortedError(ABORT_VALUE_RANGE)
            elif index == 0x1800 and subindex == 2 and value not in (254, 255):
                raise SdoAbortedError(ABORT_VALUE_RANGE)  # synchronous TPDOs need SYNC: not modelled
            elif index == 0x1017:
                self._hb_next = time.monotonic() + value / 1000.0 if value else None

    # -- NMT ------------------------------------------------------------------------------------------------
    def _on_nmt(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if len(data) < 2 or data[1] not in (0, self.node_id):
            return
        with self._lock:
            command = data[0]
            if self.nmt_state == NMT_INITIALISING:
                return  # not booted yet: no service at all
            if command == 0x01:
                self._enter(NMT_OPERATIONAL)
            elif command == 0x02:
                self._enter(NMT_STOPPED)
            elif command == 0x80:
                self._enter(NMT_PRE_OPERATIONAL)
            elif command in (0x81, 0x82):
                self._reset(application=command == 0x81)

    def _enter(self, state: int) -> None:
        old, self.nmt_state = self.nmt_state, state
        if state == NMT_OPERATIONAL and old != NMT_OPERATIONAL:
            self._send_tpdo(time.monotonic(), force=True)

    def _reset(self, application: bool) -> None:
        """Reset node (``application``) or reset communication, then boot-up and PRE-OPERATIONAL."""
        self.nmt_state = NMT_INITIALISING
        store = self.node.data_store
        for index in [i for i in store if i >= 0x1000 and (application or i < 0x2000)]:
            del store[index]
        if application:
            for (index, subindex), raw in self._power_on_values.items():
                store.setdefault(index, {})[subindex] = raw
            self.axis.power_on()
            self.error_register = self.error_code = 0
        self._tpdo_at, self._tpdo_data = -1e9, b""
        self._send(0x700 + self.node_id, b"\x00")  # boot-up
        self.nmt_state = NMT_PRE_OPERATIONAL
        period_ms = self.od(0x1017)
        self._hb_next = time.monotonic() + period_ms / 1000.0 if period_ms else None

    # -- SDO, PDO, EMCY -------------------------------------------------------------------------------------
    def _on_sdo(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if self.nmt_state in (NMT_PRE_OPERATIONAL, NMT_OPERATIONAL):
            self.node.sdo.on_request(can_id, data, timestamp)

    def _on_rpdo(self, can_id: int, data: bytearray, timestamp: float) -> None:
        with self._lock:
            if self.nmt_state != NMT_OPERATIONAL or self.od(0x1400, 1) & _COB_INVALID or len(data) < 6:
                return
            controlword, target = struct.unpack_from("<Hi", data)
            self.node.data_store.setdefault(0x607A, {})[0] = struct.pack("<i", target)
            self._controlword(controlword)

    def _controlword(self, cw: int) -> None:
        if self.axis.controlword(cw):  # transition 15: the fault is reset
            self.error_code = self.error_register = 0
            self._emcy(0x0000)
        self._send_tpdo(time.monotonic())

    def _emcy(self, code: int) -> None:
        if self.nmt_state in (NMT_PRE_OPERATIONAL, NMT_OPERATIONAL):
            self._send(0x80 + self.node_id, struct.pack("<HB5x", code, self.error_register))

    def _send_tpdo(self, now: float, force: bool = False) -> None:
        """TPDO1 if it is due: on change after the inhibit time, on the event timer, or ``force``."""
        if self.nmt_state != NMT_OPERATIONAL:
            return
        cob_id = self.od(0x1800, 1)
        if cob_id & _COB_INVALID:
            return
        axis = self.axis
        data = struct.pack("<HiB", axis.statusword(), int(round(axis.position)), axis.mode & 0xFF)
        since = now - self._tpdo_at
        timer_s = self.od(0x1800, 5) / 1000.0
        changed = data != self._tpdo_data and since >= self.od(0x1800, 3) * 1e-4
        if force or changed or (timer_s and since >= timer_s):
            self._tpdo_at, self._tpdo_data = now, data
            self._send(cob_id & 0x7FF, data)

    def _send(self, can_id: int, data: bytes) -> None:
        try:
            self.network.send_message(can_id, data)
        except can.CanError:
            pass  # a drive does not stop because one frame could not be sent

    # -- the drive's own clock: motion, heartbeat, event timer ----------------------------------------------
    def _run(self) -> None:
        last = time.monotonic()
        while not self._stop.is_set():
            now = time.monotonic()
            with self._lock:
                self.axis.step(now - last, now)
                last = now
                if self._hb_next is not None and now >= self._hb_next:
                    if not self._hb_muted:
                        self._send(0x700 + self.node_id, bytes([self.nmt_state]))
                    period_s = self.od(0x1017) / 1000.0
                    self._hb_next = max(self._hb_next + period_s, now) if period_s else None
                self._send_tpdo(now)
                wake = now + self.tick_s
                if self._hb_next is not None:
                    wake = min(wake, self._hb_next)
                timer_s = self.od(0x1800, 5) / 1000.0
                if timer_s and self.nmt_state == NMT_OPERATIONAL:
                    wake = min(wake, self._tpdo_at + timer_s)
            self._stop.wait(max(0.0, wake - time.monotonic()))

    # -- fault injection ------------------------------------------------------------------------------------
    def inject_emcy(self, code: int = 0x8611, register: int = 0x01) -> None:
        """Enter FAULT (transitions 13, 14) and send EMCY ``code`` (default 0x8611, following error) with
        ``register`` (bit 0, generic error, is always set)."""
        with self._lock:
            self.axis.fault()
            self.error_code, self.error_register = code, register | 0x01
            # EMCY (COB-ID 0x80+id) wins arbitration over TPDO1 (0x180+id): it is on the bus first
            self._emcy(code)
            self._send_tpdo(time.monotonic())

    def inject_reboot(self) -> None:
        """A power cycle: what NMT reset node does (power-on values, boot-up), with no NMT command on the
        bus."""
        with self._lock:
            self._reset(application=True)

    def inject_heartbeat_stop(self, duration_s: float | None = None) -> None:
        """Stop the heartbeat producer, for ``duration_s`` seconds or until :meth:`resume_heartbeat`."""
        self._hb_muted = True
        if duration_s is not None:
            threading.Timer(duration_s, self.resume_heartbeat).start()

    def resume_heartbeat(self) -> None:
        with self._lock:
            self._hb_muted = False
            if self._hb_next is not None:
                self._hb_next = time.monotonic()

    def inject_bus_off(self, duration_s: float) -> None:
        """Report bus-off (error frame 0x040), fall silent for ``duration_s``, then report "restarted"
        (0x100). ``duration_s`` must be in [0, 3600] (a timer cannot wait longer than the platform allows)."""
        if not 0.0 <= duration_s <= 3600.0:
            raise ValueError(f"bus-off duration_s={duration_s} must be in [0, 3600] s")
        gate = self._gate
        gate.send_raw(
            can.Message(
                arbitration_id=CAN_ERR_BUSOFF, is_error_frame=True, is_extended_id=False, data=bytes(8)
            )
        )
        gate.silent = True

        def restart():
            gate.silent = False
            if self._stop.is_set():
                return
            frame = can.Message(
                arbitration_id=CAN_ERR_RESTARTED, is_error_frame=True, is_extended_id=False, data=bytes(8)
            )
            try:
                gate.send_raw(frame)
            except can.CanError:
                pass  # the drive was stopped meanwhile

        threading.Timer(duration_s, restart).start()

    def inject_never_settle(self, on: bool = True) -> None:
        """Make the motor hunt around its target forever: "target reached" is never set."""
        with self._lock:
            self.axis.never_settle = on

    def inject_position_limit(self, min_counts: int, max_counts: int) -> None:
        """Narrow the drive's software position limit (0x607D) as a misconfigured drive would have it."""
        with self._lock:
            store = self.node.data_store.setdefault(0x607D, {})
            store[1], store[2] = struct.pack("<i", min_counts), struct.pack("<i", max_counts)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m polarstripe.nodes.drivers.simdrive",
        description="Run a simulated CiA 402 drive; fault commands on stdin.",
    )
    parser.add_argument("--channel", required=True, help="the CAN channel (ipc://PATH for the zmq interface)")
    parser.add_argument("--node-id", type=int, default=5)
    parser.add_argument("--interface", default="zmq")
    parser.add_argument("--speed", type=float, default=200_000.0, help="profile velocity [counts/s]")
    parser.add_argument("--settle", type=float, default=0.02, help="settle time [s]")
    args = parser.parse_args(argv)
    drive = SimCia402Drive(
        args.channel, args.node_id, interface=args.interface, speed_counts_s=args.speed, settle_s=args.settle
    )
    commands = {
        "emcy": lambda a: drive.inject_emcy(int(a[0], 0) if a else 0x8611),
        "reboot": lambda a: drive.inject_reboot(),
        "heartbeat_stop": lambda a: drive.inject_heartbeat_stop(float(a[0]) if a else None),
        "heartbeat_resume": lambda a: drive.resume_heartbeat(),
        "bus_off": lambda a: drive.inject_bus_off(float(a[0])),
        "never_settle": lambda a: drive.inject_never_settle(a[0] == "on"),
        "position_limit": lambda a: drive.inject_position_limit(int(a[0]), int(a[1])),
    }
    with drive:
        print("ready", flush=True)
        for line in sys.stdin:
            words = line.split()
            if not words:
                continue
            if words[0] == "quit":
                break
            try:
                commands[words[0]](words[1:])
                print("ok", line.strip(), flush=True)
            except (KeyError, IndexError, ValueError) as exc:
                print("error", line.strip(), type(exc).__name__, exc, flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
