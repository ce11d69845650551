"""Authenticated CURVE links over loopback tcp (runtime/auth.py, docs/hardware.md "Security").

A node process ("the vehicle": demo talker) with its own key pair and an allow-list holding the topside's
public certificate: the topside's client receives its topic and its service replies; a client with an unknown
key (it knows the server's public key) and a client without CURVE get no data and no reply, and the node's
log holds exactly one refusal line with the stranger's fingerprint after several attempts. A secret key
file that others may read stops the node at start with one line.
"""

from __future__ import annotations

import hashlib
import logging
import os
import signal
import socket
import subprocess
import sys
import threading

import pytest
import zmq
import zmq.auth
from polarstripe.msgs import Ack, Empty, Log
from polarstripe.runtime import auth
from polarstripe.runtime.bus import BusTimeout, CurveKeys, PubSocket, ServiceTimeout, Subscriber
from polarstripe.runtime.service import ServiceClient, ServiceServer


def _cert(folder, name) -> tuple[str, str]:
    public, secret = zmq.auth.create_certificates(folder, name)
    os.chmod(secret, 0o600)
    return public, secret


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def hosts(tmp_path):
    """vehicle and topside pairs; the vehicle's allow-list folder holds topside.key; a stranger's pair."""
    allowed = tmp_path / "allowed"
    allowed.mkdir()
    v_pub, v_sec = _cert(tmp_path, "vehicle")
    t_pub, t_sec = _cert(allowed, "topside")  # topside.key lands in allowed/ (its secret too: not *.key)
    s_pub, s_sec = _cert(tmp_path, "stranger")
    load = zmq.auth.load_certificate
    return {"dir": tmp_path, "allowed": allowed, "vehicle_secret": v_sec,
            "vehicle": load(v_sec), "topside": load(t_sec), "stranger": load(s_sec)}


def _z85_fingerprint(public: bytes) -> str:  # the documented definition, computed here independently
    return hashlib.sha256(public).hexdigest()[:8]


@pytest.fixture
def vehicle_node(hosts, tmp_path):
    pub, srv = f"tcp://127.0.0.1:{_free_port()}", f"tcp://127.0.0.1:{_free_port()}"
    env = {**os.environ, auth.KEYS_ENV: str(hosts["vehicle_secret"]), auth.ALLOW_ENV: str(hosts["allowed"])}
    env.pop(auth.SERVER_ENV, None)
    err = open(tmp_path / "talker.log", "w")  # noqa: SIM115  (the node writes it until the end)
    proc = subprocess.Popen([sys.executable, "-m", "polarstripe", "node", "polarstripe.nodes.demo:Talker",
                             "--name", "talker", "--namespace", "/rov", "--pub", pub, "--srv", srv,
                             "--param", "rate_hz=50"], env=env, stdout=err, stderr=subprocess.STDOUT)
    try:
        yield pub, srv, tmp_path / "talker.log"
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        err.close()


def test_only_allowed_keys_get_data_and_replies(hosts, vehicle_node):
    pub, srv, log_file = vehicle_node
    v_public = hosts["vehicle"][0]
    topside = CurveKeys(*hosts["topside"], server_public=v_public)
    stranger = CurveKeys(*hosts["stranger"], server_public=v_public)
    subs = {"topside": Subscriber([pub], "/rov/chatter", Log, curve=topside),
            "stranger": Subscriber([pub], "/rov/chatter", Log, curve=stranger),
            "plain": Subscriber([pub], "/rov/chatter", Log)}
    try:
        msg = subs["topside"].recv(timeout_s=30.0)  # the node needs a few seconds to start
        assert msg.text.startswith("hello ")
        with ServiceClient(srv, "/rov/talker/reset", Empty, Ack, timeout_s=10.0, curve=topside) as c:
            assert c.call(Empty()).ok
        for who in ("stranger", "plain"):  # meanwhile the talker published ~50 messages a second
            with pytest.raises(BusTimeout):
                subs[who].recv(timeout_s=1.0)
        for _ in range(3):  # a new DEALER, so a new handshake, each time
            with ServiceClient(srv, "/rov/talker/reset", Empty, Ack, curve=stranger) as c:
                with pytest.raises(ServiceTimeout, match="/rov/talker/reset.*no reply within 0.5 s") as exc:
                    c.call(Empty(), timeout_s=0.5)
                fp = _z85_fingerprint(hosts["stranger"][0])  # the client is told why, with its key's name
                assert f"refused this host's CURVE key, fingerprint {fp}: it is not on" in str(exc.value)
        with ServiceClient(srv, "/rov/talker/reset", Empty, Ack) as c:  # no CURVE at all
            with pytest.raises(ServiceTimeout):
                c.call(Empty(), timeout_s=0.5)
        assert subs["topside"].recv(timeout_s=5.0).text.startswith("hello ")  # still served
    finally:
        for s in subs.values():
            s.close()
    refusals = [line for line in log_file.read_text().splitlines() if "refused" in line]
    assert len(refusals) == 1, refusals  # once per key, however often it tried
    assert _z85_fingerprint(hosts["stranger"][0]) in refusals[0]
    assert "WARNING talker:" in refusals[0]


def test_secret_key_readable_by_others_is_refused_at_start(hosts, tmp_path):
    os.chmod(hosts["vehicle_secret"], 0o644)
    env = {**os.environ, auth.KEYS_ENV: str(hosts["vehicle_secret"]), auth.ALLOW_ENV: str(hosts["allowed"])}
    out = subprocess.run([sys.executable, "-m", "polarstripe", "node", "polarstripe.nodes.demo:Talker",
                          "--pub", f"tcp://127.0.0.1:{_free_port()}", "--srv", f"tcp://127.0.0.1:{_free_port()}"],
                         env=env, capture_output=True, text=True, timeout=60)
    assert out.returncode == 2
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1, out.stderr
    assert str(hosts["vehicle_secret"]) in lines[0] and "chmod 600" in lines[0] and "0644" in lines[0]


# ---- in one process: the bus API ------------------------------------------------------------------------
def _serve(server: ServiceServer, stop: threading.Event) -> None:
    while not stop.is_set():
        if server.socket.poll(20):
            server.handle_ready()


def test_bus_allow_list_in_process(hosts, caplog):
    v_public, v_secret = hosts["vehicle"]
    allow = frozenset({hosts["topside"][0]})
    topside = CurveKeys(*hosts["topside"], server_public=v_public)
    stranger = CurveKeys(*hosts["stranger"], server_public=v_public)
    server = ServiceServer("tcp://127.0.0.1:0", curve=CurveKeys(v_public, v_secret, allow=allow))
    server.add("/t/echo", Log, Log, lambda req: req)
    stop = threading.Event()
    t = threading.Thread(target=_serve, args=(server, stop), daemon=True)
    t.start()
    try:
        with caplog.at_level(logging.WARNING, logger="polarstripe.auth"):
            with ServiceClient(server.endpoint, "/t/echo", Log, Log, curve=topside) as c:
                assert c.call(Log(level="INFO", node="n", text="hi"), timeout_s=5.0).text == "hi"
            for _ in range(2):
                with ServiceClient(server.endpoint, "/t/echo", Log, Log, curve=stranger) as c:
                    with pytest.raises(ServiceTimeout):
                        c.call(Log(level="INFO", node="n", text="hi"), timeout_s=0.5)
    finally:
        stop.set()
        t.join(2)
        server.close()
    refused = [r.getMessage() for r in caplog.records if "refused" in r.getMessage()]
    assert refused == [refused[0]] and _z85_fingerprint(hosts["stranger"][0]) in refused[0]
    assert server.stats.requests == 1  # the stranger's requests never reached the server


def test_encryption_only_servers_still_serve_any_key_beside_an_allow_list(hosts):
    """The authenticator of a context also answers CURVE servers without a list (they only encrypt)."""
    v_public, v_secret = hosts["vehicle"]
    with PubSocket("tcp://127.0.0.1:0", curve=CurveKeys(v_public, v_secret, allow=frozenset())) as strict, \
            PubSocket("tcp://127.0.0.1:0", curve=CurveKeys(v_public, v_secret)) as open_:
        anyone = CurveKeys(server_public=v_public)  # a fresh random pair
        with Subscriber([open_.endpoint], "/t", Log, curve=anyone) as a, \
                Subscriber([strict.endpoint], "/t", Log, curve=anyone) as b:
            pa, pb = open_.publisher("/t", Log), strict.publisher("/t", Log)
            got = None
            for _ in range(250):  # slow joiner: publish until the subscription is there (at most 5 s)
                pa.publish(Log(level="INFO", node="n", text="x"))
                pb.publish(Log(level="INFO", node="n", text="x"))
                got = a.take()
                if got:
                    break
                a.socket.poll(20)
            assert got and got[0].text == "x"
            for _ in range(25):  # 0.5 s more: the subscription to the strict socket had as long
                pb.publish(Log(level="INFO", node="n", text="x"))
                b.socket.poll(20)
            assert b.take() == []


# ---- keys from the environment ---------------------------------------------------------------------------
def test_host_keys_from_env(hosts, tmp_path):
    v_public = hosts["vehicle"][0]
    env = {auth.KEYS_ENV: str(hosts["vehicle_secret"]), auth.ALLOW_ENV: str(hosts["allowed"])}
    keys = CurveKeys.from_env(env)
    assert (keys.public, keys.secret) == hosts["vehicle"]
    assert keys.allow == {hosts["topside"][0], v_public}  # the allow-list and the host itself
    assert keys.client() == CurveKeys(*hosts["vehicle"], server_public=v_public)
    assert CurveKeys.from_env({}) is None
    topside = {auth.KEYS_ENV: str(hosts["allowed"] / "topside.key_secret"),
               auth.SERVER_ENV: str(hosts["dir"] / "vehicle.key")}
    t = CurveKeys.from_env(topside)
    assert t.allow is None and t.server_public == v_public and (t.public, t.secret) == hosts["topside"]


@pytest.mark.parametrize("case, message", [
    ("missing_allow", "allow-list .*nowhere does not exist"),
    ("public_as_secret", "holds no secret key"),
    ("not_a_cert", "unknown key 'hello'"),
    ("legacy_0644", "readable by others .*chmod 600"),
])
def test_bad_key_files_are_one_clear_error(hosts, tmp_path, case, message):
    env = {auth.KEYS_ENV: str(hosts["vehicle_secret"])}
    if case == "missing_allow":
        env[auth.ALLOW_ENV] = str(tmp_path / "nowhere")
    elif case == "public_as_secret":
        env[auth.KEYS_ENV] = str(tmp_path / "vehicle.key")  # mode 0644: the wrong file, said first
    elif case == "not_a_cert":
        (tmp_path / "x.keys").write_text("hello=1\n")
        env[auth.KEYS_ENV] = str(tmp_path / "x.keys")
    else:
        p, s = zmq.curve_keypair()
        (tmp_path / "rig.keys").write_text(f"public={p.decode()}\nsecret={s.decode()}\n")
        os.chmod(tmp_path / "rig.keys", 0o644)
        env[auth.KEYS_ENV] = str(tmp_path / "rig.keys")
    with pytest.raises(auth.KeyFileError, match=message):
        CurveKeys.from_env(env)
