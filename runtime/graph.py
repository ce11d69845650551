"""The run's graph file: which nodes run, where they bind, what they publish and serve.

The launcher writes ``graph.json`` into a per-run directory ``$POLARSTRIPE_RUNS/<launch>-<stamp>-<pid>/``
(default ``$POLARSTRIPE_RUNS`` = ``${XDG_RUNTIME_DIR or /tmp}/polarstripe-<uid>/runs``); the directory
also holds
the node sockets (``sock/``) and logs (``logs/<node>.log``). Tools started later (``topic``, ``record``) find
the newest run with :func:`find_graph`, or take ``--graph FILE``.

Layout (all topic and service names are full names)::

    {"launch": "sim", "namespace": "/rig", "run_dir": "...", "pid": 1234, "started_ns": ...,
     "nodes": {"talker": {"node": "polarstripe.nodes.demo:Talker", "pub": "ipc://…", "srv": "ipc://…",
                          "publishes": {"/rig/chatter": "log"}, "subscribes": {…}, "serves": {…},
                          "params": {…}, "log": "…/logs/talker.log", "required": false, …}},
     "topics": {"/rig/chatter": {"type": "log", "publishers": ["talker"], "subscribers": ["listener"]}},
     "services": {"/rig/talker/reset": {"node": "talker", "endpoint": "ipc://…",
                                        "request": "empty", "reply": "ack"}}}
"""

from __future__ import annotations

import json
import os
from pathlib import Path

from polarstripe.errors import PolarstripeError


class GraphError(PolarstripeError):
    """No graph file, or one that cannot be read."""


def runs_dir() -> Path:
    """Where run directories live: ``$POLARSTRIPE_RUNS`` or
    ``${XDG_RUNTIME_DIR:-/tmp}/polarstripe-<uid>/runs``."""
    env = os.environ.get("POLARSTRIPE_RUNS")
    if env:
        return Path(env)
    base = os.environ.get("XDG_RUNTIME_DIR") or "/tmp"
    return Path(base) / f"polarstripe-{os.getuid()}" / "runs"


def resolve(name: str, namespace: str, node: str = "") -> str:
    """Full name of ``name`` in ``namespace``: ``resolve("camera/frame", "/rig") == "/rig/camera/frame"``; a
    name starting with ``/`` is already full; ``~/x`` is private to ``node``:
    ``resolve("~/x", "/rig", "cam") == "/rig/cam/x"`` (two instances of one node class do not clash)."""
    if name.startswith("/"):
        return name
    ns = "/" + namespace.strip("/") if namespace.strip("/") else ""
    if name.startswith("~/"):
        if not node:
            raise ValueError(f"private name {name!r} needs a node name")
        return f"{ns}/{node}/{name[2:].strip('/')}"
    return f"{ns}/{name.strip('/')}"


def write_graph(path: Path, graph: dict) -> None:
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(graph, indent=2, sort_keys=False))
    os.replace(tmp, path)


def load_graph(path: str | Path) -> dict:
    try:
        graph = json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise GraphError(f"graph file {path} does not exist") from None
    except (OSError, json.JSONDecodeError) as exc:
        raise GraphError(f"graph file {path}: {exc}") from None
    if not isinstance(graph, dict) or "nodes" not in graph:
        raise GraphError(f"graph file {path}: not a polarstripe graph (no 'nodes')")
    return graph


def pid_alive(pid: int) -> bool:
    """Whether process ``pid`` exists (one of another user counts)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def find_graph(explicit: str | None = None, *, running: bool = True) -> Path:
    """The graph file to use: ``explicit`` if given, else the newest run's (whose launcher is alive if
    ``running``). Raises :class:`GraphError` naming where it looked."""
    if explicit:
        p = Path(explicit)
        p = p / "graph.json" if p.is_dir() else p
        if not p.exists():
            raise GraphError(f"graph file {p} does not exist")
        return p
    root = runs_dir()
    candidates = sorted(root.glob("*/graph.json"), key=lambda p: p.stat().st_mtime, reverse=True)
    for p in candidates:
        if not running:
            return p
        try:
            pid = int(json.loads(p.read_text()).get("pid", 0))
        except (OSError, ValueError):
            continue
        if pid and pid_alive(pid):
            return p
    what = "running launch" if running else "launch"
    raise GraphError(f"no {what} found in {root} (start one with 'polarstripe launch FILE', or pass --graph)")


def pub_endpoints(graph: dict, topic: str) -> list[str]:
    """PUB endpoints to connect to for ``topic``: its declared publishers, or every node if none declares
    it."""
    nodes = graph.get("nodes", {})
    pubs = graph.get("topics", {}).get(topic, {}).get("publishers") or list(nodes)
    return [nodes[n]["pub"] for n in pubs if n in nodes and nodes[n].get("pub")]


def shm_offered(graph: dict, topic: str) -> bool:
    """Whether every publisher of ``topic`` offers its shared-memory ring form (the graph's
    ``shm_slots`` > 0, given to nodes bound at ipc endpoints: runtime/shm_bus.py)."""
    nodes = graph.get("nodes", {})
    pubs = graph.get("topics", {}).get(topic, {}).get("publishers") or []
    return bool(pubs) and all(
        n in nodes and int(nodes[n].get("shm_slots") or 0) > 0
        and str(nodes[n].get("pub", "")).startswith(("ipc://", "inproc://"))
        for n in pubs
    )
