"""``polarstripe keys``: CURVE certificates for the rig's hosts (docs/hardware.md "Security").

::

    polarstripe keys generate vehicle -d /etc/polarstripe/keys    # vehicle.key (public), vehicle.key_secret
    polarstripe keys fingerprint /etc/polarstripe/keys/topside.key

``generate`` writes ZeroMQ's usual certificate files (``zmq.auth.create_certificates``): ``NAME.key`` with the
public key (mode 0644, give it to the peers' allow-lists) and ``NAME.key_secret`` with both keys (mode 0600,
stays on the host). It never overwrites: a host's key pair is replaced only by deleting it first. The files
are made in a private temporary folder and linked into place, so the secret is never readable by others.
``fingerprint`` prints the short name a refusal is logged with (:func:`polarstripe.runtime.auth.fingerprint`).
"""

from __future__ import annotations

import argparse
import os
import re
import tempfile
from pathlib import Path

import zmq.auth
from polarstripe.errors import PolarstripeError
from polarstripe.runtime.auth import fingerprint, load_public_cert

HELP = "make a host's CURVE certificate pair (NAME.key, NAME.key_secret) or print a key's fingerprint"
_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]*$")


def configure(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="action", required=True, metavar="ACTION")
    gen = sub.add_parser("generate", help="write NAME.key (public) and NAME.key_secret (secret, mode 0600)")
    gen.add_argument("name", help="the host's name, e.g. vehicle or topside")
    gen.add_argument("-d", "--dir", default=".", help="folder for the two files (default: here)")
    fp = sub.add_parser("fingerprint", help="first 8 hex of sha256 of a certificate's Z85 public key")
    fp.add_argument("files", nargs="+", metavar="FILE", help="NAME.key or NAME.key_secret")


def generate(name: str, folder: str | os.PathLike = ".") -> tuple[Path, Path]:
    """Write ``folder/NAME.key`` and ``folder/NAME.key_secret`` (0600); returns their paths. Refuses (a
    :class:`PolarstripeError`) a bad name, a missing folder or an existing file."""
    if not _NAME.match(name):
        raise PolarstripeError(f"name {name!r}: use letters, digits, '_', '-' or '.' (not first)")
    folder = Path(folder)
    if not folder.is_dir():
        raise PolarstripeError(f"folder {folder} does not exist")
    public, secret = folder / f"{name}.key", folder / f"{name}.key_secret"
    for p in (public, secret):
        if p.exists():
            raise PolarstripeError(f"{p} exists; not overwriting a key (delete it first to replace the pair)")
    with tempfile.TemporaryDirectory(dir=folder, prefix=".keys-") as tmp:  # mode 0700: private meanwhile
        tmp_public, tmp_secret = zmq.auth.create_certificates(tmp, name)
        os.chmod(tmp_secret, 0o600)
        os.chmod(tmp_public, 0o644)
        os.link(tmp_secret, secret)  # link, not rename: fails if the file appeared meanwhile
        try:
            os.link(tmp_public, public)
        except FileExistsError:
            secret.unlink()
            raise PolarstripeError(f"{public} exists; not overwriting a key") from None
    return public, secret


def main(args: argparse.Namespace) -> int:
    if args.action == "generate":
        try:
            public, secret = generate(args.name, args.dir)
        except FileExistsError as exc:
            raise PolarstripeError(f"{exc.filename2 or exc.filename} exists; not overwriting a key") from None
        print(f"public  {public}  (give it to the peers: their allow-list folder)")
        print(f"secret  {secret}  (mode 0600, stays on this host)")
        print(f"fingerprint {fingerprint(load_public_cert(public))}")
        return 0
    for f in args.files:
        print(f"{fingerprint(load_public_cert(f))}  {f}")
    return 0
