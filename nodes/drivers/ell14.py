"""Thorlabs ELL14 rotation mount over pyserial: our own implementation of the small ELLx ASCII protocol.

Line: 9600 baud 8N1, half duplex, several devices on one line (addresses 0-F). Host → device
``<addr><cmd>[data]`` (data: 8 upper-case hex digits, signed 32-bit big-endian), device → host
``<addr><REPLY>[data]\\r\\n``. ``in`` gives the pulses per revolution (143 360 on an ELL14), ``ma`` moves
absolute and answers ``PO`` when the move has ended, ``gs`` answers the status (``GS00`` ok, ``GS09`` busy,
…). A move holds the line until its reply, so while it runs :attr:`angle` is ``None`` (the device cannot
report it). Whether the device reports positions modulo one turn is not known, so a reply is mapped to the
angle nearest the target that has the same position modulo 360°.
"""

from __future__ import annotations

import struct
import threading
import time

import serial
from polarstripe.nodes.drivers.errors import DeviceError, DriverError, DriverTimeout, StageFault
from polarstripe.nodes.drivers.stage import RotationStage

#: status codes of the ``GS`` reply (ELLx protocol manual)
STATUS_CODES = {
    0x00: "ok",
    0x01: "communication timeout",
    0x02: "mechanical timeout",
    0x03: "command error or not supported",
    0x04: "value out of range",
    0x05: "module isolated",
    0x06: "module out of isolation",
    0x07: "initializing error",
    0x08: "thermal error",
    0x09: "busy",
    0x0A: "sensor error",
    0x0B: "motor error",
    0x0C: "out of range",
    0x0D: "over current error",
}
BUSY = 0x09


def encode_s32(value: int) -> str:
    """Signed 32-bit → 8 upper-case hex digits, two's complement, big-endian (``-1`` → ``FFFFFFFF``)."""
    return struct.pack(">i", int(value)).hex().upper()


def decode_s32(text: str) -> int:
    """8 hex digits → signed 32-bit (``FFFFFFFF`` → ``-1``)."""
    if len(text) != 8:
        raise ValueError(f"ELL14 data {text!r} is not 8 hex digits")
    return struct.unpack(">i", bytes.fromhex(text))[0]


class Ell14Stage(RotationStage):
    """A Thorlabs ELL14 on a serial port (a USB adapter, ``/dev/ttyUSB0``, or a fake's pty).

    :param port: the serial port path or a pyserial URL.
    :param address: the device address on the line, ``"0"``-``"F"``.
    :param timeout_s: reply timeout for a query [s]; a move waits ``move_timeout_s``.
    :param busy_timeout_s: how long a ``GS09`` (busy) reply is retried before it is a fault.
    """

    def __init__(
        self,
        port: str,
        address: str = "0",
        *,
        min_deg: float = -360.0,
        max_deg: float = 360.0,
        timeout_s: float = 0.5,
        move_timeout_s: float = 5.0,
        busy_timeout_s: float = 2.0,
        tolerance_deg: float = 0.01,
    ):
        super().__init__(min_deg=min_deg, max_deg=max_deg, name=f"ELL14 {address} on {port}")
        if len(address) != 1 or address.upper() not in "0123456789ABCDEF":
            raise ValueError(f"{self.name}: address={address!r} must be one hex digit 0-F")
        self.address = address.upper()
        self.timeout_s, self.move_timeout_s, self.busy_timeout_s = timeout_s, move_timeout_s, busy_timeout_s
        self.tolerance_deg = tolerance_deg
        self._line = threading.Lock()  # one request at a time on the half-duplex line
        self._moving = False
        self._pos_deg: float | None = None
        self._mover: threading.Thread | None = None
        try:
            self._serial = serial.serial_for_url(
                port, baudrate=9600, bytesize=8, parity="N", stopbits=1, timeout=timeout_s
            )
        except (serial.SerialException, OSError) as exc:
            raise DriverError(f"{self.name}: cannot open the port: {exc}") from exc
        try:
            info = self.request("in")
            self.info = self._parse_info(info)
            self.pulses_per_rev = self.info["pulses_per_rev"]
            self._pos_deg = self._pulses_to_deg(decode_s32(self.request("gp")[3:11]), 0.0)
        except BaseException:
            self._serial.close()
            raise

    def _parse_info(self, reply: str) -> dict:
        body = reply[3:]
        if not reply[1:3] == "IN" or len(body) < 30:
            raise DeviceError(f"{self.name}: unexpected info reply {reply!r}")
        return {
            "type": int(body[0:2], 16),
            "serial": body[2:10],
            "year": int(body[10:14]),
            "firmware": body[14:16],
            "travel": int(body[18:22], 16),
            "pulses_per_rev": int(body[22:30], 16),
        }

    # -- the wire -----------------------------------------------------------------------------------------
    def request(self, cmd: str, data: str = "", timeout_s: float | None = None) -> str:
        """Send ``<addr><cmd><data>`` and return the reply line (without CR LF); retries while busy.

        :raises DeviceError: the device answered an error status (e.g. ``GS03`` for a bad command).
        :raises DriverTimeout: no reply in time, or still busy after ``busy_timeout_s``.
        """
        deadline = time.monotonic() + self.busy_timeout_s
        with self._line:
            while True:
                reply = self._exchange(cmd, data, self.timeout_s if timeout_s is None else timeout_s)
                code = int(reply[3:5], 16) if reply[1:3] == "GS" else None
                if code != BUSY:
                    break
                if time.monotonic() >= deadline:
                    raise DriverTimeout(
                        f"{self.name}: device busy (GS09) for {self.busy_timeout_s:g} s on command {cmd!r}"
                    )
                time.sleep(0.05)
        if code:  # GSxx with xx != 00 answers a command that failed
            raise DeviceError(
                f"{self.name}: command {cmd + data!r} failed: GS{code:02X} "
                f"{STATUS_CODES.get(code, 'unknown status')}"
            )
        return reply

    def _exchange(self, cmd: str, data: str, timeout_s: float) -> str:
        try:
            self._serial.reset_input_buffer()
            self._serial.write(f"{self.address}{cmd}{data}".encode("ascii"))
            self._serial.timeout = timeout_s
            while True:
                raw = self._serial.read_until(b"\n")
                if not raw.endswith(b"\n"):
                    raise DriverTimeout(f"{self.name}: no reply to {cmd + data!r} within {timeout_s:g} s")
                line = raw.decode("ascii", "replace").strip()
                if line[:1] == self.address:  # replies of other devices on the line are not ours
                    return line
        except serial.SerialException as exc:
            raise DriverError(f"{self.name}: serial port failed: {exc}") from exc

    # -- RotationStage ------------------------------------------------------------------------------------
    def _pulses_to_deg(self, pulses: int, near_deg: float) -> float:
        deg = pulses * 360.0 / self.pulses_per_rev
        return near_deg + ((deg - near_deg + 180.0) % 360.0 - 180.0)

    def _start_move(self, angle_deg: float) -> None:
        if self._mover is not None:
            self._mover.join(self.move_timeout_s + self.busy_timeout_s)
        pulses = round(angle_deg * self.pulses_per_rev / 360.0)
        self._moving = True
        self._mover = threading.Thread(
            target=self._move,
            args=("ma", encode_s32(pulses), angle_deg),
            name=f"{self.name} move",
            daemon=True,
        )
        self._mover.start()

    def _move(self, cmd: str, data: str, target_deg: float, timeout_s: float | None = None) -> None:
        try:
            reply = self.request(cmd, data, timeout_s=timeout_s or self.move_timeout_s)
            if reply[1:3] != "PO":
                raise DeviceError(f"{self.name}: move answered {reply!r}, expected a PO position")
            self._pos_deg = self._pulses_to_deg(decode_s32(reply[3:11]), target_deg)
        except DriverError as exc:
            self._pos_deg = None
            self._latch_fault(str(exc).removeprefix(f"{self.name}: "))
        finally:
            self._moving = False

    def _read_angle(self) -> float | None:
        return None if self._moving else self._pos_deg

    def _is_settled(self) -> bool:
        pos, target = self._pos_deg, self._target_deg
        return (
            not self._moving
            and pos is not None
            and target is not None
            and abs(pos - target) <= self.tolerance_deg
        )

    def _reset(self) -> None:
        if self._mover is not None:
            self._mover.join(self.move_timeout_s + self.busy_timeout_s)
        try:
            self.request("gs")
            self._pos_deg = self._pulses_to_deg(decode_s32(self.request("gp")[3:11]), self._target_deg or 0.0)
        except DriverError as exc:
            raise StageFault(f"{self.name}: fault reset failed: {exc}") from exc
        self._target_deg = self._pos_deg

    def _home(self, timeout: float) -> None:
        if self._mover is not None:
            self._mover.join(self.move_timeout_s + self.busy_timeout_s)
        self._target_deg = 0.0
        self._moving = True
        self._move("ho", "0", 0.0, timeout_s=timeout)
        self._raise_if_faulted()

    def _close(self) -> None:
        if self._mover is not None:
            self._mover.join(self.move_timeout_s)
        self._serial.close()
