"""``polarstripe bag export --to ros2``: views (:mod:`polarstripe.nodes.rig_views`) as ROS 2 messages
(:mod:`polarstripe.nodes.ros2_schemas`: the types, topics and encodings, shared with the live ROS 2 bridge),
written to a rosbag2 (MCAP storage, CDR) with the ``rosbags`` library (pure Python, no ROS install;
``pip install 'polarstripe[ros2]'``). Stamps are the recording's log times.

The bag is written in rosbag2 format 8 (ROS 2 Jazzy's ``metadata.yaml``) with the Jazzy message
definitions. Its MCAP file is written by :class:`~polarstripe.runtime.bag.BagWriter` through a rosbags storage
plugin: an image's CDR is a few header bytes plus the pixels, which go from the recording's chunk to the
file without another copy (``rosbags``' own MCAP writer copies each message four times).
"""

from __future__ import annotations

import time
from pathlib import Path

from mcap.data_stream import RecordBuilder
from mcap.records import Header as McapHeader
from polarstripe import __version__
from polarstripe.nodes.ros2_schemas import Ros2Encoder, require, typestore
from polarstripe.runtime.bag import MAGIC, BagError, BagWriter
from polarstripe.tools.prealloc import Preallocator

try:
    from rosbags.interfaces import (
        MessageDefinitionFormat,
        Qos,
        QosDurability,
        QosHistory,
        QosLiveliness,
        QosReliability,
        QosTime,
    )
    from rosbags.rosbag2 import StoragePlugin, Writer, WriterError
except ImportError:  # the optional extra: require() names it
    pass


class _Ros2McapStorage:
    """A rosbags storage plugin (the ``StorageWriter`` protocol) writing MCAP with :class:`BagWriter`:
    profile ``ros2``, schemas ``ros2msg``, the rosbag2 metadata record, payloads given as buffers."""

    def __init__(self, path: Path, compression) -> None:
        self.path = path / f"{path.name}.mcap"
        self.writer = _Ros2BagWriter(self.path, chunk_size=1 << 20, chunk_age_s=1e9).start()
        self.space = Preallocator(self.path)
        self.ids: dict[int, int] = {}

    def add_msgtype(self, connection) -> None:
        """Schemas are registered with their first channel."""

    def add_connection(self, connection, offered_qos_profiles: str) -> None:
        fmt = "ros2msg" if connection.msgdef.format == MessageDefinitionFormat.MSG else "ros2idl"
        self.ids[connection.id] = self.writer.register(
            connection.topic, connection.msgtype, connection.msgdef.data.encode(),
            {"offered_qos_profiles": offered_qos_profiles}, fmt, connection.ext.serialization_format)

    def write(self, connection, timestamp: int, data) -> None:
        parts = data if isinstance(data, list) else [data]
        self.writer.add_payload(
            self.ids[connection.id], parts, log_time_ns=timestamp, publish_time_ns=timestamp, sequence=0
        )
        self.space.ahead(self.writer.size)

    def close(self, version: int, metadata: str) -> None:
        self.writer.add_metadata("rosbag2", {"serialized_metadata": metadata})
        self.writer.finish(fsync=False)
        self.space.finish(self.writer.size)

    def abort(self) -> None:
        self.writer.finish(fsync=False)  # the caller removes the half-written folder
        self.space.finish(self.writer.size)


class _Ros2BagWriter(BagWriter):
    """:class:`BagWriter` with the MCAP profile ``ros2`` (rosbag2 and rosbags read only that profile)."""

    def start(self) -> _Ros2BagWriter:
        rb = RecordBuilder()
        McapHeader(profile="ros2", library=f"polarstripe/{__version__}").write(rb)
        self._f = open(self.path, "xb", buffering=0)  # noqa: SIM115  (closed by finish)
        self._write(MAGIC, rb.end())
        self.started_at = time.monotonic()
        return self


def _latched():
    return Qos(QosHistory.KEEP_LAST, 1, QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL,
               QosTime(0, 0), QosTime(0, 0), QosLiveliness.AUTOMATIC, QosTime(0, 0), False)


class Ros2Sink:
    """Writes views to a new rosbag2 folder ``path`` (``metadata.yaml`` and ``<name>.mcap``)."""

    def __init__(self, path, *, custom_data: dict[str, str] | None = None):
        require()
        self.ts = typestore()
        self.encoder = Ros2Encoder()
        writer_cls = type("_Writer", (Writer,), {"STORAGE_PLUGINS": {StoragePlugin.MCAP: _Ros2McapStorage}})
        try:
            self.writer = writer_cls(Path(path), version=8, storage_plugin=StoragePlugin.MCAP)
            for k, v in (custom_data or {}).items():
                self.writer.set_custom_data(k, str(v))
            self.writer.open()
        except WriterError as exc:
            raise BagError(f"ros2 bag {path}: {exc}") from None
        self.connections: dict[str, object] = {}
        self.counts: dict[tuple[str, str], int] = {}

    def write(self, v) -> None:
        """Write one view."""
        e = self.encoder.encode(v)
        conn = self.connections.get(e.topic)
        if conn is None:
            qos = [_latched()] if e.topic.startswith("/tf_static") else []
            conn = self.connections[e.topic] = self.writer.add_connection(
                e.topic, e.msgtype, typestore=self.ts, offered_qos_profiles=qos)
        self.writer.write(conn, e.stamp_ns, e.parts if len(e.parts) > 1 else e.parts[0])
        self.counts[e.topic, e.msgtype] = self.counts.get((e.topic, e.msgtype), 0) + 1

    def close(self) -> None:
        """Finish the MCAP file and write ``metadata.yaml``."""
        self.writer.close()

    def abort(self) -> None:
        """Stop without finishing (the caller removes the folder); rosbags' own ``Writer.abort`` is newer than
        0.11.0, so the storage is closed directly."""
        storage, self.writer.storage = self.writer.storage, None
        if storage is not None:
            storage.abort()
