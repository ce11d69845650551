"""The layout of a polarstripe bag, and a message's payload in it (written by :mod:`polarstripe.runtime.bag`,
read by :mod:`polarstripe.runtime.bag_reader`).

A polarstripe bag is an MCAP file (https://mcap.dev/spec):

* one channel per topic, ``message_encoding = "msgpack"``; the payload is the message's self-contained
  MessagePack form (:func:`polarstripe.msgs.pack`: arrays inline as ``{dtype, shape, data}``);
* one schema per message type, ``encoding = "jsonschema"``, name ``polarstripe/<type>``, data
  :func:`polarstripe.msgs.json_schema` (its ``version`` const is the type's schema version);
* message ``log_time`` = when the recorder received it, ``publish_time`` = the header's ``stamp_ns``,
  ``sequence`` = the header's ``seq`` (mod 2**32);
* schema and channel records sit in the data section outside chunks (a chunk lost at a crash never takes
  them along); metadata records (``launch``, ``versions``, ``recording``) carry the run's context.

:func:`payload` gives the bytes of ``pack(msg)`` as a list of buffers whose array data are views of the
message's arrays, so the writer never copies the pixels.
"""

from __future__ import annotations

import os
import struct

import msgpack
import numpy as np
from polarstripe import __version__
from polarstripe.errors import PolarstripeError
from polarstripe.msgs import Message
from polarstripe.msgs.codec import HEADER_ITEMS, packed_fields
from polarstripe.msgs.fields import ArrayKind, DictKind, OptionalKind

MAGIC = b"\x89MCAP0\r\n"
MESSAGE_ENCODING = "msgpack"
SCHEMA_ENCODING = "jsonschema"
PROFILE = ""  # no MCAP profile: the registry's well-known "msgpack" encoding with jsonschema schemas
COMPRESSIONS = ("none", "zstd", "lz4")
_packb = msgpack.Packer(use_bin_type=True).pack
_SMALL = 64 * 1024  # buffers below this are merged into the running byte string of a payload


class BagError(PolarstripeError, ValueError):
    """A bag that cannot be written or read as asked; the text names the file, topic or option."""


def library_id() -> str:
    """The MCAP header's ``library`` field: ``polarstripe/<version>``."""
    return f"polarstripe/{__version__}"


def schema_name(msg_type: type[Message]) -> str:
    """The MCAP schema name of a message type: ``polarstripe/<type>``."""
    return f"polarstripe/{msg_type.TYPE}"


# ---- payload: the pack() form as a list of buffers --------------------------------------------------------
def _map_header(n: int) -> bytes:
    return (
        bytes([0x80 | n])
        if n < 16
        else (b"\xde" + struct.pack(">H", n) if n < 65536 else b"\xdf" + struct.pack(">I", n))
    )


def _bin_header(n: int) -> bytes:
    return (
        b"\xc4" + bytes([n])
        if n < 256
        else (b"\xc5" + struct.pack(">H", n) if n < 65536 else b"\xc6" + struct.pack(">I", n))
    )


def _emit(kind, v, bufs: list, out: list, cur: bytearray) -> bytearray:
    """Append wire value ``v`` of ``kind`` (array descriptors ``[buf, dtype, shape]`` index ``bufs``) in the
    pack() form: small bytes go into ``cur``, array data over ``_SMALL`` become their own entries of ``out``
    (views, no copy); returns the running ``cur``. A plain function, not a closure: a recursive closure is a
    reference cycle, which would keep every message's arrays (the received frames) alive until the garbage
    collector runs, so the receive buffers could never be reused."""
    if v is not None and isinstance(kind, OptionalKind):
        kind = kind.inner
    if v is not None and isinstance(kind, ArrayKind):
        data = memoryview(np.ascontiguousarray(bufs[v[0]]).reshape(-1).view(np.uint8))
        cur += b"\x83" + _packb("dtype") + _packb(v[1]) + _packb("shape") + _packb(list(v[2]))
        cur += _packb("data") + _bin_header(data.nbytes)
        if data.nbytes < _SMALL:
            cur += data
        else:
            out.append(bytes(cur))
            out.append(data)
            cur = bytearray()
    elif v is not None and isinstance(kind, DictKind):
        cur += _map_header(len(v))
        for k, x in v.items():
            cur += _packb(k)
            cur = _emit(kind.inner, x, bufs, out, cur)
    else:
        cur += _packb(v)
    return cur


def payload(msg: Message, *, topic: str = "") -> list:
    """The bytes of ``pack(msg)`` as a list of buffers, array data as views (no copy of the pixels).

    ``b"".join(payload(msg)) == pack(msg)``. Raises :class:`~polarstripe.msgs.MessageError` like
    :func:`~polarstripe.msgs.encode`.
    """
    (head, fields), bufs = packed_fields(msg, topic=topic)
    out: list = []
    cur = bytearray(_map_header(len(HEADER_ITEMS) + 1))
    for key, value in zip(HEADER_ITEMS, head, strict=True):
        cur += _packb(key) + _packb(value)
    cur += _packb("fields") + _map_header(len(fields))
    for name, kind, value in fields:
        cur += _packb(name)
        cur = _emit(kind, value, bufs, out, cur)
    if cur:
        out.append(bytes(cur))
    return out


# ---- writing ----------------------------------------------------------------------------------------------
_IOV_MAX = os.sysconf("SC_IOV_MAX") if hasattr(os, "sysconf") else 1024


def write_buffers(fd: int, bufs) -> int:
    """Write ``bufs`` in order with as few ``writev`` calls as the kernel takes (no join: the payloads go
    from the received frames to the page cache in one copy); returns the bytes written."""
    views = [v if v.format == "B" and v.ndim == 1 else v.cast("B") for v in map(memoryview, bufs) if v.nbytes]
    total, i = 0, 0
    while i < len(views):
        n = os.writev(fd, views[i : i + _IOV_MAX])
        if n == 0:
            raise OSError(28, "no byte written (disk full?)")
        total += n
        while n:  # a short write (a signal, a full disk): go on after the last byte written
            if n >= views[i].nbytes:
                n -= views[i].nbytes
                i += 1
            else:
                views[i], n = views[i][n:], 0
    return total


def compressor(compression: str):
    if compression == "none":
        return None
    try:
        if compression == "zstd":
            import zstandard

            return zstandard.ZstdCompressor(level=3).compress
        if compression == "lz4":
            import lz4.frame

            return lz4.frame.compress
    except ImportError as exc:
        raise BagError(f"compression {compression!r} needs the package {exc.name!r}") from None
    raise BagError(f"compression must be one of {', '.join(COMPRESSIONS)}, got {compression!r}")
