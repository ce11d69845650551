"""``polarstripe launch FILE.toml [key=value …] [--dry-run] [--once] [--record run.mcap]``: start a rig.

The launcher checks the whole file first (:mod:`.launch_file`), makes the run directory, assigns every node
its endpoints, writes ``graph.json``, then starts each node as ``python -m polarstripe node …`` in its own
session (output to ``logs/<node>.log``) and supervises: respawn with a delay up to ``max_respawns``; a
``required`` node's exit ends the launch. Ctrl-C/SIGTERM stop the children in reverse start order: SIGINT,
then SIGTERM, then SIGKILL, ``shutdown_timeout`` seconds apart; what a node left in its process group is
waited for, then killed (:mod:`.pgroups`). Children also get SIGTERM if the launcher itself dies. At the
end it prints one line per node (exit status or signal, whether the launcher stopped it, respawns) and
writes them to ``exits.json`` in the run directory (:meth:`Launcher.exits`).

Recording: ``--record FILE`` adds a node ``recorder`` running
``polarstripe.nodes.recorder:Recorder`` with param ``path = FILE``, started first and stopped last
so it sees the whole run.
"""

from __future__ import annotations

import argparse
import ctypes
import fcntl
import hashlib
import json
import os
import re
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from polarstripe.runtime.graph import runs_dir, write_graph
from polarstripe.runtime.launch_file import LaunchError, LaunchSpec, NodeSpec, load_launch, sock_dir
from polarstripe.runtime.launch_setup import _ipc_in_use, _with_recorder, build_graph
from polarstripe.runtime.liveness import INCARNATION_ENV
from polarstripe.runtime.params import parse_assignments
from polarstripe.runtime.pgroups import dump_stacks, reap_groups, set_subreaper

HELP = "start a rig from a launch file"
USER_ERROR = 2  # a node's exit status for a one-line PolarstripeError (a bad setting, a missing device)


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "file",
        nargs="?",
        default="sim",
        help="launch file (TOML); a name such as 'sim' picks one shipped with polarstripe (default: sim)",
    )
    parser.add_argument("overrides", nargs="*", metavar="KEY=VALUE", help="override [args] of the file")
    parser.add_argument("--dry-run", action="store_true", help="print the resolved graph and exit")
    parser.add_argument(
        "--once", action="store_true", help="end when every required node has exited (status 1 if one failed)"
    )
    parser.add_argument("--record", metavar="FILE.mcap", help="also record every topic to FILE.mcap")
    # KEY=VALUE may come after the flags (`launch f.toml --once n=3`): parse positionals intermixed
    parser.parse_args = parser.parse_intermixed_args  # type: ignore[method-assign]


def _die_with_parent() -> None:  # runs in the child between fork and exec
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except OSError:
        pass


def _node_preexec() -> None:  # runs in a node's process between fork and exec
    _die_with_parent()
    # SIGINT/SIGTERM wait (pending) until the node's own handlers are in (runtime/process.py): a Ctrl-C that
    # comes while Python starts or imports would otherwise be a traceback, or lost
    signal.pthread_sigmask(signal.SIG_BLOCK, (signal.SIGINT, signal.SIGTERM))


@dataclass
class _Child:
    spec: NodeSpec
    proc: subprocess.Popen | None = None
    respawns: int = 0
    restart_at: float | None = None
    exit_code: int | None = None  # the last exit: its status, or -N if killed by signal N
    done: bool = False  # exited for good
    stopped_by: str | None = None  # the launcher's last signal to it at shutdown (None: it ended by itself)
    echoed: int = 0  # bytes of its log already shown on the console (screen = true)
    started_at: float = 0.0  # time.monotonic() of its last start
    delay: float = 0.0  # its last respawn delay [s]


class Launcher:
    """Starts and supervises the nodes of one launch. :meth:`run` returns the launch's exit status."""

    def __init__(self, spec: LaunchSpec, *, once: bool = False, out=sys.stderr):
        self.spec, self.once, self.out = spec, once, out
        stamp = time.strftime("%Y%m%dT%H%M%S")
        self.run_dir = spec.run_dir or runs_dir() / f"{spec.name}-{stamp}-{os.getpid()}"
        self.graph = build_graph(spec, self.run_dir)
        self.graph_file = self.run_dir / "graph.json"
        self.children = [_Child(n) for n in spec.nodes]
        if once and not any(n.required for n in spec.nodes):
            raise LaunchError(f"{spec.path.name}: --once needs at least one node with required = true")
        self._stop: str | None = None
        self._ended = ""  # why the launch ended
        self._claims: list[int] = []  # lock files held for the exclusive args
        self._left: list[str] = []  # files the nodes left in ${run_sock} (a node killed, or not cleaning up)
        self._groups: dict[int, str] = {}  # the process group of every process started (runtime/pgroups.py)

    def say(self, text: str) -> None:
        print(f"[launch {self.spec.name}] {text}", file=self.out, flush=True)

    def claim(self) -> None:
        """Before anything starts: hold each ``exclusive`` arg's explicit value (a lock file under the runs
        folder, held while this launch runs), and check that no explicit ipc endpoint is already served.

        :raises LaunchError: (one line) naming the arg, its value and the launch that holds it."""
        folder = runs_dir().parent / "claims"
        folder.mkdir(parents=True, exist_ok=True)
        for arg, value in self.spec.exclusive.items():
            safe = re.sub(r"[^A-Za-z0-9_.-]+", "_", value)[-40:]
            path = folder / f"{arg}-{safe}-{hashlib.sha1(value.encode()).hexdigest()[:10]}.lock"
            fd = os.open(path, os.O_CREAT | os.O_RDWR, 0o600)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = os.read(fd, 4096).decode(errors="replace").strip() or "another launch"
                os.close(fd)
                raise LaunchError(
                    f"{self.spec.path.name}: {arg}={value!r} is in use by {holder}; two launches would share "
                    f"it: leave {arg} out (one per run) or name another"
                ) from None
            os.ftruncate(fd, 0)
            os.write(fd, f"launch {self.spec.name} (pid {os.getpid()}, {self.run_dir})".encode())
            self._claims.append(fd)
        for name, node in self.graph["nodes"].items():
            spec = next(n for n in self.spec.nodes if n.name == name)
            for key in ("pub", "srv"):
                if getattr(spec, key) and _ipc_in_use(node[key]):
                    raise LaunchError(f"{self.spec.path.name}: node {name!r}: {key} {node[key]} is in use "
                                      f"(another process serves it): name another or leave {key} out")

    def _release(self) -> None:
        for fd in self._claims:
            os.close(fd)
        self._claims = []

    def prepare(self) -> None:
        """Run each ``[launch] prepare`` step (``MODULE:FUNCTION``, e.g. compiling the model's kernels) in a
        process of its own before any node starts, with a progress line; its output goes to
        ``logs/prepare.log``.

        :raises LaunchError: when a step fails (its last log line) or the launch is stopped meanwhile."""
        env = {**os.environ, **self.spec.env, "PYTHONUNBUFFERED": "1"}
        for step in self.spec.prepare:
            module, _, func = step.partition(":")
            code = f"import importlib; importlib.import_module({module!r}).{func}()"
            t0 = time.monotonic()
            self.say(f"preparing: {step} (a first run on this machine compiles; later runs load the cache) …")
            with open(self.run_dir / "logs" / "prepare.log", "ab") as log:
                proc = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.DEVNULL, stdout=log,
                                        stderr=subprocess.STDOUT, env=env, start_new_session=True,
                                        preexec_fn=_die_with_parent)
            self._groups[proc.pid] = f"prepare {step}"
            while proc.poll() is None:
                if self._stop:
                    proc.terminate()
                    proc.wait()
                    raise LaunchError(f"{self._stop} while preparing {step}")
                time.sleep(0.05)
            if proc.returncode:
                lines = (self.run_dir / "logs" / "prepare.log").read_text(errors="replace").splitlines()
                raise LaunchError(f"prepare {step} failed (exit {proc.returncode})"
                                  + (f": {lines[-1]}" if lines else ""))
            self.say(f"prepared {step} in {time.monotonic() - t0:.1f} s")

    def _spawn(self, c: _Child) -> None:
        n = c.spec
        env = {**os.environ, **self.spec.env, **n.env, "PYTHONUNBUFFERED": "1",
               INCARNATION_ENV: str(c.respawns)}  # in its heartbeat: peers tell a respawned node apart
        cmd = [
            sys.executable,
            "-m",
            "polarstripe",
            "node",
            n.module,
            "--name",
            n.name,
            "--graph",
            str(self.graph_file),
            "--params-json",
            json.dumps(n.params),
        ]
        log = open(self.run_dir / "logs" / f"{n.name}.log", "ab")  # noqa: SIM115  (the child owns it)
        try:
            c.proc = subprocess.Popen(
                cmd,
                stdin=subprocess.DEVNULL,
                stdout=log,
                stderr=subprocess.STDOUT,
                env=env,
                start_new_session=True,
                preexec_fn=_node_preexec,
            )
        finally:
            log.close()
        self._groups[c.proc.pid] = n.name
        c.restart_at = None
        c.started_at = time.monotonic()
        self.graph["nodes"][n.name]["pid"] = c.proc.pid
        write_graph(self.graph_file, self.graph)
        self.say(f"{n.name} started (pid {c.proc.pid})" + (f", respawn {c.respawns}" if c.respawns else ""))

    def _echo(self) -> None:
        """Show on the console what ``screen = true`` nodes have written to their logs since last time."""
        for c in self.children:
            if not c.spec.screen or c.proc is None:
                continue
            with open(self.run_dir / "logs" / f"{c.spec.name}.log", "rb") as f:
                f.seek(c.echoed)
                data = f.read()
            complete = data[: data.rfind(b"\n") + 1]
            c.echoed += len(complete)
            for line in complete.decode(errors="replace").splitlines():
                print(f"[{c.spec.name}] {line}", file=self.out, flush=True)

    def _on_signal(self, signum, frame) -> None:
        self._stop = self._stop or signal.Signals(signum).name

    def run(self) -> int:
        (self.run_dir / "logs").mkdir(parents=True, exist_ok=True)
        sock_dir(self.run_dir).mkdir(parents=True, exist_ok=True, mode=0o700)  # ${run_sock}: ready for nodes
        write_graph(self.graph_file, self.graph)
        old = {s: signal.signal(s, self._on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
        subreaper = set_subreaper(True)  # what a node leaves in its group becomes ours to reap
        status = 1  # if something below raises
        try:
            self.say(f"run directory {self.run_dir}")
            self.claim()
            self.prepare()
            for c in self.children:
                if self._stop:
                    break
                self._spawn(c)
            self.graph["state"] = "running"
            write_graph(self.graph_file, self.graph)
            status = self._supervise()
        except LaunchError as exc:  # before any node started: one line, status 2 (as a bad file)
            self._end(str(exc))
            status = {"SIGINT": 130, "SIGTERM": 143}.get(self._stop, 2)
        finally:
            self._shutdown()
            if subreaper is not None:
                set_subreaper(subreaper)
            self._release()
            self._echo()
            for s, h in old.items():
                signal.signal(s, h)
            self.graph["state"] = "stopped"
            write_graph(self.graph_file, self.graph)
            self._report_exits(status)
        return status

    def exits(self, status: int) -> dict:
        """What ``exits.json`` holds: the launch's exit status and, per node (in start order), ``started``,
        ``exit_code`` (None if a signal killed it), ``signal`` (the signal's name, or None), ``stopped_by``
        (the launcher's last signal to it at shutdown; None if it had ended by itself), ``respawns``,
        ``pid`` (of its last process); and ``left_sockets``: the files the nodes had left in the run's
        socket folder when they were all gone (the launcher removes them; an orderly stop leaves none)."""
        nodes = {}
        for c in self.children:
            code = c.exit_code
            nodes[c.spec.name] = {
                "started": c.proc is not None,
                "exit_code": code if code is not None and code >= 0 else None,
                "signal": signal.Signals(-code).name if code is not None and code < 0 else None,
                "stopped_by": c.stopped_by,
                "respawns": c.respawns,
                "pid": c.proc.pid if c.proc is not None else None,
            }
        return {"launch": self.spec.name, "status": status, "ended": self._ended, "nodes": nodes,
                "left_sockets": self._left}

    def _report_exits(self, status: int) -> None:
        """One line per node (exit status or signal, who stopped it, respawns), and ``exits.json`` in the run
        directory."""
        report = self.exits(status)
        for name, e in report["nodes"].items():
            if not e["started"]:
                self.say(f"{name}: not started")
                continue
            how = f"exit {e['exit_code']}" if e["signal"] is None else f"killed by {e['signal']}"
            after = f" after the launcher's {e['stopped_by']}" if e["stopped_by"] else ""
            self.say(f"{name}: {how}{after}, {e['respawns']} respawn{'s' * (e['respawns'] != 1)}")
        path = self.run_dir / "exits.json"
        tmp = path.with_suffix(".tmp")
        tmp.write_text(json.dumps(report, indent=2))
        os.replace(tmp, path)

    def _supervise(self) -> int:
        required = [c for c in self.children if c.spec.required]
        while not self._stop:
            now = time.monotonic()
            for c in self.children:
                if c.proc is not None and c.exit_code is None and c.proc.poll() is not None:
                    self._exited(c, now)
                elif c.restart_at is not None and now >= c.restart_at:
                    self._spawn(c)
                    c.exit_code = None
            if required:
                ended = [c for c in required if c.done]
                failed = [c for c in ended if c.exit_code]
                if self.once and len(ended) == len(required):
                    self._end("every required node has exited")
                    return 1 if failed else 0
                if not self.once and ended:
                    self._end(f"required node {ended[0].spec.name} exited: stopping the launch")
                    return 1 if failed else 0
                if self.once and failed:
                    self._end(f"required node {failed[0].spec.name} failed: stopping the launch")
                    return 1
            fatal = [c for c in self.children if c.done and c.exit_code
                     and (c.spec.fails_launch or c.exit_code == USER_ERROR)]
            if fatal:  # a recorder that cannot record, or a node refusing its settings: nothing to wait for
                c = fatal[0]
                why = "cannot go on without it" if c.spec.fails_launch else "its settings or device refused"
                self._end(f"{c.spec.name} exit {c.exit_code} ({why}): stopping the launch")
                return 1
            if all(c.done for c in self.children):
                self._end("every node has exited")
                return 1 if any(c.exit_code for c in self.children) else 0
            self._echo()
            time.sleep(0.05)
        self._end(f"{self._stop}: stopping")
        return 130 if self._stop == "SIGINT" else 143

    def _end(self, why: str) -> None:
        self._ended = why
        self.say(why)

    def _reason(self, c: _Child) -> str:
        """The last line of the node's log: why it exited, in its own words."""
        try:
            lines = Path(self.graph["nodes"][c.spec.name]["log"]).read_text(errors="replace").splitlines()
        except OSError:
            return ""
        lines = [ln for ln in lines if ln.strip()]
        return f" (last line: {lines[-1].strip()})" if lines else ""

    def _exited(self, c: _Child, now: float) -> None:
        c.exit_code = code = c.proc.returncode
        n = c.spec
        how = f"exit {code}" if code >= 0 else f"killed by {signal.Signals(-code).name}"
        ran_s = now - c.started_at
        if n.respawn and c.respawns < n.max_respawns:
            # a crash loop backs off: the delay doubles after each exit that came soon after its start
            # (sooner than 10 delays, at least 10 s), up to respawn_max_delay; a long run resets it
            quick = ran_s < max(10.0, 10 * c.delay)
            c.delay = min(max(n.respawn_delay, n.respawn_max_delay), c.delay * 2) if quick and c.respawns \
                else n.respawn_delay
            c.respawns += 1
            c.restart_at = now + c.delay
            self.say(f"{n.name} {how} after {ran_s:.1f} s{self._reason(c) if code else ''}; "
                     f"respawn {c.respawns}/{n.max_respawns} in {c.delay:g} s")
        else:
            c.done = True
            self.say(f"{n.name} {how}{self._reason(c) if code else ''}")

    def _shutdown(self) -> None:
        """SIGINT, then SIGTERM, then SIGKILL to every live child (reverse start order), each stage waiting up
        to ``shutdown_timeout`` s; then reap everything, and what they left in their process groups."""
        live = [c for c in reversed(self.children) if c.proc is not None and c.proc.poll() is None]
        for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGKILL):
            if not live:
                break
            for c in live:
                c.stopped_by = sig.name
                try:
                    os.killpg(c.proc.pid, sig)
                except ProcessLookupError:
                    pass
            deadline = time.monotonic() + self.spec.shutdown_timeout
            while live and time.monotonic() < deadline:
                live = [c for c in live if c.proc.poll() is None]
                time.sleep(0.02)
            if live and sig != signal.SIGKILL:
                self.say(f"{', '.join(c.spec.name for c in live)} still running after {sig.name}"
                         + (": their stacks are in their logs" if sig == signal.SIGINT else ""))
                if sig == signal.SIGINT:
                    dump_stacks([c.proc.pid for c in live])
        for c in self.children:
            if c.proc is not None:
                code = c.proc.wait()
                if c.stopped_by is not None or c.exit_code is None:  # stopped here, or died unseen
                    c.exit_code = code
        reap_groups(self._groups, self.spec.shutdown_timeout, self.say)
        sock = sock_dir(self.run_dir)
        if sock.is_dir():
            for p in sorted(sock.iterdir()):
                self._left.append(p.name)
                p.unlink(missing_ok=True)
            sock.rmdir()


def main(args: argparse.Namespace) -> int:
    if "=" in args.file and not args.file.endswith(".toml"):  # `launch out=DIR`: an arg, not a file
        args.overrides, args.file = [args.file, *args.overrides], "sim"
    overrides = parse_assignments(args.overrides, what="arg")
    spec = load_launch(args.file, overrides)
    if args.record:
        _with_recorder(spec, os.path.abspath(args.record))
    launcher = Launcher(spec, once=args.once)
    if args.dry_run:
        print(json.dumps(launcher.graph, indent=2))
        return 0
    return launcher.run()
