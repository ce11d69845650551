"""Fixtures of the export / import tests: a small recording of a simulated scan with every message type the
exports map (written with BagWriter, so the tests need no running rig).

In CI (``CI`` set) the optional packages of the export, import and Foxglove tests must be there (the
``test`` extra installs them): a missing one fails the run instead of skipping those tests."""

from __future__ import annotations

import importlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
from polarstripe.msgs import (
    AnalyzerMount,
    Composite,
    Frame,
    Header,
    Heartbeat,
    Log,
    MediumEstimate,
    Pattern,
    Plan,
    PolarizerCommand,
    PolarizerState,
    ScanEvent,
)
from polarstripe.runtime.bag import BagWriter

if os.environ.get("CI"):
    for _name in ("rosbags", "foxglove", "google.protobuf"):
        importlib.import_module(_name)  # ImportError here: install the test extra (pip install -e '.[test]')

T0 = 1_790_000_000_000_000_000
NS = "/rig"
GRAPH = {
    "launch": "synthetic",
    "namespace": NS,
    "nodes": {
        "simulator": {"module": "polarstripe.nodes.simulator", "params": {"resolution": "64x48"}},
        "emitter": {"module": "polarstripe.nodes.emitter",
                    "params": {"display_options": {"width": 40, "height": 30}}},
    },
}


@dataclass
class RigBag:
    """The recording and what went into it (by topic: (log time, message) in order)."""

    path: Path
    sent: dict[str, list] = field(default_factory=dict)

    def frames(self, topic: str = f"{NS}/camera/frame") -> list[tuple[int, Frame]]:
        return self.sent[topic]


def write_rig_bag(path: Path, *, scans: int = 2, stripes: int = 4, shape=(48, 64)) -> RigBag:
    """A recording like ``launch sim.toml --record``: truth, scan events, patterns, frames with analyzer
    angles, polarizer states, composites with metrics, medium estimates, a plan, logs, heartbeats, and an
    ``analyzer_mount`` (no dedicated view: packed)."""
    rng = np.random.default_rng(7)
    bag = RigBag(path)
    t = T0

    def add(w: BagWriter, topic: str, msg) -> None:
        nonlocal t
        t += 7_000_000
        msg = type(msg)(**{n: getattr(msg, n) for n, _ in type(msg).FIELDS},
                        header=Header(stamp_ns=t - 1_000_000, seq=len(bag.sent.get(topic, [])), frame_id=""))
        w.add_message(topic, msg, log_time_ns=t)
        bag.sent.setdefault(topic, []).append((t, msg))

    h, wd = shape
    with BagWriter(path) as w:
        w.add_metadata("launch", {"launch": "synthetic", "namespace": NS, "file": "", "args": "{}",
                                  "graph": json.dumps(GRAPH)})
        add(w, f"{NS}/log", Log(level="INFO", node="sequencer", text="scan starts"))
        add(w, f"{NS}/planner/plan", Plan(modality="stripes", separation_m=0.2, scan_type="rotate",
                                          stripe_optima=[0.02, 0.03],
                                          curves={"separation_m": np.linspace(0.05, 0.3, 6),
                                                  "quality": np.linspace(1.0, 2.0, 6)}))
        for scan in range(1, scans + 1):
            add(w, f"{NS}/simulator/truth", Composite(
                images={"S": rng.random(shape), "chart_high": rng.random(shape) > 0.5,
                        "chart_band": rng.integers(0, 4, shape, dtype=np.int32)},
                method="truth", metrics={"separation_m": 0.2, "dark_offset_dn": 64.0}))
            add(w, f"{NS}/emitter/scan", ScanEvent(scan_id=scan, event="start", method="polarized_stripes",
                                                   stripes=stripes, analyzer_deg=[0.0, 90.0]))
            for angle in (0.0, 90.0):
                add(w, f"{NS}/polarizer/cmd", PolarizerCommand(target_deg=angle))
                add(w, f"{NS}/polarizer/state",
                    PolarizerState(angle_deg=angle, target_deg=angle, settled=True))
                for k in range(stripes):
                    step = k + (stripes if angle else 0)
                    add(w, f"{NS}/emitter/pattern", Pattern(kind="stripe", index=k, count=stripes,
                                                            scan_id=scan, step=step))
                    img = rng.integers(0, 4096, shape, dtype=np.uint16)
                    tag = f"stripe:{k}/{stripes}"
                    add(w, f"{NS}/camera/frame", Frame(image=img, exposure_s=0.008, polarizer_deg=angle,
                                                       pattern=tag, scan_id=scan, step=step))
            add(w, f"{NS}/emitter/scan", ScanEvent(scan_id=scan, event="done", method="polarized_stripes",
                                                   stripes=stripes, analyzer_deg=[0.0, 90.0]))
            add(w, f"{NS}/compositor/composite", Composite(
                images={"composite": rng.random(shape).astype(np.float32),
                        "saturated": np.zeros(shape, np.uint8)},
                method="polarized_stripes", scan_id=scan,
                metrics={"contrast": 0.4 + scan / 100, "dark_offset_dn": 64.0, "frames": 2 * stripes,
                         "analyzer_deg": [0.0, 90.0], "p": 0.7}))
            add(w, f"{NS}/medium/estimate", MediumEstimate(p=0.7, scan_id=scan))
            add(w, f"{NS}/heartbeat", Heartbeat(node="compositor", pid=42, uptime_s=scan * 1.0,
                                                counters={"received": 10 * scan}))
        add(w, f"{NS}/aux/frame", Frame(image=rng.integers(0, 255, (h // 2, wd // 2), dtype=np.uint8),
                                        exposure_s=0.01, bit_depth=8, pattern="flood"))
        add(w, f"{NS}/polarizer/mount", AnalyzerMount(inserted=True))
        add(w, f"{NS}/log", Log(level="WARNING", node="compositor", text="done"))
    return bag


@pytest.fixture
def rig_bag(tmp_path) -> RigBag:
    """A small synthetic recording (see :func:`write_rig_bag`)."""
    return write_rig_bag(tmp_path / "run.mcap")


@pytest.fixture
def make_rig_bag():
    """:func:`write_rig_bag` itself, for tests that want other sizes."""
    return write_rig_bag
