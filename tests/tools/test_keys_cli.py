"""``polarstripe keys``: generate writes ZeroMQ's certificate pair (secret 0600) and never overwrites;
fingerprint prints sha256(Z85 public key)[:8]."""

from __future__ import annotations

import hashlib
import os
import stat
import subprocess
import sys

import zmq
import zmq.auth
from polarstripe.runtime.bus import CurveKeys


def _keys(*argv) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "polarstripe", "keys", *argv], capture_output=True,
                          text=True, timeout=60)


def test_generate_writes_a_usable_pair_with_a_private_secret(tmp_path):
    out = _keys("generate", "vehicle", "-d", str(tmp_path))
    assert out.returncode == 0, out.stderr
    public, secret = tmp_path / "vehicle.key", tmp_path / "vehicle.key_secret"
    assert stat.S_IMODE(os.stat(secret).st_mode) == 0o600
    assert stat.S_IMODE(os.stat(public).st_mode) == 0o644
    pub_key, none = zmq.auth.load_certificate(public)
    pub_again, sec_key = zmq.auth.load_certificate(secret)
    assert none is None and pub_again == pub_key  # the public file holds no secret
    assert zmq.curve_public(sec_key) == pub_key  # a real pair
    assert sorted(p.name for p in tmp_path.iterdir()) == ["vehicle.key", "vehicle.key_secret"]  # no leftovers
    assert hashlib.sha256(pub_key).hexdigest()[:8] in out.stdout
    keys = CurveKeys.from_env({"POLARSTRIPE_CURVE_KEYS": str(secret)})  # the runtime takes it as it is
    assert (keys.public, keys.secret) == (pub_key, sec_key)


def test_generate_refuses_to_overwrite(tmp_path):
    assert _keys("generate", "topside", "-d", str(tmp_path)).returncode == 0
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    out = _keys("generate", "topside", "-d", str(tmp_path))
    assert out.returncode == 2 and out.stdout == ""
    assert out.stderr.count("\n") == 1 and "topside.key" in out.stderr and "not overwriting" in out.stderr
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before
    (tmp_path / "topside.key").unlink()  # one file of the pair left: still refused, the secret untouched
    assert _keys("generate", "topside", "-d", str(tmp_path)).returncode == 2
    assert (tmp_path / "topside.key_secret").read_bytes() == before["topside.key_secret"]


def test_bad_name_or_folder_is_one_line(tmp_path):
    for argv in (("generate", "../evil", "-d", str(tmp_path)), ("generate", "x", "-d", str(tmp_path / "no"))):
        out = _keys(*argv)
        assert out.returncode == 2 and out.stderr.count("\n") == 1, out.stderr
    assert list(tmp_path.iterdir()) == []


def test_fingerprint_of_public_and_secret_files(tmp_path):
    public, secret = zmq.auth.create_certificates(tmp_path, "h")
    expected = hashlib.sha256(zmq.auth.load_certificate(public)[0]).hexdigest()[:8]
    out = _keys("fingerprint", public, secret)
    assert out.returncode == 0, out.stderr
    assert out.stdout.splitlines() == [f"{expected}  {public}", f"{expected}  {secret}"]
    missing = _keys("fingerprint", str(tmp_path / "none.key"))
    assert missing.returncode == 2 and "does not exist" in missing.stderr
