"""The bus's errors and its CURVE keys (re-exported by :mod:`polarstripe.runtime.bus`, where they are
used)."""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass

import zmq
from polarstripe.errors import PolarstripeError
from polarstripe.runtime import auth


class BusError(PolarstripeError):
    """A bus failure: bad endpoint, a service that failed; the text names the endpoint, topic or service."""


class BusTimeout(BusError, TimeoutError):
    """Nothing arrived in time."""


class ServiceTimeout(BusTimeout):
    """A service call got no reply within its timeout."""


class ServiceError(BusError):
    """The service replied with an error (its handler raised, or it does not know the request)."""


@dataclass(frozen=True)
class CurveKeys:
    """ZeroMQ CURVE keys (Z85 bytes, from ``zmq.curve_keypair()`` or certificate files, :mod:`.auth`).

    A binding socket (PUB, ROUTER) needs ``secret`` (and ``public``); a connecting socket needs
    ``server_public`` and gets its own ``public``/``secret`` (generated if empty). ``allow`` (server side):
    the client public keys admitted by ZAP authentication; a client with another key fails the handshake and
    gets nothing (the refusal is logged once per key, docs/hardware.md "Security"). ``allow=None`` only
    encrypts: any client that knows the server's public key is served.
    """

    public: bytes = b""
    secret: bytes = b""
    server_public: bytes = b""
    allow: frozenset[bytes] | None = None

    @staticmethod
    def load(path: str) -> CurveKeys:
        """Read ``public=…``/``secret=…``/``server_public=…`` lines (Z85) from a file (the older format)."""
        return CurveKeys(**auth.load_key_lines(path))

    @staticmethod
    def from_env(environ: Mapping[str, str] | None = None) -> CurveKeys | None:
        """This host's keys as a node or tool reads them at start (None without
        ``$POLARSTRIPE_CURVE_KEYS``): :func:`.auth.host_keys`."""
        keys = auth.host_keys(os.environ if environ is None else environ)
        return None if keys is None else CurveKeys(**keys)

    def client(self) -> CurveKeys:
        """The keys of this host's connecting sockets: its own pair (so that servers with an allow-list know
        it) and the server's public key."""
        return CurveKeys(self.public, self.secret, self.server_public or self.public)


def _apply_curve(sock: zmq.Socket, curve: CurveKeys | None, *, server: bool) -> None:
    if curve is None:
        return
    if server:
        if not curve.secret:
            raise BusError("CURVE server socket needs a secret key")
        if curve.allow is not None:  # before the socket binds: the ZAP handler must be there first
            sock.zap_domain = auth.zap_domain(sock.context, curve.allow).encode()
        sock.curve_secretkey = curve.secret
        sock.curve_publickey = curve.public or zmq.curve_public(curve.secret)
        sock.curve_server = True
    else:
        if not curve.server_public:
            raise BusError("CURVE client socket needs the server's public key")
        public, secret = (curve.public, curve.secret) if curve.secret else zmq.curve_keypair()
        sock.curve_serverkey = curve.server_public
        sock.curve_publickey = public or zmq.curve_public(secret)
        sock.curve_secretkey = secret


apply_curve = _apply_curve  # for a tool that opens its own socket (tools/topic.py)
