"""Views as an MCAP file the Foxglove app opens directly: the schemas and encodings of
:mod:`polarstripe.nodes.foxglove_schemas` (the live bridge's), written by
:class:`~polarstripe.runtime.bag.BagWriter` (payloads as buffers: image pixels are not copied again).

Channels carry the schema's message encoding (``protobuf`` for the ``foxglove.*`` schemas, ``json`` for the
``polarstripe.*`` records); message ``log_time`` and ``publish_time`` are the recording's log time. The
recording's metadata records (``launch``, ``versions``, ``recording``) are copied, plus ``export``.
"""

from __future__ import annotations

from polarstripe.nodes.foxglove_schemas import FoxgloveEncoder
from polarstripe.runtime.bag import BagWriter
from polarstripe.tools.prealloc import Preallocator


class FoxgloveSink:
    """Writes views to a new MCAP file ``path`` (Foxglove schemas)."""

    def __init__(self, path, *, metadata: dict[str, dict[str, str]] | None = None, compression: str = "none"):
        self.encoder = FoxgloveEncoder()
        self.writer = BagWriter(path, compression=compression, chunk_size=1 << 20, chunk_age_s=1e9).start()
        self.space = Preallocator(path)
        for name, data in (metadata or {}).items():
            self.writer.add_metadata(name, data)
        self.channels: dict[str, int] = {}
        self.counts: dict[tuple[str, str], int] = {}

    def write(self, view) -> None:
        """Write one view (a view Foxglove does not take is skipped)."""
        e = self.encoder.encode(view)
        if e is None:
            return
        cid = self.channels.get(e.topic)
        if cid is None:
            s = e.schema
            cid = self.channels[e.topic] = self.writer.register(
                e.topic, s.name, s.data, {}, s.encoding, s.message_encoding)
        self.writer.add_payload(cid, e.parts, log_time_ns=view.stamp_ns, publish_time_ns=view.stamp_ns,
                                sequence=self.counts.get((e.topic, e.schema.name), 0))
        self.counts[e.topic, e.schema.name] = self.counts.get((e.topic, e.schema.name), 0) + 1
        self.space.ahead(self.writer.size)

    def close(self) -> None:
        """Write the summary and footer."""
        self.writer.finish(fsync=False)
        self.space.finish(self.writer.size)

    abort = close  # the caller removes the half-written file
