"""Who may talk to this host: CURVE certificates in ZeroMQ's usual files and ZAP authentication with an
allow-list of client public keys (pyzmq's ``zmq.auth``). The bus (:mod:`polarstripe.runtime.bus`) uses this
for its CURVE server sockets; the environment variables and the rov launch are in docs/hardware.md
("Security").

Files (``zmq.auth.create_certificates``, written by ``polarstripe keys generate NAME``):

* ``NAME.key`` — the public certificate (``public-key = "…"``, Z85); give it to the peers.
* ``NAME.key_secret`` — the secret certificate (public and secret key); mode 0600, never leaves the host.
  A secret file readable by group or others is refused (:func:`load_secret_cert`).

Authentication: a server socket with an allow-list gets a ZAP domain (:func:`zap_domain`) answered by one
``zmq.auth.thread.ThreadAuthenticator`` per ZeroMQ context (its own thread; the bus sockets themselves stay in
the node's loop). A client whose key is not on the list fails the CURVE handshake: it receives no topic data
and no service reply. Each refused key is logged once per process, as a WARNING naming its
:func:`fingerprint`: the first 8 hex digits of sha256 of the Z85 public key (40 ASCII characters), so
``polarstripe keys fingerprint NAME.key`` on the client's side finds who it was. CURVE server sockets without
an allow-list (encryption only) are answered "allowed" by the same authenticator (the ``*`` domain).
"""

from __future__ import annotations

import hashlib
import logging
import os
import stat
import sys
import threading
from collections.abc import Mapping
from pathlib import Path

import zmq
import zmq.auth
from polarstripe.errors import PolarstripeError
from polarstripe.runtime.zero_copy import monitor_socket
from zmq.auth.thread import ThreadAuthenticator

KEYS_ENV = "POLARSTRIPE_CURVE_KEYS"  # this host's secret certificate (NAME.key_secret)
ALLOW_ENV = "POLARSTRIPE_CURVE_ALLOW"  # allowed client keys: a directory of *.key, or files (':'-separated)
SERVER_ENV = "POLARSTRIPE_CURVE_SERVER"  # the public certificate of the host whose servers we connect to

log = logging.getLogger("polarstripe.auth")


class KeyFileError(PolarstripeError):
    """A key file or allow-list that cannot be used; the text names the file and the fix."""


def fingerprint(public_z85: bytes | str) -> str:
    """First 8 hex digits of sha256 of the Z85 public key (its 40 ASCII characters): a short name for a key
    that gives nothing away (the public key itself is public anyway)."""
    key = public_z85.encode("ascii") if isinstance(public_z85, str) else bytes(public_z85)
    return hashlib.sha256(key).hexdigest()[:8]


def check_private(path: str | os.PathLike) -> None:
    """Refuse a secret key file that group or others may read or write (one line naming the file and the
    fix)."""
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        raise KeyFileError(f"secret key file {path} does not exist") from None
    if mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise KeyFileError(f"secret key file {path} is readable by others (mode {stat.S_IMODE(mode):04o}): "
                           f"run 'chmod 600 {path}'")


def _load(path: str | os.PathLike) -> tuple[bytes, bytes | None]:
    try:
        public, secret = zmq.auth.load_certificate(path)
    except OSError:
        raise KeyFileError(f"key file {path} does not exist") from None
    except ValueError:
        raise KeyFileError(f"{path} is not a ZeroMQ certificate (no public-key line; "
                           f"make one with 'polarstripe keys generate NAME')") from None
    for what, key in (("public", public), ("secret", secret)):
        if key is not None and len(key) != 40:
            raise KeyFileError(f"key file {path}: the {what} key is not 40 Z85 characters")
    return public, secret


def is_certificate(path: str | os.PathLike) -> bool:
    """Whether ``path`` is in ZeroMQ's certificate format (a ``public-key = "…"`` line), not the older
    ``public=…``/``secret=…`` key file."""
    try:
        with open(path, "rb") as f:
            return any(line.strip().startswith(b"public-key") for line in f)
    except FileNotFoundError:
        raise KeyFileError(f"key file {path} does not exist") from None


def load_secret_cert(path: str | os.PathLike) -> tuple[bytes, bytes]:
    """``(public, secret)`` (Z85) from a secret certificate ``NAME.key_secret``, refused unless mode 0600 or
    stricter."""
    public, secret = _load(path)
    if not secret:
        raise KeyFileError(f"key file {path} holds no secret key (give NAME.key_secret, not NAME.key)")
    check_private(path)
    return public, secret


def load_public_cert(path: str | os.PathLike) -> bytes:
    """The public key (Z85) of a certificate (public or secret)."""
    return _load(path)[0]


def load_allow(spec: str) -> frozenset[bytes]:
    """The allowed client keys: ``spec`` is a directory of public certificates (``*.key``, ZeroMQ's
    convention) or certificate files, several separated by ``:``. A missing path is an error; an empty
    directory allows no one but this host itself."""
    keys: set[bytes] = set()
    for entry in filter(None, spec.split(os.pathsep)):
        p = Path(entry)
        if p.is_dir():
            keys.update(load_public_cert(f) for f in sorted(p.glob("*.key")))
        elif p.is_file():
            keys.add(load_public_cert(p))
        else:
            raise KeyFileError(f"allow-list {entry} does not exist (give a directory of public certificates)")
    return frozenset(keys)


def load_key_lines(path: str | os.PathLike) -> dict[str, bytes]:
    """The older key file: ``public=…``, ``secret=…``, ``server_public=…`` lines (Z85), ``#`` comments."""
    values = {}
    try:
        with open(path, encoding="ascii") as f:
            for line in f:
                if "=" in line and not line.lstrip().startswith("#"):
                    k, v = line.split("=", 1)
                    values[k.strip()] = v.strip().encode()
    except FileNotFoundError:
        raise KeyFileError(f"curve key file {path} does not exist") from None
    unknown = set(values) - {"public", "secret", "server_public"}
    if unknown:
        raise KeyFileError(f"curve key file {path}: unknown key {sorted(unknown)[0]!r}")
    return values


def host_keys(env: Mapping[str, str]) -> dict | None:
    """This host's CURVE keys from the environment (the fields of ``bus.CurveKeys``), None without
    ``KEYS_ENV``:

    * ``POLARSTRIPE_CURVE_KEYS`` — this host's secret certificate ``NAME.key_secret`` (or the older
      ``public=``/``secret=`` file; one with only ``public=`` makes a client of that server). A file holding a
      secret key must be mode 0600 or stricter (else :class:`KeyFileError` naming the fix).
    * ``POLARSTRIPE_CURVE_ALLOW`` — the allow-list (:func:`load_allow`); this host's own key is always on it.
      Unset: the servers only encrypt.
    * ``POLARSTRIPE_CURVE_SERVER`` — the public certificate of the host whose servers this process's clients
      connect to (topside: the vehicle's); unset: this host's own key.
    """
    path = env.get(KEYS_ENV)
    if not path:
        return None
    if is_certificate(path):
        public, secret = load_secret_cert(path)
        server_public = public
    else:
        lines = load_key_lines(path)
        secret = lines.get("secret", b"")
        if secret:
            check_private(path)
        public = lines.get("public") or (zmq.curve_public(secret) if secret else b"")
        server_public = lines.get("server_public") or public
    server, allow = env.get(SERVER_ENV), env.get(ALLOW_ENV)
    return {"public": public, "secret": secret,
            "server_public": load_public_cert(server) if server else server_public,
            "allow": (load_allow(allow) | {public}) if allow else None}


class _AllowList:
    """A ZAP credentials provider: ``callback(domain, key)`` True for a listed key; a refusal is logged once
    per key and process."""

    def __init__(self, keys: frozenset[bytes] | None):
        self.keys = keys  # None: any key (encryption only)

    def callback(self, domain: str, key: bytes) -> bool:
        if self.keys is None or key in self.keys:
            return True
        _refused_once(key)
        return False


_refused: set[bytes] = set()
_lock = threading.Lock()
_authenticators: dict[int, tuple[zmq.Context, ThreadAuthenticator]] = {}


def _refused_once(key: bytes) -> None:
    with _lock:
        if key in _refused:
            return
        _refused.add(key)
    log.warning("refused CURVE client with key fingerprint %s: not on this host's allow-list "
                "(no data, no replies; logged once per key)", fingerprint(key))


def zap_domain(ctx: zmq.Context, allow: frozenset[bytes]) -> str:
    """The ZAP domain that admits exactly ``allow`` in ``ctx``; the context's authenticator is started on
    first use (call before the socket binds)."""
    with _lock:
        entry = _authenticators.get(id(ctx))
        if entry is None or entry[0] is not ctx:
            auth = ThreadAuthenticator(ctx, log=logging.getLogger("polarstripe.auth.zap"))
            auth.start()
            auth.configure_curve_callback("*", _AllowList(None))  # CURVE servers without a list
            entry = _authenticators[id(ctx)] = (ctx, auth)
    domain = "polarstripe-" + hashlib.sha256(b"".join(sorted(allow))).hexdigest()[:16]
    providers = entry[1].credentials_providers
    if domain not in providers:
        entry[1].configure_curve_callback(domain, _AllowList(frozenset(allow)))
    return domain


def stop_authenticator(ctx: zmq.Context) -> None:
    """Stop the authenticator of ``ctx`` (before ``ctx.term()``); sockets with a domain then fail open, so
    close them first."""
    with _lock:
        entry = _authenticators.pop(id(ctx), None)
    if entry is not None:
        entry[1].stop()


_HANDSHAKE_FAILED = zmq.EVENT_HANDSHAKE_FAILED_AUTH


def watch_refusal(sock: zmq.Socket) -> zmq.Socket:
    """A monitor of ``sock`` (a CURVE client; call before it connects) that hears the server refuse our key
    (ZAP status 400), for :func:`refusal_note`. Close it with the socket (``sock.disable_monitor()``)."""
    return monitor_socket(sock, _HANDSHAKE_FAILED)


def refusal_note(monitor: zmq.Socket | None, public: bytes) -> str:
    """A note for the client's timeout if the monitor heard the server refuse our handshake (``public``: our
    key, b"" for a throwaway pair), else ``""``."""
    if monitor is None or not monitor.poll(0):
        return ""
    while monitor.poll(0):  # drain: one note however many tries
        monitor.recv_multipart()
    which = f"this host's CURVE key, fingerprint {fingerprint(public)}" if public else "a throwaway CURVE key"
    return f" (the server refused {which}: it is not on the server's allow-list)"


def log_refusals_as(name: str) -> None:
    """Refusals on stderr in a node's format (``time WARNING name: refused …``), not on the bus: they come
    from the authenticator's thread, and a bus socket belongs to the node's loop."""
    for h in list(log.handlers):
        log.removeHandler(h)
    h = logging.StreamHandler(sys.stderr)
    h.setFormatter(logging.Formatter(f"%(asctime)s %(levelname)s {name}: %(message)s"))
    log.addHandler(h)
    log.propagate = False
