"""Views (:mod:`polarstripe.nodes.rig_views`) as ROS 2 messages in CDR, with the ``rosbags`` library (pure
Python, no ROS install; ``pip install 'polarstripe[ros2]'``): one mapping for the ROS 2 bag export
(:mod:`polarstripe.tools.export_ros2`) and the live ROS 2 bridge (:mod:`polarstripe.nodes.ros2_bridge`).

=================  =========================================  ==========================================
view               ROS 2 type                                 topic
=================  =========================================  ==========================================
Image              ``sensor_msgs/msg/Image``                  as the view (``T/image``, ``T/<name>``)
Calibration        ``sensor_msgs/msg/CameraInfo``             ``T/camera_info`` (plumb_bob, D = 0)
Transforms         ``tf2_msgs/msg/TFMessage``                 ``/tf_static`` (QoS transient local)
LogLine            ``rcl_interfaces/msg/Log``                 ``/rosout`` (name = the node)
Joint              ``sensor_msgs/msg/JointState``             ``T/joint_states``
Points             ``sensor_msgs/msg/PointCloud2``            ``T/points`` (x, y, z float32, dense)
Record ``K``       ``polarstripe_msgs/msg/K`` (registered)    as the view
Packed             ``polarstripe_msgs/msg/Packed``            as the view (type, version, msgpack)
=================  =========================================  ==========================================

Image encodings: uint16 ``mono16``, uint8 ``mono8``, bool ``mono8`` (0/255), float32 ``32FC1``, float64
``64FC1``, int32 ``32SC1``, int16 ``16SC1``, h×w×3 uint8/uint16 ``rgb8``/``rgb16``; other dtypes as
``64FC1``. Pixels are little-endian and copied bit for bit.

The ``polarstripe_msgs`` interface package is generated from :data:`~polarstripe.nodes.rig_views.RECORDS`
(:func:`msg_text`) and :data:`SERVICES` (:func:`srv_text`); ``polarstripe ros2 msgs -o DIR`` writes it and
``ros2/polarstripe_msgs/`` ships it. Type hashes (:func:`type_hash`) are REP-2016's RIHS01, computed by
``rosbags`` over the Jazzy definitions plus ours; a service's is that of its ``request_message``,
``response_message`` and ``event_message`` (``<Srv>_Event``: a ``service_msgs/ServiceEventInfo`` and at most
one request and one response), as ``rosidl`` computes it. ``ServiceEventInfo.client_gid`` is registered as
``uint8[16]``: ``rosidl`` maps the ``.msg`` type ``char`` to ``uint8`` before hashing, ``rosbags`` does not.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from polarstripe.nodes.rig_views import (
    NESTED,
    RECORDS,
    Calibration,
    Image,
    Joint,
    LogLine,
    Packed,
    Points,
    Record,
    Transforms,
)
from polarstripe.runtime.bag import BagError

try:
    from rosbags.interfaces import Nodetype
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore
except ImportError as _exc:  # the optional extra
    _MISSING: ImportError | None = _exc
else:
    _MISSING = None

PACKAGE = "polarstripe_msgs"
ROSOUT = "/rosout"
TF_MSG, IMAGE_MSG, INFO_MSG = "tf2_msgs/msg/TFMessage", "sensor_msgs/msg/Image", "sensor_msgs/msg/CameraInfo"
CLOUD_MSG = "sensor_msgs/msg/PointCloud2"
_EVENT_INFO = "service_msgs/msg/ServiceEventInfo"
_SCALARS = {"string": "string", "bool": "bool", "uint32": "uint32", "int64": "int64", "float64": "float64",
            "uint8": "uint8"}
_LEVELS = {"DEBUG": 10, "INFO": 20, "WARNING": 30, "ERROR": 40, "CRITICAL": 50}
_ENCODINGS = {("u", 2, 1): "mono16", ("u", 1, 1): "mono8", ("f", 4, 1): "32FC1", ("f", 8, 1): "64FC1",
              ("i", 4, 1): "32SC1", ("i", 2, 1): "16SC1", ("i", 1, 1): "8SC1", ("u", 1, 3): "rgb8",
              ("u", 2, 3): "rgb16", ("u", 1, 4): "rgba8", ("u", 2, 4): "rgba16"}

#: The rig's services as ROS 2 services: ROS 2 type -> (request fields, response fields), in .msg syntax.
#: Every response says whether the rig's service answered (``ok``) and why not (``detail``).
SERVICES: dict[str, tuple[str, str]] = {
    "StartScan": ("string method\nuint32 stripes\nfloat64[] analyzer_deg\nuint32 sheets\n",
                  f"bool ok\nstring detail\n{PACKAGE}/ScanEvent event\n"),
    "GetPlan": ("", f"bool ok\nstring detail\n{PACKAGE}/Plan plan\n"),
}


def require() -> None:
    """Raise :class:`BagError` if ``rosbags`` is not installed."""
    if _MISSING is not None:
        raise BagError(f"ROS 2 messages need the package 'rosbags' (pip install 'polarstripe[ros2]'): "
                       f"{_MISSING}")


def msg_text(kind: str) -> str:
    """The ``.msg`` definition of record ``kind`` (:data:`~polarstripe.nodes.rig_views.RECORDS`)."""
    lines = [] if kind in NESTED else ["std_msgs/Header header"]
    for name, typ in RECORDS[kind]:
        base, arr = (typ[:-2], "[]") if typ.endswith("[]") else (typ, "")
        lines.append(f"{_SCALARS.get(base) or f'{PACKAGE}/{base}'}{arr} {name}")
    return "\n".join(lines) + "\n"


def srv_text(name: str) -> str:
    """The ``.srv`` definition of service ``name`` (:data:`SERVICES`)."""
    request, response = SERVICES[name]
    return f"{request}---\n{response}"


def _fields(text: str) -> tuple:
    """rosbags' field definitions of ``.msg`` text."""
    return next(iter(get_types_from_msg(text, f"{PACKAGE}/msg/Fields").values()))


def service_fielddefs(srv: str, request: str, response: str) -> dict:
    """rosbags' field definitions of service ``srv`` (``pkg/srv/Name``) and of its request, response and
    event types, from the request's and response's ``.msg`` text: the structure ``rosidl`` hashes."""
    req, resp, event = f"{srv}_Request", f"{srv}_Response", f"{srv}_Event"
    return {
        req: _fields(request),
        resp: _fields(response),
        event: ([], [("info", (Nodetype.NAME, _EVENT_INFO)),
                     ("request", (Nodetype.SEQUENCE, ((Nodetype.NAME, req), 1))),
                     ("response", (Nodetype.SEQUENCE, ((Nodetype.NAME, resp), 1)))]),
        srv: ([], [("request_message", (Nodetype.NAME, req)), ("response_message", (Nodetype.NAME, resp)),
                   ("event_message", (Nodetype.NAME, event))]),
    }


def make_typestore(services: dict[str, tuple[str, str]] | None = None):
    """A typestore of ROS 2 Jazzy's message types, ``polarstripe_msgs/msg/*`` (every record kind) and the
    services ``{pkg/srv/Name: (request, response)}`` (default: ``polarstripe_msgs/srv/*`` of
    :data:`SERVICES`)."""
    require()
    jazzy = get_typestore(Stores.ROS2_JAZZY)
    store = get_typestore(Stores.EMPTY)
    consts, fields = jazzy.fielddefs[_EVENT_INFO]
    u8x16 = (Nodetype.ARRAY, ((Nodetype.BASE, ("uint8", 0)), 16))
    types = {k: v for k, v in jazzy.fielddefs.items() if k != _EVENT_INFO}
    types[_EVENT_INFO] = (consts, [(n, u8x16 if n == "client_gid" else t) for n, t in fields])
    for kind in RECORDS:
        types.update(get_types_from_msg(msg_text(kind), f"{PACKAGE}/msg/{kind}"))
    if services is None:
        services = {f"{PACKAGE}/srv/{name}": texts for name, texts in SERVICES.items()}
    for srv, (request, response) in services.items():
        types.update(service_fielddefs(srv, request, response))
    store.register(types)
    return store


@lru_cache(maxsize=1)
def typestore():
    """:func:`make_typestore` of the package's own types (made once)."""
    return make_typestore()


def type_hash(typename: str) -> str:
    """The RIHS01 hash of a message or service type (``sensor_msgs/msg/Image``,
    ``polarstripe_msgs/srv/…``)."""
    return typestore().hash_rihs01(typename)


_GENERATED = "# Generated from polarstripe ({what}) by `polarstripe ros2 msgs`; do not edit.\n"


def interface_package(version: str) -> dict[str, str]:
    """The ROS 2 interface package ``polarstripe_msgs`` as {relative path: text}: ``msg/<Kind>.msg`` per
    record kind, ``srv/<Name>.srv`` per service, ``package.xml`` and ``CMakeLists.txt`` (``colcon build``
    it in a ROS 2 workspace; ``version``: the package's version, polarstripe's)."""
    files = {f"msg/{k}.msg": _GENERATED.format(what="nodes/rig_views.py RECORDS") + msg_text(k)
             for k in RECORDS}
    files.update({f"srv/{n}.srv": _GENERATED.format(what="nodes/ros2_schemas.py SERVICES") + srv_text(n)
                  for n in SERVICES})
    interfaces = "\n".join(f'  "{path}"' for path in sorted(files))
    files["CMakeLists.txt"] = (
        "# Generated by `polarstripe ros2 msgs`; do not edit.\n"
        f"cmake_minimum_required(VERSION 3.8)\nproject({PACKAGE})\n\n"
        "find_package(ament_cmake REQUIRED)\nfind_package(rosidl_default_generators REQUIRED)\n"
        "find_package(std_msgs REQUIRED)\n\n"
        f"rosidl_generate_interfaces(${{PROJECT_NAME}}\n{interfaces}\n  DEPENDENCIES std_msgs\n)\n\n"
        "ament_export_dependencies(rosidl_default_runtime)\nament_package()\n")
    files["package.xml"] = (
        '<?xml version="1.0"?>\n<!-- Generated by `polarstripe ros2 msgs`; do not edit. -->\n'
        '<package format="3">\n'
        f"  <name>{PACKAGE}</name>\n  <version>{version}</version>\n"
        "  <description>The messages and services of polarstripe (polarized light striping) for ROS 2"
        "</description>\n  <maintainer email=\"polarstripe@example.org\">polarstripe</maintainer>\n"
        "  <license>MIT</license>\n\n"
        "  <buildtool_depend>ament_cmake</buildtool_depend>\n"
        "  <buildtool_depend>rosidl_default_generators</buildtool_depend>\n"
        "  <depend>std_msgs</depend>\n  <exec_depend>rosidl_default_runtime</exec_depend>\n"
        "  <member_of_group>rosidl_interface_packages</member_of_group>\n\n"
        "  <export>\n    <build_type>ament_cmake</build_type>\n  </export>\n</package>\n")
    return files


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


@dataclass(frozen=True)
class Encoded:
    """One view as a ROS 2 message: topic, type, stamp [ns] and its CDR as buffers (joined: the message)."""

    topic: str
    msgtype: str
    stamp_ns: int
    parts: list


class Ros2Encoder:
    """Views to CDR (module docstring). Messages whose header is all that changes are serialized once per
    frame id and shape, then re-stamped."""

    def __init__(self):
        require()
        self.ts = typestore()
        t = self.ts.types
        self._time, self._header = t["builtin_interfaces/msg/Time"], t["std_msgs/msg/Header"]
        self._cache: dict[tuple, bytes] = {}

    def stamp(self, ns: int):
        """A ``builtin_interfaces/Time``."""
        return self._time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)

    def header(self, ns: int, frame_id: str):
        """A ``std_msgs/Header``."""
        return self._header(stamp=self.stamp(ns), frame_id=frame_id)

    def cdr(self, obj, msgtype: str) -> bytes:
        """The CDR of a rosbags message object."""
        return bytes(self.ts.serialize_cdr(obj, msgtype))

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
            empty = self.ts.types[IMAGE_MSG](
                header=self.header(0, v.frame_id), height=a.shape[0], width=a.shape[1], encoding=enc,
                is_bigendian=0, step=step, data=np.empty(0, np.uint8))
            return self.ts.serialize_cdr(empty, IMAGE_MSG)

        head = self._stamped(key, v.stamp_ns, make)
        # serialized without pixels it ends with the data length, 0
        return [head[:-4] + a.nbytes.to_bytes(4, "little"), memoryview(a.reshape(-1).view(np.uint8))]

    def camera_info(self, v: Calibration) -> bytes:
        """The CDR of a ``sensor_msgs/CameraInfo`` (built once per frame id and intrinsics)."""
        t, i = self.ts.types, v.intrinsics

        def make():
            roi = t["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                        do_rectify=False)
            return self.ts.serialize_cdr(t[INFO_MSG](
                header=self.header(0, v.frame_id), height=i.height, width=i.width,
                distortion_model="plumb_bob", d=np.zeros(5), k=np.array(i.k), r=np.eye(3).reshape(-1),
                p=np.array(i.p), binning_x=0, binning_y=0, roi=roi), INFO_MSG)

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

    def encode(self, v) -> Encoded:
        """One view as a ROS 2 message."""
        t = self.ts.types
        if isinstance(v, Image):
            return Encoded(v.topic, IMAGE_MSG, v.stamp_ns, self.image(v))
        if isinstance(v, Calibration):
            return Encoded(v.topic, INFO_MSG, v.stamp_ns, [self.camera_info(v)])
        if isinstance(v, Record):
            typ = f"{PACKAGE}/msg/{v.kind}"
            obj = self.record(v.kind, v.values, self.header(v.stamp_ns, ""))
            return Encoded(v.topic, typ, v.stamp_ns, [self.cdr(obj, typ)])
        if isinstance(v, Joint):
            obj = t["sensor_msgs/msg/JointState"](
                header=self.header(v.stamp_ns, ""), name=list(v.names), position=np.array(v.positions, float),
                velocity=np.zeros(0), effort=np.zeros(0))
            return Encoded(v.topic, "sensor_msgs/msg/JointState", v.stamp_ns,
                           [self.cdr(obj, "sensor_msgs/msg/JointState")])
        if isinstance(v, Points):
            xyz = np.ascontiguousarray(v.points, dtype="<f4")
            field = t["sensor_msgs/msg/PointField"]
            obj = t[CLOUD_MSG](
                header=self.header(v.stamp_ns, v.frame_id), height=1, width=len(xyz),
                fields=[field(name=n, offset=4 * k, datatype=field.FLOAT32, count=1)
                        for k, n in enumerate("xyz")],
                is_bigendian=False, point_step=12, row_step=12 * len(xyz),
                data=xyz.reshape(-1).view(np.uint8), is_dense=True)
            return Encoded(v.topic, CLOUD_MSG, v.stamp_ns, [self.cdr(obj, CLOUD_MSG)])
        if isinstance(v, Transforms):
            vec, quat = t["geometry_msgs/msg/Vector3"], t["geometry_msgs/msg/Quaternion"]
            tfs = [t["geometry_msgs/msg/TransformStamped"](
                header=self.header(v.stamp_ns, p.parent), child_frame_id=p.child,
                transform=t["geometry_msgs/msg/Transform"](
                    translation=vec(x=p.translation[0], y=p.translation[1], z=p.translation[2]),
                    rotation=quat(x=p.rotation[0], y=p.rotation[1], z=p.rotation[2], w=p.rotation[3])))
                for p in v.poses]
            return Encoded(v.topic, TF_MSG, v.stamp_ns, [self.cdr(t[TF_MSG](transforms=tfs), TF_MSG)])
        if isinstance(v, LogLine):
            obj = t["rcl_interfaces/msg/Log"](
                stamp=self.stamp(v.stamp_ns), level=_LEVELS.get(v.level, 20), name=v.node, msg=v.text,
                file="", function="", line=0)
            return Encoded(ROSOUT, "rcl_interfaces/msg/Log", v.stamp_ns,
                           [self.cdr(obj, "rcl_interfaces/msg/Log")])
        if isinstance(v, Packed):
            obj = self.record("Packed", {"type": v.type, "version": v.version, "msgpack": v.payload},
                              self.header(v.stamp_ns, ""))
            return Encoded(v.topic, f"{PACKAGE}/msg/Packed", v.stamp_ns,
                           [self.cdr(obj, f"{PACKAGE}/msg/Packed")])
        raise TypeError(f"not a view: {type(v).__name__}")
