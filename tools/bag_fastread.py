"""Reading a finished polarstripe bag for the exports with one copy of each message: every chunk is read
once (``pread``) into fresh memory, or decompressed once, and a message's arrays are views of it.

:class:`BagReader` (``mcap``'s reader) copies a camera frame three times: the chunk into a buffer, the
record out of it, and the MessagePack ``bin`` out of the record. Here the message index of each chunk gives
the records' offsets, and a payload of 64 KiB or more is parsed by :func:`parse_packed`, which returns
``bin`` values as slices, so :func:`~polarstripe.msgs.codec.decode_views` builds the message on views. A
smaller payload, or anything the parser does not expect, goes through :func:`~polarstripe.msgs.unpack` as
usual; either way the message is validated like any decoded message. ``mapped=True`` slices a read-only
``mmap`` of the file instead (no copy at all; each chunk's pages mapped in one ``MADV_POPULATE_READ``):
on the development VM neither way was consistently faster, and faulting a mapping in page by page (an older
kernel) cost twice the read, so reading is the default.

The bag must have been opened (and checked) by :class:`~polarstripe.runtime.bag_reader.BagReader`.
"""

from __future__ import annotations

import mmap
import os
import struct
from collections import OrderedDict

import msgpack
import numpy as np
from polarstripe.msgs import Message, unpack
from polarstripe.msgs.codec import HEADER_ITEMS, decode_views
from polarstripe.msgs.fields import ArrayKind, DictKind, OptionalKind
from polarstripe.runtime.bag import BagError
from polarstripe.runtime.bag_reader import BagReader

BIG = 64 * 1024  # payloads from this size on are parsed without copying their bins
_MSG = struct.Struct("<BQHIQQ")  # message record: opcode, length, channel, sequence, log time, publish time
_IDX = np.dtype([("t", "<u8"), ("o", "<u8")])
_packb = msgpack.Packer(use_bin_type=True).pack
_POPULATE = getattr(mmap, "MADV_POPULATE_READ", 22 if hasattr(mmap.mmap, "madvise") else None)


_SIMPLE = {0xC0: None, 0xC2: False, 0xC3: True}
_FIXED = {0xCA: ">f", 0xCB: ">d", 0xCC: "B", 0xCD: ">H", 0xCE: ">I", 0xCF: ">Q", 0xD0: "b", 0xD1: ">h",
          0xD2: ">i", 0xD3: ">q"}
_SIZED = {0xC4: ("bin", "B"), 0xC5: ("bin", ">H"), 0xC6: ("bin", ">I"), 0xD9: ("str", "B"),
          0xDA: ("str", ">H"), 0xDB: ("str", ">I"), 0xDC: ("array", ">H"), 0xDD: ("array", ">I"),
          0xDE: ("map", ">H"), 0xDF: ("map", ">I")}
_STRUCTS = {f: struct.Struct(f) for f in {*_FIXED.values(), *(f for _, f in _SIZED.values())}}


class _Parser:
    """A MessagePack reader over a byte view that returns ``bin`` values as sub-views."""

    def __init__(self, view: memoryview):
        self.v, self.i = view, 0

    def _take(self, fmt: str):
        st = _STRUCTS[fmt]
        (out,) = st.unpack_from(self.v, self.i)
        self.i += st.size
        return out

    def _str(self, n: int) -> str:
        s = str(self.v[self.i : self.i + n], "utf-8")
        self.i += n
        return s

    def value(self):
        b = self.v[self.i]
        self.i += 1
        if b <= 0x7F:
            return b
        if b >= 0xE0:
            return b - 0x100
        if b <= 0x8F:
            return self._map(b & 0x0F)
        if b <= 0x9F:
            return [self.value() for _ in range(b & 0x0F)]
        if b <= 0xBF:
            return self._str(b & 0x1F)
        if b in _SIMPLE:
            return _SIMPLE[b]
        fmt = _FIXED.get(b)
        if fmt is not None:
            return self._take(fmt)
        size = _SIZED.get(b)
        if size is None:
            raise ValueError(f"MessagePack type 0x{b:02x} not expected in a packed message")
        kind, fmt = size
        n = self._take(fmt)
        if kind == "bin":
            out = self.v[self.i : self.i + n]
            if len(out) != n:
                raise ValueError("bin past the end")
            self.i += n
            return out
        if kind == "str":
            return self._str(n)
        if kind == "array":
            return [self.value() for _ in range(n)]
        return self._map(n)

    def _map(self, n: int) -> dict:
        out = {}
        for _ in range(n):
            k = self.value()
            if not isinstance(k, str):
                raise ValueError("map key is not a string")
            out[k] = self.value()
        return out


def _outline(kind, v, bufs: list):
    """An inline array ``{dtype, shape, data: view}`` as a wire descriptor (its data to ``bufs``)."""
    if isinstance(kind, OptionalKind) and v is not None:
        return _outline(kind.inner, v, bufs)
    if isinstance(kind, ArrayKind) and isinstance(v, dict) and v.keys() == {"dtype", "shape", "data"}:
        if isinstance(v["data"], memoryview):
            bufs.append(v["data"])
            return [len(bufs) - 1, v["dtype"], v["shape"]]
    if isinstance(kind, DictKind) and isinstance(v, dict):
        return {k: _outline(kind.inner, x, bufs) for k, x in v.items()}
    return _bytes(v)


def _bytes(v):
    """Views left outside arrays (``bytes`` fields) as bytes."""
    if isinstance(v, memoryview):
        return bytes(v)
    if isinstance(v, dict):
        return {k: _bytes(x) for k, x in v.items()}
    if isinstance(v, list):
        return [_bytes(x) for x in v]
    return v


def parse_packed(data: memoryview, *, topic: str, expect: type[Message]) -> Message:
    """:func:`~polarstripe.msgs.unpack` of a packed message whose arrays stay views of ``data``."""
    if data.nbytes < BIG:
        return unpack(data, topic=topic, expect=expect)
    try:
        doc = _Parser(data).value()
        fields = doc["fields"]
        head = [doc[k] for k in HEADER_ITEMS]
        if not (isinstance(fields, dict) and set(doc) == {*HEADER_ITEMS, "fields"}
                and fields.keys() == expect.FIELD_NAMES):
            raise ValueError("not the packed form of the expected type")
        bufs: list = []
        head += [_outline(kind, fields[name], bufs) for name, kind in expect.FIELDS]
        header = _packb(head)
    except (ValueError, KeyError, IndexError, TypeError, struct.error, UnicodeDecodeError):
        return unpack(bytes(data), topic=topic, expect=expect)  # the codec says what is wrong
    return decode_views(header, bufs, topic=topic, expect=expect)


class FastReader:
    """Messages of an open :class:`BagReader`'s file in log-time order (module docstring)."""

    def __init__(self, bag: BagReader, *, mapped: bool = False):
        self.bag, self.mapped = bag, mapped
        self._f = open(bag.path, "rb")  # noqa: SIM115  (closed by close)
        self._map = mmap.mmap(self._f.fileno(), 0, access=mmap.ACCESS_READ)
        self._view = memoryview(self._map)
        self._chunks: OrderedDict[int, memoryview] = OrderedDict()

    def _records(self, k: int) -> memoryview:
        """The records of chunk ``k`` (a slice of the map, or decompressed once and kept a while)."""
        got = self._chunks.get(k)
        if got is not None:
            return got
        ci = self.bag.summary.chunk_indexes[k]
        v, pos = self._view, ci.chunk_start_offset + 9 + 8 * 3 + 4
        (n,) = struct.unpack_from("<I", v, pos)
        comp = str(v[pos + 4 : pos + 4 + n], "ascii")
        pos += 4 + n
        (size,) = struct.unpack_from("<Q", v, pos)
        data = v[pos + 8 : pos + 8 + size]
        if comp:
            data = memoryview(_decompress(comp, data, ci.uncompressed_size))
        elif not self.mapped:  # one read of the chunk into fresh memory instead of faulting the mapping in
            data = memoryview(os.pread(self._f.fileno(), size, pos + 8))
        elif _POPULATE is not None:  # map the chunk's pages in one call rather than fault them one by one
            start = (pos + 8) & ~(mmap.PAGESIZE - 1)
            try:
                self._map.madvise(_POPULATE, start, pos + 8 + size - start)
            except OSError:  # a kernel before 5.14
                pass
        self._chunks[k] = data
        while len(self._chunks) > 4:
            self._chunks.popitem(last=False)
        return data

    def raw(self, topics, start_ns: int | None = None, end_ns: int | None = None):
        """``(topic, log_time_ns, payload view)`` of ``topics`` in log-time order, within [start, end]."""
        s = self.bag.summary
        wanted = {cid: ch.topic for cid, ch in s.channels.items() if ch.topic in set(topics)}
        lo, hi = start_ns or 0, end_ns if end_ns is not None else 2**64 - 1
        parts = []
        for k, ci in enumerate(s.chunk_indexes):
            if ci.message_end_time < lo or ci.message_start_time > hi:
                continue
            for cid, offset in ci.message_index_offsets.items():
                if cid not in wanted:
                    continue
                (n,) = struct.unpack_from("<I", self._view, offset + 9 + 2)
                e = np.frombuffer(self._view, _IDX, n // 16, offset + 9 + 2 + 4)
                keep = (e["t"] >= lo) & (e["t"] <= hi)
                m = int(keep.sum())
                if m:
                    parts.append((e["t"][keep], np.full(m, k), e["o"][keep], np.full(m, cid)))
        if not parts:
            return
        t, ks, offs, cids = (np.concatenate(c) for c in zip(*parts, strict=True))
        for i in np.lexsort((offs, ks, t)):
            rec = self._records(int(ks[i]))
            o = int(offs[i])
            op, length, cid, _, log, _ = _MSG.unpack_from(rec, o)
            if op != 0x05 or cid != cids[i]:
                raise BagError(f"bag {self.bag.path}: message index points at no message (chunk {ks[i]})")
            yield wanted[cid], log, rec[o + _MSG.size : o + 9 + length]

    def close(self) -> None:
        """Unmap the file (arrays still viewing it keep the mapping alive until they go)."""
        self._chunks.clear()
        try:
            self._view.release()
            self._map.close()
        except BufferError:  # a message's array still views the map: the map goes with it
            pass
        self._f.close()


def _decompress(comp: str, data: memoryview, size: int) -> bytes:
    if comp == "zstd":
        import zstandard

        return zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
    if comp == "lz4":
        import lz4.frame

        return lz4.frame.decompress(data)
    raise BagError(f"chunk compression {comp!r} is not supported")
