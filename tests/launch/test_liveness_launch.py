"""A node killed with SIGKILL mid-scan, as separate processes through ``polarstripe launch``
(runtime/liveness.py): the sequencer names the lost node within a second or two instead of waiting out its
scan timeout; with ``respawn = true`` the scan is retried once, with a new scan id, and succeeds."""

import json
import os
import re
import signal
import subprocess
import sys
import time
from datetime import datetime


def rig(tmp_path, *, respawn: str) -> str:
    """simulator (slowed to ~0.1 s a frame), grabber, compositor, emitter, sequencer: one stripe scan."""
    f = tmp_path / "rig.toml"
    f.write_text(f"""
[launch]
name = "live"
namespace = "/rig"
[launch.env]
OMP_NUM_THREADS = "1"
[[node]]
name = "simulator"
module = "polarstripe.nodes.simulator"
params = {{ resolution = "48x36", faults = ["frame_delay 0.1"] }}
[[node]]
name = "grabber"
module = "polarstripe.nodes.grabber"
[[node]]
name = "compositor"
module = "polarstripe.nodes.compositor"
params = {{ out = "{tmp_path / 'out'}", geometry = "none" }}
[[node]]
name = "emitter"
module = "polarstripe.nodes.emitter"
params = {{ stripes = 16 }}
respawn = {respawn}
respawn_delay = 0.2
[[node]]
name = "sequencer"
module = "polarstripe.nodes.sequencer"
params = {{ methods = ["stripes"], stripes = 16, plan = false, calibrate = false }}
required = true
""")
    return str(f)


def kill_mid_scan(tmp_path, file, victim):
    """Launch ``file``; SIGKILL ``victim`` once the emitter's first scan runs; the launch's output, the
    logs, the run directory and the wall time of the kill."""
    env = {**os.environ, "POLARSTRIPE_RUNS": str(tmp_path / "runs")}
    proc = subprocess.Popen([sys.executable, "-m", "polarstripe", "launch", file, "--once"], cwd=tmp_path,
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    killed_at = None
    try:
        deadline = time.monotonic() + 120
        while killed_at is None and time.monotonic() < deadline and proc.poll() is None:
            runs = list((tmp_path / "runs").glob("*/logs/emitter.log"))
            if runs and "scan 1 (stripes)" in runs[0].read_text():
                run_dir = runs[0].parents[1]
                pid = json.loads((run_dir / "graph.json").read_text())["nodes"][victim]["pid"]
                os.kill(pid, signal.SIGKILL)
                killed_at = time.time()
            time.sleep(0.02)
        out, _ = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert killed_at is not None, out
    logs = {p.stem: p.read_text() for p in (run_dir / "logs").iterdir()}
    return proc.returncode, out, logs, run_dir, killed_at


def when(log: str, text: str) -> float:
    """The wall time of the first log line containing ``text``."""
    line = next(ln for ln in log.splitlines() if text in ln)
    stamp = re.match(r"(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3})", line).group(1)
    return datetime.strptime(stamp, "%Y-%m-%d %H:%M:%S,%f").timestamp()


def test_a_killed_grabber_is_named_at_once_and_ends_the_launch(tmp_path):
    code, out, logs, _, killed_at = kill_mid_scan(tmp_path, rig(tmp_path, respawn="false"), "grabber")
    seq = logs["sequencer"]
    assert code == 1, out
    assert "stripes: scan 1: node 'grabber' lost: no heartbeat for" in seq, seq
    assert "node 'grabber' lost and the launch does not respawn it: stopping" in seq, seq
    took = when(seq, "node 'grabber' lost: no heartbeat") - killed_at
    print(f"grabber SIGKILL -> sequencer fault in {took:.2f} s")
    assert took < 3.0, took  # the deadline is 1 s; not the emitter's 35 s trigger timeout nor the 600 s scan


def test_a_killed_emitter_is_respawned_and_the_scan_retried_once_with_a_new_id(tmp_path):
    code, out, logs, run_dir, killed_at = kill_mid_scan(tmp_path, rig(tmp_path, respawn="true"), "emitter")
    seq = logs["sequencer"]
    assert code == 0, out + seq
    took = when(seq, "node 'emitter' lost") - killed_at
    print(f"emitter SIGKILL -> sequencer fault in {took:.2f} s")
    assert took < 3.0, took
    assert "stripes: retrying the scan once: node 'emitter' is back (incarnation 1)" in seq, seq
    assert "stripes: scan 2 done" in seq, seq
    assert "incarnation 1: scan ids go on from 2" in logs["emitter"]
    assert json.loads((run_dir / "state" / "emitter.json").read_text())["next_scan_id"] == 3
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())["stripes"]
    assert not metrics.get("error") and metrics["scan_id"] == 2, metrics  # composited: not "no frames"
