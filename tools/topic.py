"""``polarstripe topic list | echo TOPIC | hz TOPIC``: look at the topics of a running launch.

The launch is found through its graph file (the newest running launch, or ``--graph FILE|RUN_DIR``). TOPIC
may be a full name (``/rig/camera/frame``) or relative to the launch's namespace (``camera/frame``).
``echo`` prints the header and the small fields of each message, arrays as ``dtype[shape]``; it does not
need the message class.
"""

from __future__ import annotations

import argparse
import importlib
import json
import math
import sys
import time

import zmq
from polarstripe.msgs import REGISTRY, MessageError, describe
from polarstripe.runtime.bus import CurveKeys, apply_curve
from polarstripe.runtime.graph import find_graph, load_graph, pub_endpoints, resolve

HELP = "list, echo or time the topics of a running launch"


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--graph",
        default=None,
        metavar="FILE",
        help="graph.json or run directory of a launch (default: the newest running launch)",
    )
    sub = parser.add_subparsers(dest="action", required=True, metavar="ACTION")
    sub.add_parser("list", help="topics with their type, publishers and subscribers")
    echo = sub.add_parser("echo", help="print messages of a topic")
    echo.add_argument("topic")
    echo.add_argument("-n", "--count", type=int, default=0, help="stop after this many messages (0: never)")
    echo.add_argument("--timeout", type=float, default=0.0, help="give up after this many seconds (0: never)")
    echo.add_argument("--json", action="store_true", help="one JSON object per line")
    hz = sub.add_parser("hz", help="message rate of a topic")
    hz.add_argument("topic")
    hz.add_argument("--window", type=float, default=1.0, help="seconds per report")
    hz.add_argument("-n", "--reports", type=int, default=0, help="stop after this many reports (0: never)")
    for p in (sub.choices["list"], echo, hz):  # --graph also after the action
        p.add_argument("--graph", default=argparse.SUPPRESS, metavar="FILE", help=argparse.SUPPRESS)


def _open(graph: dict, topic: str) -> zmq.Socket:
    sock = zmq.Context.instance().socket(zmq.SUB)
    sock.linger = 0
    keys = CurveKeys.from_env()  # this host's keys when the rig's links are encrypted (docs/hardware.md)
    apply_curve(sock, keys.client() if keys else None, server=False)
    sock.rcvhwm = 100
    sock.setsockopt(zmq.SUBSCRIBE, topic.encode())
    for ep in pub_endpoints(graph, topic):
        sock.connect(ep)
    return sock


def _recv(sock: zmq.Socket, topic: bytes, timeout_s: float | None) -> list | None:
    """Next message of exactly ``topic`` (frames after the topic), or None after ``timeout_s``."""
    deadline = None if timeout_s is None else time.monotonic() + timeout_s
    while True:
        left = None if deadline is None else max(0.0, deadline - time.monotonic())
        if not sock.poll(None if left is None else int(left * 1000)):
            return None
        frames = sock.recv_multipart(copy=False)
        if frames[0].bytes == topic:
            return frames[1:]


def _list(graph: dict) -> int:
    topics = graph.get("topics", {})
    if not topics:
        print("no topics")
        return 0
    width = max(len(t) for t in topics)
    for name in sorted(topics):
        t = topics[name]
        print(
            f"{name:<{width}}  {t['type']:<18} pub: {', '.join(t['publishers']) or '-'}"
            f"   sub: {', '.join(t['subscribers']) or '-'}"
        )
    return 0


def _register_type(graph: dict, topic: str) -> None:
    """Import the topic's publishers' modules if its type is not registered here (a node may declare its
    own types), so that ``describe`` can name the fields of the positional wire header."""
    info = graph.get("topics", {}).get(topic, {})
    if info.get("type") in REGISTRY:
        return
    for name in info.get("publishers", []):
        module = str(graph.get("nodes", {}).get(name, {}).get("module", "")).partition(":")[0]
        try:
            importlib.import_module(module)
        except Exception:  # a module that does not import here: fields are shown by position
            pass


def _echo(graph: dict, topic: str, count: int, timeout_s: float, as_json: bool) -> int:
    _register_type(graph, topic)
    sock = _open(graph, topic)
    n, t_end = 0, (time.monotonic() + timeout_s) if timeout_s else None
    try:
        while not count or n < count:
            left = None if t_end is None else t_end - time.monotonic()
            if left is not None and left <= 0:
                break
            frames = _recv(sock, topic.encode(), left)
            if frames is None:
                break
            try:
                d = describe(frames, topic=topic)
            except MessageError as exc:
                print(f"bad message: {exc}", file=sys.stderr)
                continue
            n += 1
            if as_json:
                print(json.dumps(d, default=str), flush=True)
            else:
                fields = ", ".join(f"{k}={v!r}" for k, v in d["fields"].items())
                print(
                    f"[{d['type']} seq={d['seq']} stamp_ns={d['stamp_ns']}"
                    + (f" frame_id={d['frame_id']!r}" if d["frame_id"] else "")
                    + f"] {fields}",
                    flush=True,
                )
    finally:
        sock.close(0)
    if n == 0 and timeout_s:
        print(f"no message on {topic} within {timeout_s:g} s", file=sys.stderr)
        return 1
    return 0


def _hz(graph: dict, topic: str, window_s: float, reports: int) -> int:
    sock = _open(graph, topic)
    done = 0
    try:
        while not reports or done < reports:
            stamps, nbytes = [], 0
            end = time.monotonic() + window_s
            while (left := end - time.monotonic()) > 0:
                frames = _recv(sock, topic.encode(), left)
                if frames is None:
                    break
                stamps.append(time.monotonic())
                nbytes += sum(len(f.buffer) for f in frames)
            done += 1
            if len(stamps) < 2:
                print(f"{topic}: {len(stamps)} message(s) in {window_s:g} s", flush=True)
                continue
            dts = [b - a for a, b in zip(stamps, stamps[1:], strict=False)]
            mean = sum(dts) / len(dts)
            std = math.sqrt(sum((d - mean) ** 2 for d in dts) / len(dts))
            print(
                f"{topic}: {1 / mean:.2f} Hz  (n={len(stamps)}, min {min(dts) * 1e3:.2f} ms, "
                f"max {max(dts) * 1e3:.2f} ms, std {std * 1e3:.2f} ms, {nbytes / window_s / 1e6:.3f} MB/s)",
                flush=True,
            )
    finally:
        sock.close(0)
    return 0


def main(args: argparse.Namespace) -> int:
    graph = load_graph(find_graph(args.graph))
    if args.action == "list":
        return _list(graph)
    topic = resolve(args.topic, graph.get("namespace", ""))
    try:
        if args.action == "echo":
            return _echo(graph, topic, args.count, args.timeout, args.json)
        return _hz(graph, topic, args.window, args.reports)
    except KeyboardInterrupt:
        return 0
