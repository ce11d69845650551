"""MessagePack codec: a message becomes ``[header, *buffers]`` frames; arrays travel as raw buffer frames.

Wire (one ZeroMQ multipart message, the bus prepends the topic frame)::

    header  = msgpack [type: str, version: int, stamp_ns: int, seq: int, frame_id: str, *field values]
              # the values in the order the type declares its fields; an ndarray value is the descriptor
              # [buf: int, dtype: str, shape: [int, ...]] of buffer frame ``buf``
    buffers = the raw C-order bytes of each array, in "buf" order

The header is positional (an array, not a map): decoding it costs a quarter of a map with names, and the
names are in the declared type. Decoding validates everything and returns arrays as zero-copy, read-only
views of the received frames. Every problem raises :class:`MessageError` naming the topic, the field and what
was wrong. There is no pickle.

:func:`pack` / :func:`unpack` give the same message as one self-contained MessagePack map with names
(``{"type", "version", "stamp_ns", "seq", "frame_id", "fields": {name: value}}``, arrays inline as
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
from polarstripe.msgs.fields import Kind, _Array, _Dict, _List, _Optional

DEFAULT_MAX_BYTES = 128 * 2**20
"""Largest message (header plus buffers) a decoder accepts by default [bytes]."""

HEADER_ITEMS = ("type", "version", "stamp_ns", "seq", "frame_id")
"""The header array's leading items; the field values follow."""

_N_HEAD = len(HEADER_ITEMS)
_PACKED_KEYS = frozenset({*HEADER_ITEMS, "fields"})
_packb = msgpack.Packer(use_bin_type=True).pack
_unpackb = msgpack.unpackb


def encode(msg: Message, *, topic: str = "", seq: int | None = None, stamp_ns: int | None = None) -> list:
    """Encode ``msg`` to frames ``[header_bytes, *arrays]``.

    ``seq`` and ``stamp_ns`` override the message's header (the publisher stamps them); ``stamp_ns=None``
    keeps the header's stamp, or uses the current time when that is 0. Raises :class:`MessageError`
    (naming ``topic``) if a field value does not match its declared type.
    """
    cls = type(msg)
    codec = _COMPILED.get(cls)
    if codec is None:
        if not isinstance(msg, Message) or not cls.TYPE:
            raise MessageError(topic, "type", f"{cls.__name__} is not a declared message type")
        codec = _compile(cls)
    h = msg.header
    if stamp_ns is None:
        stamp_ns = h.stamp_ns or time.time_ns()
    bufs: list = []
    head = codec[0](msg.__dict__, bufs, topic, int(stamp_ns), int(h.seq if seq is None else seq), h.frame_id)
    return [_packb(head), *bufs]


_COMPILED: dict[type, tuple] = {}
_new = object.__new__
_set_header = tuple(Header.__dict__[k].__set__ for k in ("stamp_ns", "seq", "frame_id"))  # slot setters


def _compile(cls: type[Message]) -> tuple:
    """Per message type, :func:`encode`'s and :func:`decode`'s field loops unrolled into straight-line code
    generated from the declared fields: a value of the declared scalar type passes as it is, anything else
    goes through its kind, which checks it (and names the field in the error). The same checks as a loop
    over the fields, at a fraction of the interpreter's overhead; the decoder also builds the frozen message
    and its header directly (every value was checked)."""
    env: dict[str, Any] = {"MessageError": MessageError, "cls": cls, "new": _new, "Header": Header}
    env["set_stamp"], env["set_seq"], env["set_frame_id"] = _set_header
    enc = ["def enc(d, bufs, topic, stamp_ns, seq, frame_id):"]
    dec = ["def dec(h, bufs, topic):"]
    names = []
    for i, (name, kind, exact) in enumerate(cls.FAST_FIELDS):
        env[f"k{i}"], env[f"e{i}"] = kind, exact
        n = repr(name)
        names.append(name)
        enc += [
            f"    v{i} = d[{n}]",
            f"    if type(v{i}) is not e{i}:",
            "        try:",
            f"            v{i} = k{i}.enc(v{i}, bufs)",
            "        except ValueError as exc:",
            f"            raise MessageError(topic, {n}, str(exc)) from None",
        ]
        dec += [
            f"    v{i} = h[{_N_HEAD + i}]",
            f"    if type(v{i}) is not e{i}:",
            "        try:",
            f"            v{i} = k{i}.dec(v{i}, bufs)",
            "        except ValueError as exc:",
            f"            raise MessageError(topic, {n}, str(exc)) from None",
        ]
    values = "".join(f", v{i}" for i in range(len(names)))
    enc.append(f"    return [{cls.TYPE!r}, {cls.VERSION!r}, stamp_ns, seq, frame_id{values}]")
    dec += [
        "    hd = new(Header)",
        "    set_stamp(hd, h[2])",
        "    set_seq(hd, h[3])",
        "    set_frame_id(hd, h[4])",
        "    m = new(cls)",
        f"    m.__dict__.update(header=hd{''.join(f', {n}=v{i}' for i, n in enumerate(names))})",
        "    return m",
    ]
    exec("\n".join([*enc, *dec, ""]), env)  # noqa: S102  (generated from the declared field names)
    _COMPILED[cls] = (env["enc"], env["dec"])
    return _COMPILED[cls]


def _load_header(topic: str, raw: Any) -> list:
    try:
        head = _unpackb(raw)
    except Exception as exc:  # msgpack raises several unrelated classes for garbage
        why = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
        raise MessageError(topic, "header", f"not a MessagePack header ({why})") from None
    if type(head) is not list:
        raise MessageError(topic, "header", f"expected an array, got {type(head).__name__}")
    if len(head) < _N_HEAD:
        raise MessageError(
            topic, "header", f"expected [{', '.join(HEADER_ITEMS)}, *fields], got {len(head)} items"
        )
    return head


def _header_class(topic: str, head: list, expect: type[Message] | None) -> type[Message]:
    """The message class the header names, after checking type, version, stamp, seq and frame id."""
    tname, version, stamp_ns, seq, frame_id = head[:_N_HEAD]
    cls = REGISTRY.get(tname) if type(tname) is str else None
    if cls is None:
        raise MessageError(topic, "type", f"unknown message type {tname!r:.60}")
    if expect is not None and cls is not expect:
        raise MessageError(topic, "type", f"expected {expect.TYPE!r}, got {tname!r}")
    if type(version) is int and version in cls.OLDER and len(head) - _N_HEAD == cls.OLDER[version]:
        head.extend(cls.APPENDED[version])  # an older version: the fields it lacks take their defaults
    elif version != cls.VERSION:
        raise MessageError(
            topic,
            "version",
            f"unknown schema version {version!r:.20} of {tname!r} (this build reads version {cls.VERSION})",
        )
    if type(stamp_ns) is not int or type(seq) is not int or type(frame_id) is not str:
        for key, value, typ in (("stamp_ns", stamp_ns, int), ("seq", seq, int), ("frame_id", frame_id, str)):
            if type(value) is not typ:
                raise MessageError(topic, key, f"expected {typ.__name__}, got {type(value).__name__}")
    n, fields = len(head) - _N_HEAD, cls.FIELDS
    if n < len(fields):
        raise MessageError(topic, fields[n][0], f"missing (a {tname!r} needs it)")
    if n > len(fields):
        raise MessageError(topic, "fields", f"{n} values but {tname!r} has {len(fields)} fields")
    return cls


def _build(topic: str, head: list, bufs: list, expect: type[Message] | None) -> Message:
    """The message of a checked header; ``bufs`` (byte views) is consumed: arrays take their frames."""
    cls = _header_class(topic, head, expect)
    msg = (_COMPILED.get(cls) or _compile(cls))[1](head, bufs, topic)
    for b in bufs:
        if b is not None:
            used = sum(1 for b in bufs if b is None)
            raise MessageError(topic, "buffers", f"{len(bufs)} buffer frames but {used} used by fields")
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
    return decode_views(views[0], views[1:], topic=topic, expect=expect, max_bytes=max_bytes)


def decode_views(
    head: Any, bufs: list, *, topic: str = "", expect: type[Message] | None = None,
    max_bytes: int = DEFAULT_MAX_BYTES,
) -> Message:
    """:func:`decode` of a header (bytes or a byte view) and buffer frames already as flat byte views
    (``memoryview``, ``ndim == 1``, ``itemsize == 1``): the bus's receive path, without re-wrapping.
    ``bufs`` is consumed (each array takes its entry)."""
    total = len(head)
    for b in bufs:
        total += b.nbytes
    if total > max_bytes:
        raise MessageError(topic, "size", f"{total} bytes exceeds the limit of {max_bytes} bytes")
    return _build(topic, _load_header(topic, head), bufs, expect)


def _bytes_view(f: Any) -> memoryview:
    """A flat byte view of a frame (``zmq.Frame``, bytes, memoryview or a contiguous ndarray)."""
    if type(f) is bytes:
        return memoryview(f)
    v = f.buffer if isinstance(f, zmq.Frame) else memoryview(f)
    return v if v.ndim == 1 and v.itemsize == 1 else v.cast("B")


# ---- the self-contained form (MCAP payloads) -----------------------------------------------------------
def packed_fields(msg: Message, *, topic: str = "") -> tuple[list, list]:
    """``msg`` checked and split for the self-contained form: ``([type, version, stamp_ns, seq, frame_id],
    [(name, kind, wire value), …])`` and the array buffers the wire values' descriptors point into.
    Used by :func:`pack` and the MCAP writer, which inline each array as ``{dtype, shape, data}``."""
    frames = encode(msg, topic=topic)
    head = _unpackb(frames[0])
    fields = [(name, kind, head[_N_HEAD + i]) for i, (name, kind) in enumerate(type(msg).FIELDS)]
    return [head[:_N_HEAD], fields], frames[1:]


def pack(msg: Message, *, topic: str = "") -> bytes:
    """One self-contained MessagePack map: ``{type, version, stamp_ns, seq, frame_id, fields: {name:
    value}}`` with arrays inline as ``{dtype, shape, data}`` (the form :func:`~.schema.json_schema`
    describes)."""
    (head, fields), bufs = packed_fields(msg, topic=topic)
    out = dict(zip(HEADER_ITEMS, head, strict=True))
    out["fields"] = {name: inline(kind, v, bufs) for name, kind, v in fields}
    return _packb(out)


def inline(kind: Kind, v: Any, bufs: list) -> Any:
    """A wire value of ``kind`` with each array descriptor replaced by ``{dtype, shape, data: bytes}``."""
    if v is None:
        return None
    if isinstance(kind, _Optional):
        return inline(kind.inner, v, bufs)
    if isinstance(kind, _Array):
        return {"dtype": v[1], "shape": list(v[2]), "data": np.ascontiguousarray(bufs[v[0]]).tobytes()}
    if isinstance(kind, _Dict):
        return {k: inline(kind.inner, x, bufs) for k, x in v.items()}
    return v


def unpack(
    blob: bytes, *, topic: str = "", expect: type[Message] | None = None, max_bytes: int = DEFAULT_MAX_BYTES
) -> Message:
    """Inverse of :func:`pack`; validates like :func:`decode` (arrays are read-only views of ``blob``)."""
    if len(blob) > max_bytes:
        raise MessageError(topic, "size", f"{len(blob)} bytes exceeds the limit of {max_bytes} bytes")
    try:
        doc = _unpackb(blob, raw=False, strict_map_key=True)
    except Exception as exc:
        why = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
        raise MessageError(topic, "header", f"not a MessagePack map ({why})") from None
    if type(doc) is not dict:
        raise MessageError(topic, "header", f"expected a map, got {type(doc).__name__}")
    if doc.keys() != _PACKED_KEYS:
        missing = _PACKED_KEYS - doc.keys()
        if missing:
            raise MessageError(topic, sorted(missing)[0], "missing from the header")
        raise MessageError(topic, sorted(map(str, doc.keys() - _PACKED_KEYS))[0], "unknown header key")
    fields = doc["fields"]
    if type(fields) is not dict:
        raise MessageError(topic, "fields", f"expected a map, got {type(fields).__name__}")
    head = [doc[k] for k in HEADER_ITEMS]
    cls = REGISTRY.get(head[0]) if type(head[0]) is str else None
    bufs: list = []
    if cls is not None:
        version = head[1]
        n = cls.OLDER[version] if type(version) is int and version in cls.OLDER else len(cls.FIELDS)
        for name, _kind in cls.FIELDS[:n]:  # an older version lacks the trailing fields: _build adds them
            if name not in fields:
                raise MessageError(topic, name, f"missing (a {cls.TYPE!r} needs it)")
        names = cls.FIELD_NAMES if n == len(cls.FIELDS) else {name for name, _ in cls.FIELDS[:n]}
        extra = sorted(map(str, fields.keys() - names))
        if extra:
            raise MessageError(topic, extra[0], f"unknown field of {cls.TYPE!r}")
        head += [_outline(kind, fields[name], bufs) for name, kind in cls.FIELDS[:n]]
    return _build(topic, head, bufs, expect)


def _outline(kind: Kind, v: Any, bufs: list) -> Any:
    """Inverse of :func:`inline`: ``{dtype, shape, data}`` → a wire descriptor and a buffer (unchecked here:
    the field's kind checks the result)."""
    if isinstance(kind, _Optional) and v is not None:
        return _outline(kind.inner, v, bufs)
    if isinstance(kind, _Array) and isinstance(v, dict) and v.keys() == {"dtype", "shape", "data"}:
        if isinstance(v["data"], bytes):
            bufs.append(memoryview(v["data"]))
            return [len(bufs) - 1, v["dtype"], v["shape"]]
    if isinstance(kind, _Dict) and isinstance(v, dict):
        return {k: _outline(kind.inner, x, bufs) for k, x in v.items()}
    return v


def describe(frames: list, *, topic: str = "", max_bytes: int = DEFAULT_MAX_BYTES) -> dict:
    """A printable summary: header items, small fields, arrays as ``"array <u2[1024, 1280]"``.

    For tools such as ``topic echo``: it checks nothing but the header's shape. Field names come from the
    registered type; a type this process does not know shows its values by position (``"#0"``, ``"#1"``).
    Raises :class:`MessageError` for garbage.
    """
    views = [_bytes_view(f) for f in frames]
    if not views:
        raise MessageError(topic, "header", "empty message (no header frame)")
    if sum(v.nbytes for v in views) > max_bytes:
        raise MessageError(topic, "size", f"exceeds the limit of {max_bytes} bytes")
    head = _load_header(topic, views[0])
    out: dict[str, Any] = dict(zip(HEADER_ITEMS, head, strict=False))
    cls = REGISTRY.get(head[0]) if type(head[0]) is str else None
    values = head[_N_HEAD:]
    if cls is not None and len(values) == len(cls.FIELDS):
        out["fields"] = {name: _summary(kind, v) for (name, kind), v in zip(cls.FIELDS, values, strict=True)}
    else:
        out["fields"] = {f"#{i}": _summary(None, v) for i, v in enumerate(values)}
    return out


def _summary(kind: Kind | None, v: Any) -> Any:
    if isinstance(kind, _Optional):
        kind = kind.inner
    if isinstance(kind, _Array) and isinstance(v, list) and len(v) == 3:
        return f"array {v[1]}{list(v[2]) if isinstance(v[2], list | tuple) else v[2]}"
    inner = kind.inner if isinstance(kind, _Dict | _List) else None
    if isinstance(v, dict):
        return {k: _summary(inner, x) for k, x in v.items()}
    if isinstance(v, list):
        return [_summary(inner, x) for x in v[:16]] + (["…"] if len(v) > 16 else [])
    if isinstance(v, bytes):
        return f"<{len(v)} bytes>"
    return v
