"""Views (:mod:`polarstripe.nodes.rig_views`) in the schemas the Foxglove app decodes: one encoder for the
live bridge (:mod:`polarstripe.nodes.foxglove_bridge`) and the MCAP export
(:mod:`polarstripe.tools.export_foxglove`), so both show the same channels.

=============  =================================  ========================================================
view           schema (encoding)                  notes
=============  =================================  ========================================================
Image          ``foxglove.RawImage`` (protobuf)   uint16 ``mono16``, uint8 ``mono8``, bool ``mono8``
                                                  (0/255), h×w×3 uint8 ``rgb8``, anything else ``32FC1``
Calibration    ``foxglove.CameraCalibration``     plumb_bob, no distortion
Transforms     ``foxglove.FrameTransforms``       ``/tf_static``
LogLine        ``foxglove.Log``                   name = the node
Record ``K``   ``polarstripe.K`` (JSON Schema)    JSON; NaN (no value) as null; plottable numbers
Packed         ``polarstripe.<type>`` (JSON)      its ``fields``; arrays of more than 4096
                                                  values as ``{dtype, shape}`` only
Joint          (not sent)                         the PolarizerState record has ``angle_deg``
=============  =================================  ========================================================

The well-known schemas and the encoding of the small messages come from ``foxglove-sdk``
(``pip install 'polarstripe[foxglove]'``). A ``RawImage`` is encoded here as the SDK's encoding of the image
without its pixels plus the ``data`` field (protobuf field 6), so the pixels are never copied into a new
buffer; :func:`encode` returns a list of buffers.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass

import numpy as np
from polarstripe.nodes.rig_views import (
    NESTED,
    RECORDS,
    Calibration,
    Image,
    LogLine,
    Packed,
    Points,
    Record,
    Transforms,
)
from polarstripe.runtime.bag import BagError

try:
    from foxglove import messages as fm
except ImportError as _exc:  # the optional extra
    _MISSING: ImportError | None = _exc
else:
    _MISSING = None

_LEVELS = {"DEBUG": "Debug", "INFO": "Info", "WARNING": "Warning", "ERROR": "Error", "CRITICAL": "Fatal"}
_JSON_TYPES = {"string": {"type": "string"}, "bool": {"type": "boolean"}, "uint32": {"type": "integer"},
               "int64": {"type": "integer"}, "float64": {"type": ["number", "null"]}}
_MAX_INLINE = 4096  # array elements a packed message's JSON carries inline


def require() -> None:
    """Raise :class:`BagError` if ``foxglove-sdk`` is not installed."""
    if _MISSING is not None:
        raise BagError("Foxglove output needs the package 'foxglove-sdk' "
                       f"(pip install 'polarstripe[foxglove]'): {_MISSING}")


@dataclass(frozen=True)
class SchemaSpec:
    """An MCAP / Foxglove WebSocket schema and the channel's message encoding."""

    name: str
    encoding: str
    data: bytes
    message_encoding: str


@dataclass(frozen=True)
class Encoded:
    """One message for a channel: topic, schema and the payload as buffers."""

    topic: str
    schema: SchemaSpec
    parts: list


def _sdk_schema(cls) -> SchemaSpec:
    s = cls.get_schema()
    return SchemaSpec(s.name, s.encoding, bytes(s.data), "protobuf")


def record_schema(kind: str) -> dict:
    """The JSON Schema of record ``kind`` (:data:`~polarstripe.nodes.rig_views.RECORDS`)."""
    props = {}
    for name, typ in RECORDS[kind]:
        base = typ[:-2] if typ.endswith("[]") else typ
        item = record_schema(base) if base in NESTED else _JSON_TYPES.get(base, {"type": "integer"})
        props[name] = {"type": "array", "items": item} if typ.endswith("[]") else item
    if kind not in NESTED:
        props = {"stamp_ns": {"type": "integer"}, **props}
    return {"$schema": "https://json-schema.org/draft/2020-12/schema", "title": f"polarstripe.{kind}",
            "type": "object", "properties": props}


def _clean(v):
    """JSON-safe values: NaN and infinities as None, numpy scalars as Python numbers."""
    if isinstance(v, float | np.floating):
        return float(v) if math.isfinite(v) else None
    if isinstance(v, np.integer | np.bool_):
        return v.item()
    if isinstance(v, dict):
        return {str(k): _clean(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [_clean(x) for x in v]
    if isinstance(v, np.ndarray):
        if v.size > _MAX_INLINE:
            return {"dtype": v.dtype.str, "shape": list(v.shape)}
        return _clean(v.tolist())
    if isinstance(v, bytes | bytearray | memoryview):
        return {"bytes": len(v)}
    return v


def _varint(n: int) -> bytes:
    out = bytearray()
    while True:
        b, n = n & 0x7F, n >> 7
        out.append(b | (0x80 if n else 0))
        if not n:
            return bytes(out)


def image_encoding(a: np.ndarray) -> tuple[str, np.ndarray]:
    """The ``foxglove.RawImage`` encoding of an array and the C-order little-endian array to send."""
    if a.dtype == np.bool_:
        return "mono8", a.astype(np.uint8) * np.uint8(255)
    if a.ndim == 3:
        if a.dtype == np.uint8 and a.shape[2] == 3:
            return "rgb8", np.ascontiguousarray(a)
        a = a[..., 0]
    if a.dtype == np.uint16:
        return "mono16", np.ascontiguousarray(a, dtype="<u2")
    if a.dtype == np.uint8:
        return "mono8", np.ascontiguousarray(a)
    return "32FC1", np.ascontiguousarray(a, dtype="<f4")


class FoxgloveEncoder:
    """Encodes views for Foxglove (module docstring); schemas are built once."""

    def __init__(self):
        require()
        self._schemas: dict[str, SchemaSpec] = {}

    def schema(self, key: str) -> SchemaSpec:
        """The schema of a well-known type (``"RawImage"`` …), a record (``"record:FrameInfo"``) or a packed
        message type (``"packed:heartbeat"``)."""
        s = self._schemas.get(key)
        if s is None:
            kind, _, name = key.partition(":")
            if kind == "record":
                data = json.dumps(record_schema(name)).encode()
                s = SchemaSpec(f"polarstripe.{name}", "jsonschema", data, "json")
            elif kind == "packed":
                data = json.dumps({"title": f"polarstripe.{name}", "type": "object"}).encode()
                s = SchemaSpec(f"polarstripe.{name}", "jsonschema", data, "json")
            else:
                s = _sdk_schema(getattr(fm, key))
            self._schemas[key] = s
        return s

    @staticmethod
    def _ts(ns: int):
        return fm.Timestamp(sec=ns // 1_000_000_000, nsec=ns % 1_000_000_000)

    def image(self, v: Image) -> list:
        """A ``foxglove.RawImage`` as buffers: the SDK's encoding without pixels, then field 6 (data)."""
        enc, a = image_encoding(v.array)
        row = a.shape[1] * (a.shape[2] if a.ndim == 3 else 1) * a.dtype.itemsize
        head = fm.RawImage(timestamp=self._ts(v.stamp_ns), frame_id=v.frame_id, width=a.shape[1],
                           height=a.shape[0], encoding=enc, step=row).encode()
        data = memoryview(a.reshape(-1).view(np.uint8))
        return [head + b"\x32" + _varint(data.nbytes), data]

    def encode(self, v) -> Encoded | None:
        """The Foxglove message of a view (None for a view Foxglove gets otherwise: a joint)."""
        if isinstance(v, Image):
            return Encoded(v.topic, self.schema("RawImage"), self.image(v))
        if isinstance(v, Record):
            body = {"stamp_ns": v.stamp_ns, **_clean(v.values)}
            return Encoded(v.topic, self.schema(f"record:{v.kind}"), [json.dumps(body).encode()])
        if isinstance(v, Calibration):
            i = v.intrinsics
            m = fm.CameraCalibration(timestamp=self._ts(v.stamp_ns), frame_id=v.frame_id, width=i.width,
                                     height=i.height, distortion_model="plumb_bob", D=[0.0] * 5, K=i.k,
                                     R=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0], P=i.p)
            return Encoded(v.topic, self.schema("CameraCalibration"), [m.encode()])
        if isinstance(v, Transforms):
            tfs = [fm.FrameTransform(timestamp=self._ts(v.stamp_ns), parent_frame_id=p.parent,
                                     child_frame_id=p.child,
                                     translation=fm.Vector3(**dict(zip("xyz", p.translation, strict=True))),
                                     rotation=fm.Quaternion(**dict(zip("xyzw", p.rotation, strict=True))))
                   for p in v.poses]
            data = fm.FrameTransforms(transforms=tfs).encode()
            return Encoded(v.topic, self.schema("FrameTransforms"), [data])
        if isinstance(v, LogLine):
            level = getattr(fm.LogLevel, _LEVELS.get(v.level, "Info"))
            m = fm.Log(timestamp=self._ts(v.stamp_ns), level=level, message=v.text, name=v.node)
            return Encoded(v.topic, self.schema("Log"), [m.encode()])
        if isinstance(v, Points):
            xyz = np.ascontiguousarray(v.points, dtype="<f4")
            f32 = fm.PackedElementFieldNumericType.Float32
            m = fm.PointCloud(timestamp=self._ts(v.stamp_ns), frame_id=v.frame_id,
                              pose=fm.Pose(position=fm.Vector3(x=0.0, y=0.0, z=0.0),
                                           orientation=fm.Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)),
                              point_stride=12, fields=[fm.PackedElementField(name=n, offset=4 * k, type=f32)
                                                       for k, n in enumerate("xyz")], data=xyz.tobytes())
            return Encoded(v.topic, self.schema("PointCloud"), [m.encode()])
        if isinstance(v, Packed):
            body = {"type": v.type, "version": v.version, "stamp_ns": v.stamp_ns}
            if v.msg is not None:
                body.update(seq=v.msg.header.seq, frame_id=v.msg.header.frame_id,
                            fields=_clean({k: getattr(v.msg, k) for k, _ in v.msg.FIELDS}))
            return Encoded(v.topic, self.schema(f"packed:{v.type}"), [json.dumps(body).encode()])
        return None
