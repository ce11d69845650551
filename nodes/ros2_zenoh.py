"""ROS 2's Zenoh middleware (``rmw_zenoh_cpp``) on the wire, as pure functions: key expressions, liveliness
tokens, QoS strings, the attachment, the session configuration, the peer's version. The formats are those of
rmw_zenoh's design document (``docs/design.md`` in ros2/rmw_zenoh; summarized in docs/ros2.md); the bridge
node (:mod:`polarstripe.nodes.ros2_bridge`) uses them with ``eclipse-zenoh``.

* data: ``<domain>/<fully qualified name without its leading />/<DDS type name>/<RIHS01 hash>``, e.g.
  ``0/rig/camera/frame/image/sensor_msgs::msg::dds_::Image_/RIHS01_d31d…``; a service's requests are queries
  on the same form of key.
* liveliness: ``@ros2_lv/<domain>/<session id>/<node id>/<node id>/NN/<enclave>/<namespace>/<node>`` for a
  node, ``@ros2_lv/<domain>/<session id>/<node id>/<entity id>/<MP|MS|SS|SC>/<enclave>/<namespace>/<node>/
  <name>/<DDS type name>/<hash>/<qos>`` for its publishers, subscriptions, services and clients; names
  mangled (``/`` → ``%``), an unset enclave or the root namespace ``%``.
* attachment of every sample, request and reply (33 bytes): the sequence number (int64 LE), the source
  time [ns since the epoch] (int64 LE), the GID's length (one byte, 16) and the GID (16 bytes); a reply
  carries the request's sequence number and client GID.
"""

from __future__ import annotations

import hashlib
import json
import re
import struct
from dataclasses import dataclass

ADMIN_SPACE = "@ros2_lv"
GID_BYTES = 16
ATTACHMENT_BYTES = 8 + 8 + 1 + GID_BYTES
DOMAIN_MAX = 232  # ROS_DOMAIN_ID: 0 … 232 (the ROS 2 documentation's safe range)
NODE, PUBLISHER, SUBSCRIPTION, SERVICE, CLIENT = "NN", "MP", "MS", "SS", "SC"
# rmw's QoS enums: reliability RELIABLE 1, BEST_EFFORT 2; durability TRANSIENT_LOCAL 1, VOLATILE 2;
# history KEEP_LAST 1, KEEP_ALL 2. rmw_zenoh leaves a policy empty where it is the default profile's
# (reliable, volatile, keep last 10, infinite deadline, lifespan and lease, automatic liveliness).
RELIABLE, BEST_EFFORT, TRANSIENT_LOCAL, VOLATILE = 1, 2, 1, 2
_VERSION = re.compile(r"v?(\d+)\.(\d+)\.(\d+)")


class Ros2FormatError(ValueError):
    """A name, domain, attachment or endpoint rmw_zenoh's formats cannot carry (the text names it)."""


def check_domain(domain: int) -> int:
    """``domain`` if it is a ROS domain id (0 … 232), else :class:`Ros2FormatError`."""
    if isinstance(domain, bool) or not isinstance(domain, int) or not 0 <= domain <= DOMAIN_MAX:
        raise Ros2FormatError(f"ros2_domain must be an integer 0 … {DOMAIN_MAX}, got {domain!r}")
    return domain


def check_node_name(name: str) -> str:
    """``name`` if it is a ROS 2 node name (a letter or ``_``, then letters, digits, ``_``), else
    :class:`Ros2FormatError`."""
    if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", name):
        raise Ros2FormatError(f"not a ROS 2 node name (letters, digits, _): {name!r}")
    return name


def dds_type_name(typename: str) -> str:
    """``pkg/msg/Name`` (or ``pkg/srv/Name``) as DDS names it in CDR: ``pkg::msg::dds_::Name_``."""
    parts = typename.split("/")
    if len(parts) != 3 or not all(parts):
        raise Ros2FormatError(f"not a ROS 2 type name (pkg/msg/Name): {typename!r}")
    pkg, kind, name = parts
    return f"{pkg}::{kind}::dds_::{name}_"


def mangle(name: str) -> str:
    """A name in a liveliness token: each ``/`` replaced by ``%`` (the root namespace and '' are ``%``)."""
    return name.replace("/", "%") or "%"


def _check_name(name: str) -> str:
    if not name.startswith("/") or name != name.rstrip("/") or "//" in name or not re.fullmatch(
            r"[/A-Za-z0-9_~]+", name):
        raise Ros2FormatError(f"not a fully qualified ROS 2 name: {name!r}")
    return name


def data_key(domain: int, name: str, typename: str, type_hash: str) -> str:
    """The key expression of topic or service ``name`` (fully qualified: ``/rig/camera/frame/image``)."""
    return f"{check_domain(domain)}/{_check_name(name)[1:]}/{dds_type_name(typename)}/{type_hash}"


def qos_key(*, reliability: int = RELIABLE, durability: int = VOLATILE, depth: int = 10) -> str:
    """A keep-last QoS as rmw_zenoh writes it into a token (defaults elided): reliable, volatile, depth 10
    is ``::,10:,:,:,,``; transient local, depth 1 is ``:1:,1:,:,:,,``."""
    rel = "" if reliability == RELIABLE else str(reliability)
    dur = "" if durability == VOLATILE else str(durability)
    return f"{rel}:{dur}:,{int(depth)}:,:,:,,"


@dataclass(frozen=True)
class Entity:
    """One ROS 2 node of a Zenoh session (``zid``: the session id in hex)."""

    domain: int
    zid: str
    node_id: int
    namespace: str
    node: str

    def node_token(self) -> str:
        """The node's liveliness token (``NN``)."""
        return (f"{ADMIN_SPACE}/{check_domain(self.domain)}/{self.zid}/{self.node_id}/{self.node_id}/{NODE}"
                f"/%/{mangle(self.namespace)}/{check_node_name(self.node)}")

    def token(self, kind: str, entity_id: int, name: str, typename: str, type_hash: str, qos: str) -> str:
        """The liveliness token of a publisher, subscription, service or client of this node."""
        if kind not in (PUBLISHER, SUBSCRIPTION, SERVICE, CLIENT):
            raise Ros2FormatError(f"entity kind must be MP, MS, SS or SC, got {kind!r}")
        return (f"{ADMIN_SPACE}/{check_domain(self.domain)}/{self.zid}/{self.node_id}/{entity_id}/{kind}/%/"
                f"{mangle(self.namespace)}/{self.node}/{mangle(_check_name(name))}/{dds_type_name(typename)}/"
                f"{type_hash}/{qos}")

    def gid(self, entity_id: int) -> bytes:
        """A 16-byte GID unique to this session's entity (a digest of session, node and entity ids)."""
        return hashlib.sha256(f"{self.zid}/{self.node_id}/{entity_id}".encode()).digest()[:GID_BYTES]


def attachment(sequence: int, stamp_ns: int, gid: bytes) -> bytes:
    """The 33-byte attachment of a sample, request or reply."""
    if len(gid) != GID_BYTES:
        raise Ros2FormatError(f"a GID has {GID_BYTES} bytes, got {len(gid)}")
    return struct.pack("<qqB", sequence, stamp_ns, GID_BYTES) + bytes(gid)


def parse_attachment(data: bytes | None) -> tuple[int, int, bytes]:
    """(sequence number, source time [ns], GID) of an attachment; :class:`Ros2FormatError` if malformed."""
    if data is None or len(data) != ATTACHMENT_BYTES or data[16] != GID_BYTES:
        got = "none" if data is None else f"{len(data)} bytes"
        raise Ros2FormatError(
            f"an rmw_zenoh attachment has {ATTACHMENT_BYTES} bytes (GID length 16), got {got}")
    sequence, stamp_ns = struct.unpack_from("<qq", data)
    return sequence, stamp_ns, bytes(data[17:])


def session_config(endpoint: str, *, tls_ca: str = "", tls_cert: str = "",
                   tls_key: str = "") -> dict[str, str]:
    """The bridge's Zenoh session configuration as (path, JSON5 value) pairs for
    ``zenoh.Config.insert_json5``:
    a Zenoh *client* of the router at ``endpoint`` (``rmw_zenohd``): every sample, query and token goes over
    that one link, which the router routes to the ROS 2 peers (no multicast or gossip scouting, no listening
    port, no peer-to-peer links); ``tls/HOST:PORT`` with mutual TLS (``tls_ca`` the only CA trusted,
    ``tls_cert``/``tls_key`` this host's certificate, which the router checks against the same CA)."""
    proto = endpoint.split("/", 1)[0]
    if proto not in ("tcp", "tls") or not re.fullmatch(r"(tcp|tls)/[^/\s]+:\d+", endpoint):
        raise Ros2FormatError(f"ros2_endpoint must be tcp/HOST:PORT or tls/HOST:PORT, got {endpoint!r}")
    tls = (tls_ca, tls_cert, tls_key)
    if proto == "tls" and not all(tls):
        raise Ros2FormatError(f"ros2_endpoint {endpoint!r} needs tls_ca, tls_cert and tls_key")
    if proto == "tcp" and any(tls):
        raise Ros2FormatError(f"tls_ca/tls_cert/tls_key are for a tls/ endpoint, not {endpoint!r}")
    cfg = {
        "mode": "client",
        "connect/endpoints": [endpoint],
        "connect/timeout_ms": 0,  # overridden by the bridge with its connect timeout
        "connect/exit_on_failure": True,
        "listen/endpoints": [],
        "scouting/multicast/enabled": False,
        "scouting/gossip/enabled": False,
    }
    if proto == "tls":
        cfg.update({"transport/link/tls/root_ca_certificate": tls_ca,
                    "transport/link/tls/connect_certificate": tls_cert,
                    "transport/link/tls/connect_private_key": tls_key,
                    "transport/link/tls/enable_mtls": True,
                    "transport/link/tls/verify_name_on_connect": True})
    return {k: json.dumps(v) for k, v in cfg.items()}


def zenoh_version(text: str) -> tuple[int, int, int] | None:
    """(major, minor, patch) of a Zenoh version string (``1.4.0``, ``v1.4.0 built with rustc …``); None if
    it names no release (a build from a git commit reports ``v<hash> built with …``)."""
    m = _VERSION.match(text.strip())
    return (int(m[1]), int(m[2]), int(m[3])) if m else None


def version_mismatch(ours: str, admin_reply: bytes) -> str | None:
    """One line if the router's admin space record (``@/<zid>/router``, JSON with ``version``) names a Zenoh
    release whose major.minor differs from ours; None when they agree or its version names no release."""
    try:
        record = json.loads(admin_reply)
        theirs = str(record["version"])
    except (ValueError, KeyError, TypeError):
        return None
    a, b = zenoh_version(ours), zenoh_version(theirs)
    if a is None or b is None or a[:2] == b[:2]:
        return None
    return (f"the Zenoh router {record.get('zid', '?')} runs Zenoh {'.'.join(map(str, b))}, this bridge "
            f"{'.'.join(map(str, a))}: install the eclipse-zenoh {b[0]}.{b[1]} that matches the ROS 2 "
            f"release's rmw_zenoh, or run that release's router")
