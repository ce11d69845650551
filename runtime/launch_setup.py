"""What the launcher sets up before any process starts: the run's graph (every node's endpoints, topics and
services, :func:`build_graph`), the recorder node of ``--record`` and its checks, and whether an ipc endpoint
is already served by someone else."""

from __future__ import annotations

import errno
import os
import socket
import time
from pathlib import Path

from polarstripe.runtime.graph import resolve
from polarstripe.runtime.launch_file import LaunchError, LaunchSpec, NodeSpec, sock_dir
from polarstripe.runtime.runner import load_node_class
from polarstripe.runtime.shm_bus import DEFAULT_SLOTS, local

RECORDER = "polarstripe.nodes.recorder:Recorder"


def _free_port(host: str) -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def build_graph(spec: LaunchSpec, run_dir: Path) -> dict:
    """Endpoints for every node, and who publishes, subscribes and serves what (full names)."""
    sock = sock_dir(run_dir)
    nodes, topics, services = {}, {}, {}
    for n in spec.nodes:
        cls = n.node_class
        if spec.transport == "ipc":
            pub, srv = f"ipc://{sock}/{n.name}.pub", f"ipc://{sock}/{n.name}.srv"
        else:
            pub = f"tcp://{spec.host}:{_free_port(spec.host)}"
            srv = f"tcp://{spec.host}:{_free_port(spec.host)}"
        pub, srv = n.pub or pub, n.srv or srv
        full = {t: resolve(t, spec.namespace, n.name) for t in (*cls.PUBLISHES, *cls.SUBSCRIBES, *cls.SERVES)}
        publishes = {full[t]: m.TYPE for t, m in cls.PUBLISHES.items()}
        publishes[resolve("log", spec.namespace)] = "log"
        publishes[resolve("heartbeat", spec.namespace)] = "heartbeat"
        nodes[n.name] = {
            "module": n.module,
            "pub": pub,
            "srv": srv,
            "shm_slots": DEFAULT_SLOTS if local(pub) else 0,  # the ring form offered (runtime/shm_bus.py)
            "publishes": publishes,
            "subscribes": {full[t]: m.TYPE for t, m in cls.SUBSCRIBES.items()},
            "serves": {full[s]: [q.TYPE, r.TYPE] for s, (q, r) in cls.SERVES.items()},
            "params": n.params,
            "env": n.env,
            "required": n.required,
            "respawn": n.respawn,
            "respawn_delay": n.respawn_delay,
            "max_respawns": n.max_respawns,
            "log": str(run_dir / "logs" / f"{n.name}.log"),
            "pid": None,
        }
        for t, typ in publishes.items():
            topics.setdefault(t, {"type": typ, "publishers": [], "subscribers": []})["publishers"].append(
                n.name
            )
        for s, (q, r) in nodes[n.name]["serves"].items():
            if s in services:
                raise LaunchError(
                    f"{spec.path.name}: service {s!r} is served by both "
                    f"{services[s]['node']!r} and {n.name!r}"
                )
            services[s] = {"node": n.name, "endpoint": srv, "request": q, "reply": r}
    for n in spec.nodes:
        for t, typ in nodes[n.name]["subscribes"].items():
            topics.setdefault(t, {"type": typ, "publishers": [], "subscribers": []})["subscribers"].append(
                n.name
            )
    return {
        "launch": spec.name,
        "file": str(spec.path),
        "namespace": spec.namespace,
        "run_dir": str(run_dir),
        "pid": os.getpid(),
        "started_ns": time.time_ns(),
        "state": "starting",
        "args": spec.args,
        "nodes": nodes,
        "topics": topics,
        "services": services,
    }


def _check_writable(path: str) -> None:
    """``--record FILE``: refuse at once what the recorder could not write (a missing or read-only folder,
    a folder in place of the file, a read-only file)."""
    p = Path(path)
    folder = p.parent
    if p.is_dir():
        raise LaunchError(f"--record {path}: is a folder; give a file, e.g. {p / 'run.mcap'}")
    if not folder.is_dir():
        raise LaunchError(f"--record {path}: folder {folder} does not exist")
    if not os.access(folder, os.W_OK | os.X_OK) or (p.exists() and not os.access(p, os.W_OK)):
        raise LaunchError(f"--record {path}: cannot write there ({os.strerror(errno.EACCES).lower()})")


def _with_recorder(spec: LaunchSpec, path: str) -> None:

    _check_writable(path)
    try:
        cls = load_node_class(RECORDER)
    except Exception:
        raise LaunchError(f"--record: recording is not available in this build (needs {RECORDER})") from None
    recorder = NodeSpec(name="recorder", module=RECORDER, params={"path": str(path)}, node_class=cls,
                        fails_launch=True)  # a launch that was asked to record and does not, fails
    spec.nodes.insert(0, recorder)  # first up, last down: it sees the whole run


def _ipc_in_use(endpoint: str) -> bool:
    """Whether a process accepts connections at ``ipc://PATH`` (a stale socket file does not count)."""
    if not endpoint.startswith("ipc://") or not os.path.exists(endpoint[6:]):
        return False
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        try:
            s.connect(endpoint[6:])
        except OSError:
            return False
    return True
