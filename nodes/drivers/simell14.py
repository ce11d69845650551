"""A simulated Thorlabs ELL14 speaking the ELLx bytes on a pty (see :mod:`.ell14` for the protocol).

The host's bytes are cut into commands by the manual's command table (:data:`~.ell14.COMMAND_DATA`: address,
two letters, a fixed number of data characters), so several commands in one write are each answered, in
order, and a CR LF between them is tolerated. Like the real device it stays silent for other addresses (their
commands are skipped by the same table), answers ``GS03`` to a command it does not know or does not run (and
goes on with the next one), ``GS01`` (communication timeout) to a command whose data stop short for
``frame_timeout_s``, ``PO`` only when a move has ended (moves take ``|Δ| / speed``, the speed scaled by the
velocity percent), and ``GS09`` (busy) to anything that arrives while it moves or searches.

Modelled: ``in``, ``gs``, ``gp``, ``ma``, ``mr``, ``ho`` (to pulse 0), ``fw``/``bw`` (one jog step),
``gj``/``sj``, ``go``/``so`` (stored), ``gv``/``sv`` (1-100 %, else ``GS04``), ``i1``/``i2`` (motor info:
loop, motor, current, ramps, periods), ``f1``/``b1``/``f2``/``b2`` (periods; ``8FFF`` restores the factory
value), ``s1``/``s2``/``om`` (frequency search / optimisation: busy for ``search_s``, then ``GS00``), ``cm``
(cleaning, busy until done or ``st``), ``st``, ``ca`` (answered ``<new>GS00`` from the new address), ``us``.
Not modelled (answered ``GS03``): isolation ``is``, group address ``ga``, current curves ``c1``…, motor 3,
continuous jog (jog step 0), persistence of ``us``. Injectable: :meth:`inject_busy` (the next N commands get
``GS09``, as after power-up), :meth:`inject_move_error` (the next move ends in ``GSxx``),
:meth:`inject_silence`.

As a process, for a manual run of a driver: ``python -m polarstripe.nodes.drivers.simell14`` prints the pty
path to open and serves it until Ctrl-C.
"""

from __future__ import annotations

import signal
import threading
import time

from polarstripe.nodes.drivers.ell14 import COMMAND_DATA, decode_s32, encode_s32
from polarstripe.nodes.drivers.pty_device import PtyDevice

ELL14_PULSES_PER_REV = 143_360
_ADDRESSES = b"0123456789ABCDEF"
_HEX = frozenset("0123456789ABCDEFabcdef")
#: factory motor periods (forward, backward) of motors 1 and 2: about 90 kHz from the 14.74 MHz clock
FACTORY_PERIODS = {1: (0x00A3, 0x00A5), 2: (0x00A4, 0x00A2)}


class SimEll14(PtyDevice):
    """A fake ELL14 on a pty: ``with SimEll14() as dev: Ell14Stage(dev.port)``.

    :param deg_per_s: rotation speed [deg/s] at 100 % velocity (about 430 on the real mount).
    :param search_s: how long a frequency search (``s1``, ``s2``) or ``om`` keeps the device busy.
    :param frame_timeout_s: how long the device waits for the rest of a command before ``GS01``.
    """

    def __init__(
        self,
        address: str = "0",
        deg_per_s: float = 430.0,
        serial_number: str = "11400123",
        *,
        search_s: float = 0.2,
        frame_timeout_s: float = 0.1,
    ):
        super().__init__()
        self.address = address
        self.pulses_per_rev = ELL14_PULSES_PER_REV
        self.position = 0  # pulses, modulo one turn
        self.jog, self.offset = ELL14_PULSES_PER_REV // 8, 0
        self.speed = deg_per_s * ELL14_PULSES_PER_REV / 360.0  # pulses/s at 100 %
        self.velocity = 100  # percent
        self.periods = {m: list(p) for m, p in FACTORY_PERIODS.items()}
        self.search_s, self.frame_timeout_s = search_s, frame_timeout_s
        self.moving = False
        self._busy_task: str | None = None  # "search" | "clean" while one runs
        self._task_stop = threading.Event()
        self._busy_left = 0
        self._move_error: int | None = None
        self._silent = False
        self._buf = b""
        self._buf_at = 0.0
        self.info_body = f"IN0E{serial_number}20231400{0x168:04X}{ELL14_PULSES_PER_REV:08X}"

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

    # -- framing --------------------------------------------------------------------------------------------
    def feed(self, data: bytes) -> None:
        self._buf += data
        self._buf_at = time.monotonic()
        while True:
            self._buf = self._buf.lstrip(b"\r\n")
            if not self._buf:
                return
            if self._buf[0] not in _ADDRESSES:  # noise: no command starts with it
                self._buf = self._buf[1:]
                continue
            if len(self._buf) < 3:
                return  # wait for the command letters
            cmd = self._buf[1:3].decode("ascii", "replace")
            size = 3 + COMMAND_DATA.get(cmd, 0)
            if len(self._buf) < size:
                return  # wait for the data (poll() gives up after frame_timeout_s)
            frame, self._buf = self._buf[:size].decode("ascii", "replace"), self._buf[size:]
            self._answer(self.handle(frame))

    def poll(self) -> None:
        if self._buf and time.monotonic() - self._buf_at > self.frame_timeout_s:
            frame, self._buf = self._buf.decode("ascii", "replace"), b""
            if frame[:1] == self.address:
                self._answer(f"{self.address}GS01")  # the rest of the command never came

    def _answer(self, line: str | None) -> None:
        if line and not self._silent:
            self.reply(line.encode() + b"\r\n")

    # -- the device ---------------------------------------------------------------------------------------
    def handle(self, frame: str) -> str | None:
        """One command (``"0ma00004600"``) → the reply line without CR LF, or None (another address, or the
        reply comes when a move or search ends)."""
        a, c, d = frame[0], frame[1:3], frame[3:]
        if a != self.address:
            return None
        if c == "st" and self._busy_task is not None:
            self._task_stop.set()
            return f"{a}GS00"
        if self.moving or self._busy_task is not None or self._busy_left > 0:
            self._busy_left = max(0, self._busy_left - 1)
            return f"{a}GS09"
        if any(ch not in _HEX for ch in d) or (c == "ho" and d not in ("0", "1")):
            return f"{a}GS04"
        simple = {
            "in": lambda: f"{a}{self.info_body}",
            "gs": lambda: f"{a}GS00",
            "gp": lambda: f"{a}PO{encode_s32(self.position)}",
            "go": lambda: f"{a}HO{encode_s32(self.offset)}",
            "gj": lambda: f"{a}GJ{encode_s32(self.jog)}",
            "gv": lambda: f"{a}GV{self.velocity:02X}",
            "us": lambda: f"{a}GS00",
            "st": lambda: f"{a}GS00",
            "i1": lambda: self._motor_info(1),
            "i2": lambda: self._motor_info(2),
            "ho": lambda: self._start_move(0),
            "fw": lambda: self._start_move(self.position + self.jog),
            "bw": lambda: self._start_move(self.position - self.jog),
            "s1": lambda: self._start_task("search", self.search_s),
            "s2": lambda: self._start_task("search", self.search_s),
            "om": lambda: self._start_task("search", self.search_s),
            "cm": lambda: self._start_task("clean", 60.0),
        }
        if c in simple:
            return simple[c]()
        return self._handle_with_data(a, c, d)

    def _handle_with_data(self, a: str, c: str, d: str) -> str | None:
        if c == "ca":
            self.address = d.upper()
            return f"{self.address}GS00"
        if c == "sv":
            value = int(d, 16)
            if not 1 <= value <= 100:
                return f"{a}GS04"
            self.velocity = value
            return f"{a}GS00"
        if c[0] in "fb" and c[1] in "12":
            value, motor = int(d, 16), int(c[1])
            period = FACTORY_PERIODS[motor][c[0] == "b"] if value == 0x8FFF else value & 0x7FFF
            if not period:
                return f"{a}GS04"
            self.periods[motor][c[0] == "b"] = period
            return f"{a}GS00"
        if len(d) == 8:
            value = decode_s32(d)
            if c == "ma":
                return self._start_move(value)
            if c == "mr":
                return self._start_move(self.position + value)
            if c in ("so", "sj"):
                setattr(self, "offset" if c == "so" else "jog", value)
                return f"{a}GS00"
        return f"{a}GS03"  # not in the table, or not run by this device

    def _motor_info(self, motor: int) -> str:
        forward, backward = self.periods[motor]
        return f"{self.address}I{motor}11{0:04X}{0xFFFF:04X}{0xFFFF:04X}{forward:04X}{backward:04X}"

    def _start_move(self, target: int) -> None:
        self.moving = True
        threading.Thread(target=self._finish_move, args=(target,), daemon=True).start()
        return None

    def _finish_move(self, target: int) -> None:
        time.sleep(abs(target - self.position) / (self.speed * self.velocity / 100.0))
        error, self._move_error = self._move_error, None
        if error is None:
            self.position = target % self.pulses_per_rev
        self.moving = False
        body = f"GS{error:02X}" if error is not None else f"PO{encode_s32(self.position)}"
        self._answer(f"{self.address}{body}")

    def _start_task(self, task: str, duration_s: float) -> None:
        """A long operation (frequency search, optimisation, cleaning): busy, then ``GS00`` when done (a
        ``st`` ends it early and is answered instead)."""
        self._busy_task = task
        self._task_stop.clear()

        def run():
            stopped = self._task_stop.wait(duration_s)
            if task == "search":
                self.periods = {m: list(p) for m, p in FACTORY_PERIODS.items()}
            self._busy_task = None
            if not stopped:
                self._answer(f"{self.address}GS00")

        threading.Thread(target=run, daemon=True).start()
        return None


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
