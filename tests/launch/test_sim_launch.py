"""The simulated rig as separate processes through ``polarstripe launch``: a clean run ends by itself with
every node stopping in order; a stage that never settles and a camera that disappears end in a published
fault and a clean shutdown, never a hang. The full ``launch/sim.toml`` at a small size checks the paper's
claim on the chart: polarized light striping beats flood lighting in contrast."""

import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
NODES = ["simulator", "polarizer", "grabber", "emitter", "sequencer"]


@pytest.fixture
def can():
    folder = tempfile.mkdtemp(prefix="ps-can-", dir="/tmp")  # ipc paths are limited to ~107 bytes
    yield f"ipc://{folder}/bus"
    shutil.rmtree(folder, ignore_errors=True)


def launch(tmp_path, file, *overrides, timeout=90):
    env = {**os.environ, "POLARSTRIPE_RUNS": str(tmp_path / "runs")}
    proc = subprocess.run([sys.executable, "-m", "polarstripe", "launch", str(file), "--once", *overrides],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=timeout)
    (run_dir,) = (tmp_path / "runs").iterdir()
    logs = {p.stem: p.read_text() for p in (run_dir / "logs").iterdir()}
    proc.exits = json.loads((run_dir / "exits.json").read_text())["nodes"]  # the launcher's record
    return proc, logs


def assert_clean_exit(proc, logs, names, *, failed=()):
    """Every node exited 0 (those in ``failed``: 1, by themselves), by itself or at the launcher's first
    SIGINT, without a traceback."""
    assert "still running after" not in proc.stderr, proc.stderr  # nobody needed SIGTERM or SIGKILL
    assert sorted(proc.exits) == sorted(names)
    for name in names:
        assert "Traceback" not in logs[name], logs[name]
        e = proc.exits[name]
        code = 1 if name in failed else 0
        assert (e["exit_code"], e["signal"], e["respawns"]) == (code, None, 0), (name, e, logs[name])
        assert e["stopped_by"] in ((None,) if name in failed else (None, "SIGINT")), (name, e)


def half_rig(tmp_path, can, *, methods, sim_params="", emitter_params="", polarizer_params=""):
    """simulator, polarizer (CiA 402 over the zmq CAN bus), grabber, emitter and sequencer; no planner or
    compositor."""
    f = tmp_path / "half.toml"
    f.write_text(f"""
[launch]
name = "half"
namespace = "/rig"
[launch.env]
OMP_NUM_THREADS = "1"
[[node]]
name = "simulator"
module = "polarstripe.nodes.simulator"
params = {{ resolution = "48x36", can_channel = "{can}" {sim_params} }}
[[node]]
name = "polarizer"
module = "polarstripe.nodes.polarizer"
params = {{ stage = "cia402", stage_options = {{ interface = "zmq", channel = "{can}" }} {polarizer_params} }}
[[node]]
name = "grabber"
module = "polarstripe.nodes.grabber"
[[node]]
name = "emitter"
module = "polarstripe.nodes.emitter"
params = {{ stripes = 3 {emitter_params} }}
[[node]]
name = "sequencer"
module = "polarstripe.nodes.sequencer"
params = {{ methods = {json.dumps(methods)}, stripes = 3, plan = false, wait_composite = false }}
required = true
""")
    return launch(tmp_path, f)


def test_scans_run_to_the_end_and_every_node_stops_cleanly(tmp_path, can):
    proc, logs = half_rig(tmp_path, can, methods=["flood", "polarized_stripes", "hf_separation"])
    assert proc.returncode == 0, proc.stderr + logs["sequencer"]
    assert "sequencer exit 0" in proc.stderr
    for method, sid in (("flood", 1), ("polarized_stripes", 2), ("hf_separation", 3)):
        assert f"{method}: scan {sid} done" in logs["sequencer"]
    # the simulator rendered each pattern once: the second analyzer angle came from its cache
    stats = json.loads(logs["simulator"].split("stats ", 1)[1].splitlines()[0])
    assert stats["frames"] == 1 + 3 * 2 + 2 and stats["renders"] == 1 + 3 + 2
    assert_clean_exit(proc, logs, NODES)


def test_stage_that_never_settles_ends_in_a_published_fault(tmp_path, can):
    proc, logs = half_rig(tmp_path, can, methods=["polarized_flood", "flood"],
                          sim_params=', faults = ["never_settle on"]',
                          emitter_params=", settle_timeout_s = 4.0",
                          polarizer_params=", settle_timeout_s = 1.0")
    assert proc.returncode == 1 and "sequencer exit 1" in proc.stderr
    assert "polarized_flood: scan 1 fault: polarizer/state" in logs["sequencer"], logs["sequencer"]
    assert "flood: scan 2 done" in logs["sequencer"]  # the rig is usable after the fault
    assert_clean_exit(proc, logs, NODES, failed=["sequencer"])


def test_camera_that_disappears_ends_in_a_published_fault(tmp_path, can):
    proc, logs = half_rig(tmp_path, can, methods=["stripes"], sim_params=', faults = ["camera_lost on"]')
    assert proc.returncode == 1
    assert "step 0 (stripe:0/3): camera/trigger: DeviceLost" in logs["sequencer"], logs["sequencer"]
    assert "ERROR grabber: frame of scan 1 step 0" in logs["grabber"]
    assert_clean_exit(proc, logs, NODES, failed=["sequencer"])


SMALL = ("resolution=96x72", "stripes=8")


@pytest.fixture(scope="module")
def alone(tmp_path_factory):
    """One small sim launch by itself (its CAN segment, sockets and files named per run)."""
    tmp = tmp_path_factory.mktemp("alone")
    out = tmp / "out"
    proc, logs = launch(tmp, ROOT / "launch" / "sim.toml", f"out={out}", *SMALL, timeout=150)
    return tmp, out, proc, logs


def test_sim_launch_polarized_stripes_beat_flood(alone):
    tmp_path, out, proc, logs = alone
    assert proc.returncode == 0, proc.stderr + logs.get("sequencer", "")
    assert "prepared polarstripe.nodes.planner:warm_kernels in" in proc.stderr  # kernels before the graph
    metrics = json.loads((out / "metrics.json").read_text())
    assert set(metrics) == {"flood", "polarized_flood", "stripes", "polarized_stripes", "hf_separation"}
    assert metrics["polarized_stripes"]["contrast"] > metrics["flood"]["contrast"]
    errors = {name: m["error_vs_truth"] for name, m in metrics.items()}
    assert all(isinstance(e, float) and 0.0 < e < 1.0 for e in errors.values()), errors
    for name in ("polarized_stripes", "flood", "comparison"):
        assert (out / f"{name}.png").is_file()
    assert_clean_exit(proc, logs, [*NODES, "compositor", "planner"])


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    """Two small sim launches at once, ``a`` naming its CAN segment on the command line (a runs folder each);
    while ``a`` runs, a third launch in ``a``'s runs folder naming the same segment: the refusal, and how
    long it took."""
    tmp = tmp_path_factory.mktemp("pair")
    segment = f"ps-test-shared-{os.getpid()}"
    cmd = [sys.executable, "-m", "polarstripe", "launch", str(ROOT / "launch" / "sim.toml"), "--once", *SMALL]
    procs = {}
    try:
        for name, extra in (("a", [f"can={segment}"]), ("b", [])):
            env = {**os.environ, "POLARSTRIPE_RUNS": str(tmp / f"runs_{name}")}
            with open(tmp / f"{name}.txt", "w") as console:  # a file, not a pipe nobody reads meanwhile
                procs[name] = subprocess.Popen([*cmd, *extra, f"out={tmp / name}"], cwd=tmp, env=env,
                                               text=True, stdout=console, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + 120
        while not list((tmp / "runs_a").glob("*/graph.json")):  # a claims the segment right after
            assert time.monotonic() < deadline and procs["a"].poll() is None, (tmp / "a.txt").read_text()
            time.sleep(0.05)
        t0 = time.monotonic()
        refused = subprocess.run([*cmd, f"can={segment}", "plan=false", "calibrate=false",
                                  f"out={tmp / 'c'}"],
                                 cwd=tmp, env={**os.environ, "POLARSTRIPE_RUNS": str(tmp / "runs_a")},
                                 text=True, capture_output=True, timeout=120)
        took = time.monotonic() - t0
        still_running = procs["a"].poll() is None  # the refusal came while a held the segment
        for p in procs.values():
            p.wait(timeout=240)
    finally:
        for p in procs.values():
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
                p.wait(timeout=60)
    outputs = {name: (tmp / f"{name}.txt").read_text() for name in procs}
    return tmp, procs, outputs, segment, refused, took, still_running


def test_two_sim_launches_at_once_do_not_meet(alone, pair):
    """Two demos at the same time (each its own CAN segment, sockets and out folder) give the numbers of one
    alone."""
    _, out_alone, proc, _ = alone
    assert proc.returncode == 0, proc.stderr
    tmp_path, procs, outputs, *_ = pair
    # the launchers' own lines (each node's exit, with its log's last line when not 0) and the sequencer's
    # errors, not the rest (a string: pytest shows it whole, where it cuts the repr of a dict short)
    said = "\n".join(f"{name}: {ln}" for name, text in outputs.items() for ln in text.splitlines()
                     if ln.startswith("[launch") or " ERROR " in ln)
    assert [p.returncode for p in procs.values()] == [0, 0], said
    alone_m = json.loads((out_alone / "metrics.json").read_text())
    for name in ("a", "b"):
        m = json.loads((tmp_path / name / "metrics.json").read_text())
        assert set(m) == set(alone_m)
        for method in m:
            for key in ("contrast", "error_vs_truth"):
                assert m[method][key] == pytest.approx(alone_m[method][key], rel=1e-6, abs=1e-9), \
                    (name, method, key, m[method][key], alone_m[method][key])
            assert m[method]["analyzer_deg"] == pytest.approx(alone_m[method]["analyzer_deg"], abs=1e-6)


def test_a_named_can_segment_in_use_is_refused(pair):
    """A CAN segment named on the command line while another launch uses it is refused at once (the launch
    ``a`` of :func:`pair` holds it: no launch of its own here)."""
    *_, segment, refused, took, still_running = pair
    assert still_running
    assert refused.returncode == 2, refused.stderr
    assert f"can='{segment}' is in use by launch sim (pid " in refused.stderr
    assert "simulator started" not in refused.stderr and took < 30


@pytest.mark.long
def test_sim_polarization_launch_scans_one_frame_per_stripe_and_ends_with_metrics(tmp_path):
    """launch/sim_polarization.toml (a polarization camera, no polarizer node): every method through the
    mosaic, polarized stripes in N frames (a rotating analyzer takes 2N), the chart's contrast above
    flood's."""
    out = tmp_path / "out"
    proc, logs = launch(tmp_path, ROOT / "launch" / "sim_polarization.toml", f"out={out}", *SMALL,
                        timeout=150)
    assert proc.returncode == 0, proc.stderr + logs.get("sequencer", "")
    metrics = json.loads((out / "metrics.json").read_text())
    assert set(metrics) == {"flood", "polarized_flood", "stripes", "polarized_stripes", "hf_separation"}
    assert metrics["polarized_stripes"]["frames"] == 8 and metrics["polarized_flood"]["frames"] == 1
    assert metrics["polarized_stripes"]["mosaic"]["layout_deg"] == [90.0, 45.0, 135.0, 0.0]
    assert metrics["polarized_stripes"]["contrast"] > metrics["flood"]["contrast"]
    assert 0.0 < metrics["polarized_stripes"]["p"] < 1.0
    assert_clean_exit(proc, logs, ["simulator", "grabber", "emitter", "sequencer", "compositor", "planner"])
