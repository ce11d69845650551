"""Two tiny nodes that show the runtime: a talker publishing a counter and a listener counting what it hears.

``launch/demo.toml`` runs them (``polarstripe launch launch/demo.toml``); the tests use them as a small graph.
"""

from __future__ import annotations

from polarstripe.msgs import Ack, Empty, Log
from polarstripe.runtime.node import Node, Received, Stop, Tick
from polarstripe.runtime.params import NodeParams


class Talker(Node):
    """Publishes ``"<text> <n>"`` on ``chatter`` at ``rate_hz``; stops by itself after ``count`` messages
    (0: never). Serves ``~/reset`` (private: ``<namespace>/<node name>/reset``) (sets n back to 0)."""

    class Params(NodeParams):
        rate_hz: float = 10.0
        text: str = "hello"
        count: int = 0

        def validate(self):
            super().validate()
            if not self.rate_hz > 0:
                raise ValueError(f"rate_hz must be > 0, got {self.rate_hz}")
            if self.count < 0:
                raise ValueError(f"count must be >= 0, got {self.count}")

    PUBLISHES = {"chatter": Log}
    SERVES = {"~/reset": (Empty, Ack)}

    def setup(self):
        self.n = 0
        self.chatter = self.publisher("chatter")
        self.every(1.0 / self.params.rate_hz, self.tick)
        self.serve("~/reset", self.reset)

    def tick(self):
        self.chatter.publish(Log(level="INFO", node=self.name, text=f"{self.params.text} {self.n}"))
        self.n += 1
        if self.params.count and self.n >= self.params.count:
            self.stop(f"sent {self.n} messages")

    def reset(self, request: Empty) -> Ack:
        old, self.n = self.n, 0
        return Ack(ok=True, detail=f"reset from {old}")


class Listener(Node):
    """Counts messages on ``chatter`` (every one: mode ``all``) and serves the count on ``~/count``;
    stops by itself after hearing ``count`` messages (0: never). A loop-style node: it matches events."""

    class Params(NodeParams):
        count: int = 0
        report_s: float = 5.0

    SUBSCRIBES = {"chatter": Log}
    SERVES = {"~/count": (Empty, Ack)}

    def setup(self):
        self.heard = 0
        self.last = ""
        self.subscribe("chatter", mode="all")
        self.serve("~/count", lambda req: Ack(ok=True, detail=str(self.heard)))
        self.every(self.params.report_s, name="report")

    def run(self):
        for event in self.events():
            match event:
                case Received(topic="chatter", msg=msg):
                    self.heard += 1
                    self.last = msg.text
                    if self.params.count and self.heard >= self.params.count:
                        self.stop(f"heard {self.heard} messages")
                case Tick(timer="report"):
                    self.log.info("heard %d messages, last %r", self.heard, self.last)
                case Stop(reason=reason):
                    self.log.info("heard %d messages in all (%s)", self.heard, reason)
