"""``polarstripe bag info FILE …``, ``bag recover IN -o OUT``, ``bag export IN --to ros2|foxglove OUT`` and
``bag import ROSBAG2 -o OUT``: look into MCAP recordings, repair one whose writer died, and convert to and
from the formats the robotics tools open (:mod:`polarstripe.tools.bag_export`,
:mod:`polarstripe.tools.bag_import`).

``info`` prints, per topic, the message type and schema version, the count, the rate and the gaps (the
recorder's count of messages lost upstream, from the bag's ``recording`` metadata; ``--scan`` also reads
every message, checks that it decodes, and counts gaps in the recorded sequence numbers). A truncated file,
a file that is not MCAP, and a channel recorded with an unknown schema version each give one line of error.
"""

from __future__ import annotations

import argparse
import json
import time

from polarstripe.runtime.bag import COMPRESSIONS
from polarstripe.runtime.bag_reader import BagReader, recover
from polarstripe.tools.bag_export import FORMATS

HELP = "inspect, recover, export (ROS 2, Foxglove) or import (ROS 2) recordings"


def configure(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="action", required=True, metavar="ACTION")
    info = sub.add_parser("info", help="topics, types, counts, rates, duration and gaps of a bag")
    info.add_argument("files", nargs="+", metavar="FILE")
    info.add_argument(
        "--scan",
        action="store_true",
        help="also decode every message and count gaps in the recorded sequence numbers",
    )
    info.add_argument("--json", action="store_true", help="one JSON object per file")
    rec = sub.add_parser("recover", help="write an indexed copy of a bag whose writer died")
    rec.add_argument("input", metavar="IN")
    rec.add_argument("-o", "--output", required=True, metavar="OUT")
    rec.add_argument("--compression", choices=COMPRESSIONS, default="none")
    exp = sub.add_parser("export", help="write a rosbag2 (ROS 2) or a Foxglove MCAP of a bag")
    exp.add_argument("input", metavar="IN")
    exp.add_argument("output", metavar="OUT", help="a new folder (ros2) or file (foxglove)")
    exp.add_argument("--to", required=True, choices=FORMATS, help="ros2: rosbag2 (MCAP, CDR); foxglove: MCAP")
    exp.add_argument("--topics", nargs="+", metavar="T", help="topics or shell patterns (default: all)")
    exp.add_argument("--start", type=float, metavar="S", help="from S seconds after the recording's start")
    exp.add_argument("--end", type=float, metavar="S", help="up to S seconds after the recording's start")
    exp.add_argument("--image-every", type=int, default=1, metavar="N",
                     help="keep every N-th camera frame and projector pattern of each topic (default 1)")
    exp.add_argument("--scene", metavar="FILE", help="the rig's scene TOML (default: the recording's)")
    exp.add_argument("--no-progress", action="store_true", help="no progress bar")
    exp.add_argument("--json", action="store_true", help="print one JSON object")
    imp = sub.add_parser("import", help="convert a rosbag2 of camera frames into a bag replay reads")
    imp.add_argument("input", metavar="ROSBAG2", help="a rosbag2 folder")
    imp.add_argument("-o", "--output", required=True, metavar="OUT", help="the new .mcap file")
    imp.add_argument("--no-progress", action="store_true", help="no progress bar")


def info(path, *, scan: bool = False) -> dict:
    """Everything ``bag info`` shows, as a dict (raises BagError for a bad file)."""
    with BagReader(path) as bag:
        rec = bag.metadata.get("recording", {})
        try:
            rec_topics = json.loads(rec.get("topics", "{}"))
        except ValueError:
            rec_topics = {}
        out = {
            "file": str(bag.path),
            "bytes": bag.size,
            "messages": bag.message_count,
            "start_ns": bag.start_ns,
            "end_ns": bag.end_ns,
            "duration_s": bag.duration_s,
            "compression": bag.compression,
            "chunks": len(bag.summary.chunk_indexes),
            "launch": bag.metadata.get("launch", {}).get("launch", ""),
            "polarstripe": bag.metadata.get("versions", {}).get("polarstripe", ""),
            "topics": {},
        }
        for t, s in bag.topics.items():
            out["topics"][t] = {
                "type": s.type,
                "version": s.version,
                "known": s.known,
                "messages": s.count,
                "rate_hz": s.rate_hz,
                "gaps": rec_topics.get(t, {}).get("gaps"),
            }
        if scan:
            decoded = 0
            for _ in bag.messages([t for t, s in bag.topics.items() if s.known]):
                decoded += 1
            out["decoded"] = decoded
            for t, g in bag.sequence_gaps().items():
                out["topics"][t]["sequence_gaps"] = g
    return out


def _print(d: dict) -> None:
    start = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(d["start_ns"] / 1e9)) if d["start_ns"] else "-"
    print(
        f"file:        {d['file']} ({d['bytes'] / 1e6:.1f} MB, {d['chunks']} chunks, "
        f"compression {', '.join(d['compression']) or '-'})"
    )
    print(
        f"recorded:    {start}, {d['duration_s']:.3f} s, {d['messages']} messages"
        + (f", launch {d['launch']!r}" if d["launch"] else "")
        + (f", polarstripe {d['polarstripe']}" if d["polarstripe"] else "")
    )
    if "decoded" in d:
        print(f"decoded:     {d['decoded']} messages, every one valid")
    if not d["topics"]:
        print("topics:      none")
        return
    w = max(len(t) for t in d["topics"])
    print(
        f"{'topic':<{w}}  {'type':<20} {'messages':>9} {'rate/Hz':>9} {'gaps':>6}"
        + ("  seq gaps" if "decoded" in d else "")
    )
    for t, s in d["topics"].items():
        typ = f"{s['type']} v{s['version']}" + ("" if s["known"] else " (?)")
        gaps = "-" if s["gaps"] is None else str(s["gaps"])
        print(
            f"{t:<{w}}  {typ:<20} {s['messages']:>9} {s['rate_hz']:>9.2f} {gaps:>6}"
            + (f"  {s['sequence_gaps']:>8}" if "sequence_gaps" in s else "")
        )


def main(args: argparse.Namespace) -> int:
    if args.action == "export":
        from polarstripe.tools import bag_export

        opt = bag_export.ExportOptions(topics=args.topics, start_s=args.start, end_s=args.end,
                                       image_every=args.image_every, scene=args.scene,
                                       progress=False if args.no_progress else None)
        res = bag_export.export(args.input, args.output, args.to, opt)
        print(bag_export.as_json(res) if args.json else bag_export.summary(res))
        return 0
    if args.action == "import":
        from polarstripe.tools import bag_import

        print(bag_import.summary(bag_import.import_ros2(args.input, args.output,
                                                       progress=False if args.no_progress else None)))
        return 0
    if args.action == "info":
        for i, f in enumerate(args.files):
            d = info(f, scan=args.scan)
            if args.json:
                print(json.dumps(d))
            else:
                if i:
                    print()
                _print(d)
        return 0
    r = recover(args.input, args.output, compression=args.compression)
    print(
        f"recovered {r.messages} messages in {r.chunks} chunks to {args.output}"
        + (f"; stopped at the damaged tail ({r.stopped})" if r.stopped else "; the input was complete")
    )
    for t, n in sorted(r.topics.items()):
        print(f"  {t}: {n}")
    return 0
