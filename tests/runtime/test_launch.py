"""The launcher and the runtime with real processes: launch files, respawn, services, bad messages,
shutdown."""

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import msgpack
import numpy as np
import pytest
import zmq
from polarstripe.msgs import Ack, Empty, Frame, Heartbeat, Log, encode
from polarstripe.runtime.bus import BusTimeout, ServiceTimeout, Subscriber
from polarstripe.runtime.graph import pub_endpoints
from polarstripe.runtime.service import ServiceClient

TEST_NODES = """
import signal
from polarstripe.errors import PolarstripeError
from polarstripe.msgs import Ack, Empty, Frame
from polarstripe.runtime.node import Node


class FrameCounter(Node):
    SUBSCRIBES = {"camera/frame": Frame}
    SERVES = {"counter/count": (Empty, Ack)}

    def setup(self):
        self.n = 0
        self.subscribe("camera/frame", self.on_frame, mode="all")
        self.serve("counter/count", lambda req: Ack(ok=True, detail=str(self.n)))

    def on_frame(self, msg):
        self.n += 1


class Camera(Node):
    PUBLISHES = {"camera/frame": Frame}
    SERVES = {"camera/trigger": (Empty, Ack)}

    def setup(self):
        self.serve("camera/trigger", lambda req: Ack(ok=True, detail="click"))


class Refuses(Node):
    def setup(self):
        raise PolarstripeError("param 'fidelity': 'ultra' is not a fidelity")


class Crashy(Node):
    def setup(self):
        raise RuntimeError("the device is not there")


class Stubborn(Node):
    def setup(self):
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
"""


def _env(tmp_path):
    return {**os.environ, "POLARSTRIPE_RUNS": str(tmp_path / "runs"), "PYTHONPATH": str(tmp_path)}


def _launch(tmp_path, toml, *args):
    (tmp_path / "ps_test_nodes.py").write_text(TEST_NODES)
    f = tmp_path / "test.toml"
    f.write_text(textwrap.dedent(toml))
    out = open(tmp_path / "launch.out", "wb")  # noqa: SIM115
    return subprocess.Popen(
        [sys.executable, "-m", "polarstripe", "launch", str(f), *args],
        stdout=out,
        stderr=subprocess.STDOUT,
        env=_env(tmp_path),
    )


def _output(tmp_path):
    return (tmp_path / "launch.out").read_text()


def _graph(tmp_path, timeout=15.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        files = list((tmp_path / "runs").glob("*/graph.json"))
        if files:
            try:
                g = json.loads(files[0].read_text())
            except json.JSONDecodeError:
                g = {}
            if g.get("state") == "running":
                return g
        time.sleep(0.05)
    raise AssertionError(f"launch did not start:\n{_output(tmp_path)}")


def _alive(pid):
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    with open(f"/proc/{pid}/stat") as f:  # a zombie is dead
        return f.read().split(")")[1].split()[0] != "Z"


def _processes_mentioning(text):
    found = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                if text.encode() in (d / "cmdline").read_bytes() and int(d.name) != os.getpid():
                    found.append(int(d.name))
            except OSError:
                pass
    return found


def _call(graph, service, timeout_s=3.0):
    ep = graph["services"][service]["endpoint"]
    with ServiceClient(ep, service, Empty, Ack, timeout_s=timeout_s) as c:
        return c.call(Empty())


def _wait_count(graph, service, above, timeout=10.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        n = int(_call(graph, service).detail)
        if n > above:
            return n
        time.sleep(0.05)
    raise AssertionError(f"{service} stayed at {n}")


def _stop(proc, timeout=15):
    proc.send_signal(signal.SIGINT)
    return proc.wait(timeout)


def test_two_nodes_exchange_messages_and_respawn_stops_at_its_limit(tmp_path):
    proc = _launch(
        tmp_path,
        """
        [launch]
        namespace = "/rig"
        [args]
        n = 20
        [[node]]
        name = "talker"
        module = "polarstripe.nodes.demo:Talker"
        params = { rate_hz = 20 }
        [[node]]
        name = "listener"
        module = "polarstripe.nodes.demo:Listener"
        params = { count = "${n}" }
        required = true
        [[node]]
        name = "crasher"
        module = "polarstripe.nodes.demo:Talker"
        params = { rate_hz = 50, count = 1 }
        respawn = true
        respawn_delay = 0.1
        max_respawns = 2
        required = true   # --once waits for its last respawn too
    """,
        "--once",
        "n=40",
    )
    assert proc.wait(30) == 0, _output(tmp_path)
    out = _output(tmp_path)
    run = next((tmp_path / "runs").iterdir())
    assert "heard 40 messages in all" in (run / "logs" / "listener.log").read_text()
    assert out.count("crasher started") == 3 and "respawn 2/2" in out, out
    graph = json.loads((run / "graph.json").read_text())
    assert graph["state"] == "stopped"
    assert graph["topics"]["/rig/chatter"] == {
        "type": "log",
        "publishers": ["talker", "crasher"],
        "subscribers": ["listener"],
    }
    assert not any(_alive(n["pid"]) for n in graph["nodes"].values())
    assert not (run / "sock").exists()
    exits = json.loads((run / "exits.json").read_text())
    assert (exits["status"], exits["ended"]) == (0, "every required node has exited")
    assert list(exits["nodes"]) == ["talker", "listener", "crasher"]
    n = exits["nodes"]
    assert n["talker"] == {"started": True, "exit_code": 0, "signal": None, "stopped_by": "SIGINT",
                           "respawns": 0, "pid": graph["nodes"]["talker"]["pid"]}
    assert (n["listener"]["exit_code"], n["listener"]["stopped_by"]) == (0, None)  # ended by itself
    assert (n["crasher"]["exit_code"], n["crasher"]["respawns"]) == (0, 2)
    assert "talker: exit 0 after the launcher's SIGINT, 0 respawns" in out
    assert "crasher: exit 0, 2 respawns" in out


def test_respawned_publisher_reaches_subscribers_again_then_ctrl_c_leaves_no_process(tmp_path):
    proc = _launch(
        tmp_path,
        """
        [launch]
        namespace = "/rig"
        [[node]]
        name = "talker"
        module = "polarstripe.nodes.demo:Talker"
        params = { rate_hz = 50, text = "hi" }
        respawn = true
        respawn_delay = 0.2
        [[node]]
        name = "listener"
        module = "polarstripe.nodes.demo:Listener"
    """,
    )
    try:
        g = _graph(tmp_path)
        sub = Subscriber(pub_endpoints(g, "/rig/chatter"), "/rig/chatter", Log, mode="all")
        assert sub.recv(timeout_s=10).text.startswith("hi ")
        heard = _wait_count(g, "/rig/listener/count", 0)

        env = _env(tmp_path)
        cli = [sys.executable, "-m", "polarstripe", "topic"]
        listing = subprocess.run([*cli, "list"], capture_output=True, text=True, env=env, timeout=20)
        assert "/rig/chatter" in listing.stdout and "pub: talker" in listing.stdout, listing.stderr
        echo = subprocess.run(
            [*cli, "echo", "chatter", "-n", "2", "--timeout", "10"],
            capture_output=True,
            text=True,
            env=env,
            timeout=20,
        )
        assert echo.stdout.count("[log seq=") == 2 and "text='hi " in echo.stdout, echo.stderr
        hz = subprocess.run(
            [*cli, "hz", "/rig/chatter", "-n", "1", "--window", "1"],
            capture_output=True,
            text=True,
            env=env,
            timeout=20,
        )
        rate = float(hz.stdout.split(": ")[1].split(" Hz")[0])
        assert 20 < rate < 80, hz.stdout  # a 50 Hz talker, on a loaded machine

        old_pid = g["nodes"]["talker"]["pid"]
        os.kill(old_pid, signal.SIGKILL)
        deadline = time.monotonic() + 10
        while json.loads(Path(g["run_dir"], "graph.json").read_text())["nodes"]["talker"]["pid"] == old_pid:
            assert time.monotonic() < deadline, _output(tmp_path)
            time.sleep(0.05)
        restarts_before = sub.stats.restarts
        deadline = time.monotonic() + 10
        while sub.stats.restarts == restarts_before:  # until seq goes back: the new process is heard
            assert time.monotonic() < deadline, "no message from the respawned talker"
            got = sub.recv(timeout_s=10)
        assert got.text.startswith("hi ") and sub.stats.restarts == restarts_before + 1
        assert _wait_count(g, "/rig/listener/count", heard + 10) > heard + 10  # the node's subscriber too
        sub.close()
    finally:
        status = _stop(proc)
    assert status == 130
    g = json.loads(Path(g["run_dir"], "graph.json").read_text())
    assert not any(_alive(n["pid"]) for n in g["nodes"].values())
    assert _processes_mentioning(g["run_dir"]) == []
    assert re.search(r"talker killed by SIGKILL after [0-9.]+ s.*; respawn 1/5 in 0.2 s", _output(tmp_path))


def test_bad_messages_service_timeout_and_shutdown_escalation(tmp_path):
    proc = _launch(
        tmp_path,
        """
        [launch]
        namespace = "/rig"
        shutdown_timeout = 0.5
        [[node]]
        name = "camera"
        module = "ps_test_nodes:Camera"
        [[node]]
        name = "counter"
        module = "ps_test_nodes:FrameCounter"
        params = { max_message_bytes = 100000, heartbeat_s = 0.1 }
        [[node]]
        name = "stubborn"
        module = "ps_test_nodes:Stubborn"
    """,
    )
    try:
        g = _graph(tmp_path)
        assert _call(g, "/rig/camera/trigger").detail == "click"
        os.kill(g["nodes"]["camera"]["pid"], signal.SIGKILL)
        t0 = time.monotonic()
        with pytest.raises(ServiceTimeout, match="'/rig/camera/trigger' at ipc://"):
            _call(g, "/rig/camera/trigger", timeout_s=0.5)
        assert time.monotonic() - t0 < 2.0

        # Stand in for the dead camera at its endpoint: the counter reconnects by itself.
        raw = zmq.Context.instance().socket(zmq.PUB)
        raw.bind(g["nodes"]["camera"]["pub"])
        good = encode(Frame(image=np.zeros((4, 4), np.uint16), exposure_s=0.1))
        deadline = time.monotonic() + 10
        while int(_call(g, "/rig/counter/count").detail) == 0:
            assert time.monotonic() < deadline
            raw.send_multipart([b"/rig/camera/frame", *good])
            time.sleep(0.05)
        before = int(_call(g, "/rig/counter/count").detail)

        head = msgpack.unpackb(good[0])  # [type, version, stamp_ns, seq, frame_id, image, …, mosaic_deg]
        bad_frames = []
        for i, value in ((1, 9), (0, "nonesuch")):  # version, type
            bad_frames.append([msgpack.packb([*head[:i], value, *head[i + 1:]]), good[1]])
        bad_frames.append([msgpack.packb(head[:-2]), good[1]])  # the last two (step, mosaic_deg) missing
        shape = [*head[:5], [0, "<u2", [5, 4]], *head[6:]]  # image: 40 bytes for a 32-byte buffer
        bad_frames.append([msgpack.packb(shape), good[1]])
        bad_frames.append([b"\xc1 not msgpack"])
        bad_frames.append(encode(Log(level="INFO", node="x", text="wrong type")))
        bad_frames.append(encode(Frame(image=np.zeros(200_000, np.uint8), exposure_s=0.1)))  # over the limit
        for frames in bad_frames:
            raw.send_multipart([b"/rig/camera/frame", *frames])
        raw.send_multipart([b"/rig/camera/frame", *good])
        assert _wait_count(g, "/rig/counter/count", before) == before + 1  # alive, and the good one counted

        with Subscriber([g["nodes"]["counter"]["pub"]], "/rig/heartbeat", Heartbeat) as hb:
            beat = hb.recv(timeout_s=5)
        assert beat.node == "counter" and beat.counters["bad"] == len(bad_frames) == 7
        raw.close(0)
        log = (Path(g["run_dir"]) / "logs" / "counter.log").read_text()
        assert log.count("dropped bad message: topic '/rig/camera/frame': field ") == 5  # then rate-limited
        for field in ("'version'", "'type'", "'step'", "'image'", "'header'"):
            assert f"field {field}" in log
    finally:
        status = _stop(proc)
    assert status == 130
    out = _output(tmp_path)
    assert "stubborn still running after SIGINT: their stacks are in their logs" in out
    assert "stubborn still running after SIGTERM" in out
    # where it was when it ignored the SIGINT: every thread's stack (faulthandler, __main__.py), its loop's
    stuck = (Path(g["run_dir"]) / "logs" / "stubborn.log").read_text()
    assert "(most recent call first)" in stuck and "runner.py" in stuck, stuck
    n = json.loads((Path(g["run_dir"]) / "exits.json").read_text())["nodes"]
    assert (n["stubborn"]["signal"], n["stubborn"]["stopped_by"]) == ("SIGKILL", "SIGKILL")
    assert (n["camera"]["signal"], n["camera"]["stopped_by"]) == ("SIGKILL", None)  # the test killed it
    counter = n["counter"]
    assert (counter["exit_code"], counter["signal"], counter["stopped_by"]) == (0, None, "SIGINT")
    assert "stubborn: killed by SIGKILL after the launcher's SIGKILL, 0 respawns" in out
    assert not any(_alive(n["pid"]) for n in g["nodes"].values())
    assert _processes_mentioning(g["run_dir"]) == []


def test_cli_rejects_before_anything_starts_and_dry_run_prints_the_graph(tmp_path):
    f = tmp_path / "x.toml"
    f.write_text(
        '[args]\nrate=10\n[[node]]\nname="a"\nmodule="polarstripe.nodes.demo:Talker"\n'
        'params={rate_hz="${rate}"}\n'
    )
    env = _env(tmp_path)
    cmd = [sys.executable, "-m", "polarstripe", "launch", str(f)]
    bad = subprocess.run([*cmd, "speed=3"], capture_output=True, text=True, env=env, timeout=30)
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1 and "unknown arg 'speed'" in bad.stderr
    assert not (tmp_path / "runs").exists()
    dry = subprocess.run([*cmd, "rate=25", "--dry-run"], capture_output=True, text=True, env=env, timeout=30)
    graph = json.loads(dry.stdout)
    assert graph["nodes"]["a"]["params"] == {"rate_hz": 25.0}
    assert graph["services"]["/a/reset"]["node"] == "a"
    assert not (tmp_path / "runs").exists()
    once = subprocess.run([*cmd, "--once"], capture_output=True, text=True, env=env, timeout=30)
    assert once.returncode == 2 and "--once needs at least one node with required = true" in once.stderr
    assert not (tmp_path / "runs").exists()
    rec = subprocess.run(
        [*cmd, "--record", str(tmp_path / "r.mcap"), "--dry-run"],
        capture_output=True,
        text=True,
        env=env,
        timeout=30,
    )
    assert rec.returncode == 0 or "recording is not available in this build" in rec.stderr


def test_tcp_transport_with_curve(tmp_path):
    public, secret = zmq.curve_keypair()
    keys = tmp_path / "rig.keys"
    keys.write_text(f"public={public.decode()}\nsecret={secret.decode()}\n")
    os.chmod(keys, 0o600)  # a secret key readable by others is refused at start
    toml = """
        [launch]
        namespace = "/net"
        transport = "tcp"
        [launch.env]
        POLARSTRIPE_CURVE_KEYS = "@KEYFILE@"
        [[node]]
        name = "talker"
        module = "polarstripe.nodes.demo:Talker"
        params = { rate_hz = 50 }
        [[node]]
        name = "listener"
        module = "polarstripe.nodes.demo:Listener"
        params = { report_s = 0.3 }
    """
    proc = _launch(tmp_path, toml.replace("@KEYFILE@", str(keys)))
    try:
        g = _graph(tmp_path)
        assert g["nodes"]["talker"]["pub"].startswith("tcp://127.0.0.1:")
        assert g["services"]["/net/talker/reset"]["endpoint"].startswith("tcp://127.0.0.1:")
        with Subscriber([g["nodes"]["talker"]["pub"]], "/net/chatter", Log) as plain:  # no keys: nothing
            with pytest.raises(BusTimeout):
                plain.recv(timeout_s=1.0)
        env = {**_env(tmp_path), "POLARSTRIPE_CURVE_KEYS": str(keys)}
        echo = subprocess.run(
            [sys.executable, "-m", "polarstripe", "topic", "echo", "chatter", "-n", "1", "--timeout", "10"],
            capture_output=True,
            text=True,
            env=env,
            timeout=20,
        )
        assert "text='hello " in echo.stdout, echo.stderr
        deadline = time.monotonic() + 10
        while "heard" not in (Path(g["run_dir"]) / "logs" / "listener.log").read_text():
            assert time.monotonic() < deadline
            time.sleep(0.1)
    finally:
        assert _stop(proc) == 130
    assert "heard" in (Path(g["run_dir"]) / "logs" / "listener.log").read_text()


def test_shipped_launch_file_by_name_from_anywhere_with_screen_output(tmp_path):
    """`polarstripe launch demo` finds the launch file shipped with polarstripe from any directory; the
    listener is `screen = true`, so its log lines reach the launcher's console prefixed with its name."""
    r = subprocess.run(
        [sys.executable, "-m", "polarstripe", "launch", "demo", "count=5", "rate=50", "--once"],
        cwd=tmp_path,
        env=_env(tmp_path),
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    listener_lines = [line for line in r.stderr.splitlines() if line.startswith("[listener] ")]
    assert listener_lines, r.stderr[-2000:]
    assert not any(line.startswith("[talker] ") for line in r.stderr.splitlines())  # not a screen node


def test_a_crash_loop_backs_off_and_says_why(tmp_path):
    proc = _launch(
        tmp_path,
        """
        [[node]]
        name = "crashy"
        module = "ps_test_nodes:Crashy"
        respawn = true
        respawn_delay = 0.1
        max_respawns = 3
        required = true
    """,
        "--once",
    )
    assert proc.wait(60) == 1, _output(tmp_path)
    out = _output(tmp_path)
    delays = [float(d) for d in re.findall(r"respawn \d/3 in ([0-9.]+) s", out)]
    assert delays == [0.1, 0.2, 0.4], out  # doubling after each quick exit
    assert out.count("(last line: RuntimeError: the device is not there)") == 4, out  # 3 respawns + the end


def test_record_to_a_path_that_cannot_be_written_fails_before_anything_starts(tmp_path):
    t0 = time.monotonic()
    r = subprocess.run([sys.executable, "-m", "polarstripe", "launch", "demo", "--once", "count=3",
                        "--record", "/proc/no/such/run.mcap"], capture_output=True, text=True,
                       env=_env(tmp_path), timeout=30)
    assert r.returncode == 2 and time.monotonic() - t0 < 10
    assert r.stderr.strip().splitlines() == [
        "polarstripe launch: error: --record /proc/no/such/run.mcap: folder /proc/no/such does not exist"]
    assert not (tmp_path / "runs").exists()


EXCLUSIVE = """
    [launch]
    exclusive = ["segment"]
    [args]
    segment = "${run_id}"
    [[node]]
    name = "talker"
    module = "polarstripe.nodes.demo:Talker"
    params = { rate_hz = 5, text = "${segment}" }
"""


def test_an_explicit_shared_name_in_use_by_another_launch_is_refused(tmp_path):
    first = _launch(tmp_path, EXCLUSIVE, "segment=bus7")
    try:
        g = _graph(tmp_path)
        assert g["nodes"]["talker"]["params"]["text"] == "bus7"
        r = subprocess.run([sys.executable, "-m", "polarstripe", "launch", str(tmp_path / "test.toml"),
                            "segment=bus7"], capture_output=True, text=True, env=_env(tmp_path), timeout=30)
        assert r.returncode == 2, r.stderr
        assert "segment='bus7' is in use by launch test (pid " in r.stderr, r.stderr
        assert "talker started" not in r.stderr
        # per run (the default) never clashes: a second launch of the same file starts
        other = tmp_path / "other"
        other.mkdir()
        second = subprocess.Popen([sys.executable, "-m", "polarstripe", "launch",
                                   str(tmp_path / "test.toml")],
                                  stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                  env={**_env(tmp_path), "POLARSTRIPE_RUNS": str(other / "runs")})
        deadline = time.monotonic() + 15
        while not list((other / "runs").glob("*/graph.json")) and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.5)
        second.send_signal(signal.SIGINT)
        assert second.wait(15) == 130, second.stdout.read()
    finally:
        assert _stop(first) == 130, _output(tmp_path)
    # released at the end: the name can be used again
    shutil.rmtree(tmp_path / "runs")
    again = _launch(tmp_path, EXCLUSIVE, "segment=bus7")
    _graph(tmp_path)
    assert _stop(again) == 130


def test_a_node_refusing_its_settings_ends_the_launch_at_once(tmp_path):
    t0 = time.monotonic()
    proc = _launch(
        tmp_path,
        """
        [[node]]
        name = "talker"
        module = "polarstripe.nodes.demo:Talker"
        [[node]]
        name = "refuses"
        module = "ps_test_nodes:Refuses"
        [[node]]
        name = "listener"
        module = "polarstripe.nodes.demo:Listener"
        required = true
    """,
        "--once",
    )
    assert proc.wait(30) == 1, _output(tmp_path)
    assert time.monotonic() - t0 < 15  # not the required node's start-up timeout
    out = _output(tmp_path)
    refusal = "param 'fidelity': 'ultra' is not a fidelity"
    assert f"refuses exit 2 (last line: polarstripe node: error: {refusal})" in out, out
    assert "refuses exit 2 (its settings or device refused): stopping the launch" in out
