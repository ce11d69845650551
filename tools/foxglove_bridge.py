"""A live view in the Foxglove app: a node that serves the bus over Foxglove's WebSocket protocol.

Needs the optional extra ``foxglove`` (``pip install 'polarstripe[foxglove]'``, i.e. ``foxglove-sdk``). Add it
to a launch file::

    [[node]]
    name = "foxglove"
    module = "polarstripe.tools.foxglove_bridge:FoxgloveBridge"
    params = { port = 8765 }          # then open ws://<host>:8765 in the Foxglove app

It subscribes (``mode="latest"``: a viewer drops what it cannot show) to the chosen topics (default: every
topic of the launch) and logs

* each message as it is on the wire of a bag: channel ``<topic>``, ``message_encoding = "msgpack"``, the
  type's JSON Schema (the app shows it like schemaless JSON: fields in the raw-message and plot panels);
* each image as ``foxglove.RawImage`` for the image panel: frames on ``<topic>/image`` (``mono16`` for
  uint16, ``mono8``, or ``32FC1``) and each image of a composite on ``<topic>/<name>``.

The server binds ``host`` (default ``127.0.0.1``: this machine only; use the rig's address to reach it from
topside, with the same care as any unauthenticated port).
"""

from __future__ import annotations

import json

import numpy as np
from polarstripe.msgs import REGISTRY, Composite, Frame, Message, json_schema, pack
from polarstripe.runtime.graph import resolve
from polarstripe.runtime.node import Node, NodeError
from polarstripe.runtime.params import NodeParams

_ENCODINGS = {
    np.dtype("<u2"): ("mono16", np.dtype("<u2")),
    np.dtype("u1"): ("mono8", np.dtype("u1")),
    np.dtype("<f4"): ("32FC1", np.dtype("<f4")),
}


def raw_image_fields(img: np.ndarray) -> dict:
    """``foxglove.RawImage`` fields (width, height, encoding, step, data) for a 2-D image; other dtypes are
    sent as ``32FC1``."""
    if img.ndim != 2:
        raise ValueError(f"image must be 2-D, got shape {img.shape}")
    enc, dt = _ENCODINGS.get(img.dtype, ("32FC1", np.dtype("<f4")))
    a = np.ascontiguousarray(img, dtype=dt)
    return {
        "width": a.shape[1],
        "height": a.shape[0],
        "encoding": enc,
        "step": a.shape[1] * dt.itemsize,
        "data": a.tobytes(),
    }


class FoxgloveBridge(Node):
    """Serves the launch's topics to the Foxglove app (see the module docstring)."""

    class Params(NodeParams):
        host: str = "127.0.0.1"
        port: int = 8765  # 0 picks a free port (logged)
        topics: list[str] = []  # full or relative; empty: every topic of the graph
        images: bool = True  # also foxglove.RawImage channels for frames and composites

    def setup(self):
        try:
            import foxglove
            from foxglove.channels import RawImageChannel
        except ImportError:
            raise NodeError(
                f"node {self.name!r}: needs the optional extra 'foxglove' "
                "(pip install 'polarstripe[foxglove]')"
            ) from None

        self._fox, self._RawImageChannel = foxglove, RawImageChannel
        graph = self.graph
        known = graph.get("topics", {})
        wanted = [resolve(t, self.namespace) for t in self.params.topics] or sorted(known)
        self.server = foxglove.start_server(
            host=self.params.host,
            port=self.params.port,
            name=f"polarstripe {graph.get('launch', '')}".strip(),
        )
        self.port = self.server.port
        self.channels: dict[str, object] = {}
        self.image_channels: dict[str, object] = {}
        for topic in wanted:
            cls = REGISTRY.get(known.get(topic, {}).get("type", ""))
            if cls is None:
                self.log.warning("not serving %s: unknown message type", topic)
                continue
            self.add_topic(topic, cls)
            self.subscribe(topic, lambda m, t=topic: self.forward(t, m), msg_type=cls, mode="latest")
        self.log.info(
            "Foxglove WebSocket on ws://%s:%d (%d topics)", self.params.host, self.port, len(self.channels)
        )

    def add_topic(self, topic: str, cls: type[Message]) -> None:
        """Advertise ``topic`` as a msgpack channel with its JSON Schema."""
        schema = self._fox.Schema(
            name=f"polarstripe/{cls.TYPE}", encoding="jsonschema", data=json.dumps(json_schema(cls)).encode()
        )
        self.channels[topic] = self._fox.Channel(topic, schema=schema, message_encoding="msgpack")

    def _image(self, topic: str, stamp_ns: int, frame_id: str, img: np.ndarray) -> None:
        from foxglove.messages import RawImage, Timestamp

        ch = self.image_channels.get(topic)
        if ch is None:
            ch = self.image_channels[topic] = self._RawImageChannel(topic)
        ts = Timestamp(stamp_ns // 1_000_000_000, stamp_ns % 1_000_000_000)
        ch.log(RawImage(timestamp=ts, frame_id=frame_id, **raw_image_fields(img)), log_time=stamp_ns)

    def forward(self, topic: str, msg: Message) -> None:
        """Log one received message (and its images) to the Foxglove server."""
        stamp = msg.header.stamp_ns
        self.channels[topic].log(pack(msg, topic=topic), log_time=stamp)
        if not self.params.images:
            return
        if isinstance(msg, Frame):
            self._image(f"{topic}/image", stamp, msg.header.frame_id or "camera", msg.image)
        elif isinstance(msg, Composite):
            for name, img in msg.images.items():
                if img.ndim == 2:
                    self._image(f"{topic}/{name}", stamp, msg.method, img)

    def teardown(self):
        server = getattr(self, "server", None)
        if server is not None:
            server.stop()


NODE = "FoxgloveBridge"
