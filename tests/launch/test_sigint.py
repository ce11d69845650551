"""Ctrl-C that stops (docs/architecture.md "Shutdown"): SIGINT to the launcher of a small sim launch at seeded
random moments — the ``[launch] prepare`` step, nodes starting (the planner plans in its setup), the sequencer
waiting for the plan, the calibration, the scans — and each time: the launcher exits by itself (130), every
node exited by itself after that first SIGINT (``exits.json``: nobody needed the launcher's SIGTERM or
SIGKILL, no traceback), no process of the launch is left (its process groups, and any process carrying the
launch's marker in its environment) and no socket file was left in the run's ``${run_sock}``.

One launch per moment, so each moment costs the time to reach it. To fit ~90 s: two launches run at a time;
moments after the prepare step run the shipped file without its ``prepare`` line (the kernels are compiled by
then: the same nodes, params and graph, ~2 s less per launch); and the fast variant's 10 moments lean toward
the cheap early phases (where the issue's hangs were) with every phase at least once. ``slow`` runs 40 spread
evenly."""

import json
import os
import random
import signal
import subprocess
import sys
import time
import uuid
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
from polarstripe.runtime.launch_file import find_launch_file

ARGS = ["--once", "resolution=64x48", "stripes=4"]
SHUTDOWN_TIMEOUT_S = 5.0  # launch/sim.toml's shutdown_timeout

# phase -> (where its clock starts: the launcher's console or a node's log, the text that marks it, the
# longest random delay after the mark [s])
PHASES = {
    "prepare": ("console", "preparing:", 1.0),
    "start-up": ("console", "simulator started", 2.5),
    "planning": ("sequencer", "INFO sequencer: started", 1.0),
    "calibration": ("sequencer", "sequencer: plan:", 1.0),
    "scans": ("sequencer", "sequencer: calibrated:", 2.5),
}


def _marked(marker: str) -> list[int]:
    """Pids of the processes whose environment carries ``marker`` (everything the launch started)."""
    pids = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                if marker.encode() in (d / "environ").read_bytes():
                    pids.append(int(d.name))
            except OSError:
                pass
    return pids


def _text(path: Path) -> str:
    try:
        return path.read_text(errors="replace")
    except OSError:
        return ""


def sigint_at(tmp: Path, phase: str, delay_s: float) -> dict:
    """One launch, SIGINT ``delay_s`` after ``phase``'s mark; returns what was checked (or asserts)."""
    where, mark, _ = PHASES[phase]
    marker = f"PS_SIGINT_TEST={uuid.uuid4().hex}"
    runs = tmp / "runs"
    env = {**os.environ, "POLARSTRIPE_RUNS": str(runs), marker.split("=")[0]: marker.split("=")[1]}
    console = tmp / "console.txt"
    file = find_launch_file("sim")
    if phase != "prepare":  # the same launch without compiling (loading) the kernels first
        text = file.read_text()
        file = tmp / "sim.toml"
        file.write_text("\n".join(ln for ln in text.splitlines() if not ln.startswith("prepare =")))
    with open(console, "wb") as out:
        proc = subprocess.Popen([sys.executable, "-m", "polarstripe", "launch", str(file), *ARGS,
                                 f"out={tmp}/out"], cwd=tmp, env=env, stdout=out, stderr=subprocess.STDOUT,
                                start_new_session=True)
    try:
        # the planner plans in its setup, with all orders of scattering: ~15 s CPU at 64x48 (the higher
        # orders' grid solve per model call), 115 s of wall time at a load average of 13 on the 2-core machine
        deadline = time.monotonic() + 180
        run_dir = None
        while time.monotonic() < deadline and proc.poll() is None:
            if run_dir is None and runs.is_dir():
                run_dir = next(iter(runs.iterdir()), None)
            log = run_dir / "logs" / f"{where}.log" if run_dir else None
            source = console if where == "console" else log
            if source is not None and mark in _text(source):
                break
            time.sleep(0.02)
        else:
            raise AssertionError(f"{phase}: {mark!r} never came (exit {proc.poll()}):\n{_text(console)}")
        time.sleep(delay_s)
        sent = time.monotonic()
        proc.send_signal(signal.SIGINT)
        try:
            status = proc.wait(timeout=SHUTDOWN_TIMEOUT_S + 5)
        except subprocess.TimeoutExpired:
            raise AssertionError(f"{phase}+{delay_s:.2f}s: the launcher did not exit:\n{_text(console)}"
                                 ) from None
        took = time.monotonic() - sent
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    text = _text(console)
    what = f"{phase}+{delay_s:.2f}s"
    if status == 0 and "every required node has exited" in text:
        return {"phase": phase, "delay_s": delay_s, "stop_s": took, "late": True}  # ended before the SIGINT
    assert status == 130, (what, status, text)
    exits = json.loads((run_dir / "exits.json").read_text())
    assert "still running after" not in text, (what, text)
    for name, e in exits["nodes"].items():
        if not e["started"]:
            continue
        log = _text(run_dir / "logs" / f"{name}.log")
        assert e["stopped_by"] in (None, "SIGINT"), (what, name, e, log[-2000:])  # no SIGTERM, no SIGKILL
        assert e["signal"] is None and e["exit_code"] in (0, 130), (what, name, e, log[-2000:])
        assert "Traceback" not in log, (what, name, log[-3000:])
        with pytest.raises(ProcessLookupError):
            os.killpg(e["pid"], 0)  # nothing left in the node's process group
    assert exits["left_sockets"] == [], (what, exits["left_sockets"])  # every node removed its own
    graph = json.loads((run_dir / "graph.json").read_text())
    sock = {Path(n["pub"][len("ipc://"):]).parent for n in graph["nodes"].values()}  # ${run_sock}
    assert len(sock) == 1 and not sock.pop().exists(), what
    assert _marked(marker) == [], (what, "orphans")
    started = [n for n, e in exits["nodes"].items() if e["started"]]
    return {"phase": phase, "delay_s": delay_s, "stop_s": took, "late": False, "started": started}


def _moments(counts: dict[str, int], seed: int) -> list[tuple[str, float]]:
    rng = random.Random(seed)
    return [(phase, rng.uniform(0.0, PHASES[phase][2])) for phase, n in counts.items() for _ in range(n)]


def _one(tmp_path, i, phase, delay):
    tmp = tmp_path / f"m{i:02d}"
    tmp.mkdir()
    t0 = time.monotonic()
    result = sigint_at(tmp, phase, delay)
    result["total_s"] = time.monotonic() - t0
    return result


def _run_moments(tmp_path, counts, seed):
    # two launches at a time (each its own run directory, sockets and CAN segment): a launch mostly waits
    # (process start-up, timers, exits), so two share the cores well and the moments take ~60 % of the time
    with ThreadPoolExecutor(2) as pool:
        results = list(pool.map(lambda m: _one(tmp_path, m[0], *m[1]), enumerate(_moments(counts, seed))))
    print("\n".join(f"{r['phase']:<12} +{r['delay_s']:.2f} s: stopped in {r['stop_s']:.2f} s"
                    f" (moment {r['total_s']:.1f} s)"
                    + (" (the launch had ended)" if r["late"] else f", {len(r['started'])} nodes up")
                    for r in results))
    late = [r for r in results if r["late"]]
    assert len(late) <= len(results) // 10, late  # the moments fall inside the launch, not after it
    assert max(r["stop_s"] for r in results) < SHUTDOWN_TIMEOUT_S + 3
    return results


@pytest.mark.timeout(400)  # ~20 s; more on a loaded machine
def test_sigint_at_6_random_moments_stops_every_node_by_itself(tmp_path):
    """One moment in each phase, two in start-up (where most processes come and go): the suite's budget;
    the 40 moments below under --long."""
    counts = {"prepare": 1, "start-up": 2, "planning": 1, "calibration": 1, "scans": 1}
    results = _run_moments(tmp_path, counts, seed=12)
    assert len(results) == 6


@pytest.mark.long
@pytest.mark.timeout(900)  # ~5 minutes: pytest --long
def test_sigint_at_40_moments_spread_evenly(tmp_path):
    counts = dict.fromkeys(PHASES, 8)
    results = _run_moments(tmp_path, counts, seed=1212)
    assert len(results) == 40


LEAVING_NODES = """
import os, subprocess, sys
from polarstripe.runtime.node import Node

# a child in the node's process group that ignores the stop signals; it writes 'ready', and once its node is
# gone it stays LINGER more seconds (then writes 'done' and exits)
CHILD = '''
import os, signal, sys, time
signal.signal(signal.SIGINT, signal.SIG_IGN)
signal.signal(signal.SIGTERM, signal.SIG_IGN)
folder, linger, parent = sys.argv[1], float(sys.argv[2]), os.getppid()
open(os.path.join(folder, 'ready'), 'w').close()
while os.getppid() == parent:
    time.sleep(0.01)
time.sleep(linger)
open(os.path.join(folder, 'done'), 'w').close()
'''


class Leaver(Node):
    LINGER = 0.0

    def setup(self):
        folder = os.path.join(os.environ["PS_LEAVE_DIR"], self.name)
        os.makedirs(folder)
        subprocess.Popen([sys.executable, "-c", CHILD, folder, str(self.LINGER)])


class Lingers(Leaver):
    LINGER = 1.0


class Stays(Leaver):
    LINGER = 600.0
"""


def test_what_a_node_leaves_in_its_process_group_is_waited_for_then_killed(tmp_path):
    """A child a node started (in its process group) that outlives it: one that ends 1 s after its node is
    waited for, one that would stay is killed after shutdown_timeout; the launcher exits only then, so that
    nothing is left (runtime/pgroups.py)."""
    (tmp_path / "ps_leaving_nodes.py").write_text(LEAVING_NODES)
    (tmp_path / "leave.toml").write_text(
        '[launch]\nname = "leave"\nshutdown_timeout = 2.0\n'
        '[[node]]\nname = "lingers"\nmodule = "ps_leaving_nodes:Lingers"\n'
        '[[node]]\nname = "stays"\nmodule = "ps_leaving_nodes:Stays"\n'
    )
    env = {**os.environ, "POLARSTRIPE_RUNS": str(tmp_path / "runs"), "PS_LEAVE_DIR": str(tmp_path),
           "PYTHONPATH": os.pathsep.join([str(tmp_path), *filter(None, [os.environ.get("PYTHONPATH")])])}
    console = tmp_path / "console.txt"
    with open(console, "wb") as out:
        proc = subprocess.Popen([sys.executable, "-m", "polarstripe", "launch", str(tmp_path / "leave.toml")],
                                cwd=tmp_path, env=env, stdout=out, stderr=subprocess.STDOUT,
                                start_new_session=True)
    try:
        deadline = time.monotonic() + 60
        while not all((tmp_path / name / "ready").exists() for name in ("lingers", "stays")):
            assert proc.poll() is None and time.monotonic() < deadline, _text(console)
            time.sleep(0.05)
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=30) == 130, _text(console)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    text = _text(console)
    exits = json.loads(next((tmp_path / "runs").glob("*/exits.json")).read_text())
    for name in ("lingers", "stays"):
        e = exits["nodes"][name]
        assert e["exit_code"] == 0 and e["stopped_by"] == "SIGINT", (name, e, text)
        with pytest.raises(ProcessLookupError):
            os.killpg(e["pid"], 0)  # the launcher reaped its child too
    assert (tmp_path / "lingers" / "done").exists()  # waited for: it ended by itself
    assert not (tmp_path / "stays" / "done").exists()
    assert "stays left processes in its group after it exited: SIGKILL" in text, text
    assert "lingers left" not in text, text
