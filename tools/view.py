"""``polarstripe view [--graph FILE | --bag FILE] -o sheet.png``: a contact sheet a person can look at — the
latest camera frame of each frame topic and the latest composite of each method, of a running launch (or of a
recording), as one PNG with a caption per tile.

Live, it subscribes (``mode="latest"``) to every topic of type ``frame`` or ``composite`` in the launch's
graph and waits ``--wait`` seconds for what arrives; from a bag it takes the last of each. Images are shown in
grey with a 0.5–99.5 percentile stretch; composites of several images (``composite``, ``e_b``, ``e_w``,
``global``) get one tile each, saturation masks are left out.
"""

from __future__ import annotations

import argparse
import time

import matplotlib
import matplotlib.pyplot as plt
import numpy as np
import zmq
from polarstripe.errors import PolarstripeError
from polarstripe.msgs import REGISTRY, Composite, Frame, Message
from polarstripe.runtime.bag_reader import BagReader
from polarstripe.runtime.bus import Subscriber
from polarstripe.runtime.graph import find_graph, load_graph, pub_endpoints

HELP = "write a contact sheet of the latest frames and composites"
VIEW_TYPES = ("frame", "composite")


class ViewError(PolarstripeError):
    """Nothing to show, or a bad view option; the text says which topics were watched."""


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("-o", "--output", required=True, metavar="SHEET.png", help="the PNG to write")
    src = parser.add_mutually_exclusive_group()
    src.add_argument(
        "--graph",
        default=None,
        metavar="FILE",
        help="graph.json or run directory of a launch (default: the newest running launch)",
    )
    src.add_argument("--bag", default=None, metavar="FILE", help="take the latest messages of a recording")
    parser.add_argument(
        "--wait",
        type=float,
        default=5.0,
        metavar="S",
        help="live: collect messages for this long (default 5)",
    )
    parser.add_argument("--columns", type=int, default=4, help="tiles per row (default 4)")


def latest_from_bag(path) -> dict[str, Message]:
    """The last message of each frame topic and of each composite method (key: caption)."""

    out: dict[str, Message] = {}
    with BagReader(path) as bag:
        topics = [t for t, s in bag.topics.items() if s.type in VIEW_TYPES and s.known]
        for topic, _, msg in bag.messages(topics):
            out[_key(topic, msg)] = msg
    return out


def latest_live(graph: dict, wait_s: float) -> dict[str, Message]:
    """The newest message of each frame/composite topic of a running launch, collected for ``wait_s``."""

    topics = [t for t, info in graph.get("topics", {}).items() if info.get("type") in VIEW_TYPES]
    if not topics:
        raise ViewError(f"launch {graph.get('launch', '?')!r} has no frame or composite topics")
    subs = [
        Subscriber(pub_endpoints(graph, t), t, REGISTRY[graph["topics"][t]["type"]], mode="latest")
        for t in topics
    ]
    poller = zmq.Poller()
    for s in subs:
        poller.register(s.socket, zmq.POLLIN)
    out: dict[str, Message] = {}
    deadline = time.monotonic() + wait_s
    try:
        while (left := deadline - time.monotonic()) > 0:
            ready = dict(poller.poll(int(left * 1000) + 1))
            for s in subs:
                if s.socket in ready:
                    for msg in s.take():
                        if isinstance(msg, (Frame, Composite)):
                            out[_key(s.topic, msg)] = msg
    finally:
        for s in subs:
            s.close()
    if not out:
        raise ViewError(f"no frame or composite arrived within {wait_s:g} s on {', '.join(sorted(topics))}")
    return out


def _key(topic: str, msg: Message) -> str:
    return f"{topic} [{msg.method}]" if isinstance(msg, Composite) else topic


def tiles(latest: dict[str, Message]) -> list[tuple[str, np.ndarray]]:
    """(caption, 2-D image) for each tile of the sheet, frames first."""
    out = []
    for key, msg in sorted(latest.items(), key=lambda kv: (isinstance(kv[1], Composite), kv[0])):
        if isinstance(msg, Frame):
            pol = "" if msg.polarizer_deg is None else f", analyzer {msg.polarizer_deg:.1f}°"
            out.append((f"{key}\nscan {msg.scan_id} step {msg.step} {msg.pattern}{pol}", msg.image))
        else:
            for name, img in msg.images.items():
                if name != "saturated" and img.ndim == 2:
                    out.append((f"{key} {name}\nscan {msg.scan_id}", img))
    return out


def contact_sheet(items: list[tuple[str, np.ndarray]], path, *, columns: int = 4) -> None:
    """Write the tiles as one PNG (matplotlib, Agg)."""

    matplotlib.use("Agg")

    if not items:
        raise ViewError("nothing to show (no frames or composites)")
    if columns < 1:
        raise ViewError(f"--columns must be >= 1, got {columns}")
    cols = min(columns, len(items))
    rows = -(-len(items) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.6 * cols, 3.2 * rows), squeeze=False)
    for ax in axes.flat:
        ax.axis("off")
    for ax, (caption, img) in zip(axes.flat, items, strict=False):
        a = np.asarray(img, dtype=np.float64)
        finite = a[np.isfinite(a)]
        lo, hi = np.percentile(finite, [0.5, 99.5]) if finite.size else (0.0, 1.0)
        ax.imshow(a, cmap="gray", vmin=lo, vmax=hi if hi > lo else lo + 1, interpolation="nearest")
        ax.set_title(f"{caption}\n{a.shape[1]}×{a.shape[0]}, {lo:.4g}…{hi:.4g}", fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(args: argparse.Namespace) -> int:
    if args.bag:
        latest = latest_from_bag(args.bag)
    else:

        latest = latest_live(load_graph(find_graph(args.graph)), args.wait)
    items = tiles(latest)
    contact_sheet(items, args.output, columns=args.columns)
    print(f"wrote {args.output}: {len(items)} tiles ({', '.join(sorted(latest))})")
    return 0
