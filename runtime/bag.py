"""Writing MCAP bags of bus messages: a zero-copy chunked writer with crash-bounded loss.

The layout of a bag and a message's payload are in :mod:`polarstripe.runtime.bag_format` (its names are
importable from here too: ``BagError``, ``payload``, ``MAGIC``, ``COMPRESSIONS`` …).

:class:`BagWriter` follows mcap's writer lifecycle (``start`` / ``add_message`` / ``flush`` / ``finish``) but
never copies a payload: a chunk is a list of buffers (the arrays are views of the received ZeroMQ frames)
written with one ``os.writev`` (chunk and message indexes) to an unbuffered file when the chunk closes.
Chunks close by size (``chunk_size``) and by age (``chunk_age_s``, checked on every message and by
:meth:`BagWriter.flush_stale`), and each closed chunk is handed to the kernel at once, so a writer killed
with SIGKILL loses at most its open chunk.
"""

from __future__ import annotations

import json
import os
import struct
import time
import zlib
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (
    Channel,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    MessageIndex,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)
from polarstripe.msgs import Message, json_schema
from polarstripe.runtime.bag_format import (
    COMPRESSIONS,
    MAGIC,
    MESSAGE_ENCODING,
    PROFILE,
    SCHEMA_ENCODING,
    BagError,
    compressor,
    library_id,
    payload,
    schema_name,
    write_buffers,
)
from polarstripe.runtime.shm_bus import lease_of

__all__ = [  # the writer, and the layout's names from bag_format (importable from here as before)
    "COMPRESSIONS", "MAGIC", "MESSAGE_ENCODING", "PROFILE", "SCHEMA_ENCODING",
    "BagError", "BagWriter", "library_id", "payload", "schema_name", "write_buffers",
]


# ---- writer ------------------------------------------------------------------------------------------------
def _records(*records) -> bytes:
    rb = RecordBuilder()
    for r in records:
        r.write(rb)
    return rb.end()


MAX_LEASES = 8
"""Messages viewing shared-memory ring slots that one chunk may hold (a ring has 32 slots by default)."""


@dataclass
class _Chunk:
    parts: list = field(default_factory=list)  # per message: (channel id, log time, [record head, *payload])
    size: int = 0
    opened: float = 0.0  # monotonic time of the first message
    leases: list = field(default_factory=list)  # (message number, lease) of messages viewing a ring slot


class BagWriter:
    """Writes one MCAP file of bus messages.

    Parameters
    ----------
    path : str or Path
        The file (created or truncated).
    compression : {"none", "zstd", "lz4"}
        Chunk compression. ``none`` (default) writes payloads without copying them; zstd costs a core per
        ~45 frames/s of 1-megapixel 16-bit frames.
    chunk_size : int
        A chunk closes once it holds this many bytes [bytes].
    chunk_age_s : float
        A chunk closes once its first message is this old [s] (slow topics reach the disk too).
    crc : bool, optional
        Store the CRC-32 of each chunk's records. Default: only for compressed chunks (it costs about 1 ms
        per 2.6 MB frame, a quarter of an uncompressed write; a torn chunk is found by its length anyway).
    on_torn : callable, optional
        ``on_torn(topic)`` for each message dropped because its shared-memory slot was reused before its
        chunk was written out (a message received as views of a ring slot, ``Subscriber(shm="view")``:
        the chunk is written, its leases checked, and written again without the torn ones). A chunk
        closes once it holds :data:`MAX_LEASES` such messages, so that it never outlives a ring's lap.
    """

    def __init__(
        self,
        path,
        *,
        compression: str = "none",
        chunk_size: int = 1 << 20,
        chunk_age_s: float = 1.0,
        crc: bool | None = None,
        on_torn=None,
    ):
        if chunk_size <= 0 or not chunk_age_s > 0:
            raise BagError(f"chunk size and age must be > 0, got {chunk_size} bytes, {chunk_age_s} s")
        self.path = Path(path)
        self._compress = compressor(compression)
        self.compression = "" if compression == "none" else compression
        self.chunk_size, self.chunk_age_s = int(chunk_size), float(chunk_age_s)
        self.crc = self._compress is not None if crc is None else bool(crc)
        self._f = None
        self._pos = 0
        self.on_torn = on_torn
        self._topics: dict[int, str] = {}
        self._schemas: dict[str, Schema] = {}
        self._channels: dict[str, Channel] = {}
        self._chunk = _Chunk()
        self._chunk_indexes: list[ChunkIndex] = []
        self._metadata_indexes: list[MetadataIndex] = []
        self.stats = Statistics(
            message_count=0,
            schema_count=0,
            channel_count=0,
            attachment_count=0,
            metadata_count=0,
            chunk_count=0,
            message_start_time=0,
            message_end_time=0,
            channel_message_counts=defaultdict(int),
        )
        self.started_at = 0.0

    # -- lifecycle
    def start(self) -> BagWriter:
        """Create the file and write the magic and header."""
        self._f = open(self.path, "wb", buffering=0)  # noqa: SIM115  (closed by finish; unbuffered: _write)
        self._write(MAGIC, _records(Header(profile=PROFILE, library=library_id())))
        self.started_at = time.monotonic()
        return self

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """A metadata record (name, string map), outside chunks; indexed in the summary."""
        self._close_chunk()
        rec = _records(Metadata(name=name, metadata={str(k): str(v) for k, v in data.items()}))
        self._metadata_indexes.append(MetadataIndex(offset=self._pos, length=len(rec), name=name))
        self.stats.metadata_count += 1
        self._write(rec)

    def channel(self, topic: str, msg_type: type[Message]) -> int:
        """The channel id of ``topic`` (registering its schema and channel on first use)."""
        ch = self._channels.get(topic)
        if ch is not None:
            return ch.id
        return self.register(
            topic,
            schema_name(msg_type),
            lambda: json.dumps(json_schema(msg_type), separators=(",", ":")).encode(),
            {"type": msg_type.TYPE, "version": str(msg_type.VERSION)},
        )

    def register(
        self,
        topic: str,
        schema: str,
        schema_data,
        metadata: dict[str, str],
        schema_encoding: str = SCHEMA_ENCODING,
        message_encoding: str = MESSAGE_ENCODING,
    ) -> int:
        """Register ``topic`` with a schema given by name and data (bytes, or a callable giving them the
        first time the name is seen); returns the channel id. :meth:`channel` is the usual way."""
        if topic in self._channels:
            return self._channels[topic].id
        sc, out = self._schemas.get(schema), []
        if sc is None:
            data = schema_data() if callable(schema_data) else bytes(schema_data)
            sc = self._schemas[schema] = Schema(
                id=len(self._schemas) + 1, name=schema, encoding=schema_encoding, data=data
            )
            self.stats.schema_count += 1
            out.append(sc)
        ch = self._channels[topic] = Channel(
            id=len(self._channels) + 1,
            topic=topic,
            message_encoding=message_encoding,
            schema_id=sc.id,
            metadata=dict(metadata),
        )
        self.stats.channel_count += 1
        out.append(ch)
        self._topics[ch.id] = topic
        self._write(_records(*out))
        return ch.id

    def add_message(self, topic: str, msg: Message, *, log_time_ns: int | None = None) -> int:
        """Append ``msg`` on ``topic``; returns the payload size [bytes]. ``log_time_ns`` defaults to now."""
        cid = self.channel(topic, type(msg))
        parts = payload(msg, topic=topic)
        h = msg.header
        return self.add_payload(
            cid,
            parts,
            log_time_ns=time.time_ns() if log_time_ns is None else log_time_ns,
            publish_time_ns=h.stamp_ns,
            sequence=h.seq,
            lease=lease_of(msg),
        )

    def add_payload(
        self, channel_id: int, parts: list, *, log_time_ns: int, publish_time_ns: int, sequence: int,
        lease=None,
    ) -> int:
        """Append a payload given as buffers (see :func:`payload`) on a channel from :meth:`channel`;
        ``lease``: the buffers view a ring slot (checked after the chunk is written, ``on_torn``)."""
        n = sum(memoryview(p).nbytes for p in parts)
        c = self._chunk
        if not c.parts:
            c.opened = time.monotonic()
        if lease is not None:
            c.leases.append((len(c.parts), lease))
        head = struct.pack(
            "<BQHIQQ", Opcode.MESSAGE, 22 + n, channel_id, sequence & 0xFFFFFFFF, log_time_ns, publish_time_ns
        )
        c.parts.append((channel_id, log_time_ns, [head, *parts]))
        c.size += 31 + n
        st = self.stats
        if st.message_count == 0:
            st.message_start_time = log_time_ns
        st.message_start_time = min(st.message_start_time, log_time_ns)
        st.message_end_time = max(st.message_end_time, log_time_ns)
        st.message_count += 1
        st.channel_message_counts[channel_id] += 1
        if (c.size >= self.chunk_size or time.monotonic() - c.opened >= self.chunk_age_s
                or len(c.leases) >= MAX_LEASES):
            self._close_chunk()
        return n

    def flush_stale(self) -> None:
        """Close the open chunk if it is older than ``chunk_age_s`` (call it now and then)."""
        if self._chunk.parts and time.monotonic() - self._chunk.opened >= self.chunk_age_s:
            self._close_chunk()

    def flush(self) -> None:
        """Close the open chunk and hand everything to the kernel."""
        self._close_chunk()

    @property
    def size(self) -> int:
        """Bytes written so far plus the open chunk [bytes]."""
        return self._pos + self._chunk.size

    def finish(self, *, fsync: bool = True) -> None:
        """Close the last chunk, write the summary and footer, close (and fsync) the file. Idempotent."""
        if self._f is None:
            return
        self._close_chunk()
        self._write(_records(DataEnd(data_section_crc=0)))
        start = self._pos
        groups, rb = [], RecordBuilder()
        for opcode, recs in (
            (Opcode.SCHEMA, self._schemas.values()),
            (Opcode.CHANNEL, self._channels.values()),
            (Opcode.STATISTICS, [self.stats]),
            (Opcode.CHUNK_INDEX, self._chunk_indexes),
            (Opcode.METADATA_INDEX, self._metadata_indexes),
        ):
            g0 = rb.count
            for r in recs:
                r.write(rb)
            groups.append(
                SummaryOffset(group_opcode=opcode, group_start=start + g0, group_length=rb.count - g0)
            )
        offsets_start = start + rb.count
        for g in groups:
            g.write(rb)
        summary = rb.end()
        crc = zlib.crc32(struct.pack("<BQQQ", Opcode.FOOTER, 20, start, offsets_start), zlib.crc32(summary))
        self._write(
            summary,
            _records(Footer(summary_start=start, summary_offset_start=offsets_start, summary_crc=crc)),
            MAGIC,
        )
        f, self._f = self._f, None
        if fsync:
            os.fsync(f.fileno())
        f.close()

    def __enter__(self) -> BagWriter:
        return self if self._f is not None else self.start()

    def __exit__(self, *exc) -> None:
        self.finish()

    # -- internals
    def _write(self, *bufs) -> None:
        if self._f is None:
            raise BagError(f"bag {self.path}: not started (or already finished)")
        try:
            self._pos += write_buffers(self._f.fileno(), bufs)
        except OSError as exc:
            raise BagError(f"bag {self.path}: write failed at byte {self._pos}: {exc.strerror}") from None

    def _close_chunk(self) -> None:
        """Write the open chunk; where a message viewing a ring slot is torn after all, undo the write and
        write the chunk again without it (the kernel has copied the bytes once ``writev`` returns)."""
        c, self._chunk = self._chunk, _Chunk()
        while c.parts:
            start = self._pos
            self._write_chunk(c.parts)
            torn = {i for i, lease in c.leases if not lease.valid()}
            if not torn:
                return
            os.ftruncate(self._f.fileno(), start)
            os.lseek(self._f.fileno(), start, os.SEEK_SET)
            self._pos = start
            self._chunk_indexes.pop()
            self.stats.chunk_count -= 1
            for i in sorted(torn):
                cid = c.parts[i][0]
                self.stats.message_count -= 1
                self.stats.channel_message_counts[cid] -= 1
                if self.on_torn is not None:
                    self.on_torn(self._topics.get(cid, ""))
            leases, kept = dict(c.leases), [i for i in range(len(c.parts)) if i not in torn]
            c.parts = [c.parts[i] for i in kept]
            c.leases = [(j, leases[i]) for j, i in enumerate(kept) if i in leases]

    def _write_chunk(self, messages: list) -> None:
        """One chunk of ``messages`` (channel id, log time, buffers) and its message indexes, one writev."""
        index, parts, size = defaultdict(list), [], 0
        for cid, log_ns, bufs in messages:
            index[cid].append((log_ns, size))
            parts.extend(bufs)
            size += sum(memoryview(b).nbytes for b in bufs)
        start_ns, end_ns = min(m[1] for m in messages), max(m[1] for m in messages)
        crc = 0
        if self._compress is not None:
            joined = b"".join(parts)
            crc = zlib.crc32(joined) if self.crc else 0
            parts = [self._compress(joined)]
        elif self.crc:
            for p in parts:  # no join: the payload buffers go to the file as they are
                crc = zlib.crc32(p, crc)
        stored = sum(memoryview(p).nbytes for p in parts)
        comp = self.compression.encode()
        head = (
            struct.pack(
                "<BQQQQI",
                Opcode.CHUNK,
                8 * 3 + 4 + 4 + len(comp) + 8 + stored,
                start_ns,
                end_ns,
                size,
                crc,
            )
            + struct.pack("<I", len(comp))
            + comp
            + struct.pack("<Q", stored)
        )
        chunk_start = self._pos
        chunk_length = len(head) + stored
        offsets, index_start, indexes = {}, chunk_start + chunk_length, []
        for cid, entries in index.items():
            offsets[cid] = index_start + sum(len(r) for r in indexes)
            indexes.append(_records(MessageIndex(channel_id=cid, records=entries)))
        self._write(head, *parts, *indexes)  # one writev: the chunk and its indexes
        self._chunk_indexes.append(
            ChunkIndex(
                message_start_time=start_ns,
                message_end_time=end_ns,
                chunk_start_offset=chunk_start,
                chunk_length=chunk_length,
                message_index_offsets=offsets,
                message_index_length=self._pos - index_start,
                compression=self.compression,
                compressed_size=stored,
                uncompressed_size=size,
            )
        )
        self.stats.chunk_count += 1
