"""``polarstripe bag import ROSBAG2 -o OUT.mcap``: a ROS 2 recording as a polarstripe bag that ``replay``
and the compositor take, so scans recorded on a ROS 2 rig are processed here.

The input is a rosbag2 folder (MCAP or SQLite storage, read with ``rosbags``) in the layout
``polarstripe bag export --to ros2`` writes (:mod:`polarstripe.tools.export_ros2`):

===============================================  =================================================
ROS 2                                             polarstripe
===============================================  =================================================
``T/image`` ``sensor_msgs/msg/Image`` with       ``Frame`` on ``T`` (pixels as they are; pattern tag,
``T/info`` ``polarstripe_msgs/msg/FrameInfo``    analyzer angle, exposure, scan id and step from the
(paired by header stamp)                         info; stamp and seq the info's)
``polarstripe_msgs/msg/ScanEvent`` on ``T``       ``ScanEvent`` on ``T`` (likewise PolarizerState,
                                                  PolarizerCommand, MediumEstimate, Plan, Heartbeat)
``T/info`` ``polarstripe_msgs/msg/PatternInfo``  ``Pattern`` on ``T``
``rcl_interfaces/msg/Log`` (``/rosout``)          ``Log`` on ``<namespace>/log``
``polarstripe_msgs/msg/Packed`` on ``T``          the packed message on ``T``
===============================================  =================================================

Everything else (camera info, tf, joint states, composite images and metrics: the compositor makes them
again) is skipped and listed. A camera on a ROS 2 rig publishes its ``sensor_msgs/Image`` on ``T/image`` and
a ``FrameInfo`` with the same header stamp on ``T/info``. Log time = the rosbag2 timestamp. A bag without a
frame, an unreadable bag and an existing output are one-line :class:`~polarstripe.runtime.bag.BagError`\\ s;
the output is written under a temporary name and renamed at the end.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from polarstripe import __version__
from polarstripe.msgs import (
    Frame,
    Header,
    Heartbeat,
    Log,
    MediumEstimate,
    MessageError,
    Pattern,
    PatternError,
    Plan,
    PolarizerCommand,
    PolarizerState,
    ScanEvent,
    unpack,
)
from polarstripe.nodes.ros2_schemas import PACKAGE, ROSOUT, require, typestore
from polarstripe.runtime.bag import BagError, BagWriter

_DTYPES = {"mono8": ("u1", 1), "8UC1": ("u1", 1), "mono16": ("u2", 1), "16UC1": ("u2", 1), "8SC1": ("i1", 1),
           "16SC1": ("i2", 1), "32SC1": ("i4", 1), "32FC1": ("f4", 1), "64FC1": ("f8", 1), "rgb8": ("u1", 3),
           "bgr8": ("u1", 3), "rgba8": ("u1", 4), "rgb16": ("u2", 3), "rgba16": ("u2", 4)}
_LEVELS = {10: "DEBUG", 20: "INFO", 30: "WARNING", 40: "ERROR", 50: "CRITICAL"}
_PENDING = 256  # images or infos waiting for their partner, per topic


@dataclass
class Imported:
    """What :func:`import_ros2` wrote: messages per topic, skipped ROS 2 topics, unpaired images."""

    path: Path
    written: Counter = field(default_factory=Counter)
    skipped: Counter = field(default_factory=Counter)
    unpaired: int = 0
    namespace: str = ""


def image_array(m) -> np.ndarray:
    """The pixels of a ``sensor_msgs/Image`` as an (h, w) or (h, w, c) array (row padding dropped)."""
    code = _DTYPES.get(m.encoding)
    if code is None:
        raise BagError(f"image encoding {m.encoding!r} is not supported (use one of {', '.join(_DTYPES)})")
    dt = np.dtype(code[0]).newbyteorder(">" if m.is_bigendian else "<")
    row = m.width * code[1] * dt.itemsize
    data = np.asarray(m.data, np.uint8)
    if m.step < row or data.size < m.step * m.height:
        raise BagError(f"image {m.width}x{m.height} {m.encoding}: {data.size} bytes, step {m.step}: "
                       "too short")
    rows = data[: m.step * m.height].reshape(m.height, m.step)[:, :row]
    a = np.ascontiguousarray(rows).view(dt).astype(dt.newbyteorder("="), copy=False)
    return a.reshape(m.height, m.width) if code[1] == 1 else a.reshape(m.height, m.width, code[1])


def _ns(stamp) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def _opt(v: float) -> float | None:
    return None if math.isnan(v) else float(v)


def _record(kind: str, m, stamp_ns: int):
    """The polarstripe message of a ``polarstripe_msgs`` record (None for a record not imported)."""
    h = Header(stamp_ns=stamp_ns)
    if kind == "ScanEvent":
        return ScanEvent(header=h, scan_id=int(m.scan_id), event=m.event, method=m.method,
                         stripes=int(m.stripes), analyzer_deg=[float(x) for x in m.analyzer_deg],
                         detail=m.detail, sheets=int(getattr(m, "sheets", 1)) or 1)
    if kind == "PolarizerState":
        return PolarizerState(header=h, angle_deg=float(m.angle_deg), target_deg=float(m.target_deg),
                              settled=bool(m.settled), fault=m.fault)
    if kind == "PolarizerCommand":
        return PolarizerCommand(header=h, target_deg=float(m.target_deg))
    if kind == "MediumEstimate":
        return MediumEstimate(header=h, p=float(m.p), sigma_t_per_m=_opt(m.sigma_t_per_m),
                              scan_id=int(m.scan_id), mean_cosine=_opt(m.mean_cosine), p_std=_opt(m.p_std),
                              sigma_t_std=_opt(m.sigma_t_std), mean_cosine_std=_opt(m.mean_cosine_std),
                              reason=m.reason)
    if kind == "Plan":
        return Plan(header=h, modality=m.modality, separation_m=float(m.separation_m), scan_type=m.scan_type,
                    stripe_optima=[float(x) for x in m.stripe_optima],
                    curves={c.name: np.asarray(c.values, np.float64) for c in m.curves},
                    sheets=int(getattr(m, "sheets", 1)) or 1)
    if kind == "Heartbeat":
        return Heartbeat(header=h, node=m.node, pid=int(m.pid), uptime_s=float(m.uptime_s),
                         counters=dict(zip(m.counter_names, map(int, m.counter_values), strict=False)))
    if kind == "PatternInfo":
        try:  # the tag holds what the fields do not (a stripe's sheets, a Gray code's axis, inverse, XOR)
            return dataclasses.replace(Pattern.of(m.tag, int(m.scan_id), int(m.step)), header=h)
        except PatternError:
            return Pattern(header=h, kind=m.kind, index=int(m.index), count=int(m.count), size=int(m.size),
                           shift=int(m.shift), scan_id=int(m.scan_id), step=int(m.step))
    if kind == "Packed":
        try:
            return unpack(bytes(np.asarray(m.msgpack, np.uint8)))
        except MessageError:  # a type this build does not declare
            return None
    return None


def _frame(img, info) -> Frame:
    a = image_array(img)
    stamp = int(info.stamp_ns) or _ns(img.header.stamp)
    return Frame(header=Header(stamp_ns=stamp, seq=int(info.seq), frame_id=img.header.frame_id), image=a,
                 exposure_s=float(info.exposure_s), gain=float(info.gain), bit_depth=int(info.bit_depth),
                 pattern=info.pattern, polarizer_deg=_opt(info.polarizer_deg), scan_id=int(info.scan_id),
                 step=int(info.step))


def _base(topic: str, leaf: str) -> str | None:
    return topic[: -len(leaf) - 1] if topic.endswith("/" + leaf) else None


def _namespace(reader, frame_topics: list[str]) -> str:
    custom = getattr(getattr(reader.readers[0], "metadata", None), "custom", None) or {}
    ns = custom.get("polarstripe.namespace")
    if ns is not None:
        return ns
    heads = {t.split("/")[1] for t in frame_topics if t.count("/") >= 3}
    return f"/{heads.pop()}" if len(heads) == 1 else ""


def _open(src: Path):
    """An open ``AnyReader`` of ``src``; BagError for anything rosbags cannot read (its errors vary: a
    definition it cannot parse is a KeyError, a torn file a ReaderError)."""
    from rosbags.highlevel import AnyReader

    reader = AnyReader([src], default_typestore=typestore())
    try:
        reader.open()
    except Exception as exc:  # noqa: BLE001  (the library's many error classes, one line for the user)
        raise BagError(f"bag import: {src}: unreadable rosbag2 ({type(exc).__name__}: {exc})") from None
    return reader


def import_ros2(src, dst, *, progress: bool | None = None) -> Imported:
    """Convert rosbag2 ``src`` (a folder) into a new polarstripe bag ``dst`` (module docstring)."""
    require()
    from rosbags.highlevel import AnyReaderError
    from rosbags.rosbag2 import ReaderError
    from tqdm import tqdm

    src, dst = Path(src), Path(dst)
    if dst.exists() or dst.is_symlink():
        raise BagError(f"bag import: output {dst} exists; remove it or choose another name")
    if not src.exists():
        raise BagError(f"bag import: {src}: no such file or folder")
    if not src.is_dir():
        raise BagError(f"bag import: {src}: not a rosbag2 folder (give the folder with metadata.yaml)")
    res = Imported(dst)
    tmp = dst.parent / f".{dst.name}.partial-{os.getpid()}"
    reader = _open(src)
    try:
        conns = {c.id: c for c in reader.connections}
        types = {c.topic: c.msgtype for c in conns.values()}
        frames = {b for t, ty in types.items() if ty == f"{PACKAGE}/msg/FrameInfo"
                  if (b := _base(t, "info")) and types.get(f"{b}/image") == "sensor_msgs/msg/Image"}
        if not frames:
            images = sorted(t for t, ty in types.items() if ty == "sensor_msgs/msg/Image")
            raise BagError(
                f"bag import: {src}: no camera frames (a sensor_msgs/msg/Image on T/image with a "
                f"{PACKAGE}/msg/FrameInfo on T/info); image topics: {', '.join(images) or 'none'}")
        res.namespace = _namespace(reader, sorted(frames))
        meta = {"launch": {"launch": "import", "namespace": res.namespace, "file": "", "args": "{}"},
                "imported": {"source": str(src), "polarstripe": __version__,
                             "types": json.dumps(types, sort_keys=True)}}
        with BagWriter(tmp) as w:
            for name, data in meta.items():
                w.add_metadata(name, data)
            total = sum(c.msgcount for c in conns.values())
            with tqdm(total=total, unit="msg", unit_scale=True, desc=f"import {src.name}", leave=False,
                      disable=None if progress is None else not progress, mininterval=0.5) as bar:
                _copy(reader, frames, w, res, bar)
        os.rename(tmp, dst)
    except (AnyReaderError, ReaderError) as exc:
        raise BagError(f"bag import: {src}: unreadable rosbag2 ({type(exc).__name__}: {exc})") from None
    finally:
        reader.close()
        if tmp.exists():
            tmp.unlink()
    return res


def _copy(reader, frames: set[str], w: BagWriter, res: Imported, bar) -> None:
    images: dict[str, dict[int, tuple[int, object]]] = {b: {} for b in frames}
    infos: dict[str, dict[int, object]] = {b: {} for b in frames}

    def put(topic: str, log_ns: int, msg) -> None:
        w.add_message(topic, msg, log_time_ns=log_ns)
        res.written[topic] += 1

    for conn, log_ns, raw in reader.messages():
        bar.update(1)
        topic, typ = conn.topic, conn.msgtype
        base_img, base_info = _base(topic, "image"), _base(topic, "info")
        if base_img in frames and typ == "sensor_msgs/msg/Image":
            m = reader.deserialize(raw, typ)
            info = infos[base_img].pop(_ns(m.header.stamp), None)
            if info is None:
                images[base_img][_ns(m.header.stamp)] = (log_ns, m)
                res.unpaired += _trim(images[base_img])
            else:
                put(base_img, log_ns, _frame(m, info))
        elif base_info in frames and typ == f"{PACKAGE}/msg/FrameInfo":
            m = reader.deserialize(raw, typ)
            pending = images[base_info].pop(_ns(m.header.stamp), None)
            if pending is None:
                infos[base_info][_ns(m.header.stamp)] = m
                res.unpaired += _trim(infos[base_info])
            else:
                put(base_info, pending[0], _frame(pending[1], m))
        elif typ == "rcl_interfaces/msg/Log" and topic == ROSOUT:
            m = reader.deserialize(raw, typ)
            put(f"{res.namespace}/log", log_ns, Log(header=Header(stamp_ns=_ns(m.stamp)), node=m.name,
                                                    text=m.msg, level=_LEVELS.get(int(m.level), "INFO")))
        elif typ.startswith(f"{PACKAGE}/msg/"):
            kind = typ.rsplit("/", 1)[1]
            m = reader.deserialize(raw, typ)
            msg = _record(kind, m, _ns(m.header.stamp))
            target = _base(topic, "info") if kind == "PatternInfo" else topic
            if msg is None or target is None:
                res.skipped[f"{topic} ({typ})"] += 1
            else:
                put(target, log_ns, msg)
        else:
            res.skipped[f"{topic} ({typ})"] += 1
    res.unpaired += sum(len(v) for v in images.values()) + sum(len(v) for v in infos.values())


def _trim(pending: dict) -> int:
    """Drop the oldest entries beyond :data:`_PENDING`; how many were dropped."""
    n = 0
    while len(pending) > _PENDING:
        pending.pop(next(iter(pending)))
        n += 1
    return n


def summary(res: Imported) -> str:
    """The lines ``bag import`` prints."""
    lines = [f"imported {sum(res.written.values())} messages on {len(res.written)} topics to {res.path}"
             + (f" (namespace {res.namespace})" if res.namespace else "")
             + (f"; {res.unpaired} images or frame infos without their partner were dropped" if res.unpaired
                else "")]
    lines += [f"  {t}: {n}" for t, n in sorted(res.written.items())]
    if res.skipped:
        lines.append(f"skipped {sum(res.skipped.values())} messages (not imported: derived or geometry):")
        lines += [f"  {t}: {n}" for t, n in sorted(res.skipped.items())]
    return "\n".join(lines)
