"""``polarstripe bench soak --minutes N [--chaos SECONDS] [--json]``: the simulated rig scanning for N
minutes after its warm-up, optionally killing a random node every SECONDS; what held and what did not.

The N minutes start when the warm-up ends (``WARM_SCANS`` completed scans), so a slow start (the planner's
plan, the calibration, a loaded machine) shortens neither the chaos nor the memory watch; start-up and
warm-up together must end within ``WARM_TIMEOUT_S`` (300 s), or the soak fails with the launch's last lines.

The launch is the shipped ``launch/sim.toml`` with, for the soak, every node respawned by the launcher
(``respawn = true``, 0.5 s, no respawn limit) and the sequencer scanning until stopped (``repeat = 0``, its
scan and composite waits bounded at 60 s and 30 s so a scan that hangs is counted, not waited on for 10
minutes). Chaos (``--chaos``) sends SIGKILL to one node at a time, picked at random (seeded) among the nodes
(never the launcher; the sequencer too, since the soak's launch respawns it); the next kill waits until the
rig has recovered from the last one, and none comes in the last 30 s. At the end the launcher gets SIGINT,
and its ``exits.json`` says whether every node then stopped by itself.

Measured from the bus (the launch's own topics, as ``polarstripe topic`` reads them) and ``/proc``:

* **scans** — completed (a composite without an error), failed with a clear fault (an ``emitter/scan`` fault
  or a composite error, with its text), failed without one (a fault with no text), and unended (started,
  never ended: the emitter was killed under it; the sequencer names the lost node);
* **frames lost** — sequence gaps on the single-publisher topics the rig reads in ``all`` mode
  (``camera/frame``, ``emitter/scan``, ``compositor/composite``), counted by the soak's own ``all``
  subscribers as the bus counts them (``runtime/bus.py``), split into those within a kill's window (kill →
  recovered + 5 s) and those outside any (must be 0). (The nodes' heartbeat ``gaps`` cannot serve: they
  sum over every subscription, ``heartbeat`` too, whose seven publishers' sequences interleave.)
* **memory** — every node's RSS (``/proc/PID/status`` VmRSS) after the warm-up (``WARM_SCANS`` = 15
  completed scans, three passes over the methods: the compositor grows ~110 MB over its first ~15 scans,
  matplotlib and the depth path loading and caching, then stays flat) and at the end, for the process that
  lived longest (a respawned process from its own warm-up: 15 scans after it appeared); a node whose RSS
  grew by more than ``GROWTH_BOUND_MB`` (or ``GROWTH_BOUND_FRACTION``, whichever is larger) fails the soak;
  a killed node whose new process was not warm when the soak ended has no numbers ("not warm"), any other
  node without them fails it;
* **recovery** — per kill, the time until the launcher's new process of that node is in the graph
  (respawned), until the first scan started after the kill was composited (first scan), and until every
  method that had worked before the kill has worked again in scans started after it (recovered: a killed
  simulator takes the CAN drive with it, and polarized scans fail until the polarizer has reconnected).

Exit status 0 when nothing was lost outside a kill, every kill was recovered from, no node grew beyond the
bound, at least one scan completed and the final SIGINT stopped every node by itself; 1 otherwise.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import tomllib
from pathlib import Path

import zmq
from polarstripe.bench.soak_table import WARM_SCANS, table
from polarstripe.errors import PolarstripeError
from polarstripe.msgs import Composite, Frame, ScanEvent
from polarstripe.runtime.bus import Subscriber
from polarstripe.runtime.graph import pub_endpoints
from polarstripe.runtime.launch_file import find_launch_file

GROWTH_BOUND_MB = 30.0
GROWTH_BOUND_FRACTION = 0.10
KILL_GRACE_S = 5.0  # after a recovery, gaps still count as the kill's
SAMPLE_S = 5.0  # RSS sampling period
LAST_KILL_S = 30.0  # no kill this close to the end: the rig gets the time to recover
WARM_TIMEOUT_S = 300.0  # start-up (plan, calibration) and warm-up must end within this


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--minutes", type=float, default=2.0,
                        help="how long to scan after the warm-up (default 2)")
    parser.add_argument("--chaos", type=float, default=0.0, metavar="SECONDS",
                        help="kill a random node every SECONDS (after it recovered from the last; 0: never)")
    parser.add_argument("--resolution", default="64x48", help="camera WxH (default 64x48)")
    parser.add_argument("--stripes", type=int, default=8, help="stripes per scan (default 8)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the chaos's choices")
    parser.add_argument("--keep", metavar="DIR", help="keep the run (logs, exits.json, composites) in DIR")


# ---- the launch -----------------------------------------------------------------------------------------
def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int | float):
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)  # a JSON string is a TOML basic string
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{k} = {_toml_value(x)}" for k, x in v.items()) + " }"
    raise TypeError(f"no TOML for {v!r}")


def soak_launch(folder: Path) -> Path:
    """The shipped sim launch with respawn on every node and the sequencer scanning until stopped."""
    doc = tomllib.loads(find_launch_file("sim").read_text())
    lines = ["[launch]"] + [f"{k} = {_toml_value(v)}" for k, v in doc["launch"].items() if k != "env"]
    lines += ["[launch.env]"] + [f"{k} = {_toml_value(v)}" for k, v in doc["launch"].get("env", {}).items()]
    lines += ["[args]"] + [f"{k} = {_toml_value(v)}" for k, v in doc["args"].items()]
    for node in doc["node"]:
        node.update(respawn=True, respawn_delay=0.5, max_respawns=1_000_000, respawn_max_delay=8.0)
        if node["name"] == "sequencer":
            node["params"].update(repeat=0, scan_timeout_s=60.0, composite_timeout_s=30.0)
        lines += ["[[node]]"] + [f"{k} = {_toml_value(v)}" for k, v in node.items()]
    path = folder / "soak.toml"
    path.write_text("\n".join(lines) + "\n")
    return path


def _rss_mb(pid: int) -> float | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except (OSError, ValueError):
        pass
    return None


class Soak:
    """One soak run: start the launch, watch it, kill nodes, stop it, and the report (:meth:`report`)."""

    def __init__(self, args: argparse.Namespace, folder: Path):
        self.args, self.folder = args, folder
        self.rng = random.Random(args.seed)
        self.scans = {"completed": 0, "failed_clear": 0, "failed_unclear": 0, "unended": 0}
        self.faults: list[str] = []
        self.open: dict[int, float] = {}  # scan id -> start time, until it ended
        self.started: dict[int, float] = {}  # scan id -> start time
        self.methods_ok: set[str] = set()  # the methods composited without an error so far
        self.ended: set[int] = set()
        self.kills: list[dict] = []
        self.lost = {"outside": 0, "within": 0}
        self.lost_by_topic: dict[str, int] = {}
        self.rss: dict[tuple[str, int], list[float]] = {}  # (node, pid) -> [first, last, samples]
        self.seen: dict[tuple[str, int], int] = {}  # (node, pid) -> completed scans when first seen
        self.warm = False
        self.warmup_s: float | None = None  # from the graph up to the warm-up's end
        self.t0 = 0.0

    # ---- running ---------------------------------------------------------------------------------------
    def run(self) -> dict:
        a = self.args
        env = {**os.environ, "POLARSTRIPE_RUNS": str(self.folder / "runs")}
        cmd = [sys.executable, "-m", "polarstripe", "launch", str(soak_launch(self.folder)),
               f"resolution={a.resolution}", f"stripes={a.stripes}", f"out={self.folder / 'out'}"]
        with open(self.folder / "console.txt", "wb") as out:
            self.proc = subprocess.Popen(cmd, env=env, stdout=out, stderr=subprocess.STDOUT,
                                         start_new_session=True)
        try:
            self.graph_file = self._wait_graph()
            self._watch()
            return self._stop()
        finally:
            if self.proc.poll() is None:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait()

    def _wait_graph(self) -> Path:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise PolarstripeError(f"soak: the launch ended at start (exit {self.proc.returncode}): "
                                       + _tail(self.folder / "console.txt"))
            for g in (self.folder / "runs").glob("*/graph.json"):
                try:
                    if json.loads(g.read_text()).get("state") == "running":
                        return g
                except (OSError, ValueError):
                    pass
            time.sleep(0.1)
        raise PolarstripeError("soak: the launch did not start within 120 s")

    def graph(self) -> dict:
        try:
            return json.loads(self.graph_file.read_text())
        except (OSError, ValueError):  # being rewritten: the last one read
            return self._graph

    def _watch(self) -> None:
        self._graph = json.loads(self.graph_file.read_text())
        ns = self._graph["namespace"].rstrip("/")
        subs = {t: Subscriber(pub_endpoints(self._graph, f"{ns}/{t}"), f"{ns}/{t}", typ, mode="all")
                for t, typ in (("emitter/scan", ScanEvent), ("compositor/composite", Composite),
                               ("camera/frame", Frame))}
        poller = zmq.Poller()
        for sub in subs.values():
            poller.register(sub.socket, zmq.POLLIN)
        self.t0 = time.monotonic()
        end = self.t0 + WARM_TIMEOUT_S  # until the warm-up; then the soak's minutes from it on
        next_sample = next_kill = 0.0
        try:
            while time.monotonic() < end:
                if self.proc.poll() is not None:
                    raise PolarstripeError(f"soak: the launch ended by itself (exit {self.proc.returncode}): "
                                           + _tail(self.folder / "console.txt"))
                ready = dict(poller.poll(50))
                for topic, sub in subs.items():
                    if sub.socket in ready:
                        gaps = sub.stats.gaps
                        for msg in sub.take():
                            if not isinstance(msg, Exception):
                                self._on(topic, msg)
                        self._lost(topic, sub.stats.gaps - gaps)
                now = time.monotonic()
                if self.warm and self.warmup_s is None:
                    self.warmup_s = now - self.t0
                    end = now + 60.0 * self.args.minutes
                if now >= next_sample:
                    self._sample()
                    next_sample = now + SAMPLE_S
                if (self.args.chaos > 0 and self.warm and now >= next_kill and self._recovered()
                        and end - now > LAST_KILL_S):
                    self._kill()
                    next_kill = now + self.args.chaos
                self._respawns()
        finally:
            for sub in subs.values():
                sub.close()
        self._sample()
        if not self.warm:
            self._stop()
            raise PolarstripeError(f"soak: the rig did not complete {WARM_SCANS} scans within "
                                   f"{WARM_TIMEOUT_S:.0f} s of starting ({self.scans['completed']} did): "
                                   + _tail(self.folder / "console.txt"))

    def _on(self, topic: str, msg) -> None:
        now = time.monotonic() - self.t0
        if topic == "emitter/scan":
            if msg.event == "start":
                self.open[msg.scan_id] = self.started[msg.scan_id] = now
            elif msg.event == "fault" and msg.scan_id not in self.ended:
                self.ended.add(msg.scan_id)
                self.open.pop(msg.scan_id, None)
                self.scans["failed_clear" if msg.detail else "failed_unclear"] += 1
                self.faults.append(f"t={now:.0f} s scan {msg.scan_id} {msg.method}: {msg.detail}")
            elif msg.event == "done":
                self.open.pop(msg.scan_id, None)
        elif topic == "compositor/composite" and msg.scan_id not in self.ended:
            self.ended.add(msg.scan_id)
            self.open.pop(msg.scan_id, None)
            if msg.metrics.get("error"):
                self.scans["failed_clear"] += 1
                self.faults.append(f"t={now:.0f} s scan {msg.scan_id} {msg.method}: {msg.metrics['error']}")
                return
            self.scans["completed"] += 1
            if not self.warm and self.scans["completed"] >= WARM_SCANS:
                self.warm = True
                self.rss.clear()  # memory counts from the warm-up on (a respawned process: from its own)
            self.methods_ok.add(msg.method)
            began = self.started.get(msg.scan_id, -1.0)
            for k in self.kills:  # scans started after the kill: the first composited, then every method
                if began <= k["t_s"] or k["recovered_s"] is not None:
                    continue
                if k["first_scan_s"] is None:
                    k["first_scan_s"] = now - k["t_s"]
                k["methods"].add(msg.method)
                if k["methods"] >= k["expect"]:
                    k["recovered_s"] = now - k["t_s"]

    def _lost(self, topic: str, new: int) -> None:
        if new > 0:
            self.lost_by_topic[topic] = self.lost_by_topic.get(topic, 0) + new
            self.lost["within" if self._in_kill_window(time.monotonic() - self.t0) else "outside"] += new

    def _in_kill_window(self, now: float) -> bool:
        for k in self.kills:
            ends = k["t_s"] + (k["recovered_s"] if k["recovered_s"] is not None else 1e9) + KILL_GRACE_S
            if k["t_s"] - 1.0 <= now <= ends:
                return True
        return False

    def _recovered(self) -> bool:
        return not self.kills or self.kills[-1]["recovered_s"] is not None

    def _kill(self) -> None:
        g = self.graph()
        alive = [(n, e["pid"]) for n, e in g["nodes"].items() if e.get("pid") and _rss_mb(e["pid"])]
        if not alive:
            return
        name, pid = self.rng.choice(sorted(alive))
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            return
        self.kills.append({"t_s": time.monotonic() - self.t0, "node": name, "pid": pid, "respawned_s": None,
                           "first_scan_s": None, "recovered_s": None, "methods": set(),
                           "expect": set(self.methods_ok)})

    def _respawns(self) -> None:
        pending = [k for k in self.kills if k["respawned_s"] is None]
        if pending:
            nodes = self.graph()["nodes"]
            for k in pending:
                pid = nodes.get(k["node"], {}).get("pid")
                if pid and pid != k["pid"]:
                    k["respawned_s"] = time.monotonic() - self.t0 - k["t_s"]

    def _sample(self) -> None:
        done = self.scans["completed"]
        for name, e in self.graph()["nodes"].items():
            pid = e.get("pid")
            seen = self.seen.setdefault((name, pid), done)
            mb = _rss_mb(pid) if pid else None
            # a process counts from its own warm-up on: WARM_SCANS completed scans after it was first seen
            # (a respawned node starts small and loads its modules and caches again)
            if mb is not None and self.warm and done - seen >= WARM_SCANS * (seen > 0):
                v = self.rss.setdefault((name, pid), [mb, mb, 0])
                v[1], v[2] = mb, v[2] + 1

    def _stop(self) -> dict:
        self.scans["unended"] = len(self.open)
        self.proc.send_signal(signal.SIGINT)
        try:
            status = self.proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            status = None
        run_dir = self.graph_file.parent
        try:
            exits = json.loads((run_dir / "exits.json").read_text())
        except (OSError, ValueError):
            exits = {"nodes": {}, "left_sockets": []}
        unclean = {n: e for n, e in exits["nodes"].items() if e["started"] and
                   (e["stopped_by"] not in (None, "SIGINT") or e["signal"] or e["exit_code"] not in (0, 130))}
        return {"launcher_status": status, "unclean": unclean, "left_sockets": exits.get("left_sockets", []),
                "run_dir": str(run_dir)}

    # ---- the report --------------------------------------------------------------------------------------
    def memory(self) -> dict[str, dict]:
        """Per node: RSS after the warm-up and at the end [MB], of its longest-lived process; a node none of
        whose processes lived through a warm-up (killed, and the soak ended before its new process was warm)
        has no numbers (``ok`` None)."""
        out = {}
        for name in self.graph()["nodes"]:
            pids = {pid: v for (n, pid), v in self.rss.items() if n == name}
            if not pids:
                out[name] = {"pid": None, "processes": 0, "start_mb": None, "end_mb": None, "growth_mb": None,
                             "bound_mb": None, "ok": None}
                continue
            pid, (first, last, _) = max(pids.items(), key=lambda kv: kv[1][2])  # sampled the longest
            growth = last - first
            bound = max(GROWTH_BOUND_MB, GROWTH_BOUND_FRACTION * first)
            out[name] = {"pid": pid, "processes": len(pids), "start_mb": round(first, 1),
                         "end_mb": round(last, 1), "growth_mb": round(growth, 1), "bound_mb": round(bound, 1),
                         "ok": growth <= bound}
        return out

    def report(self, stop: dict) -> dict:
        rec = [k["recovered_s"] for k in self.kills if k["recovered_s"] is not None]
        mem, killed = self.memory(), {k["node"] for k in self.kills}
        checks = {
            "scans_completed": self.scans["completed"] > 0,
            "no_loss_outside_kills": self.lost["outside"] == 0,
            "every_kill_recovered": len(rec) == len(self.kills),
            # every node measured, except one killed whose new process was not warm at the end
            "memory_within_bound": all(m["ok"] or (m["ok"] is None and name in killed)
                                       for name, m in mem.items()),
            "clean_shutdown": stop["launcher_status"] == 130 and not stop["unclean"],
        }
        return {
            "minutes": self.args.minutes, "chaos_s": self.args.chaos, "resolution": self.args.resolution,
            "stripes": self.args.stripes, "seed": self.args.seed,
            "warmup_s": round(self.warmup_s, 1) if self.warmup_s is not None else None, "scans": self.scans,
            "faults": self.faults, "frames_lost": {**self.lost, "by_topic": self.lost_by_topic},
            "kills": [{k: sorted(v) if isinstance(v, set) else v for k, v in kill.items()}
                      for kill in self.kills],
            "recovery_s": {"median": round(sorted(rec)[len(rec) // 2], 2) if rec else None,
                           "max": round(max(rec), 2) if rec else None},
            "memory": mem, "growth_bound": {"mb": GROWTH_BOUND_MB, "fraction": GROWTH_BOUND_FRACTION},
            "shutdown": stop, "checks": checks, "ok": all(checks.values()),
        }


def _tail(path: Path, n: int = 3) -> str:
    try:
        return " | ".join(path.read_text(errors="replace").splitlines()[-n:])
    except OSError:
        return ""


def main(args: argparse.Namespace) -> int:
    if not args.minutes > 0 or args.chaos < 0:
        raise PolarstripeError(f"soak: --minutes must be > 0 and --chaos >= 0, got {args.minutes}, "
                               f"{args.chaos}")
    folder = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="ps-soak-"))
    folder.mkdir(parents=True, exist_ok=True)
    try:
        soak = Soak(args, folder)
        r = soak.report(soak.run())
    finally:
        if not args.keep:
            shutil.rmtree(folder, ignore_errors=True)
    print(json.dumps(r, indent=2) if args.json else table(r))
    return 0 if r["ok"] else 1
