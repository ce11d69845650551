"""A serial trigger box / laser-line controller: the pattern is set by a small line protocol over pyserial.

The protocol (``polarstripe trigger protocol 1``, documented in docs/hardware.md): ASCII lines ending in
``\\n`` (a ``\\r`` before it is ignored), one request, one reply, 115 200 baud 8N1 by default.

===========================  ================================  ===========================================
request                      meaning                              reply
===========================  ================================  ===========================================
``ID?``                      identify                          ``ID <model> <firmware> 1`` (1: protocol)
``PAT FLOOD`` / ``PAT OFF``  everything lit / nothing lit      ``OK <seq>``
``PAT STRIPE <k> <n>``       stripe k of n (0 ≤ k < n)         ``OK <seq>``
``PAT CHECKER <size> <sh>``  checker of size px shifted sh px  ``OK <seq>``
``TRIG <exposure_us>``       one camera trigger pulse          ``OK <seq>``
===========================  ================================  ===========================================

``<seq>`` counts the box's accepted commands (0-65535, wrapping); a reply with an unexpected count means
the box restarted or a reply was lost, and is an error. Failures reply ``ERR <code> <text>``: 1 unknown
command, 2 bad argument, 3 pattern not supported by this box (a laser line has no checker), 4 busy,
5 hardware fault.
"""

from __future__ import annotations

import threading
import time

import serial
from polarstripe.msgs.patterns import PatternSpec
from polarstripe.nodes.drivers.backend import BackendOptions
from polarstripe.nodes.drivers.display import Display
from polarstripe.nodes.drivers.errors import DeviceError, DriverError, DriverTimeout, DriverValueError

PROTOCOL_VERSION = 1
ERROR_CODES = {1: "unknown command", 2: "bad argument", 3: "not supported", 4: "busy", 5: "hardware fault"}


def pattern_command(pattern: PatternSpec) -> str:
    """The request line (without ``\\n``) that sets ``pattern``; DriverValueError for a pattern protocol 1
    has no command for (``gray``: a trigger box or laser line has no pixels to show a Gray code on)."""
    if pattern.kind == "gray":
        raise DriverValueError(f"pattern {pattern}: a serial trigger box (protocol {PROTOCOL_VERSION}) shows "
                               "flood, off, stripe and checker only; Gray code needs a projector "
                               "(display = window)")
    if pattern.kind == "stripe" and pattern.sheets > 1:
        raise DriverValueError(f"pattern {pattern}: a serial trigger box (protocol {PROTOCOL_VERSION}) "
                               "lights one sheet at a time; several sheets need a projector "
                               "(display = window)")
    if pattern.kind == "stripe":
        return f"PAT STRIPE {pattern.index} {pattern.count}"
    if pattern.kind == "checker":
        return f"PAT CHECKER {pattern.size} {pattern.shift}"
    return f"PAT {pattern.kind.upper()}"


class SerialTriggerDisplay(Display):
    """A trigger box or laser-line controller on a serial port (``/dev/ttyACM0``, a pty, a pyserial URL).

    :param timeout_s: reply timeout per request [s].
    """

    class Options(BackendOptions):
        port: str  # the serial port (/dev/ttyACM0) or a pyserial URL
        baudrate: int = 115_200
        timeout_s: float = 0.5  # reply timeout per request [s]
        width: int = 1280  # the projector's size [px] (pattern semantics)
        height: int = 800

    def __init__(
        self,
        port: str,
        *,
        baudrate: int = 115_200,
        timeout_s: float = 0.5,
        width: int = 1280,
        height: int = 800,
    ):
        super().__init__(width, height, name=f"trigger box on {port}")
        self.timeout_s = timeout_s
        self._lock = threading.Lock()
        self._seq: int | None = None
        try:
            self._serial = serial.serial_for_url(port, baudrate=baudrate, timeout=timeout_s)
        except (serial.SerialException, OSError) as exc:
            raise DriverError(f"{self.name}: cannot open the port: {exc}") from exc
        try:
            reply = self._request("ID?")
            words = reply.split()
            if len(words) != 4 or words[0] != "ID" or words[3] != str(PROTOCOL_VERSION):
                raise DeviceError(f"{self.name}: {reply!r} is not an ID reply of protocol {PROTOCOL_VERSION}")
            self.model, self.firmware = words[1], words[2]
        except BaseException:
            self._serial.close()
            raise

    def _request(self, line: str) -> str:
        with self._lock:
            try:
                self._serial.reset_input_buffer()
                self._serial.write(line.encode("ascii") + b"\n")
                raw = self._serial.read_until(b"\n")
            except serial.SerialException as exc:
                raise DriverError(f"{self.name}: serial port failed on {line!r}: {exc}") from exc
        if not raw.endswith(b"\n"):
            raise DriverTimeout(f"{self.name}: no reply to {line!r} within {self.timeout_s:g} s")
        reply = raw.decode("ascii", "replace").strip()
        if reply.startswith("ERR"):
            parts = reply.split(maxsplit=2)
            code = int(parts[1]) if len(parts) > 1 and parts[1].isdigit() else 0
            text = parts[2] if len(parts) > 2 else ERROR_CODES.get(code, "")
            raise DeviceError(f"{self.name}: {line!r} refused: ERR {code} {text}")
        return reply

    def _command(self, line: str) -> float:
        reply = self._request(line)
        stamp = time.monotonic()
        words = reply.split()
        if len(words) != 2 or words[0] != "OK" or not words[1].isdigit():
            raise DeviceError(f"{self.name}: unexpected reply {reply!r} to {line!r}")
        seq = int(words[1])
        if self._seq is not None and seq != (self._seq + 1) % 65536:
            self._seq = seq
            raise DeviceError(
                f"{self.name}: reply count {seq} after {line!r} (box restarted, or a reply was lost)"
            )
        self._seq = seq
        return stamp

    def _show(self, pattern: PatternSpec) -> float:
        return self._command(pattern_command(pattern))

    def trigger(self, exposure_s: float) -> float:
        """Fire one camera trigger pulse of ``exposure_s`` seconds; return the time the box confirmed it."""
        if not 0.5e-6 <= exposure_s < 100:  # the box counts whole microseconds, at least 1
            raise DriverValueError(f"{self.name}: exposure_s={exposure_s} must be in [0.5 µs, 100 s)")
        return self._command(f"TRIG {round(exposure_s * 1e6)}")

    def _close(self) -> None:
        self._serial.close()
