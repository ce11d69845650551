import json
import os
import subprocess
import sys

import pytest
from polarstripe.runtime.graph import GraphError, find_graph, pub_endpoints, resolve


def test_resolve_names():
    assert resolve("camera/frame", "/rig") == "/rig/camera/frame"
    assert resolve("camera/frame", "rig/") == "/rig/camera/frame"
    assert resolve("camera/frame", "") == "/camera/frame"
    assert resolve("/abs/x", "/rig") == "/abs/x"
    assert resolve("~/reset", "/rig", "talker") == "/rig/talker/reset"
    with pytest.raises(ValueError, match="needs a node name"):
        resolve("~/reset", "/rig")


def _run(root, name, pid, mtime):
    d = root / name
    d.mkdir(parents=True)
    f = d / "graph.json"
    f.write_text(json.dumps({"pid": pid, "nodes": {}}))
    os.utime(f, (mtime, mtime))
    return f


def test_find_graph_takes_the_newest_running_launch(tmp_path, monkeypatch):
    monkeypatch.setenv("POLARSTRIPE_RUNS", str(tmp_path))
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    older = _run(tmp_path, "a", os.getpid(), 1_000)
    newest_dead = _run(tmp_path, "b", dead.pid, 3_000)
    assert find_graph() == older  # the newest one's launcher is gone
    assert find_graph(running=False) == newest_dead
    assert find_graph(str(tmp_path / "b")) == newest_dead  # a run directory works too
    with pytest.raises(GraphError, match="does not exist"):
        find_graph(str(tmp_path / "nope.json"))


def test_find_graph_says_where_it_looked(tmp_path, monkeypatch):
    monkeypatch.setenv("POLARSTRIPE_RUNS", str(tmp_path))
    with pytest.raises(GraphError, match=f"no running launch found in {tmp_path}"):
        find_graph()


def test_pub_endpoints_prefer_declared_publishers():
    graph = {
        "nodes": {"cam": {"pub": "ipc://cam"}, "emit": {"pub": "ipc://emit"}},
        "topics": {"/rig/frame": {"publishers": ["cam"]}},
    }
    assert pub_endpoints(graph, "/rig/frame") == ["ipc://cam"]
    assert sorted(pub_endpoints(graph, "/rig/undeclared")) == ["ipc://cam", "ipc://emit"]
