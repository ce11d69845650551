"""Replay: messages on their original topics, paced by log time, found through a graph file; and a recorded
simulated scan replayed into a fresh compositor gives the live composites bit for bit."""

import os
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest
from polarstripe.msgs import Composite, Frame, Header, Log
from polarstripe.runtime.bag import BagWriter
from polarstripe.runtime.bag_reader import BagReader
from polarstripe.runtime.bus import BusTimeout, Subscriber
from polarstripe.runtime.graph import find_graph, load_graph, pub_endpoints

T0 = 1_700_000_000_000_000_000


def _frame(k: int) -> Frame:
    img = np.random.default_rng(k).integers(0, 4096, size=(30, 40), dtype=np.uint16)
    return Frame(image=img, exposure_s=0.01, step=k, header=Header(stamp_ns=T0 + k, seq=k))


def _bag(path, n=6, spacing_s=0.2):
    with BagWriter(path) as w:
        for k in range(n):
            w.add_message("/rig/camera/frame", _frame(k), log_time_ns=T0 + int(k * spacing_s * 1e9))
            w.add_message(
                "/rig/log",
                Log(level="INFO", node="x", text=str(k)),
                log_time_ns=T0 + int((k * spacing_s + 0.01) * 1e9),
            )
    return path


def _replay(tmp_path, bag, *args):
    env = {**os.environ, "POLARSTRIPE_RUNS": str(tmp_path / "runs")}
    proc = subprocess.Popen(
        [sys.executable, "-m", "polarstripe", "replay", str(bag), *args],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    deadline = time.monotonic() + 20
    while True:  # the replayer's graph file, found like a running launch's
        try:
            return proc, load_graph(find_graph())
        except Exception:
            assert proc.poll() is None, proc.communicate()[1]
            assert time.monotonic() < deadline, "no graph file"
            time.sleep(0.05)


def test_replay_paces_by_log_time_and_keeps_messages_intact(tmp_path, monkeypatch):
    monkeypatch.setenv("POLARSTRIPE_RUNS", str(tmp_path / "runs"))
    bag = _bag(tmp_path / "b.mcap")
    proc, graph = _replay(tmp_path, bag, "--rate", "2", "--delay", "1.0", "--topics", "camera/frame")
    assert set(graph["topics"]) == {"/rig/camera/frame"}  # --topics (relative names resolve)
    frames = Subscriber(pub_endpoints(graph, "/rig/camera/frame"), "/rig/camera/frame", Frame, mode="all")
    logs = Subscriber(pub_endpoints(graph, "/rig/log"), "/rig/log", Log, mode="all")
    got, times = [], []
    try:
        for _ in range(6):
            got.append(frames.recv(timeout_s=15))
            times.append(time.monotonic())
        out, err = proc.communicate(timeout=20)
        assert proc.returncode == 0, err
        with pytest.raises(BusTimeout):  # only the chosen topic was replayed (the bag also has /rig/log)
            logs.recv(timeout_s=0.2)
    finally:
        frames.close()
        logs.close()
        if proc.poll() is None:
            proc.kill()
    for k, m in enumerate(got):
        sent = _frame(k)
        assert np.array_equal(m.image, sent.image) and m.step == k
        assert m.header.stamp_ns == sent.header.stamp_ns  # the original stamp
    assert 0.25 < times[-1] - times[0] < 5  # paced, not dumped (exact pacing: the harness test below)
    assert "100%" in err  # the progress bar reached the end
    assert load_graph(find_graph(running=False))["state"] == "stopped"


def test_replayer_publishes_each_message_when_its_log_time_is_due(tmp_path):
    """Virtual clock: recorded 0.2 s apart, at rate 2 message k is due 0.1·k s after the start delay."""
    from polarstripe.nodes.replayer import Replayer
    from polarstripe.runtime.testing import NodeHarness

    bag = _bag(tmp_path / "b.mcap", n=6, spacing_s=0.2)
    h = NodeHarness(
        Replayer,
        namespace="/rig",
        params={"path": str(bag), "rate": 2, "delay_s": 0.5, "topics": ["camera/frame"], "linger_s": 0.3},
    )
    counts = []
    for _ in range(50):  # 1.0 s of virtual time in 20 ms steps
        h.advance(0.02)
        counts.append(len(h.published("/rig/camera/frame")))
    t = 0.02 * np.arange(1, 51)
    # due at 0.5 + 0.1 k (k = 0..5); the pump runs every 2 ms: a message is out at most 2 ms after it is due
    expected = np.clip(np.floor((t - 0.5) / 0.1 + 1e-9) + 1, 0, 6)
    late = np.clip(np.floor((t - 0.502) / 0.1 + 1e-9) + 1, 0, 6)
    assert np.all((np.array(counts) <= expected) & (np.array(counts) >= late)), counts
    h.advance(0.01)
    assert [m.step for m in h.published("/rig/camera/frame")] == list(range(6))
    assert h.published("/rig/log") == [] or all(m.node != "x" for m in h.published("/rig/log"))
    h.advance(0.5)
    assert h.node.stopping  # linger over: the replay ends by itself


def test_replayer_waits_until_the_nodes_it_waits_for_are_set_up(tmp_path):
    """A heartbeat that says ``starting`` (setup still running, e.g. a compositor loading its kernels) does
    not count: replaying then would publish into a node that drops what it receives."""
    from polarstripe.msgs.types import Heartbeat
    from polarstripe.nodes.replayer import Replayer
    from polarstripe.runtime.testing import NodeHarness

    bag = _bag(tmp_path / "b.mcap", n=3, spacing_s=0.1)
    h = NodeHarness(
        Replayer,
        namespace="/rig",
        params={"path": str(bag), "rate": 10, "delay_s": 0.1, "topics": ["camera/frame"],
                "wait_for": ["compositor"]},
    )
    h.deliver("heartbeat", Heartbeat(node="compositor", pid=1, uptime_s=1.0, counters={"starting": 1}))
    h.advance(1.0)
    assert h.published("/rig/camera/frame") == []  # alive, not ready: nothing yet
    h.deliver("heartbeat", Heartbeat(node="compositor", pid=1, uptime_s=2.0, counters={}))
    h.advance(0.05)  # ready, but its subscriptions may still be connecting: delay_s after readiness
    assert h.published("/rig/camera/frame") == []
    h.advance(1.0)
    assert [m.step for m in h.published("/rig/camera/frame")] == [0, 1, 2]


def test_replayer_start_skips_the_beginning(tmp_path):
    from polarstripe.nodes.replayer import Replayer
    from polarstripe.runtime.testing import NodeHarness

    bag = _bag(tmp_path / "b.mcap", n=6, spacing_s=0.2)  # frames at 0, 0.2, … 1.0 s
    h = NodeHarness(
        Replayer,
        namespace="/rig",
        params={
            "path": str(bag),
            "start_s": 0.5,
            "delay_s": 0.1,
            "topics": ["/rig/camera/frame"],
            "rate": 10,
        },
    )
    h.advance(0.5)
    assert [m.step for m in h.published("/rig/camera/frame")] == [3, 4, 5]


def test_replay_loops(tmp_path, monkeypatch):
    monkeypatch.setenv("POLARSTRIPE_RUNS", str(tmp_path / "runs"))
    bag = _bag(tmp_path / "b.mcap", n=3, spacing_s=0.05)
    proc, graph = _replay(tmp_path, bag, "--rate", "5", "--delay", "1.0", "--loop")
    sub = Subscriber(pub_endpoints(graph, "/rig/camera/frame"), "/rig/camera/frame", Frame, mode="all")
    try:
        steps = [sub.recv(timeout_s=15).step for _ in range(7)]
    finally:
        sub.close()
        proc.send_signal(2)
        proc.communicate(timeout=20)
    first = steps.index(0)
    assert steps[first : first + 4] == [0, 1, 2, 0]  # back to the start after the last message


def test_replay_rejects_a_topic_the_bag_does_not_have(tmp_path):
    bag = _bag(tmp_path / "b.mcap", n=1)
    r = subprocess.run(
        [sys.executable, "-m", "polarstripe", "replay", str(bag), "--topics", "/rig/nope"],
        env={**os.environ, "POLARSTRIPE_RUNS": str(tmp_path / "runs")},
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 2 and "no topic '/rig/nope'" in r.stderr and "Traceback" not in r.stderr


# ---- a simulated scan, live and replayed -------------------------------------------------------------------
LIVE = """
[launch]
name = "live"
namespace = "/rig"
shutdown_timeout = 3.0
[launch.env]
OMP_NUM_THREADS = "1"
[[node]]
name = "simulator"
module = "polarstripe.nodes.simulator"
params = {{ resolution = "64x48", fidelity = "preview", can_channel = "{can}" }}
[[node]]
name = "polarizer"
module = "polarstripe.nodes.polarizer"
params = {{ stage = "cia402", stage_options = {{ interface = "zmq", channel = "{can}" }} }}
[[node]]
name = "grabber"
module = "polarstripe.nodes.grabber"
params = {{ camera = "sim" }}
[[node]]
name = "compositor"
module = "polarstripe.nodes.compositor"
params = {{ use_truth = true }}
[[node]]
name = "emitter"
module = "polarstripe.nodes.emitter"
params = {{ display = "null", stripes = 4 }}
[[node]]
name = "sequencer"
module = "polarstripe.nodes.sequencer"
params = {{ stripes = 4, plan = false }}
required = true
"""


def _composites(path) -> dict[str, Composite]:
    with BagReader(path) as bag:
        return {m.method: m for _, _, m in bag.messages(["/rig/compositor/composite"])}


@pytest.mark.slow
def test_replayed_scan_gives_the_live_composites_bit_for_bit(tmp_path):
    """Live: the simulated rig scans with every method, recorded; the compositor scores against the
    simulator's ground truth (dark offset, object-free region for p, chart bars). Replay: launch/replay.toml
    feeds the recorded frames, scan events and truth into a fresh compositor (no simulator), recorded too.
    Every composite image and its metrics must be identical, bit for bit."""
    env = {**os.environ, "POLARSTRIPE_RUNS": str(tmp_path / "runs"), "XDG_RUNTIME_DIR": str(tmp_path)}
    live_toml = tmp_path / "live.toml"
    live_toml.write_text(textwrap.dedent(LIVE.format(can=f"ps-replay-test-{os.getpid()}")))
    live, replayed = tmp_path / "live.mcap", tmp_path / "replayed.mcap"
    cmd = [sys.executable, "-m", "polarstripe", "launch"]
    r = subprocess.run(
        [*cmd, str(live_toml), "--once", "--record", str(live)],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    replay_toml = os.path.join(os.path.dirname(__file__), "..", "..", "launch", "replay.toml")
    r = subprocess.run(
        [
            *cmd,
            replay_toml,
            "--once",
            f"bag={live}",
            "rate=4",
            "resolution=64x48",  # the planner plans the live run's rig (the default 320x240 took ~30 s)
            "stripes=4",
            "--record",
            str(replayed),
        ],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    a, b = _composites(live), _composites(replayed)
    with BagReader(live) as bag:
        n_frames = bag.topics["/rig/camera/frame"].count
    assert n_frames >= 4 + 2 * 4  # a real scan was recorded: stripes at one and at two analyzer angles
    assert set(a) == {"flood", "polarized_flood", "stripes", "polarized_stripes", "hf_separation"}
    assert set(b) == set(a)
    for method, live_c in a.items():
        rep = b[method]
        assert live_c.images, f"{method}: the live scan made no composite ({live_c.metrics})"
        assert set(rep.images) == set(live_c.images)
        for name, img in live_c.images.items():
            assert img.dtype == rep.images[name].dtype and img.shape == rep.images[name].shape
            assert img.tobytes() == rep.images[name].tobytes(), (
                f"{method}/{name} differs: live {live_c.metrics}, replayed {rep.metrics}")
        assert np.ptp(live_c.images["composite"]) > 0  # not a blank image that would match anything
        assert rep.metrics["frames"] == live_c.metrics["frames"]
        assert live_c.metrics["error_vs_truth"] is not None  # the live run did score against the truth
        for key in ("error_vs_truth", "contrast", "dark_offset_dn", "p"):
            assert rep.metrics.get(key) == live_c.metrics.get(key), f"{method}: {key} differs"
