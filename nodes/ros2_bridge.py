"""ROS 2, live: a node that speaks ROS 2's Zenoh middleware (``rmw_zenoh_cpp``) so that a ROS 2 machine with
``RMW_IMPLEMENTATION=rmw_zenoh_cpp`` sees the rig (``ros2 topic list``/``echo``, rviz2, ``ros2 service
call``) without rclpy here. Needs the optional extra ``ros2`` (``pip install 'polarstripe[ros2]'``:
``eclipse-zenoh`` and ``rosbags``). ``launch/sim.toml`` and ``launch/rov.toml`` have it behind ``ros2=true``::

    [[node]]
    name = "ros2"
    module = "polarstripe.nodes.ros2_bridge:Ros2Bridge"
    params = { endpoint = "tcp/127.0.0.1:7447", domain = 0 }   # the router: ros2 run rmw_zenoh_cpp rmw_zenohd

The bridge is a Zenoh client of the ROS 2 router at ``endpoint`` (the formats: :mod:`polarstripe.nodes.
ros2_zenoh`). It declares a ROS 2 node (``ros_node`` in the launch namespace) and forwards the chosen topics
(default: every topic of the launch; camera frames and projector patterns newest-only) as the views of
:mod:`polarstripe.nodes.rig_views` in the ROS 2 types of :mod:`polarstripe.nodes.ros2_schemas` (the bag
export's topics and types): ``T/image`` (``sensor_msgs/Image``) and ``T/camera_info`` of frames, each
composite image, ``/tf_static`` (sent again every second: late subscribers get it within one), ``/rosout``,
``polarstripe_msgs/*``. Each publisher is announced by a liveliness token when its first message goes out.
The rig's services ``emitter/start_scan`` and ``planner/plan`` are ROS 2 services of types
``polarstripe_msgs/srv/StartScan`` and ``GetPlan`` under the same names; a request is answered from the
node's loop (the loop waits for the rig's reply: a plan may take seconds, frames wait meanwhile).

At start it reads the router's Zenoh version (its admin space) and refuses, in one line, one whose
major.minor differs from this ``eclipse-zenoh``'s (docs/ros2.md, "Versions").
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path

from polarstripe.msgs import (
    Empty,
    Message,
    MessageError,
    Plan,
    ScanEvent,
    ScanRequest,
)
from polarstripe.nodes.rig_geometry import geometry_from_metadata
from polarstripe.nodes.rig_views import RECORDS, TF_STATIC, Record, RigViews, ViewGate, subscribe_bridged
from polarstripe.nodes.ros2_schemas import PACKAGE, Ros2Encoder, type_hash
from polarstripe.nodes.ros2_zenoh import (
    PUBLISHER,
    SERVICE,
    TRANSIENT_LOCAL,
    Entity,
    Ros2FormatError,
    attachment,
    check_domain,
    check_node_name,
    data_key,
    parse_attachment,
    qos_key,
    session_config,
    version_mismatch,
)
from polarstripe.runtime.auth import KeyFileError, check_private
from polarstripe.runtime.bag import BagError
from polarstripe.runtime.bus import BusError
from polarstripe.runtime.graph import resolve
from polarstripe.runtime.node import Node, NodeError
from polarstripe.runtime.params import NodeParams
from polarstripe.sim.scene import SceneError

#: rig service -> (ROS 2 service type, request type, reply type, timeout [s])
RIG_SERVICES = {
    "emitter/start_scan": ("StartScan", ScanRequest, ScanEvent, 5.0),
    "planner/plan": ("GetPlan", Empty, Plan, 60.0),
}
_BLANK = {"string": "", "bool": False}


@dataclass
class _Pub:
    publisher: object
    gid: bytes
    token: object
    sequence: int = 0


class Ros2Bridge(Node):
    """Shows the rig to ROS 2 over rmw_zenoh (see the module docstring)."""

    class Params(NodeParams):
        endpoint: str = "tcp/127.0.0.1:7447"  # the ROS 2 Zenoh router: tcp/HOST:PORT or tls/HOST:PORT
        domain: int = 0  # ROS_DOMAIN_ID
        ros_node: str = "polarstripe"  # the ROS 2 node's name (in the launch namespace)
        topics: list[str] = []  # full or relative; empty: every topic of the graph
        images: bool = True  # send images (frames, patterns, composites)
        image_max_hz: float = 0.0  # images per topic and second at most; 0: every one
        services: bool = True  # the rig's services as ROS 2 services
        scene: str = ""  # the rig's scene TOML for tf and camera info; "": the launch's
        connect_timeout_s: float = 5.0  # the router must answer within this
        tls_ca: str = ""  # tls/ endpoints: the CA that signed the router's and this host's certificates
        tls_cert: str = ""  # … this host's certificate (PEM)
        tls_key: str = ""  # … and its private key (PEM)

    def setup(self):
        try:
            import zenoh

            self.encoder = Ros2Encoder()
        except (ImportError, BagError):
            raise NodeError(f"node {self.name!r}: needs the optional extra 'ros2' "
                            "(pip install 'polarstripe[ros2]')") from None
        p = self.params
        try:
            check_domain(p.domain), check_node_name(p.ros_node)
            config = session_config(p.endpoint, tls_ca=p.tls_ca, tls_cert=p.tls_cert, tls_key=p.tls_key)
        except Ros2FormatError as exc:
            raise NodeError(f"node {self.name!r}: {exc}") from None
        if p.endpoint.startswith("tls/"):
            self._check_tls_files()
        graph = self.graph
        meta = {"launch": {"graph": json.dumps(graph), "file": graph.get("file", "")}}
        try:
            geometry, note = geometry_from_metadata(meta, p.scene or None)
        except (SceneError, OSError) as exc:
            raise NodeError(f"node {self.name!r}: scene: {exc}") from None
        config["connect/timeout_ms"] = json.dumps(int(p.connect_timeout_s * 1000))
        zconf = zenoh.Config()
        try:
            for key, value in config.items():
                zconf.insert_json5(key, value)
            self.session = zenoh.open(zconf)
        except zenoh.ZError as exc:
            why = str(exc).split(" at /")[0]  # zenoh appends its source location
            raise NodeError(f"node {self.name!r}: ROS 2 router {p.endpoint}: {why}") from None
        self._check_version()
        self.entity = Entity(p.domain, str(self.session.info.zid()), 0, self.namespace or "/", p.ros_node)
        self.node_token = self.session.liveliness().declare_token(self.entity.node_token())
        self._next_id = 1
        self.pubs: dict[tuple[str, str], _Pub] = {}
        self.queryables: list[tuple[str, object, object, object]] = []
        self.views = RigViews(geometry)
        self.gate = ViewGate(self.views.start(time.time_ns()), self.params.images, self.params.image_max_hz)
        self._send(self.gate.static)
        self.every(1.0, self._resend_static)
        known = graph.get("topics", {})
        self.topics = subscribe_bridged(self, [resolve(t, self.namespace) for t in p.topics] or sorted(known),
                                        known, self.forward, "bridging")
        if p.services:
            served = graph.get("services", {})
            for service, spec in RIG_SERVICES.items():
                if not graph or self.resolve(service) in served:
                    self._declare_service(service, *spec)
            self.every(0.02, self.answer_requests)
        self.log.info("ROS 2 (rmw_zenoh) via %s, domain %d, node %s: %d topics, %d services (geometry: %s)",
                      p.endpoint, p.domain, p.ros_node, len(self.topics), len(self.queryables), note)

    # ---- the router ----------------------------------------------------------------------------------------
    def _check_tls_files(self) -> None:
        """The CA and certificate exist and the private key is this user's alone (as the CURVE keys)."""
        p = self.params
        for what, path in (("tls_ca", p.tls_ca), ("tls_cert", p.tls_cert)):
            if not Path(path).is_file():
                raise NodeError(f"node {self.name!r}: {what} {path} does not exist")
        try:
            check_private(p.tls_key)
        except KeyFileError as exc:
            raise NodeError(f"node {self.name!r}: tls_key: {exc}") from None

    def _check_version(self) -> None:
        """Refuse a router whose Zenoh major.minor differs from ours (one line), where it says its version."""
        ours = metadata.version("eclipse-zenoh")
        for reply in self.session.get("@/*/router", timeout=self.params.connect_timeout_s):
            if reply.ok is None:
                continue
            line = version_mismatch(ours, reply.ok.payload.to_bytes())
            if line:
                self.session.close()
                raise NodeError(f"node {self.name!r}: {line}")

    def _entity_id(self) -> int:
        self._next_id += 1
        return self._next_id - 1

    # ---- topics --------------------------------------------------------------------------------------------
    def _publisher(self, topic: str, msgtype: str) -> _Pub:
        pub = self.pubs.get((topic, msgtype))
        if pub is None:
            h, eid = type_hash(msgtype), self._entity_id()
            latched = topic == TF_STATIC
            qos = qos_key(durability=TRANSIENT_LOCAL, depth=1) if latched else qos_key()
            token = self.session.liveliness().declare_token(
                self.entity.token(PUBLISHER, eid, topic, msgtype, h, qos))
            pub = self.pubs[topic, msgtype] = _Pub(
                self.session.declare_publisher(data_key(self.params.domain, topic, msgtype, h)),
                self.entity.gid(eid), token)
        return pub

    def _send(self, views) -> None:
        for v in views:
            e = self.encoder.encode(v)
            pub = self._publisher(e.topic, e.msgtype)
            pub.sequence += 1
            pub.publisher.put(b"".join(e.parts), attachment=attachment(pub.sequence, time.time_ns(), pub.gid))

    def _resend_static(self) -> None:
        """The latched poses again (a subscriber that joined since gets them)."""
        self._send(self.gate.static)

    def forward(self, topic: str, msg: Message) -> None:
        """Publish one received message (as its views) to ROS 2."""
        views = self.views.views(topic, msg.header.stamp_ns or time.time_ns(), msg)
        self._send(self.gate.select(views, time.monotonic()))

    # ---- services ------------------------------------------------------------------------------------------
    def _declare_service(self, service: str, ros_type: str, req_type, resp_type, timeout_s: float) -> None:
        srv, name = f"{PACKAGE}/srv/{ros_type}", self.resolve(service)
        h, eid = type_hash(srv), self._entity_id()
        token = self.session.liveliness().declare_token(
            self.entity.token(SERVICE, eid, name, srv, h, qos_key()))
        queryable = self.session.declare_queryable(data_key(self.params.domain, name, srv, h), complete=True)
        client = self.client(service, req_type, resp_type, timeout_s=timeout_s)
        self.queryables.append((srv, queryable, token, client))

    def answer_requests(self) -> None:
        """Answer the ROS 2 requests that arrived (each with the rig's reply, or ``ok`` false and why)."""
        for srv, queryable, _, client in self.queryables:
            while (query := queryable.try_recv()) is not None:
                try:
                    self._answer(srv, query, client)
                finally:
                    query.drop()

    def _answer(self, srv: str, query, client) -> None:
        raw = query.attachment.to_bytes() if query.attachment is not None else None
        try:
            sequence, _, gid = parse_attachment(raw)
        except Ros2FormatError as exc:
            self.log.warning("%s: request without a valid attachment: %s", srv, exc)
            return
        ts, detail, reply = self.encoder.ts, "", None
        try:
            request = ts.deserialize_cdr(query.payload.to_bytes() if query.payload else b"", f"{srv}_Request")
            rig_request = self._rig_request(srv, request)
        except Exception as exc:  # malformed CDR or values: answered, not raised into the loop
            detail = f"bad request: {type(exc).__name__}: {exc}"
        else:
            try:
                reply = client.call(rig_request)
            except (BusError, MessageError) as exc:
                detail = str(exc)
        response = ts.types[f"{srv}_Response"](ok=reply is not None, detail=detail,
                                               **self._rig_reply(srv, reply))
        payload = self.encoder.cdr(response, f"{srv}_Response")
        query.reply(query.key_expr, payload, attachment=attachment(sequence, time.time_ns(), gid))

    @staticmethod
    def _rig_request(srv: str, request) -> Message:
        if srv.endswith("/StartScan"):
            return ScanRequest(method=request.method, stripes=int(request.stripes),
                               analyzer_deg=[float(a) for a in request.analyzer_deg],
                               sheets=int(getattr(request, "sheets", 0)))
        return Empty()

    def _rig_reply(self, srv: str, reply: Message | None) -> dict:
        """The response's message field: the reply's record (as the topics carry it), blank if none."""
        field, kind = ("event", "ScanEvent") if srv.endswith("/StartScan") else ("plan", "Plan")
        values = {name: _BLANK.get(typ, [] if typ.endswith("[]") else 0) for name, typ in RECORDS[kind]}
        stamp = time.time_ns()
        if reply is not None:
            stamp = reply.header.stamp_ns or stamp
            values = next(v.values for v in self.views.views(srv, stamp, reply) if isinstance(v, Record))
        return {field: self.encoder.record(kind, values, self.encoder.header(stamp, ""))}

    def teardown(self):
        session = getattr(self, "session", None)
        if session is not None:
            session.close()


NODE = Ros2Bridge
