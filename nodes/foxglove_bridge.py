"""A live view in the Foxglove app: a node that serves the bus over Foxglove's WebSocket protocol.

Needs the optional extra ``foxglove`` (``pip install 'polarstripe[foxglove]'``, i.e. ``foxglove-sdk``). Add it
to a launch file (``launch/sim.toml`` and ``launch/rov.toml`` have it behind the launch argument
``foxglove=true``)::

    [[node]]
    name = "foxglove"
    module = "polarstripe.nodes.foxglove_bridge:FoxgloveBridge"
    params = { port = 8765 }          # then open ws://<host>:8765 in the Foxglove app

It subscribes to the chosen topics (default: every topic of the launch; camera frames and projector patterns
``mode="latest"``, a viewer drops what it cannot show; everything else ``mode="all"``) and logs each message
as the views of :mod:`polarstripe.nodes.rig_views` in the schemas of :mod:`polarstripe.nodes.foxglove_schemas`
(the same channels as ``polarstripe bag export --to foxglove``): images as ``foxglove.RawImage``
(``<topic>/image`` for frames and patterns, ``<topic>/<name>`` per composite image), camera intrinsics as
``foxglove.CameraCalibration``, the rig's poses as ``foxglove.FrameTransforms`` on ``/tf_static`` (sent
again to each new client), logs as ``foxglove.Log``, numbers as JSON records (``polarstripe.*``: plottable).
Message log times are the messages' stamps. ``image_max_hz`` caps the images per topic (0: every one; the
tether of ``rov.toml`` carries 2 per second).

The server binds ``host`` (default ``127.0.0.1``: this machine only; use the rig's address to reach it from
topside, with the same care as any unauthenticated port).
"""

from __future__ import annotations

import json
import time

from polarstripe.msgs import Message
from polarstripe.nodes.foxglove_schemas import FoxgloveEncoder
from polarstripe.nodes.rig_geometry import geometry_from_metadata
from polarstripe.nodes.rig_views import RigViews, ViewGate, subscribe_bridged
from polarstripe.runtime.bag import BagError
from polarstripe.runtime.graph import resolve
from polarstripe.runtime.node import Node, NodeError
from polarstripe.runtime.params import NodeParams
from polarstripe.sim.scene import SceneError


class FoxgloveBridge(Node):
    """Serves the launch's topics to the Foxglove app (see the module docstring)."""

    class Params(NodeParams):
        host: str = "127.0.0.1"
        port: int = 8765  # 0 picks a free port (logged)
        topics: list[str] = []  # full or relative; empty: every topic of the graph
        images: bool = True  # send images (frames, patterns, composites)
        image_max_hz: float = 0.0  # images per topic and second at most; 0: every one
        scene: str = ""  # the rig's scene TOML for tf and camera info; "": the launch's

    def setup(self):
        try:
            import foxglove

            self.encoder = FoxgloveEncoder()
        except (ImportError, BagError):
            raise NodeError(
                f"node {self.name!r}: needs the optional extra 'foxglove' "
                "(pip install 'polarstripe[foxglove]')"
            ) from None
        self._fox = foxglove
        graph = self.graph
        known = graph.get("topics", {})
        wanted = [resolve(t, self.namespace) for t in self.params.topics] or sorted(known)
        meta = {"launch": {"graph": json.dumps(graph), "file": graph.get("file", "")}}
        try:
            geometry, note = geometry_from_metadata(meta, self.params.scene or None)
        except (SceneError, OSError) as exc:
            raise NodeError(f"node {self.name!r}: scene: {exc}") from None
        self.views = RigViews(geometry)
        self.context = foxglove.Context()
        self.channels: dict[str, object] = {}
        self.gate = ViewGate(self.views.start(time.time_ns()), self.params.images, self.params.image_max_hz)
        self.server = foxglove.start_server(
            host=self.params.host,
            port=self.params.port,
            name=f"polarstripe {graph.get('launch', '')}".strip(),
            context=self.context,
        )
        self.port = self.server.port
        self.topics = subscribe_bridged(self, wanted, known, self.forward, "serving")
        self._send(self.gate.static)
        self.every(1.0, self._resend_static)
        self.log.info(
            "Foxglove WebSocket on ws://%s:%d (%d topics; geometry: %s)",
            self.params.host, self.port, len(self.topics), note,
        )

    def _send(self, views) -> None:
        for v in views:
            e = self.encoder.encode(v)
            if e is None:
                continue
            ch = self.channels.get(e.topic)
            if ch is None:
                s = e.schema
                ch = self.channels[e.topic] = self._fox.Channel(
                    e.topic,
                    schema=self._fox.Schema(name=s.name, encoding=s.encoding, data=s.data),
                    message_encoding=s.message_encoding,
                    context=self.context,
                )
            ch.log(b"".join(e.parts), log_time=v.stamp_ns)

    def _resend_static(self) -> None:
        """The latched poses again (a client that connected since gets them)."""
        if self.gate.static:
            self._send(self.gate.static)

    def forward(self, topic: str, msg: Message) -> None:
        """Log one received message (as its views) to the Foxglove server."""
        views = self.views.views(topic, msg.header.stamp_ns or time.time_ns(), msg)
        self._send(self.gate.select(views, time.monotonic()))

    def teardown(self):
        server = getattr(self, "server", None)
        if server is not None:
            server.stop()


NODE = FoxgloveBridge
