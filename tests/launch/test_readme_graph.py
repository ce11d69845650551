"""The README's node graph is the one `launch/sim.toml` starts: every topic arrow is a publisher → subscriber
pair of the resolved graph (and every pair is drawn), every service arrow ends at the node that serves it."""

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def graph(tmp_path_factory) -> dict:
    """The resolved graph of ``launch/sim.toml`` (one dry run for both tests)."""
    r = subprocess.run([sys.executable, "-m", "polarstripe", "launch", str(ROOT / "launch" / "sim.toml"),
                        "--dry-run"], capture_output=True, text=True, timeout=60,
                       env={"POLARSTRIPE_RUNS": str(tmp_path_factory.mktemp("runs")),
                            "PATH": str(Path(sys.executable).parent)})
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)


def _readme_arrows(kind: str) -> set[tuple[str, str, str]]:
    text = (ROOT / "README.md").read_text()
    block = text[text.index("```mermaid"):]
    block = block[:block.index("```", 10)]
    arrow = r'(\w+) -- "([^"]+)" --> (\w+)' if kind == "topic" else r'(\w+) -\. "([^"]+)" \.-> (\w+)'
    return {(a, name.strip(), b) for a, names, b in re.findall(arrow, block) for name in names.split(",")}


def test_topic_arrows_are_the_launch_graph(graph):
    g = graph
    ns = g["namespace"] + "/"
    pubs: dict[str, set[str]] = {}
    subs: dict[str, set[str]] = {}
    for node, v in g["nodes"].items():
        for t in v["publishes"]:
            pubs.setdefault(t, set()).add(node)
        for t in v["subscribes"]:
            subs.setdefault(t, set()).add(node)
    edges = {(a, t.removeprefix(ns), b) for t in subs for a in pubs.get(t, ()) for b in subs[t]
             if not t.endswith(("/log", "/heartbeat"))}
    assert edges, "the launch graph has no topics"
    assert _readme_arrows("topic") == edges


def test_service_arrows_end_at_their_server(graph):
    g = graph
    ns = g["namespace"] + "/"
    served = {(s.removeprefix(ns), node) for node, v in g["nodes"].items() for s in v["serves"]}
    calls = _readme_arrows("service")
    assert calls and {(name, server) for _, name, server in calls} <= served
