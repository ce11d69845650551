"""A simulated trigger box / laser-line controller on a pty, speaking the protocol of :mod:`.serial_trigger`.

It keeps the pattern it was told (:attr:`SimTriggerBox.pattern`) and counts triggers. ``supported`` limits the
pattern kinds (a laser line: ``("flood", "off", "stripe")``); :meth:`SimTriggerBox.inject_fault` makes the
next command answer ``ERR 5``; :meth:`SimTriggerBox.inject_restart` resets the reply count as a rebooted box
would. Not modelled: timing of the trigger pulse, the projector's own latency.
"""

from __future__ import annotations

from polarstripe.nodes.drivers.pty_device import PtyDevice


class SimTriggerBox(PtyDevice):
    """``with SimTriggerBox() as box: SerialTriggerDisplay(box.port)``."""

    def __init__(
        self,
        supported=("flood", "off", "stripe", "checker"),
        model: str = "sim-trigger",
        firmware: str = "1.0",
    ):
        super().__init__()
        self.supported = tuple(supported)
        self.model, self.firmware = model, firmware
        self.pattern: str | None = None
        self.triggers: list[int] = []  # exposure [µs] of each pulse
        self.seq = -1
        self._buf = b""
        self._fault = False

    def inject_fault(self) -> None:
        self._fault = True

    def inject_restart(self) -> None:
        self.seq = -1

    def feed(self, data: bytes) -> None:
        self._buf += data
        while b"\n" in self._buf:
            line, self._buf = self._buf.split(b"\n", 1)
            self.reply(self.handle(line.decode("ascii", "replace").strip()).encode() + b"\n")

    def _ok(self) -> str:
        self.seq = (self.seq + 1) % 65536
        return f"OK {self.seq}"

    def handle(self, line: str) -> str:
        """One request line → its reply line."""
        words = line.split()
        if not words:
            return "ERR 1 empty command"
        if words == ["ID?"]:
            return f"ID {self.model} {self.firmware} 1"
        if self._fault:
            self._fault = False
            return "ERR 5 lamp driver fault"
        if words[0] == "TRIG":
            if len(words) != 2 or not words[1].isdigit() or int(words[1]) <= 0:
                return f"ERR 2 bad arguments for TRIG: {' '.join(words[1:])}"
            self.triggers.append(int(words[1]))
            return self._ok()
        if words[0] != "PAT" or len(words) < 2:
            return f"ERR 1 unknown command {words[0]}"
        kind, args = words[1].lower(), words[2:]
        if kind not in ("flood", "off", "stripe", "checker"):
            return f"ERR 2 unknown pattern {words[1]}"
        if kind not in self.supported:
            return f"ERR 3 pattern {kind} not supported by this box"
        if not all(a.isdigit() for a in args) or len(args) != {"stripe": 2, "checker": 2}.get(kind, 0):
            return f"ERR 2 bad arguments for {kind}: {' '.join(args)}"
        numbers = [int(a) for a in args]
        if kind == "stripe" and not numbers[0] < numbers[1]:
            return f"ERR 2 stripe {numbers[0]} of {numbers[1]}"
        self.pattern = {"stripe": "stripe:{}/{}", "checker": "checker:{}:{}"}.get(kind, kind).format(*numbers)
        return self._ok()
