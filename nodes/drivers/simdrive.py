"""A simulated CiA 402 drive that speaks real CANopen: the polarizer stage when there is no hardware.

It is a :class:`canopen.LocalNode` built from the shipped EDS (``data/sim402.eds``): SDO server, NMT slave
with a heartbeat producer (0x1017), EMCY producer, TPDO1 (statusword, position actual value, mode display;
sent every 10 ms and on change, in NMT OPERATIONAL only) and RPDO1 (controlword, target position). It runs the
CiA 402 state machine from the controlword, profile position mode (set-point handshake, target reached after a
finite speed and a settle time, software position limit 0x607D with "internal limit active") and homing mode
(moves to count 0, then "homing attained").

Injectable faults: :meth:`inject_emcy` (FAULT state plus an EMCY), :meth:`inject_heartbeat_stop`,
:meth:`inject_bus_off` (an error frame 0x040, silence, then 0x100 "restarted"), :meth:`inject_never_settle`,
:meth:`inject_position_limit`. Not modelled: following error, quick-stop deceleration, SYNC, PDO remapping,
LSS, the drive's own bus-off counters.

Embedded: ``SimCia402Drive(channel=…, node_id=5).start()`` … ``.stop()``. As a process::

    python -m polarstripe.nodes.drivers.simdrive --channel ipc:///tmp/rig-can --node-id 5

prints ``ready`` and then reads commands on stdin, one a line, answering ``ok <command>``: ``emcy [CODE]``,
``heartbeat_stop [SECONDS]``, ``heartbeat_resume``, ``bus_off SECONDS``, ``never_settle on|off``,
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
from polarstripe.nodes.drivers.cia402_states import (
    EDS_PATH,
    SW_INTERNAL_LIMIT,
    SW_REMOTE,
    SW_SETPOINT_ACK,
    SW_TARGET_REACHED,
    State,
    statusword_for,
)
from polarstripe.nodes.drivers.zmqcan import CAN_ERR_BUSOFF, CAN_ERR_RESTARTED

MODE_PROFILE_POSITION, MODE_HOMING = 1, 6


class _GatedBus(can.BusABC):
    """Wraps the drive's bus so the simulation can make the drive fall silent (bus-off) in both directions."""

    def __init__(self, inner: can.BusABC):
        self._inner = inner
        self.silent = False
        super().__init__(channel=getattr(inner, "channel_info", "sim"))
        self.channel_info = inner.channel_info

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if not self.silent:
            self._inner.send(msg, timeout)

    def send_raw(self, msg: can.Message) -> None:
        self._inner.send(msg)

    def _recv_internal(self, timeout):
        msg = self._inner.recv(timeout)
        if msg is not None and self.silent:
            return None, True
        return msg, True

    def shutdown(self) -> None:
        if self._is_shutdown:
            return
        super().shutdown()
        self._inner.shutdown()


class SimCia402Drive:
    """A simulated CiA 402 rotation drive on a python-can bus (see the module docstring).

    :param channel, interface: the python-can bus (``zmq`` crosses processes; ``virtual`` stays in one).
    :param node_id: CANopen node id, 1-127.
    :param speed_counts_s: profile velocity [counts/s] until the host writes 0x6081.
    :param settle_s: time [s] the drive stands at the target before it reports "target reached".
    :param tick_s: motion model and TPDO1 period [s].
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
        self.settle_s, self.tick_s = settle_s, tick_s
        self._bus_kwargs = bus_kwargs
        self._speed = speed_counts_s
        self._lock = threading.RLock()
        self.state = State.SWITCH_ON_DISABLED  # after transitions 0 and 1
        self.position = 0.0  # counts, float inside the model
        self._cw = 0
        self._flags = SW_TARGET_REACHED
        self._target: int | None = None
        self._mode = 0
        self._reached_since: float | None = None
        self._never_settle = False
        self._heartbeat_ms = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.network: canopen.Network | None = None
        self.node = canopen.LocalNode(node_id, eds)
        self._gate: _GatedBus | None = None

    # -- life cycle ----------------------------------------------------------------------------------------
    def start(self) -> SimCia402Drive:
        inner = can.Bus(interface=self.interface, channel=self.channel, **self._bus_kwargs)
        self._gate = _GatedBus(inner)
        self.network = canopen.Network(self._gate)
        self.network.NOTIFIER_CYCLE = 0.05
        self.network.add_node(self.node)
        self.network.connect()
        self.node.add_write_callback(self._on_write)
        self.node.tpdo.read(from_od=True)
        self.node.rpdo.read(from_od=True)
        self.node.rpdo[1].subscribe()
        self.node.rpdo[1].add_callback(self._on_rpdo)
        self._heartbeat_ms = self.node.sdo[0x1017].raw
        self.node.nmt.send_command(0x81)  # reset node: boot-up message
        self.node.nmt.send_command(0x80)  # to PRE-OPERATIONAL: the heartbeat producer starts
        self._thread = threading.Thread(target=self._run, name=f"simdrive {self.node_id}", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop the drive and leave the bus; idempotent."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)
            self._thread = None
        if self.network is not None:
            self.node.nmt.stop_heartbeat()
            self.network.disconnect()
            self.network = None

    def __enter__(self) -> SimCia402Drive:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    # -- fault injection ----------------------------------------------------------------------------------
    def inject_emcy(self, code: int = 0x8611, register: int = 0x01) -> None:
        """Enter FAULT (transitions 13, 14) and send EMCY ``code`` (default 0x8611, following error)."""
        with self._lock:
            self.state = State.FAULT
            self._target = None
            self.node.data_store.setdefault(0x603F, {})[0] = struct.pack("<H", code)
            self.node.data_store.setdefault(0x1001, {})[0] = struct.pack("<B", register)
            # EMCY (COB-ID 0x80+id) wins arbitration over TPDO1 (0x180+id): it is on the bus first
            self.node.emcy.send(code, register)
            self._send_tpdo()

    def inject_heartbeat_stop(self, duration_s: float | None = None) -> None:
        """Stop the heartbeat producer, for ``duration_s`` seconds or until :meth:`resume_heartbeat`."""
        self.node.nmt.stop_heartbeat()
        if duration_s is not None:
            threading.Timer(duration_s, self.resume_heartbeat).start()

    def resume_heartbeat(self) -> None:
        if not self._stop.is_set():
            self.node.nmt.start_heartbeat(self._heartbeat_ms)

    def inject_bus_off(self, duration_s: float) -> None:
        """Report bus-off (error frame 0x040), fall silent for ``duration_s``, then report "restarted"
        (0x100)."""
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
            self._never_settle = on

    def inject_position_limit(self, min_counts: int, max_counts: int) -> None:
        """Narrow the drive's software position limit (0x607D) as a misconfigured drive would have it."""
        with self._lock:
            store = self.node.data_store.setdefault(0x607D, {})
            store[1], store[2] = struct.pack("<i", min_counts), struct.pack("<i", max_counts)

    # -- CANopen callbacks --------------------------------------------------------------------------------
    def _on_rpdo(self, pdo_map) -> None:
        # A LocalNode does not store RPDO data itself.
        self.node.data_store.setdefault(0x607A, {})[0] = struct.pack("<i", pdo_map["Target position"].raw)
        self._controlword(pdo_map["Controlword"].raw)

    def _on_write(self, index: int, subindex: int, od, data: bytes) -> None:
        # Called BEFORE the value is stored.
        if index == 0x6040:
            self._controlword(struct.unpack("<H", data)[0])
        elif index == 0x6060:
            with self._lock:
                self._mode = struct.unpack("<b", data)[0]
        elif index == 0x6081:
            with self._lock:
                self._speed = float(struct.unpack("<I", data)[0])
        elif index == 0x1017:
            self._heartbeat_ms = struct.unpack("<H", data)[0]

    def _limits(self) -> tuple[int, int]:
        lo = struct.unpack("<i", self.node.get_data(0x607D, 1))[0]
        hi = struct.unpack("<i", self.node.get_data(0x607D, 2))[0]
        return lo, hi

    def _controlword(self, cw: int) -> None:
        """The device control of the standard: decode the command bits, take the transition."""
        with self._lock:
            old, self._cw, s = self._cw, cw, self.state
            if s is State.FAULT:
                if cw & 0x80 and not old & 0x80:  # 15: fault reset on the rising edge of bit 7
                    s = State.SWITCH_ON_DISABLED
                    self.node.data_store.setdefault(0x603F, {})[0] = struct.pack("<H", 0)
                    self.node.emcy.reset()
            elif cw & 0x82 == 0x00:  # disable voltage: 7, 9, 10, 12
                s = State.SWITCH_ON_DISABLED
            elif cw & 0x86 == 0x02:  # quick stop: 11 from OPERATION ENABLED, else 7 / 10
                s = State.QUICK_STOP_ACTIVE if s is State.OPERATION_ENABLED else State.SWITCH_ON_DISABLED
            elif cw & 0x87 == 0x06:  # shutdown: 2, 6, 8
                if s in (State.SWITCH_ON_DISABLED, State.SWITCHED_ON, State.OPERATION_ENABLED):
                    s = State.READY_TO_SWITCH_ON
            elif cw & 0x8F == 0x07:  # switch on 3 / disable operation 5
                if s in (State.READY_TO_SWITCH_ON, State.OPERATION_ENABLED):
                    s = State.SWITCHED_ON
            elif cw & 0x8F == 0x0F:  # enable operation: 4, 16 (3+4 from READY TO SWITCH ON)
                if s in (State.SWITCHED_ON, State.QUICK_STOP_ACTIVE, State.READY_TO_SWITCH_ON):
                    s = State.OPERATION_ENABLED
            if s is not State.OPERATION_ENABLED:
                self._target = None
                self._flags &= ~SW_INTERNAL_LIMIT  # the limited set-point is dropped with the power stage
            self.state = s
            rising = cw & 0x10 and not old & 0x10
            if s is State.OPERATION_ENABLED and rising and self._mode == MODE_PROFILE_POSITION:
                target = struct.unpack("<i", self.node.get_data(0x607A, 0))[0]
                lo, hi = self._limits()
                clamped = min(max(target, lo), hi)
                self._flags = (self._flags | SW_SETPOINT_ACK) & ~(SW_TARGET_REACHED | SW_INTERNAL_LIMIT)
                if clamped != target:
                    self._flags |= SW_INTERNAL_LIMIT
                self._target, self._reached_since = clamped, None
            elif s is State.OPERATION_ENABLED and rising and self._mode == MODE_HOMING:
                self._flags &= ~(SW_SETPOINT_ACK | SW_TARGET_REACHED | SW_INTERNAL_LIMIT)
                self._target, self._reached_since = 0, None
            if not cw & 0x10 and self._mode == MODE_PROFILE_POSITION:
                self._flags &= ~SW_SETPOINT_ACK
            self._send_tpdo()

    # -- the motion model and the periodic TPDO -----------------------------------------------------------
    def _step(self, dt: float) -> None:
        if self._target is None or self.state is not State.OPERATION_ENABLED:
            return
        error = self._target - self.position
        step = self._speed * dt
        if self._never_settle:
            # hunting: overshoot by a few counts either side, never inside the window
            self.position = self._target + (25.0 if self.position <= self._target else -25.0)
            return
        if abs(error) > step:
            self.position += step if error > 0 else -step
            return
        self.position = float(self._target)
        now = time.monotonic()
        if self._reached_since is None:
            self._reached_since = now
        elif now - self._reached_since >= self.settle_s and not self._flags & SW_TARGET_REACHED:
            self._flags |= SW_TARGET_REACHED
            if self._mode == MODE_HOMING:
                self._flags |= SW_SETPOINT_ACK  # homing attained
            self._target = None

    def _statusword(self) -> int:
        return statusword_for(self.state) | SW_REMOTE | self._flags

    def _send_tpdo(self) -> None:
        sw, pos = self._statusword(), int(round(self.position))
        store = self.node.data_store
        store.setdefault(0x6041, {})[0] = struct.pack("<H", sw)
        store.setdefault(0x6064, {})[0] = struct.pack("<i", pos)
        store.setdefault(0x6061, {})[0] = struct.pack("<b", self._mode)
        tpdo = self.node.tpdo[1]
        tpdo["Statusword"].raw, tpdo["Position actual value"].raw = sw, pos
        tpdo["Modes of operation display"].raw = self._mode
        if self.node.nmt.state == "OPERATIONAL":
            try:
                tpdo.transmit()
            except can.CanError:
                pass  # a drive does not stop because one frame could not be sent

    def _run(self) -> None:
        last = time.monotonic()
        while not self._stop.wait(self.tick_s):
            now = time.monotonic()
            with self._lock:
                self._step(now - last)
                self._send_tpdo()
            last = now


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
