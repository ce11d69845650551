"""Views (:mod:`polarstripe.nodes.rig_views`) as ROS 2 messages, written to a rosbag2 (MCAP storage, CDR)
with the ``rosbags`` library (pure Python, no ROS install; ``pip install 'polarstripe[ros2]'``).

=================  =========================================  ==========================================
view               ROS 2 type                                 topic
=================  =========================================  ==========================================
Image              ``sensor_msgs/msg/Image``                  as the view (``T/image``, ``T/<name>``)
Calibration        ``sensor_msgs/msg/CameraInfo``             ``T/camera_info`` (plumb_bob, D = 0)
Transforms         ``tf2_msgs/msg/TFMessage``                 ``/tf_static`` (QoS transient local)
LogLine            ``rcl_interfaces/msg/Log``                 ``/rosout`` (name = the node)
Joint              ``sensor_msgs/msg/JointState``             ``T/joint_states``
Record ``K``       ``polarstripe_msgs/msg/K`` (registered)    as the view
Packed             ``polarstripe_msgs/msg/Packed``            as the view (type, version, msgpack)
=================  =========================================  ==========================================

Image encodings: uint16 ``mono16``, uint8 ``mono8``, bool ``mono8`` (0/255), float32 ``32FC1``, float64
``64FC1``, int32 ``32SC1``, int16 ``16SC1``, h×w×3 uint8/uint16 ``rgb8``/``rgb16``; other dtypes as
``64FC1``. Pixels are little-endian and copied bit for bit. Stamps are the recording's log times.

The bag is written in rosbag2 format 8 (ROS 2 Jazzy's ``metadata.yaml``) with the Jazzy message
definitions. Its MCAP file is written by :class:`~polarstripe.runtime.bag.BagWriter` through a rosbags storage
plugin: an image's CDR is a few header bytes plus the pixels, which go from the recording's chunk to the
file without another copy (``rosbags``' own MCAP writer copies each message four times).
"""

from __future__ import annotations

import time
from functools import lru_cache
from pathlib import Path

import numpy as np
from mcap.data_stream import RecordBuilder
from mcap.records import Header as McapHeader
from polarstripe import __version__
from polarstripe.nodes.rig_views import (
    NESTED,
    RECORDS,
    Calibration,
    Image,
    Joint,
    LogLine,
    Packed,
    Record,
    Transforms,
)
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
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore
except ImportError as _exc:  # the optional extra
    _MISSING: ImportError | None = _exc
else:
    _MISSING = None

PACKAGE = "polarstripe_msgs"
ROSOUT = "/rosout"
_SCALARS = {"string": "string", "bool": "bool", "uint32": "uint32", "int64": "int64", "float64": "float64",
            "uint8": "uint8"}
_LEVELS = {"DEBUG": 10, "INFO": 20, "WARNING": 30, "ERROR": 40, "CRITICAL": 50}
_ENCODINGS = {("u", 2, 1): "mono16", ("u", 1, 1): "mono8", ("f", 4, 1): "32FC1", ("f", 8, 1): "64FC1",
              ("i", 4, 1): "32SC1", ("i", 2, 1): "16SC1", ("i", 1, 1): "8SC1", ("u", 1, 3): "rgb8",
              ("u", 2, 3): "rgb16", ("u", 1, 4): "rgba8", ("u", 2, 4): "rgba16"}


def require() -> None:
    """Raise :class:`BagError` if ``rosbags`` is not installed."""
    if _MISSING is not None:
        raise BagError(f"the ROS 2 export needs the package 'rosbags' (pip install 'polarstripe[ros2]'): "
                       f"{_MISSING}")


def msg_text(kind: str) -> str:
    """The ``.msg`` definition of record ``kind`` (:data:`~polarstripe.nodes.rig_views.RECORDS`)."""
    lines = [] if kind in NESTED else ["std_msgs/Header header"]
    for name, typ in RECORDS[kind]:
        base, arr = (typ[:-2], "[]") if typ.endswith("[]") else (typ, "")
        lines.append(f"{_SCALARS.get(base) or f'{PACKAGE}/{base}'}{arr} {name}")
    return "\n".join(lines) + "\n"


@lru_cache(maxsize=1)
def typestore():
    """ROS 2 Jazzy's message types plus ``polarstripe_msgs/msg/*`` (every record kind)."""
    require()
    store = get_typestore(Stores.ROS2_JAZZY)
    types: dict = {}
    for kind in RECORDS:
        types.update(get_types_from_msg(msg_text(kind), f"{PACKAGE}/msg/{kind}"))
    store.register(types)
    return store


def image_encoding(a: np.ndarray) -> tuple[str, np.ndarray]:
    """The ``sensor_msgs/Image`` encoding of an array and the little-endian C-order array to send."""
    if a.dtype == np.bool_:
        a = a.astype(np.uint8) * np.uint8(255)
    channels = a.shape[2] if a.ndim == 3 else 1
    enc = _ENCODINGS.get((a.dtype.kind, a.dtype.itemsize, channels))
    if enc is None:
        a, enc = a.astype(np.float64), "64FC1"
        if channels != 1:
            a = a[..., 0]
    a = a.astype(a.dtype.newbyteorder("<"), copy=False)
    return enc, np.ascontiguousarray(a)


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
        t = self.ts.types
        self._time, self._header = t["builtin_interfaces/msg/Time"], t["std_msgs/msg/Header"]
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
        self._cache: dict[tuple, bytes] = {}

    def _stamp(self, ns: int):
        return self._time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)

    def header(self, ns: int, frame_id: str):
        """A ``std_msgs/Header``."""
        return self._header(stamp=self._stamp(ns), frame_id=frame_id)

    def _put(self, topic: str, msgtype: str, stamp_ns: int, data) -> None:
        conn = self.connections.get(topic)
        if conn is None:
            qos = [_latched()] if topic.startswith("/tf_static") else []
            conn = self.connections[topic] = self.writer.add_connection(
                topic, msgtype, typestore=self.ts, offered_qos_profiles=qos)
        self.writer.write(conn, stamp_ns, data)
        self.counts[topic, msgtype] = self.counts.get((topic, msgtype), 0) + 1

    def _obj(self, topic: str, msgtype: str, stamp_ns: int, obj) -> None:
        self._put(topic, msgtype, stamp_ns, self.ts.serialize_cdr(obj, msgtype))

    def _stamped(self, key: tuple, stamp_ns: int, make) -> bytes:
        """The CDR of a message whose first field is a ``std_msgs/Header``, built once per ``key`` by
        ``make()`` and re-stamped: the stamp's sec (int32) and nanosec (uint32) follow the 4-byte CDR
        encapsulation header."""
        head = self._cache.get(key)
        if head is None:
            head = self._cache[key] = bytes(make())
        sec, nsec = divmod(stamp_ns, 1_000_000_000)
        return head[:4] + sec.to_bytes(4, "little", signed=True) + nsec.to_bytes(4, "little") + head[12:]

    def image(self, v: Image) -> list:
        """The CDR of a ``sensor_msgs/Image`` as buffers: a header, then the pixels without a copy."""
        enc, a = image_encoding(v.array)
        step = a.shape[1] * (a.shape[2] if a.ndim == 3 else 1) * a.dtype.itemsize
        key = ("image", v.frame_id, a.shape[0], a.shape[1], enc, step)

        def make():
            empty = self.ts.types["sensor_msgs/msg/Image"](
                header=self.header(0, v.frame_id), height=a.shape[0], width=a.shape[1], encoding=enc,
                is_bigendian=0, step=step, data=np.empty(0, np.uint8))
            return self.ts.serialize_cdr(empty, "sensor_msgs/msg/Image")

        head = self._stamped(key, v.stamp_ns, make)
        # serialized without pixels it ends with the data length, 0
        return [head[:-4] + a.nbytes.to_bytes(4, "little"), memoryview(a.reshape(-1).view(np.uint8))]

    def camera_info(self, v: Calibration) -> bytes:
        """The CDR of a ``sensor_msgs/CameraInfo`` (built once per frame id and intrinsics)."""
        t, i = self.ts.types, v.intrinsics

        def make():
            roi = t["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                        do_rectify=False)
            return self.ts.serialize_cdr(t["sensor_msgs/msg/CameraInfo"](
                header=self.header(0, v.frame_id), height=i.height, width=i.width,
                distortion_model="plumb_bob", d=np.zeros(5), k=np.array(i.k), r=np.eye(3).reshape(-1),
                p=np.array(i.p), binning_x=0, binning_y=0, roi=roi), "sensor_msgs/msg/CameraInfo")

        return self._stamped(("info", v.frame_id, i), v.stamp_ns, make)

    def record(self, kind: str, values: dict, header=None):
        """The ``polarstripe_msgs/msg/<kind>`` object of a record's values."""
        kw = {} if header is None else {"header": header}
        for name, typ in RECORDS[kind]:
            v = values[name]
            if typ == "uint8[]":
                v = np.frombuffer(bytes(v), np.uint8)
            elif typ == "float64[]":
                v = np.asarray(v, np.float64).reshape(-1)
            elif typ == "int64[]":
                v = np.asarray(v, np.int64).reshape(-1)
            elif typ == "string[]":
                v = [str(x) for x in v]
            elif typ.endswith("[]"):
                v = [self.record(typ[:-2], x) for x in v]
            else:
                v = {"string": str, "bool": bool, "float64": float}.get(typ, int)(v)
            kw[name] = v
        return self.ts.types[f"{PACKAGE}/msg/{kind}"](**kw)

    def write(self, v) -> None:
        """Write one view."""
        t = self.ts.types
        if isinstance(v, Image):
            self._put(v.topic, "sensor_msgs/msg/Image", v.stamp_ns, self.image(v))
        elif isinstance(v, Record):
            typ = f"{PACKAGE}/msg/{v.kind}"
            obj = self.record(v.kind, v.values, self.header(v.stamp_ns, ""))
            self._obj(v.topic, typ, v.stamp_ns, obj)
        elif isinstance(v, Calibration):
            self._put(v.topic, "sensor_msgs/msg/CameraInfo", v.stamp_ns, self.camera_info(v))
        elif isinstance(v, Joint):
            obj = t["sensor_msgs/msg/JointState"](
                header=self.header(v.stamp_ns, ""), name=list(v.names), position=np.array(v.positions, float),
                velocity=np.zeros(0), effort=np.zeros(0))
            self._obj(v.topic, "sensor_msgs/msg/JointState", v.stamp_ns, obj)
        elif isinstance(v, Transforms):
            vec, quat = t["geometry_msgs/msg/Vector3"], t["geometry_msgs/msg/Quaternion"]
            tfs = [t["geometry_msgs/msg/TransformStamped"](
                header=self.header(v.stamp_ns, p.parent), child_frame_id=p.child,
                transform=t["geometry_msgs/msg/Transform"](
                    translation=vec(x=p.translation[0], y=p.translation[1], z=p.translation[2]),
                    rotation=quat(x=p.rotation[0], y=p.rotation[1], z=p.rotation[2], w=p.rotation[3])))
                for p in v.poses]
            obj = t["tf2_msgs/msg/TFMessage"](transforms=tfs)
            self._obj(v.topic, "tf2_msgs/msg/TFMessage", v.stamp_ns, obj)
        elif isinstance(v, LogLine):
            obj = t["rcl_interfaces/msg/Log"](
                stamp=self._stamp(v.stamp_ns), level=_LEVELS.get(v.level, 20), name=v.node, msg=v.text,
                file="", function="", line=0)
            self._obj(ROSOUT, "rcl_interfaces/msg/Log", v.stamp_ns, obj)
        elif isinstance(v, Packed):
            obj = self.record("Packed", {"type": v.type, "version": v.version, "msgpack": v.payload},
                              self.header(v.stamp_ns, ""))
            self._obj(v.topic, f"{PACKAGE}/msg/Packed", v.stamp_ns, obj)

    def close(self) -> None:
        """Finish the MCAP file and write ``metadata.yaml``."""
        self.writer.close()

    def abort(self) -> None:
        """Stop without finishing (the caller removes the folder); rosbags' own ``Writer.abort`` is newer than
        0.11.0, so the storage is closed directly."""
        storage, self.writer.storage = self.writer.storage, None
        if storage is not None:
            storage.abort()
