"""``polarstripe bench pipeline``: a full simulated scan through the real node processes.

For each camera size and simulator fidelity it launches the rig (simulator with its CiA 402 drive, polarizer
over the zmq CAN bus, grabber, emitter, compositor when there is one, and a sequencer), runs a one-frame flood
scan to warm every process up, then a ``polarized_stripes`` scan (``--stripes`` stripes at two analyzer
angles), and splits that scan's wall time:

* **simulation** — how long the simulator kept each frame request waiting (request to reply: model, resize,
  sensor, less what was made ahead while the previous frames travelled), from its per-frame log;
* **transport** — the emitter's camera round trips plus frame waits, minus the simulation: bus, codec,
  service hand-offs, the grabber;
* **analyzer** — waiting for the stage to turn and settle (physical: 90° at the stage's speed);
* **compositing** — the running max/min (:class:`~polarstripe.imaging.composite.RunningComposite`) over the
  same number of frames of this size, timed in this process (the compositor folds frames as they come, off
  the critical path);

and the CPU seconds of each node process during the scan (``/proc/PID/stat``), as a share of the rig's total,
with the simulator's system seconds and minor page faults (fresh pages: the patterns' sources it keeps).
``--threads 1,2`` runs each config with the simulator at each thread count (its ``threads`` param: frames
made at once) and gives the speedup of the scan (stage moves aside) against the first count.
The physical limit is a 30 fps camera: 60 frames in 2 s (the target for ``preview`` at 640×480).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from polarstripe.errors import PolarstripeError
from polarstripe.imaging.composite import RunningComposite

CAMERA_FPS = 30.0
DEFAULT_CONFIGS = "640x480:preview,640x480:standard,1280x1024:preview"


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--configs", default=DEFAULT_CONFIGS,
                        help="comma-separated SIZE:FIDELITY runs (default %(default)s; e.g. add "
                             "1280x1024:standard or 640x480:reference, which take minutes)")
    parser.add_argument("--stripes", type=int, default=30, help="stripes per scan (default 30)")
    parser.add_argument("--timeout", type=float, default=600.0, help="seconds allowed per run")
    parser.add_argument("--sim-param", action="append", default=[], metavar="KEY=VALUE",
                        help="extra simulator param (TOML value), e.g. render_ahead=false; repeatable")
    parser.add_argument("--threads", default="0", metavar="N[,N...]",
                        help="the simulator's threads per run (0: the CPU affinity, default); several, e.g. "
                             "1,2: each config at each count, the scaling against the first")


def _have(module: str) -> bool:

    return importlib.util.find_spec(module) is not None


def _launch_file(folder: Path, size: str, fidelity: str, stripes: int, can: str, sim_extra: str = "") -> Path:
    compositor = ""
    if _have("polarstripe.nodes.compositor"):
        compositor = f"""
[[node]]
name = "compositor"
module = "polarstripe.nodes.compositor"
params = {{ out = "{folder / 'out'}", comparison = false }}
"""
    sim = (f'resolution = "{size}", fidelity = "{fidelity}", can_channel = "{can}", '
           f'log_level = "DEBUG"{sim_extra}')
    seq = (f'methods = ["flood", "polarized_stripes"], stripes = {stripes}, plan = false, '
           'wait_composite = false, scan_timeout_s = 3000.0')
    text = f"""
[launch]
name = "bench"
namespace = "/bench"
[launch.env]
OMP_NUM_THREADS = "1"
[[node]]
name = "simulator"
module = "polarstripe.nodes.simulator"
params = {{ {sim} }}
[[node]]
name = "polarizer"
module = "polarstripe.nodes.polarizer"
params = {{ stage = "cia402", stage_options = {{ interface = "zmq", channel = "{can}" }} }}
[[node]]
name = "grabber"
module = "polarstripe.nodes.grabber"
params = {{ grab_timeout_s = 120.0 }}
{compositor}
[[node]]
name = "emitter"
module = "polarstripe.nodes.emitter"
params = {{ trigger_timeout_s = 125.0 }}
[[node]]
name = "sequencer"
module = "polarstripe.nodes.sequencer"
params = {{ {seq} }}
required = true
"""
    path = folder / "bench.toml"
    path.write_text(text)
    return path


def _cpu_s(pid: int) -> np.ndarray | None:
    """(CPU s, of it system s, minor page faults) of process ``pid`` so far (/proc/PID/stat)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None
    tick = os.sysconf("SC_CLK_TCK")
    return np.array([(int(fields[11]) + int(fields[12])) / tick, int(fields[12]) / tick, int(fields[7])])


def run_one(size: str, fidelity: str, stripes: int, timeout: float, sim_params: list[str] = ()) -> dict:
    """Launch the rig once and measure its polarized stripe scan."""

    folder = Path(tempfile.mkdtemp(prefix="ps-bench-", dir="/tmp"))
    try:
        can = f"ipc://{folder}/can"
        extra = "".join(", {} = {}".format(*(x.strip() for x in kv.partition("=")[::2])) for kv in sim_params)
        toml = _launch_file(folder, size, fidelity, stripes, can, extra)
        env = {**os.environ, "POLARSTRIPE_RUNS": str(folder / "runs")}
        proc = subprocess.Popen([sys.executable, "-m", "polarstripe", "launch", str(toml), "--once"], env=env,
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        start_cpu: dict[str, np.ndarray] = {}
        last_cpu: dict[str, np.ndarray] = {}
        scan_id = 2
        deadline = time.monotonic() + timeout
        graph, emitter_log = None, None
        while proc.poll() is None:
            if time.monotonic() > deadline:
                proc.terminate()
                proc.wait(10)
                raise PolarstripeError(f"bench run {size} {fidelity}: not done within {timeout:g} s")
            if graph is None:
                found = list((folder / "runs").glob("*/graph.json"))
                if found:
                    graph = found[0]
                    emitter_log = graph.parent / "logs" / "emitter.log"
            if graph is not None:
                try:
                    nodes = json.loads(graph.read_text())["nodes"]
                except (OSError, ValueError):
                    nodes = {}
                text = emitter_log.read_text() if emitter_log.exists() else ""
                for name, node in nodes.items():
                    cpu = _cpu_s(node["pid"]) if node.get("pid") else None
                    if cpu is None:
                        continue
                    if f"scan {scan_id} (" not in text:  # before the measured scan: keep the baseline
                        start_cpu[name] = cpu
                    elif f"scan {scan_id} (polarized_stripes) done" not in text and "fault" not in text:
                        last_cpu[name] = cpu
            time.sleep(0.05)
        logs = {p.stem: p.read_text() for p in graph.parent.glob("logs/*.log")} if graph else {}
        if proc.returncode != 0:
            raise PolarstripeError(f"bench run {size} {fidelity} failed: {proc.stderr.read()[-2000:]}"
                               f"{logs.get('sequencer', '')[-1000:]}")
        m = re.search(rf"scan {scan_id} \(polarized_stripes\) done in ([\d.]+) s: (\d+) frames, analyzer "
                      r"([\d.]+) s, camera ([\d.]+) s, frame wait ([\d.]+) s", logs["emitter"])
        scan_s, frames, analyzer_s, camera_s, wait_s = (float(g) for g in m.groups())
        sim_s = sum(float(t) for t in re.findall(rf"frame scan {scan_id} step \d+ \S+: ([\d.]+) s",
                                                   logs["simulator"]))
        used = {n: np.maximum(0.0, last_cpu.get(n, start_cpu[n]) - start_cpu[n]) for n in start_cpu}
        cpu = {n: float(u[0]) for n, u in used.items()}
        sim_sys_s, sim_faults = (float(v) for v in used.get("simulator", np.zeros(3))[1:])
        w, h = (int(v) for v in size.split("x"))
        scale = re.search(r"model at 1/(\d+)", logs.get("simulator", ""))
        return {"size": size, "fidelity": fidelity, "frames": int(frames), "scan_s": scan_s,
                "simulation_s": sim_s, "transport_s": max(0.0, camera_s + wait_s - sim_s),
                "analyzer_s": analyzer_s, "compositing_s": _compositing_s(w, h, int(frames)),
                "camera_only_s": scan_s - analyzer_s, "cpu_s": cpu, "simulator_system_s": sim_sys_s,
                "simulator_minor_faults": int(sim_faults),
                "render_scale": int(scale.group(1)) if scale else None,
                "error_vs_truth": _error_vs_truth(folder / "out" / "metrics.json")}
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def _error_vs_truth(path: Path) -> float | None:
    """The polarized stripe composite's error vs T from the compositor's metrics.json (None without it):
    what the simulator's model scale costs in the image (docs/planning.md §6.1)."""
    try:
        value = json.loads(path.read_text())["polarized_stripes"]["error_vs_truth"]
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return float(value) if value is not None else None


def _compositing_s(w: int, h: int, frames: int) -> float:

    rng = np.random.default_rng(0)
    distinct = [rng.integers(0, 4096, (h, w), dtype=np.uint16) for _ in range(4)]
    comp = RunningComposite((h, w), np.uint16, saturation=4095)
    t0 = time.perf_counter()
    for k in range(frames):
        comp.add(distinct[k % 4], 0.0 if k < frames // 2 else 90.0)
    return time.perf_counter() - t0


def main(args: argparse.Namespace) -> int:

    configs = []
    for item in args.configs.split(","):
        size, _, fidelity = item.strip().partition(":")
        if not re.fullmatch(r"\d+x\d+", size) or fidelity not in ("preview", "standard", "reference"):
            raise PolarstripeError(f"--configs: {item!r} is not SIZE:FIDELITY, e.g. 640x480:preview")
        configs.append((size, fidelity))
    try:
        counts = [int(n) for n in str(args.threads).split(",")]
    except ValueError:
        counts = [-1]
    if min(counts) < 0:
        raise PolarstripeError(f"--threads: {args.threads!r} is not a list of counts >= 0, e.g. 1,2")
    rows = []
    for size, fid in configs:
        first = None
        for n in counts:
            row = run_one(size, fid, args.stripes, args.timeout, [*args.sim_param, f"threads={n}"])
            first = first or row
            row["threads"], row["speedup"] = n, first["camera_only_s"] / row["camera_only_s"]
            rows.append(row)
    limit_s = 2 * args.stripes / CAMERA_FPS
    for r in rows:
        r["camera_limit_s"] = limit_s
        r["vs_camera_limit"] = r["camera_only_s"] / limit_s
    if args.json:
        print(json.dumps({"bench": "pipeline", "stripes": args.stripes, "camera_fps": CAMERA_FPS,
                          "runs": rows}))
        return 0
    print(f"polarized stripe scan: {args.stripes} stripes x 2 analyzer angles; physical limit: a "
          f"{CAMERA_FPS:g} fps camera takes {limit_s:.2f} s for {2 * args.stripes} frames")
    head = (f"{'size':>10} {'fidelity':>9} {'model':>5} {'threads':>7} {'frames':>6} {'scan s':>7} "
            f"{'w/o stage':>9} {'x limit':>7} {'speedup':>7} {'sim s':>7} {'transport s':>11} {'stage s':>7} "
            f"{'composite s':>11} {'error vs T':>10}")
    print(head)
    print("-" * len(head))
    for r in rows:
        model = f"1/{r['render_scale']}" if r["render_scale"] else "?"
        err = f"{r['error_vs_truth']:.3f}" if r["error_vs_truth"] is not None else "-"
        print(f"{r['size']:>10} {r['fidelity']:>9} {model:>5} {r['threads'] or 'auto':>7} {r['frames']:>6} "
              f"{r['scan_s']:>7.2f} {r['camera_only_s']:>9.2f} {r['vs_camera_limit']:>7.2f} "
              f"{r['speedup']:>7.2f} {r['simulation_s']:>7.2f} "
              f"{r['transport_s']:>11.3f} "
              f"{r['analyzer_s']:>7.2f} {r['compositing_s']:>11.3f} {err:>10}")
    print("model: the simulator's model resolution (1/k of the camera's, resized up; --sim-param "
          "render_scale=1 for none); error vs T: the polarized stripe composite's (docs/planning.md §6.1)")
    print("\nCPU seconds per node during the scan (share of the rig's CPU):")
    for r in rows:
        total = sum(r["cpu_s"].values()) or 1.0
        parts = ", ".join(f"{n} {s:.2f} ({100 * s / total:.0f}%)" for n, s in
                          sorted(r["cpu_s"].items(), key=lambda kv: -kv[1]))
        print(f"  {r['size']} {r['fidelity']} threads {r['threads'] or 'auto'}: {parts}; the simulator's "
              f"system s {r['simulator_system_s']:.2f}, minor page faults {r['simulator_minor_faults']}")
    return 0
