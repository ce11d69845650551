"""A simulated Thorlabs ELL14 speaking the ELLx bytes on a pty (see :mod:`.ell14` for the protocol).

Like the real device it stays silent for other addresses, tolerates a missing or a CR LF terminator, answers
an unknown command with ``GS03``, answers ``PO`` only when a move has ended (moves take ``|Δ| / speed``), and
answers ``GS09`` (busy) to anything that arrives while it moves. Injectable: :meth:`inject_busy` (the next N
commands get ``GS09``, as after power-up), :meth:`inject_move_error` (the next move ends in ``GSxx``),
:meth:`inject_silence`. Not modelled: velocity, jog and motor-tuning commands beyond ``gj``/``sj``, address
changes, user data.

As a process, for a manual run of a driver: ``python -m polarstripe.nodes.drivers.simell14`` prints the pty
path to open and serves it until Ctrl-C.
"""

from __future__ import annotations

import re
import signal
import threading
import time

from polarstripe.nodes.drivers.ell14 import decode_s32, encode_s32
from polarstripe.nodes.drivers.pty_device import PtyDevice

ELL14_PULSES_PER_REV = 143_360
_FRAME = re.compile(
    rb"([0-9A-F])(ma|mr|so|sj)([0-9A-F]{8})|([0-9A-F])(ho)([01])|([0-9A-F])([a-z]{2})(?![0-9A-F])"
)
_NEEDS_DATA = (b"ma", b"mr", b"so", b"sj", b"ho")


class SimEll14(PtyDevice):
    """A fake ELL14 on a pty: ``with SimEll14() as dev: Ell14Stage(dev.port)``.

    :param deg_per_s: rotation speed [deg/s] of the motion model (about 430 on the real mount).
    """

    def __init__(self, address: str = "0", deg_per_s: float = 430.0, serial_number: str = "11400123"):
        super().__init__()
        self.address = address
        self.pulses_per_rev = ELL14_PULSES_PER_REV
        self.position = 0  # pulses, modulo one turn
        self.jog, self.offset = ELL14_PULSES_PER_REV // 8, 0
        self.speed = deg_per_s * ELL14_PULSES_PER_REV / 360.0  # pulses/s
        self.moving = False
        self._busy_left = 0
        self._move_error: int | None = None
        self._silent = False
        self._buf = b""
        self.info = f"{address}IN0E{serial_number}20231400{0x168:04X}{ELL14_PULSES_PER_REV:08X}"

    # -- injection ----------------------------------------------------------------------------------------
    def inject_busy(self, count: int) -> None:
        """Answer the next ``count`` commands with ``GS09`` (busy)."""
        self._busy_left = count

    def inject_move_error(self, code: int = 0x02) -> None:
        """End the next move with status ``GS<code>`` instead of a position (default 02, mechanical
        timeout)."""
        self._move_error = code

    def inject_silence(self, on: bool = True) -> None:
        """Stop answering (a cut cable, a device without power)."""
        self._silent = on

    # -- the device ---------------------------------------------------------------------------------------
    def feed(self, data: bytes) -> None:
        self._buf += data
        while True:
            self._buf = self._buf.lstrip(b"\r\n")
            m = _FRAME.match(self._buf)
            if not m:
                if len(self._buf) > 64:  # garbage: drop it, as a UART would after a framing error
                    self._buf = b""
                return
            if m.group(8) and m.end() == len(self._buf) and m.group(8) in _NEEDS_DATA:
                return  # an incomplete frame: wait for its data
            self._buf = self._buf[m.end() :]
            reply = self.handle(b"".join(g for g in m.groups() if g is not None).decode())
            if reply and not self._silent:
                self.reply(reply.encode() + b"\r\n")

    def handle(self, cmd: str) -> str | None:
        """One command (``"0ma00004600"``) → the reply line without CR LF, or None for another address."""
        a, c, d = cmd[0], cmd[1:3], cmd[3:]
        if a != self.address:
            return None
        if self.moving or self._busy_left > 0:
            self._busy_left = max(0, self._busy_left - 1)
            return f"{a}GS09"
        if c == "in":
            return self.info
        if c == "gs":
            return f"{a}GS00"
        if c == "gp":
            return f"{a}PO{encode_s32(self.position)}"
        if c == "go":
            return f"{a}HO{encode_s32(self.offset)}"
        if c == "gj":
            return f"{a}GJ{encode_s32(self.jog)}"
        if c == "ho":
            return self._start_move(0)
        if c == "fw":
            return self._start_move(self.position + self.jog)
        if c == "bw":
            return self._start_move(self.position - self.jog)
        if len(d) == 8:
            value = decode_s32(d)
            if c == "ma":
                return self._start_move(value)
            if c == "mr":
                return self._start_move(self.position + value)
            if c == "so":
                self.offset = value
                return f"{a}GS00"
            if c == "sj":
                self.jog = value
                return f"{a}GS00"
        return f"{a}GS03"

    def _start_move(self, target: int) -> None:
        self.moving = True
        threading.Thread(target=self._finish_move, args=(target,), daemon=True).start()
        return None

    def _finish_move(self, target: int) -> None:
        time.sleep(abs(target - self.position) / self.speed)
        error, self._move_error = self._move_error, None
        if error is None:
            self.position = target % self.pulses_per_rev
        self.moving = False
        body = f"GS{error:02X}" if error is not None else f"PO{encode_s32(self.position)}"
        if not self._silent:
            self.reply(f"{self.address}{body}\r\n".encode())


def main() -> int:
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    with SimEll14() as device:
        print(device.port, flush=True)
        stop.wait()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
