"""MessagePack codec: a message becomes ``[header, *buffers]`` frames; arrays travel as raw buffer frames.

Wire (one ZeroMQ multipart message, the bus prepends the topic frame)::

    header  = msgpack {"type": str, "version": int, "stamp_ns": int, "seq": int, "frame_id": str,
                       "fields": {name: value}}      # an ndarray field is {"buf": i, "dtype": "<u2",
                                                     # "shape": [..]}
    buffers = the raw C-order bytes of each array, in "buf" order

Decoding validates everything and returns arrays as zero-copy, read-only views of the received frames. Every
problem raises :class:`MessageError` naming the topic, the field and what was wrong. There is no pickle.

:func:`pack` / :func:`unpack` give the same message as one self-contained MessagePack blob (arrays inline as
``{"dtype", "shape", "data"}``), the form described by :func:`polarstripe.msgs.schema.json_schema` and used
for recordings.
"""

from __future__ import annotations

import time
from typing import Any

import msgpack
import numpy as np
import zmq
from polarstripe.msgs.base import REGISTRY, Header, Message, MessageError
from polarstripe.msgs.fields import Buffers

DEFAULT_MAX_BYTES = 128 * 2**20
"""Largest message (header plus buffers) a decoder accepts by default [bytes]."""

_HEADER_KEYS = frozenset({"type", "version", "stamp_ns", "seq", "frame_id", "fields"})
_packb = msgpack.Packer(use_bin_type=True).pack


def encode(msg: Message, *, topic: str = "", seq: int | None = None, stamp_ns: int | None = None) -> list:
    """Encode ``msg`` to frames ``[header_bytes, *arrays]``.

    ``seq`` and ``stamp_ns`` override the message's header (the publisher stamps them); ``stamp_ns=None``
    keeps the header's stamp, or uses the current time when that is 0. Raises :class:`MessageError`
    (naming ``topic``) if a field value does not match its declared type.
    """
    cls = type(msg)
    if not isinstance(msg, Message) or not cls.TYPE:
        raise MessageError(topic, "type", f"{cls.__name__} is not a declared message type")
    bufs: list = []
    fields = (_COMPILED.get(cls) or _compile(cls))[0](msg.__dict__, bufs, topic)
    h = msg.header
    if stamp_ns is None:
        stamp_ns = h.stamp_ns or time.time_ns()
    head = {
        "type": cls.TYPE,
        "version": cls.VERSION,
        "stamp_ns": int(stamp_ns),
        "seq": int(h.seq if seq is None else seq),
        "frame_id": h.frame_id,
        "fields": fields,
    }
    return [_packb(head), *bufs]


_COMPILED: dict[type, tuple] = {}


def _compile(cls: type[Message]) -> tuple:
    """Per message type, the field loops of :func:`encode` and :func:`decode` unrolled into straight-line code
    (generated from the declared fields; a value of the declared scalar type passes as it is, anything else
    goes through its kind, which checks it). Same checks as a loop, about half the Python overhead."""
    env: dict[str, Any] = {"MessageError": MessageError}
    enc = ["def enc(d, bufs, topic):", "    f = {}"]
    dec = ["def dec(d, bufs, topic):"]
    for i, (name, kind, exact) in enumerate(cls.FAST_FIELDS):
        env[f"k{i}"], env[f"e{i}"] = kind, exact
        n = repr(name)
        enc += [
            f"    v = d[{n}]",
            f"    if type(v) is e{i}:",
            f"        f[{n}] = v",
            "    else:",
            "        try:",
            f"            f[{n}] = k{i}.enc(v, bufs)",
            "        except ValueError as exc:",
            f"            raise MessageError(topic, {n}, str(exc)) from None",
        ]
        dec += [
            f"    v = d[{n}]",
            f"    if type(v) is not e{i}:",
            "        try:",
            f"            d[{n}] = k{i}.dec(v, bufs)",
            "        except ValueError as exc:",
            f"            raise MessageError(topic, {n}, str(exc)) from None",
        ]
    exec("\n".join([*enc, "    return f", *dec, "    return d", ""]), env)  # noqa: S102
    _COMPILED[cls] = (env["enc"], env["dec"])
    return _COMPILED[cls]


def _load_header(topic: str, raw: Any) -> dict:
    try:
        head = msgpack.unpackb(raw, raw=False, strict_map_key=True)
    except Exception as exc:  # msgpack raises several unrelated classes for garbage
        why = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
        raise MessageError(topic, "header", f"not a MessagePack header ({why})") from None
    if not isinstance(head, dict):
        raise MessageError(topic, "header", f"expected a map, got {type(head).__name__}")
    if head.keys() == _HEADER_KEYS:
        return head
    missing = _HEADER_KEYS - head.keys()
    if missing:
        raise MessageError(topic, sorted(missing)[0], "missing from the header")
    extra = head.keys() - _HEADER_KEYS
    if extra:
        raise MessageError(topic, sorted(extra)[0], "unknown header key")
    return head


def _build(topic: str, head: dict, bufs: list, expect: type[Message] | None) -> Message:
    tname = head["type"]
    cls = REGISTRY.get(tname) if isinstance(tname, str) else None
    if cls is None:
        raise MessageError(topic, "type", f"unknown message type {tname!r:.60}")
    if expect is not None and cls is not expect:
        raise MessageError(topic, "type", f"expected {expect.TYPE!r}, got {tname!r}")
    version = head["version"]
    if version != cls.VERSION:
        raise MessageError(
            topic,
            "version",
            f"unknown schema version {version!r:.20} of {tname!r} (this build reads version {cls.VERSION})",
        )
    stamp_ns, seq, frame_id = head["stamp_ns"], head["seq"], head["frame_id"]
    if type(stamp_ns) is not int or type(seq) is not int or type(frame_id) is not str:
        for key, value, typ in (("stamp_ns", stamp_ns, int), ("seq", seq, int), ("frame_id", frame_id, str)):
            if type(value) is not typ:
                raise MessageError(topic, key, f"expected {typ.__name__}, got {type(value).__name__}")
    wire = head["fields"]
    if type(wire) is not dict:
        raise MessageError(topic, "fields", f"expected a map, got {type(wire).__name__}")
    fast = cls.FAST_FIELDS
    if len(wire) == len(fast) and wire.keys() == cls.FIELD_NAMES:
        values = (_COMPILED.get(cls) or _compile(cls))[1](dict(wire), bufs, topic)
    else:
        for name, _kind, _exact in fast:
            if name not in wire:
                raise MessageError(topic, name, f"missing (a {tname!r} needs it)")
        extra = sorted(set(map(str, wire)) - cls.FIELD_NAMES)
        raise MessageError(topic, extra[0] if extra else "fields", f"unknown field of {tname!r}")
    values["header"] = Header(stamp_ns, seq, frame_id)
    msg = cls.__new__(cls)  # every field was validated above: skip the frozen __init__ (2 µs per message)
    msg.__dict__.update(values)
    return msg


def decode(
    frames: list, *, topic: str = "", expect: type[Message] | None = None, max_bytes: int = DEFAULT_MAX_BYTES
) -> Message:
    """Decode frames ``[header, *buffers]`` (bytes, memoryviews or ``zmq.Frame``) into a message.

    Arrays are zero-copy read-only views of the buffer frames. ``expect`` rejects any other type.
    Raises :class:`MessageError` for garbage, an unknown or unexpected type, an unknown schema version,
    a missing or mistyped field, an array whose dtype/shape does not match its buffer, or more than
    ``max_bytes`` in total.
    """
    if not frames:
        raise MessageError(topic, "header", "empty message (no header frame)")
    views = [_bytes_view(f) for f in frames]
    total = sum(v.nbytes for v in views)
    if total > max_bytes:
        raise MessageError(topic, "size", f"{total} bytes exceeds the limit of {max_bytes} bytes")
    bufs = Buffers(views[1:])
    head = _load_header(topic, views[0])
    msg = _build(topic, head, bufs, expect)
    if len(bufs.used) != len(bufs):
        raise MessageError(topic, "buffers", f"{len(bufs)} buffer frames but {len(bufs.used)} used by fields")
    return msg


def _bytes_view(f: Any) -> memoryview:
    """A flat byte view of a frame (``zmq.Frame``, bytes, memoryview or a contiguous ndarray)."""
    if type(f) is bytes:
        return memoryview(f)
    v = f.buffer if isinstance(f, zmq.Frame) else memoryview(f)
    return v if v.ndim == 1 and v.itemsize == 1 else v.cast("B")


def pack(msg: Message, *, topic: str = "") -> bytes:
    """One self-contained MessagePack blob: the header map with arrays inline as ``{dtype, shape, data}``."""
    frames = encode(msg, topic=topic)
    head = msgpack.unpackb(frames[0], raw=False)
    bufs = frames[1:]
    for name, value in head["fields"].items():
        head["fields"][name] = _inline(value, bufs)
    return _packb(head)


def _inline(v: Any, bufs: list) -> Any:
    if isinstance(v, dict):
        if set(v) == {"buf", "dtype", "shape"} and type(v["buf"]) is int:
            return {
                "dtype": v["dtype"],
                "shape": v["shape"],
                "data": np.ascontiguousarray(bufs[v["buf"]]).tobytes(),
            }
        return {k: _inline(x, bufs) for k, x in v.items()}
    if isinstance(v, list):
        return [_inline(x, bufs) for x in v]
    return v


def unpack(
    blob: bytes, *, topic: str = "", expect: type[Message] | None = None, max_bytes: int = DEFAULT_MAX_BYTES
) -> Message:
    """Inverse of :func:`pack`; validates like :func:`decode` (arrays are read-only views of ``blob``)."""
    if len(blob) > max_bytes:
        raise MessageError(topic, "size", f"{len(blob)} bytes exceeds the limit of {max_bytes} bytes")
    head = _load_header(topic, blob)
    bufs = Buffers()
    cls = REGISTRY.get(head["type"]) if isinstance(head["type"], str) else None
    if isinstance(head["fields"], dict) and cls is not None:
        head["fields"] = {k: _outline(v, bufs) for k, v in head["fields"].items()}
    return _build(topic, head, bufs, expect)


def _outline(v: Any, bufs: list) -> Any:
    if isinstance(v, dict):
        if set(v) == {"dtype", "shape", "data"} and isinstance(v["data"], bytes):
            bufs.append(memoryview(v["data"]))
            return {"buf": len(bufs) - 1, "dtype": v["dtype"], "shape": v["shape"]}
        return {k: _outline(x, bufs) for k, x in v.items()}
    if isinstance(v, list):
        return [_outline(x, bufs) for x in v]
    return v


def describe(frames: list, *, topic: str = "", max_bytes: int = DEFAULT_MAX_BYTES) -> dict:
    """A printable summary (header keys, small fields, arrays as ``dtype[shape]``), without the class.

    For tools such as ``topic echo`` that may not know every type. Raises :class:`MessageError` for garbage.
    """
    views = [_bytes_view(f) for f in frames]
    if not views:
        raise MessageError(topic, "header", "empty message (no header frame)")
    if sum(v.nbytes for v in views) > max_bytes:
        raise MessageError(topic, "size", f"exceeds the limit of {max_bytes} bytes")
    head = _load_header(topic, views[0])

    def summary(v: Any) -> Any:
        if isinstance(v, dict):
            if set(v) == {"buf", "dtype", "shape"}:
                return f"array {v['dtype']}{v['shape']}"
            return {k: summary(x) for k, x in v.items()}
        if isinstance(v, list):
            return [summary(x) for x in v[:16]] + (["…"] if len(v) > 16 else [])
        if isinstance(v, bytes):
            return f"<{len(v)} bytes>"
        return v

    head["fields"] = summary(head["fields"])
    return head
