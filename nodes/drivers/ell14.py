"""Thorlabs ELL14 rotation mount over pyserial: our own implementation of the small ELLx ASCII protocol.

Line: 9600 baud 8N1, half duplex, several devices on one line (addresses 0-F). Host → device
``<addr><cmd>[data]`` (data: 8 upper-case hex digits, signed 32-bit big-endian), device → host
``<addr><REPLY>[data]\\r\\n``. ``in`` gives the pulses per revolution (143 360 on an ELL14), ``ma`` moves
absolute and answers ``PO`` when the move has ended, ``gs`` answers the status (``GS00`` ok, ``GS09`` busy,
…). A move holds the line until its reply, so while it runs :attr:`angle` is ``None`` (the device cannot
report it). Whether the device reports positions modulo one turn is not known, so a reply is mapped to the
angle nearest the target that has the same position modulo 360°.

Commands carry no length and no terminator: a device finds where a command ends from the manual's command
table (:data:`COMMAND_DATA`), so :meth:`Ell14Stage.request` refuses a known command with the wrong number of
data characters rather than put a frame on the line that would run into the next one. ``ca`` (change address)
is answered from the new address (:meth:`Ell14Stage.change_address`).
"""

from __future__ import annotations

import struct
import threading
import time

import serial
from polarstripe.nodes.drivers.backend import BackendOptions
from polarstripe.nodes.drivers.errors import (
    DeviceError,
    DriverError,
    DriverTimeout,
    DriverValueError,
    StageFault,
)
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

#: the host commands of the ELLx protocol manual and how many data characters each carries (``ho``: the
#: direction, ``ca``/``ga``: an address, ``is``: minutes as 2 hex digits, ``sv``: percent as 2 hex digits,
#: ``f1``/``b1``…: a motor period as 4 hex digits, positions and steps: 8 hex digits)
COMMAND_DATA = {
    "in": 0, "gs": 0, "us": 0, "ca": 1, "is": 2, "ga": 1,
    "i1": 0, "i2": 0, "i3": 0, "f1": 4, "b1": 4, "f2": 4, "b2": 4, "f3": 4, "b3": 4,
    "s1": 0, "s2": 0, "s3": 0, "c1": 0, "c2": 0, "c3": 0,
    "ho": 1, "ma": 8, "mr": 8, "go": 0, "so": 8, "gj": 0, "sj": 8, "fw": 0, "bw": 0, "st": 0,
    "gp": 0, "gv": 0, "sv": 2, "om": 0, "cm": 0,
}  # fmt: skip
#: the motor clock: a motor frequency is this over its period (``i1`` reply, ``f1``/``b1`` data)
MOTOR_CLOCK_HZ = 14_740_000


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

    class Options(BackendOptions):
        port: str  # the serial port (/dev/ttyUSB0) or a pyserial URL
        address: str = "0"  # the device address on the line, 0-F
        timeout_s: float = 0.5  # reply timeout for a query [s]
        move_timeout_s: float = 5.0  # a move must end within this [s]
        busy_timeout_s: float = 2.0  # how long a busy reply (GS09) is retried [s]
        tolerance_deg: float = 0.01  # how far from the target a settled stage may be [deg]

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
        :raises DriverValueError: a command of the manual with the wrong number of data characters.
        """
        expected = COMMAND_DATA.get(cmd)
        if expected is not None and len(data) != expected:
            raise DriverValueError(
                f"{self.name}: command {cmd!r} takes {expected} data characters, got data={data!r}"
            )
        reply_address = data.upper() if cmd == "ca" else self.address
        deadline = time.monotonic() + self.busy_timeout_s
        with self._line:
            while True:
                timeout = self.timeout_s if timeout_s is None else timeout_s
                reply = self._exchange(cmd, data, timeout, reply_address)
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

    def _exchange(self, cmd: str, data: str, timeout_s: float, reply_address: str) -> str:
        try:
            self._serial.reset_input_buffer()
            self._serial.write(f"{self.address}{cmd}{data}".encode("ascii"))
            self._serial.timeout = timeout_s
            while True:
                raw = self._serial.read_until(b"\n")
                if not raw.endswith(b"\n"):
                    raise DriverTimeout(f"{self.name}: no reply to {cmd + data!r} within {timeout_s:g} s")
                line = raw.decode("ascii", "replace").strip()
                if line[:1] == reply_address:  # replies of other devices on the line are not ours
                    return line
        except serial.SerialException as exc:
            raise DriverError(f"{self.name}: serial port failed: {exc}") from exc

    # -- device settings ----------------------------------------------------------------------------------
    def change_address(self, new: str) -> None:
        """``ca``: the device answers at ``new`` from now on (until power-off, unless saved with ``us``)."""
        new = new.upper()
        if len(new) != 1 or new not in "0123456789ABCDEF":
            raise DriverValueError(f"{self.name}: address={new!r} must be one hex digit 0-F")
        self.request("ca", new)
        self.address, self.name = new, self.name.replace(f"ELL14 {self.address}", f"ELL14 {new}", 1)

    @property
    def velocity(self) -> int:
        """``gv``: the drive power in percent of the maximum."""
        return int(self.request("gv")[3:5], 16)

    @velocity.setter
    def velocity(self, percent: int) -> None:
        if not 0 <= int(percent) <= 0xFF:
            raise DriverValueError(f"{self.name}: velocity percent={percent!r} outside 0-255")
        self.request("sv", f"{int(percent):02X}")

    def motor_info(self, motor: int) -> dict:
        """``i1``/``i2``: loop and motor state, current [A], ramps and the motor frequencies [Hz]."""
        if motor not in (1, 2, 3):
            raise DriverValueError(f"{self.name}: motor={motor!r} must be 1, 2 or 3")
        body = self.request(f"i{motor}")[3:]
        if len(body) < 22:
            raise DeviceError(f"{self.name}: unexpected motor info reply {body!r}")
        forward, backward = int(body[14:18], 16), int(body[18:22], 16)
        return {
            "loop": body[0] == "1",
            "motor": body[1] == "1",
            "current_a": int(body[2:6], 16) / 1866.0,
            "ramp_up": int(body[6:10], 16),
            "ramp_down": int(body[10:14], 16),
            "forward_hz": MOTOR_CLOCK_HZ / forward if forward else None,
            "backward_hz": MOTOR_CLOCK_HZ / backward if backward else None,
        }

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
