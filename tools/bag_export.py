"""``polarstripe bag export IN --to ros2|foxglove OUT``: a recording in the formats the robotics tools open.

* ``--to ros2``: a rosbag2 folder (MCAP storage, CDR; :mod:`polarstripe.tools.export_ros2`) that
  ``ros2 bag play`` and the ``rosbags`` library read;
* ``--to foxglove``: one MCAP file with Foxglove's schemas (:mod:`polarstripe.tools.export_foxglove`), the
  live bridge's channels.

Both map each message through :class:`~polarstripe.nodes.rig_views.RigViews` (images, camera info, tf,
logs, plottable records). Options: ``--topics`` (names or shell patterns, full or relative to the recorded
namespace), ``--start``/``--end`` (seconds from the recording's start), ``--image-every N`` (keep every N-th
camera frame and projector pattern of each topic; composites are always kept), ``--scene FILE`` (the rig's
geometry when the recording does not name it). A tqdm progress bar runs on a terminal.

The output is written under a temporary name beside ``OUT`` and renamed at the end: an error or Ctrl-C
leaves nothing half-written. Errors a user can cause are :class:`~polarstripe.runtime.bag.BagError`
(one line): a file that is not a finished bag, a channel that is not a polarstripe one, an existing output,
a topic filter that matches nothing, a selection with no message.
"""

from __future__ import annotations

import fnmatch
import json
import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

from polarstripe import __version__
from polarstripe.msgs import Composite, Frame, Pattern
from polarstripe.nodes.rig_geometry import geometry_from_metadata
from polarstripe.nodes.rig_views import Packed, RigViews
from polarstripe.runtime.bag import BagError
from polarstripe.runtime.bag_reader import BagReader
from polarstripe.sim.scene import SceneError
from polarstripe.tools.bag_fastread import FastReader, parse_packed

FORMATS = ("ros2", "foxglove")
DECIMATED = (Frame.TYPE, Pattern.TYPE)


@dataclass
class ExportOptions:
    """What to export: topics (None: all), the time range [s from the recording's start], image decimation,
    a scene file, and whether to show a progress bar (None: on a terminal)."""

    topics: list[str] | None = None
    start_s: float | None = None
    end_s: float | None = None
    image_every: int = 1
    scene: str | None = None
    progress: bool | None = None


@dataclass
class ExportResult:
    """What was written: messages read and skipped, output messages per (topic, type), the geometry note."""

    path: Path
    fmt: str
    read: int = 0
    skipped: int = 0
    written: dict = field(default_factory=dict)
    geometry: str = ""
    seconds: float = 0.0


def select_topics(bag: BagReader, patterns: list[str] | None) -> list[str]:
    """The bag's topics chosen by ``patterns`` (names or shell patterns, full or relative to the recorded
    namespace); BagError naming a pattern that matches nothing."""
    if not patterns:
        return list(bag.topics)
    ns = bag.metadata.get("launch", {}).get("namespace", "").rstrip("/")
    chosen: list[str] = []
    for p in patterns:
        if any(c in p for c in "*?["):
            full = p if p.startswith("/") else f"{ns}/{p}"
            hits = [t for t in bag.topics if fnmatch.fnmatchcase(t, full) or fnmatch.fnmatchcase(t, p)]
        else:
            try:
                hits = bag.resolve_topics([p])
            except BagError:
                hits = []
        if not hits:
            raise BagError(f"bag {bag.path}: no topic matches {p!r} (has {', '.join(bag.topics) or 'none'})")
        chosen += [t for t in hits if t not in chosen]
    return chosen


def _first_separation(bag: BagReader, topics: list[str]) -> float | None:
    """The source distance of the recording's first simulator truth (where the tf puts the projector)."""
    comps = [t for t in topics if bag.types.get(t) is Composite]
    for _, _, msg in bag.messages(comps):
        if msg.method == "truth" and isinstance(msg.metrics.get("separation_m"), int | float):
            return float(msg.metrics["separation_m"])
    return None


def _temporary(dst: Path) -> tuple[Path, Path]:
    """(folder to remove at the end, path to write) beside ``dst``."""
    tmp = dst.parent / f".{dst.name}.partial-{os.getpid()}"
    if tmp.exists():
        shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=False)
    return tmp, tmp / dst.name


def _sink(fmt: str, path: Path, bag: BagReader, src: Path):
    info = {"source": str(src), "polarstripe": __version__,
            "launch": bag.metadata.get("launch", {}).get("launch", ""),
            "namespace": bag.metadata.get("launch", {}).get("namespace", "")}
    if fmt == "ros2":
        from polarstripe.tools.export_ros2 import Ros2Sink

        return Ros2Sink(path, custom_data={f"polarstripe.{k}": v for k, v in info.items()})
    from polarstripe.tools.export_foxglove import FoxgloveSink

    return FoxgloveSink(path, metadata={**bag.metadata, "export": info})


def _progress(total: int | None, enabled: bool | None, desc: str):
    from tqdm import tqdm

    disable = None if enabled is None else not enabled  # None: only on a terminal
    return tqdm(total=total, unit="msg", unit_scale=True, desc=desc, disable=disable, leave=False,
                mininterval=0.5)


def export(src, dst, fmt: str, options: ExportOptions | None = None) -> ExportResult:
    """Export bag ``src`` to ``dst`` as ``fmt`` (``ros2``: a new folder; ``foxglove``: a new file)."""
    opt = options or ExportOptions()
    src, dst = Path(src), Path(dst)
    if fmt not in FORMATS:
        raise BagError(f"bag export: format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    if opt.image_every < 1:
        raise BagError(f"bag export: --image-every must be >= 1, got {opt.image_every}")
    if dst.exists() or dst.is_symlink():
        raise BagError(f"bag export: output {dst} exists; remove it or choose another name")
    if not dst.parent.is_dir():
        raise BagError(f"bag export: output folder {dst.parent} does not exist")
    t0 = time.perf_counter()
    res = ExportResult(dst, fmt)
    with BagReader(src) as bag:
        topics = select_topics(bag, opt.topics)
        start_ns = bag.start_ns + int(opt.start_s * 1e9) if opt.start_s else None
        end_ns = bag.start_ns + int(opt.end_s * 1e9) if opt.end_s is not None else None
        try:
            geometry, res.geometry = geometry_from_metadata(bag.metadata, opt.scene)
        except (SceneError, OSError) as exc:
            raise BagError(f"bag export: --scene: {exc}") from None
        rig = RigViews(geometry)
        sep = _first_separation(bag, topics) if geometry is not None else None
        if sep is not None:
            rig.place(sep)
        total = None if (start_ns or end_ns) else sum(bag.topics[t].count for t in topics)
        if total == 0:
            raise BagError(f"bag {src}: no messages to export on {', '.join(topics) or 'any topic'}")
        tmp, out = _temporary(dst)
        try:
            sink = _sink(fmt, out, bag, src)
            try:
                _run(bag, topics, (start_ns, end_ns, total), opt, rig, sink, res)
                if res.read - res.skipped == 0:
                    raise BagError(f"bag {src}: no messages to export in the chosen topics and time range")
            except BaseException:
                sink.abort()
                raise
            sink.close()
            res.written = dict(sink.counts)
            if dst.exists():
                raise BagError(f"bag export: output {dst} appeared while exporting; not overwriting it")
            os.rename(out, dst)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    res.seconds = time.perf_counter() - t0
    return res


def _run(bag: BagReader, topics, span, opt: ExportOptions, rig: RigViews, sink, res: ExportResult) -> None:
    start_ns, end_ns, total = span
    seen: dict[str, int] = {}
    reader = FastReader(bag)
    try:
        with _progress(total, opt.progress, f"export {bag.path.name}") as bar:
            for topic, log_ns, data in reader.raw(topics, start_ns, end_ns):
                res.read += 1
                bar.update(1)
                info = bag.topics[topic]
                if opt.image_every > 1 and info.type in DECIMATED:
                    k = seen[topic] = seen.get(topic, -1) + 1
                    if k % opt.image_every:
                        res.skipped += 1
                        continue
                cls = bag.types.get(topic)
                if cls is None:  # a type this build does not know: its MessagePack form as it is
                    views = [Packed(topic, log_ns, info.type, info.version, bytes(data))]
                    if not rig.started:
                        views = rig.start(log_ns) + views
                else:
                    views = rig.views(topic, log_ns, parse_packed(data, topic=topic, expect=cls))
                for v in views:
                    sink.write(v)
    finally:
        reader.close()


def summary(res: ExportResult) -> str:
    """The lines ``bag export`` prints."""
    n = sum(res.written.values())
    lines = [f"exported {res.read - res.skipped} of {res.read} messages as {n} {res.fmt} messages on "
             f"{len(res.written)} topics to {res.path} in {res.seconds:.1f} s"
             + (f" ({res.skipped} images skipped by --image-every)" if res.skipped else ""),
             f"geometry: {res.geometry}"]
    w = max((len(t) for t, _ in res.written), default=5)
    lines += [f"  {t:<{w}}  {typ:<36} {c:>7}" for (t, typ), c in sorted(res.written.items())]
    return "\n".join(lines)


def as_json(res: ExportResult) -> str:
    """The result as one JSON object."""
    return json.dumps({"path": str(res.path), "format": res.fmt, "read": res.read, "skipped": res.skipped,
                       "geometry": res.geometry, "seconds": res.seconds,
                       "topics": [{"topic": t, "type": typ, "messages": c}
                                  for (t, typ), c in sorted(res.written.items())]})
