"""``polarstripe ros2``: the ROS 2 side of the rig (docs/ros2.md).

::

    polarstripe ros2 msgs -o ~/ros2_ws/src/polarstripe_msgs
    cd ~/ros2_ws && colcon build --packages-select polarstripe_msgs

``msgs`` writes the ROS 2 interface package ``polarstripe_msgs`` (``msg/*.msg``, ``srv/*.srv``,
``package.xml``, ``CMakeLists.txt``) generated from the records and services of
:mod:`polarstripe.nodes.ros2_schemas`, the types the bag export and the live bridge send.
``ros2/polarstripe_msgs/`` in the repository is its output, kept equal by a test. Into an existing package
folder it rewrites the files and removes ``.msg``/``.srv`` files the package no longer has; a folder that
holds anything else is refused.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from polarstripe import __version__
from polarstripe.errors import PolarstripeError
from polarstripe.nodes.ros2_schemas import interface_package

HELP = "write the ROS 2 interface package polarstripe_msgs (msg, srv, package.xml, CMakeLists.txt)"


def configure(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="action", required=True, metavar="ACTION")
    msgs = sub.add_parser("msgs", help="write the polarstripe_msgs package into a folder")
    msgs.add_argument("-o", "--out", required=True, metavar="DIR", help="the package folder (made if absent)")


def write_package(out: str | Path) -> list[Path]:
    """Write the package into ``out``; returns the files written. Refuses (:class:`PolarstripeError`) a
    folder with files that are not the package's (anything but msg/, srv/, package.xml, CMakeLists.txt)."""
    out = Path(out)
    files = interface_package(__version__)
    if out.exists():
        if not out.is_dir():
            raise PolarstripeError(f"{out} is not a folder")
        foreign = [p for p in out.rglob("*") if p.is_file() and str(p.relative_to(out)) not in files
                   and not (p.parent.name in ("msg", "srv") and p.parent.parent == out
                            and p.suffix in (".msg", ".srv"))]
        if foreign:
            raise PolarstripeError(f"{out} holds files that are not polarstripe_msgs' (e.g. {foreign[0]}); "
                                   "give an empty or new folder")
        for p in [*out.glob("msg/*.msg"), *out.glob("srv/*.srv")]:
            if str(p.relative_to(out)) not in files:
                p.unlink()
    written = []
    for rel, text in sorted(files.items()):
        path = out / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
        written.append(path)
    return written


def main(args: argparse.Namespace) -> int:
    written = write_package(args.out)
    print(f"polarstripe_msgs {__version__}: {len(written)} files in {args.out}")
    return 0
