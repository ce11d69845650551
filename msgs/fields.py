"""Field kinds: how each declared field type is checked, put on the wire, read back, and described as JSON
Schema. :func:`kind_of` maps an annotation to its kind; ``TypeError`` if the codec cannot carry it."""

from __future__ import annotations

import types
import typing
from typing import Any, Literal

import numpy as np

FIELD_TYPES = (
    "bool, int, float, str, bytes, numpy.ndarray, Literal['a', 'b'], X | None, list[X] for a scalar X, "
    "dict[str, X] for a scalar X, dict[str, numpy.ndarray], dict[str, Any] (MessagePack primitives only)"
)


# ----------------------------------------------------------------------------------------------------------
# Field kinds: each knows how to check a value, put it on the wire, read it back, and describe it as JSON
# Schema.
class Kind:
    """One field type. ``enc`` checks a Python value and returns its MessagePack form (arrays go to ``bufs``);
    ``dec`` checks a wire value and returns the Python value; both raise ``ValueError`` with the problem."""

    def enc(self, v: Any, bufs: list) -> Any:
        raise NotImplementedError

    def dec(self, v: Any, bufs: list) -> Any:
        raise NotImplementedError

    def schema(self) -> dict:
        raise NotImplementedError


def _tname(v: Any) -> str:
    return type(v).__name__


class _Bool(Kind):
    def enc(self, v, bufs):
        if isinstance(v, bool | np.bool_):
            return bool(v)
        raise ValueError(f"expected bool, got {_tname(v)} {v!r:.60}")

    def dec(self, v, bufs):
        if type(v) is bool:
            return v
        raise ValueError(f"expected bool, got {_tname(v)} {v!r:.60}")

    def schema(self):
        return {"type": "boolean"}


class _Int(Kind):
    def enc(self, v, bufs):
        if type(v) is int:
            return v
        if isinstance(v, int | np.integer) and not isinstance(v, bool):
            return int(v)
        raise ValueError(f"expected int, got {_tname(v)} {v!r:.60}")

    dec = enc

    def schema(self):
        return {"type": "integer"}


class _Float(Kind):
    def enc(self, v, bufs):
        if type(v) is float:
            return v
        if isinstance(v, int | float | np.integer | np.floating) and not isinstance(v, bool):
            return float(v)
        raise ValueError(f"expected float, got {_tname(v)} {v!r:.60}")

    dec = enc

    def schema(self):
        return {"type": "number"}


class _Str(Kind):
    def enc(self, v, bufs):
        if isinstance(v, str):
            return v
        raise ValueError(f"expected str, got {_tname(v)} {v!r:.60}")

    dec = enc

    def schema(self):
        return {"type": "string"}


class _Bytes(Kind):
    def enc(self, v, bufs):
        if isinstance(v, bytes):
            return v
        raise ValueError(f"expected bytes, got {_tname(v)}")

    dec = enc

    def schema(self):
        return {"type": "string", "contentEncoding": "base64"}


class _Literal(Kind):
    def __init__(self, choices: tuple[str, ...]):
        self.choices = choices

    def enc(self, v, bufs):
        if isinstance(v, str) and v in self.choices:
            return v
        raise ValueError(f"expected one of {', '.join(self.choices)}, got {v!r:.60}")

    dec = enc

    def schema(self):
        return {"enum": list(self.choices)}


class _Optional(Kind):
    def __init__(self, inner: Kind):
        self.inner = inner

    def enc(self, v, bufs):
        return None if v is None else self.inner.enc(v, bufs)

    def dec(self, v, bufs):
        return None if v is None else self.inner.dec(v, bufs)

    def schema(self):
        return {"anyOf": [self.inner.schema(), {"type": "null"}]}


class _List(Kind):
    def __init__(self, inner: Kind):
        self.inner = inner

    def enc(self, v, bufs):
        if not isinstance(v, list | tuple):
            raise ValueError(f"expected a list, got {_tname(v)}")
        return [self.inner.enc(x, bufs) for x in v]

    def dec(self, v, bufs):
        if not isinstance(v, list):
            raise ValueError(f"expected a list, got {_tname(v)}")
        return [self.inner.dec(x, bufs) for x in v]

    def schema(self):
        return {"type": "array", "items": self.inner.schema()}


class _Dict(Kind):
    def __init__(self, inner: Kind):
        self.inner = inner

    def enc(self, v, bufs):
        if not isinstance(v, dict):
            raise ValueError(f"expected a dict, got {_tname(v)}")
        out = {}
        for k, x in v.items():
            if not isinstance(k, str):
                raise ValueError(f"expected str keys, got {_tname(k)} {k!r:.40}")
            try:
                out[k] = self.inner.enc(x, bufs)
            except ValueError as exc:
                raise ValueError(f"key {k!r}: {exc}") from None
        return out

    def dec(self, v, bufs):
        if not isinstance(v, dict):
            raise ValueError(f"expected a map, got {_tname(v)}")
        out = {}
        for k, x in v.items():
            if not isinstance(k, str):
                raise ValueError(f"expected str keys, got {_tname(k)} {k!r:.40}")
            try:
                out[k] = self.inner.dec(x, bufs)
            except ValueError as exc:
                raise ValueError(f"key {k!r}: {exc}") from None
        return out

    def schema(self):
        return {"type": "object", "additionalProperties": self.inner.schema()}


_ARRAY_KINDS = (
    "biufc"  # bool, signed, unsigned, float, complex: plain numbers only (no object, void, strings)
)


_DTYPES: dict[str, np.dtype] = {}  # dtype.str -> dtype, of the dtypes that may travel
_DTYPE_STR: dict[np.dtype, str] = {}  # the reverse


def _dtype(text: Any) -> np.dtype:
    """A plain numeric dtype from its ``dtype.str``, cached; ``ValueError`` for anything else."""
    try:
        dt = np.dtype(text) if isinstance(text, str) else None
    except TypeError:
        dt = None
    if dt is None or dt.kind not in _ARRAY_KINDS or dt.hasobject:
        raise ValueError(f"bad dtype {text!r:.40}")
    if len(_DTYPES) < 64:
        _DTYPES[text] = dt
    return dt


class _Array(Kind):
    """An ndarray: on the wire a descriptor ``[buf, dtype, shape]`` (buffer frame index, ``dtype.str``, shape)
    plus raw frame ``buf``.

    Decoding takes ``bufs``, a list of flat byte ``memoryview``s it may change: each array replaces its
    frame by None, so a frame cannot be taken twice and the frames left over are stray."""

    def enc(self, v, bufs):
        if not isinstance(v, np.ndarray):
            raise ValueError(f"expected numpy.ndarray, got {_tname(v)}")
        dt = v.dtype
        code = _DTYPE_STR.get(dt)
        if code is None:
            if dt.kind not in _ARRAY_KINDS or dt.hasobject:
                raise ValueError(f"dtype {dt} cannot travel (plain numeric dtypes only)")
            code = dt.str
            if len(_DTYPE_STR) < 64:
                _DTYPE_STR[dt] = code
        if not v.flags.c_contiguous:
            v = np.ascontiguousarray(v)
        bufs.append(v)
        return [len(bufs) - 1, code, v.shape]

    def dec(self, v, bufs):
        if type(v) is not list or len(v) != 3:
            raise ValueError("expected an array descriptor [buf, dtype, shape]")
        i, dtype, shape = v
        if type(i) is not int or not 0 <= i < len(bufs):
            raise ValueError(f"buffer index {i!r:.20} out of range (message has {len(bufs)} buffers)")
        dt = _DTYPES.get(dtype) if type(dtype) is str else None
        if dt is None:
            dt = _dtype(dtype)
        if type(shape) is not list:
            raise ValueError(f"bad shape {shape!r:.60}")
        n = dt.itemsize
        for d in shape:
            if type(d) is not int or d < 0:
                raise ValueError(f"bad shape {shape!r:.60}")
            n *= d
        buf = bufs[i]
        if buf is None:
            raise ValueError(f"buffer {i} is taken by another array")
        bufs[i] = None  # taken: what is left over at the end are stray frames
        if n != buf.nbytes:
            raise ValueError(f"dtype {dt.str} shape {tuple(shape)} needs {n} bytes, buffer has {buf.nbytes}")
        buf = buf.toreadonly()  # a view of the received frame, never written into: the array is read-only
        return np.frombuffer(buf, dt) if len(shape) == 1 else np.ndarray(shape, dt, buffer=buf)

    def schema(self):
        return {
            "type": "object",
            "description": "ndarray: raw C-order bytes with dtype (numpy dtype.str) and shape",
            "properties": {
                "dtype": {"type": "string"},
                "shape": {"type": "array", "items": {"type": "integer", "minimum": 0}},
                "data": {"type": "string", "contentEncoding": "base64"},
            },
            "required": ["dtype", "shape", "data"],
        }


ArrayKind, DictKind, ListKind, OptionalKind = _Array, _Dict, _List, _Optional
"""The kinds a tool walking wire values needs to tell apart (e.g. the MCAP writer inlining arrays)."""

_MAX_DEPTH = 8


def _check_primitive(v: Any, depth: int = 0) -> Any:
    if v is None or isinstance(v, bool | int | float | str):
        return v
    if isinstance(v, np.integer | np.floating | np.bool_):
        return v.item()
    if depth >= _MAX_DEPTH:
        raise ValueError(f"nested deeper than {_MAX_DEPTH} levels")
    if isinstance(v, list | tuple):
        return [_check_primitive(x, depth + 1) for x in v]
    if isinstance(v, dict):
        out = {}
        for k, x in v.items():
            if not isinstance(k, str):
                raise ValueError(f"expected str keys, got {_tname(k)} {k!r:.40}")
            out[k] = _check_primitive(x, depth + 1)
        return out
    raise ValueError(f"{_tname(v)} is not a MessagePack primitive (None, bool, int, float, str, list, dict)")


class _Any(Kind):
    """A MessagePack primitive value (metrics, details): None, bool, int, float, str, lists and str-keyed
    maps."""

    def enc(self, v, bufs):
        return _check_primitive(v)

    dec = enc

    def schema(self):
        return {}


class _Never:
    """No value has this type: fields without a fast path always go through their kind."""


def exact_type(kind: Kind) -> type:
    """The wire type a value may have to be taken without further checks (decoding's fast path)."""
    for cls, typ in ((_Bool, bool), (_Int, int), (_Float, float), (_Str, str), (_Bytes, bytes)):
        if type(kind) is cls:
            return typ
    return type(None) if isinstance(kind, _Optional) else _Never


_SCALARS: dict[Any, Kind] = {bool: _Bool(), int: _Int(), float: _Float(), str: _Str(), bytes: _Bytes()}


def kind_of(tp: Any) -> Kind:
    """The :class:`Kind` for an annotation; ``TypeError`` if the codec cannot carry it."""
    if tp in _SCALARS:
        return _SCALARS[tp]
    if tp is np.ndarray:
        return _Array()
    if tp is Any:
        return _Any()
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin is Literal and all(isinstance(a, str) for a in args):
        return _Literal(tuple(args))
    if origin in (typing.Union, types.UnionType) and len(args) == 2 and type(None) in args:
        inner = args[0] if args[1] is type(None) else args[1]
        return _Optional(kind_of(inner))
    if origin is list and len(args) == 1:
        inner = kind_of(args[0])
        if isinstance(inner, _Array | _List | _Dict):
            raise TypeError(f"list[{args[0]}] is not supported")
        return _List(inner)
    if origin is dict and len(args) == 2 and args[0] is str:
        inner = kind_of(args[1])
        if isinstance(inner, _List | _Dict):
            raise TypeError(f"dict[str, {args[1]}] is not supported")
        return _Dict(inner)
    raise TypeError(f"unsupported field type {tp!r}")
