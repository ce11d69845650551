"""Reading polarstripe bags: :class:`BagReader` (checked at open: MCAP magic, footer, every channel's schema
and version), :func:`check_file`, and :func:`recover` for a file whose writer died.

The layout is described in :mod:`polarstripe.runtime.bag`. ``polarstripe bag info`` and ``replay``
read through here; errors a user can cause are :class:`~polarstripe.runtime.bag.BagError`, one line
naming the file and topic.
"""

from __future__ import annotations

import inspect
import json
import os
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.reader import SeekingReader
from mcap.records import Channel, Chunk, MessageIndex, Metadata, Schema
from mcap.records import Message as McapMessage
from mcap.stream_reader import StreamReader, breakup_chunk
from polarstripe.msgs import REGISTRY, Message, unpack
from polarstripe.runtime.bag import MAGIC, MESSAGE_ENCODING, SCHEMA_ENCODING, BagError, BagWriter
from polarstripe.runtime.graph import resolve


# ---- reader ------------------------------------------------------------------------------------------------
@dataclass
class TopicSummary:
    """One channel of a bag: its message type and version, how many messages, first/last log time [ns]."""

    topic: str
    type: str
    version: int
    known: bool  # this build has the type (messages can be decoded)
    count: int = 0
    first_ns: int = 0
    last_ns: int = 0

    @property
    def rate_hz(self) -> float:
        span = (self.last_ns - self.first_ns) / 1e9
        return (self.count - 1) / span if self.count > 1 and span > 0 else 0.0


def check_file(path) -> int:
    """Check that ``path`` is a complete MCAP file; return its size [bytes].

    Raises :class:`BagError` (one line, naming the file) for a missing, empty or non-MCAP file and for a
    truncated one (no footer: its writer died), which ``polarstripe bag recover`` can repair.
    """
    p = Path(path)
    try:
        with open(p, "rb") as f:
            head = f.read(8)
            size = f.seek(0, os.SEEK_END)
            f.seek(max(0, size - 8))
            tail = f.read(8)
    except FileNotFoundError:
        raise BagError(f"bag {p}: no such file") from None
    except IsADirectoryError:
        raise BagError(f"bag {p}: is a directory, not an MCAP file") from None
    if head != MAGIC:
        raise BagError(f"bag {p}: not an MCAP file (starts with {head[:8]!r})")
    if size < 2 * len(MAGIC) + 9 + 20 or tail != MAGIC:
        raise BagError(
            f"bag {p}: truncated MCAP file ({size} bytes, no footer: its writer died?); "
            f"repair it with 'polarstripe bag recover {p} -o FIXED.mcap'"
        )
    return size


def _schema_type(path: Path, topic: str, schema: Schema | None, channel: Channel) -> tuple[str, int]:
    """(type name, version) declared by a polarstripe channel's JSON Schema; BagError otherwise."""
    if channel.message_encoding != MESSAGE_ENCODING or schema is None or schema.encoding != SCHEMA_ENCODING:
        raise BagError(
            f"bag {path}: topic {topic!r}: message encoding {channel.message_encoding!r} with schema "
            f"encoding {getattr(schema, 'encoding', None)!r} is not a polarstripe channel "
            f"(expected {MESSAGE_ENCODING!r} + {SCHEMA_ENCODING!r})"
        )
    try:
        props = json.loads(schema.data)["properties"]
        tname, version = props["type"]["const"], props["version"]["const"]
    except (ValueError, KeyError, TypeError):
        raise BagError(
            f"bag {path}: topic {topic!r}: schema {schema.name!r} is not a polarstripe message "
            "schema (no type/version consts)"
        ) from None
    if not isinstance(tname, str) or type(version) is not int:
        raise BagError(
            f"bag {path}: topic {topic!r}: schema {schema.name!r}: bad type {tname!r} or version {version!r}"
        )
    return tname, version


class BagReader:
    """Reads a finished bag (a seekable MCAP with a summary); checks every channel's schema at open.

    Raises :class:`BagError` for a file that is not MCAP, a truncated file, a channel that is not a
    polarstripe msgpack/jsonschema channel, or a known message type recorded with another schema version.
    A type this build does not know is listed (``TopicSummary.known`` False) but cannot be decoded.
    """

    def __init__(self, path):

        self.path = Path(path)
        self.size = check_file(self.path)
        self._f = open(self.path, "rb")  # noqa: SIM115  (closed by close)
        try:
            self._reader = SeekingReader(self._f)
            summary = self._reader.get_summary()
            if summary is None:
                raise BagError(
                    f"bag {self.path}: has no summary section (not indexed); "
                    f"run 'polarstripe bag recover {self.path} -o FIXED.mcap'"
                )
            self.metadata = {m.name: dict(m.metadata) for m in self._reader.iter_metadata()}
        except McapError as exc:
            self._f.close()
            raise BagError(f"bag {self.path}: unreadable MCAP ({type(exc).__name__}: {exc})") from None
        except BaseException:
            self._f.close()
            raise
        self.summary = summary
        st = summary.statistics
        self.topics: dict[str, TopicSummary] = {}
        self.types: dict[str, type[Message] | None] = {}
        for cid, ch in sorted(summary.channels.items()):
            tname, version = _schema_type(self.path, ch.topic, summary.schemas.get(ch.schema_id), ch)
            cls = REGISTRY.get(tname)
            if cls is not None and cls.VERSION != version and version not in cls.OLDER:
                self._f.close()
                raise BagError(
                    f"bag {self.path}: topic {ch.topic!r}: unknown schema version {version} of "
                    f"{tname!r} (this build reads version {cls.VERSION})"
                )
            self.types[ch.topic] = cls
            self.topics[ch.topic] = TopicSummary(
                ch.topic,
                tname,
                version,
                cls is not None,
                count=st.channel_message_counts.get(cid, 0) if st else 0,
            )
        for t, first, last in self._index_times(summary):
            t = self.topics[t]
            t.first_ns = min(t.first_ns or first, first)
            t.last_ns = max(t.last_ns, last)
        self.start_ns = st.message_start_time if st else 0
        self.end_ns = st.message_end_time if st else 0
        self.message_count = st.message_count if st else 0
        self.compression = sorted({ci.compression or "none" for ci in summary.chunk_indexes})

    def _index_times(self, summary):
        """(topic, first, last log time) of each chunk's message index record (exact per topic)."""

        for ci in summary.chunk_indexes:
            for cid, offset in ci.message_index_offsets.items():
                self._f.seek(offset + 9)
                entries = MessageIndex.read(ReadDataStream(self._f)).records
                if entries:
                    times = [e[0] for e in entries]
                    yield summary.channels[cid].topic, min(times), max(times)

    @property
    def duration_s(self) -> float:
        return (self.end_ns - self.start_ns) / 1e9

    def resolve_topics(self, names, namespace: str = "") -> list[str]:
        """Full topic names of the bag for ``names``: full names as they are, relative ones in ``namespace``
        (default: the recorded launch's) or, failing that, the one topic of the bag ending in ``/name``.
        Raises :class:`BagError` naming a topic the bag does not have."""

        ns = namespace or self.metadata.get("launch", {}).get("namespace", "")
        out = []
        for name in names:
            full = resolve(name, ns)
            if full not in self.topics and not name.startswith("/"):
                ends = [t for t in self.topics if t.endswith("/" + name.strip("/"))]
                full = ends[0] if len(ends) == 1 else full
            if full not in self.topics:
                raise BagError(f"bag {self.path}: no topic {name!r} (has {', '.join(self.topics)})")
            out.append(full)
        return out

    def raw(self, topics=None, start_ns: int | None = None):
        """``(topic, log_time_ns, sequence, payload bytes)`` in log-time order."""
        if topics is not None:
            unknown = sorted(set(topics) - set(self.topics))
            if unknown:
                raise BagError(f"bag {self.path}: no topic {unknown[0]!r} (has {', '.join(self.topics)})")

        since = (
            "starting_at"
            if "starting_at" in inspect.signature(self._reader.iter_messages).parameters
            else ("start_time")
        )  # mcap >= 1.6 deprecates start_time
        for _, ch, m in self._reader.iter_messages(topics=topics, **{since: start_ns}):
            yield ch.topic, m.log_time, m.sequence, m.data

    def messages(self, topics=None, start_ns: int | None = None):
        """``(topic, log_time_ns, Message)`` in log-time order, each decoded and validated (arrays are
        read-only views). Raises :class:`BagError` for a topic whose type this build does not know."""

        chosen = list(self.topics) if topics is None else list(topics)
        for t in chosen:
            if t in self.types and self.types[t] is None:
                raise BagError(
                    f"bag {self.path}: topic {t!r}: message type {self.topics[t].type!r} is not "
                    "known to this build (import the module that declares it)"
                )
        for topic, log_ns, _, data in self.raw(chosen, start_ns):
            yield topic, log_ns, unpack(data, topic=topic, expect=self.types[topic])

    def sequence_gaps(self, topics=None) -> dict[str, int]:
        """Messages missing according to the recorded ``seq`` per topic (a full pass over the file)."""
        last: dict[str, int] = {}
        gaps: dict[str, int] = defaultdict(int)
        for _, ch, m in self._reader.iter_messages(topics=topics, log_time_order=False):
            prev = last.get(ch.topic)
            if prev is not None and m.sequence > prev + 1:
                gaps[ch.topic] += m.sequence - prev - 1
            last[ch.topic] = m.sequence
        return {t: gaps.get(t, 0) for t in (topics or self.topics)}

    def close(self) -> None:
        self._f.close()

    def __enter__(self) -> BagReader:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# ---- recover -----------------------------------------------------------------------------------------------
@dataclass
class Recovered:
    """What :func:`recover` copied: messages, chunks, and why it stopped reading (empty if the file ended)."""

    messages: int
    chunks: int
    topics: dict[str, int]
    stopped: str


def recover(src, dst, *, compression: str = "none", chunk_size: int = 1 << 20) -> Recovered:
    """Copy every complete record of ``src`` (e.g. a bag whose writer was killed) into a new indexed bag
    ``dst``: schemas, channels, metadata and the messages of every complete chunk; a torn last chunk is
    dropped. Raises :class:`BagError` if ``src`` is not MCAP or ``dst`` is ``src``.
    """

    src, dst = Path(src), Path(dst)
    with open(src, "rb") as f:
        if f.read(8) != MAGIC:
            raise BagError(f"bag {src}: not an MCAP file")
    if dst.exists() and dst.resolve() == src.resolve():
        raise BagError(f"bag recover: output {dst} is the input; choose another file")
    schemas: dict[int, Schema] = {}
    cmap: dict[int, int] = {}
    counts: dict[str, int] = defaultdict(int)
    n = chunks = 0
    stopped = ""
    w = BagWriter(dst, compression=compression, chunk_size=chunk_size, chunk_age_s=1e9).start()
    try:
        with open(src, "rb") as f:

            def copy(rec) -> None:
                nonlocal n
                if isinstance(rec, Schema):
                    schemas[rec.id] = rec
                elif isinstance(rec, Channel) and rec.id not in cmap:
                    sc = schemas.get(rec.schema_id)
                    cmap[rec.id] = w.register(
                        rec.topic,
                        sc.name if sc else "",
                        sc.data if sc else b"",
                        dict(rec.metadata),
                        sc.encoding if sc else "",
                        rec.message_encoding,
                    )
                    cmap[-rec.id] = rec.topic  # type: ignore[assignment]
                elif isinstance(rec, McapMessage) and rec.channel_id in cmap:
                    w.add_payload(
                        cmap[rec.channel_id],
                        [rec.data],
                        log_time_ns=rec.log_time,
                        publish_time_ns=rec.publish_time,
                        sequence=rec.sequence,
                    )
                    counts[cmap[-rec.channel_id]] += 1
                    n += 1
                elif isinstance(rec, Metadata):
                    w.add_metadata(rec.name, dict(rec.metadata))

            try:
                for rec in StreamReader(f, skip_magic=False, emit_chunks=True).records:
                    if isinstance(rec, Chunk):
                        inner = breakup_chunk(rec, validate_crc=True)  # whole chunk or nothing
                        chunks += 1
                        for r in inner:
                            copy(r)
                    else:
                        copy(rec)
            except Exception as exc:  # the damaged tail: EndOfFile, a torn record, a bad CRC
                stopped = f"{type(exc).__name__} at byte {f.tell()}" + (f": {exc}" if str(exc) else "")
    finally:
        w.finish()
    return Recovered(n, chunks, dict(counts), stopped)
