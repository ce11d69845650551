"""Reading a launch file (TOML, stdlib ``tomllib``): check every key and type, substitute ``${arg}``, import
each node class and build its params, so a bad file is rejected with one line before anything starts.

The format is documented in docs/architecture.md ("Launch files").
"""

from __future__ import annotations

import hashlib
import os
import re
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import polarstripe
from polarstripe.errors import PolarstripeError
from polarstripe.runtime.graph import runs_dir
from polarstripe.runtime.params import ParamError, build_params
from polarstripe.runtime.runner import load_node_class


class LaunchError(PolarstripeError, ValueError):
    """A launch file or command line that cannot be launched; the text names the file, key and value."""


_LAUNCH_KEYS = {
    "name": str,
    "namespace": str,
    "transport": str,
    "host": str,
    "shutdown_timeout": float,
    "env": dict,
    "exclusive": list,
    "prepare": list,
}
_NODE_KEYS = {
    "name": str,
    "module": str,
    "params": dict,
    "env": dict,
    "respawn": bool,
    "respawn_delay": float,
    "max_respawns": int,
    "required": bool,
    "enabled": bool,
    "pub": str,
    "srv": str,
    "screen": bool,
    "respawn_max_delay": float,
}
_TOP_KEYS = {"launch", "args", "node"}
_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_-]*$")
_ARG = re.compile(r"\$\{([A-Za-z_][A-Za-z0-9_]*)\}")
BUILTIN_ARGS = ("run_id", "run_dir", "run_sock")  # per run, given by the launcher (see run_builtins)


def sock_dir(run_dir: Path) -> Path:
    """The folder of a run's ipc sockets: ``<run_dir>/sock``, or a short folder under /tmp when that path
    would be too long for an ipc endpoint (the kernel limits socket paths to ~107 bytes)."""
    d = run_dir / "sock"
    if len(str(d)) > 80:
        digest = hashlib.sha1(str(run_dir).encode()).hexdigest()[:10]  # the same in every process
        d = Path("/tmp") / f"ps-{os.getuid()}-{os.getpid()}-{digest}"
    return d


def run_builtins(run_dir: Path) -> dict[str, str]:
    """The args every launch file has without declaring them, one value per run: ``run_id``
    (``<name>-<stamp>-<pid>``), ``run_dir`` (the run directory) and ``run_sock`` (the folder of the run's
    ipc sockets). A default such as ``can = "ipc://${run_sock}/can"`` names a thing per run, so two launches
    of one file never meet."""
    return {"run_id": run_dir.name, "run_dir": str(run_dir), "run_sock": str(sock_dir(run_dir))}


@dataclass
class NodeSpec:
    name: str
    module: str
    params: dict[str, Any]
    env: dict[str, str] = field(default_factory=dict)
    respawn: bool = False
    respawn_delay: float = 1.0
    max_respawns: int = 5
    required: bool = False
    pub: str = ""
    srv: str = ""
    screen: bool = False  # also show its log lines on the launcher's console
    respawn_max_delay: float = 60.0  # the respawn delay doubles after each quick exit, up to this [s]
    node_class: Any = None
    fails_launch: bool = False  # its failure (exit != 0, not respawned) ends the launch with status 1


@dataclass
class LaunchSpec:
    path: Path
    name: str
    namespace: str = ""
    transport: str = "ipc"
    host: str = "127.0.0.1"
    shutdown_timeout: float = 3.0
    env: dict[str, str] = field(default_factory=dict)
    args: dict[str, Any] = field(default_factory=dict)
    nodes: list[NodeSpec] = field(default_factory=list)
    exclusive: dict[str, str] = field(default_factory=dict)  # arg -> value given explicitly (not per run)
    prepare: list[str] = field(default_factory=list)  # "module:function" run before the graph starts
    run_dir: Path | None = None


def _type_ok(value: Any, typ: type) -> bool:
    if typ is float:
        return isinstance(value, int | float) and not isinstance(value, bool)
    if typ is int:
        return isinstance(value, int) and not isinstance(value, bool)
    return isinstance(value, typ)


def _substitute(value: Any, args: dict[str, Any], where: str) -> Any:
    """Replace ``${name}`` in strings (recursively); a string that is exactly ``${name}`` takes the arg's
    value with its type."""
    if isinstance(value, str):
        m = _ARG.fullmatch(value)
        if m:
            if m.group(1) not in args:
                raise LaunchError(f"{where}: unknown arg ${{{m.group(1)}}} (declared: {_names(args)})")
            return args[m.group(1)]

        def one(m: re.Match) -> str:
            if m.group(1) not in args:
                raise LaunchError(f"{where}: unknown arg ${{{m.group(1)}}} (declared: {_names(args)})")
            v = args[m.group(1)]
            return str(v).lower() if isinstance(v, bool) else str(v)

        return _ARG.sub(one, value)
    if isinstance(value, dict):
        return {k: _substitute(v, args, f"{where}.{k}") for k, v in value.items()}
    if isinstance(value, list):
        return [_substitute(v, args, where) for v in value]
    return value


def _names(args: dict) -> str:
    return ", ".join(sorted(args)) or "none"


def _coerce_typed(value: Any, typ: type, where: str) -> Any:
    """A value after substitution may be a string standing for a bool or number (``"${use_sim}"``)."""
    if _type_ok(value, typ):
        return float(value) if typ is float else value
    if isinstance(value, str):
        low = value.strip().lower()
        try:
            if typ is bool and low in ("true", "false", "1", "0", "yes", "no"):
                return low in ("true", "1", "yes")
            if typ is int:
                return int(low)
            if typ is float:
                return float(low)
        except ValueError:
            pass
    raise LaunchError(f"{where}: expected {typ.__name__}, got {type(value).__name__} {value!r}")


def _check_table(table: Any, keys: dict[str, type], where: str, args: dict) -> dict:
    if not isinstance(table, dict):
        raise LaunchError(f"{where}: expected a table, got {type(table).__name__}")
    out = {}
    for key, value in table.items():
        if key not in keys:
            raise LaunchError(f"{where}: unknown key {key!r} (known: {', '.join(sorted(keys))})")
        value = _substitute(value, args, f"{where}.{key}")
        out[key] = _coerce_typed(value, keys[key], f"{where}.{key}")
    for key in ("env",):
        for k, v in out.get(key, {}).items():
            if not isinstance(v, str | int | float | bool):
                raise LaunchError(f"{where}.env.{k}: expected a string, got {type(v).__name__}")
        if key in out:
            out[key] = {k: str(v) for k, v in out[key].items()}
    return out


def find_launch_file(path: str | Path) -> Path:
    """``path`` if it exists, else the launch file of that name shipped with polarstripe (``sim``,
    ``sim.toml`` and ``launch/sim.toml`` all name the embedded ``launch/sim.toml``), else ``path``."""
    path = Path(path)
    if path.is_file() or path.is_absolute():  # not a directory: "sim" in the repository root is a package
        return path

    shipped = Path(polarstripe.__file__).parent / "launch" / path.name
    for candidate in (shipped, shipped.with_name(shipped.name + ".toml")):
        if candidate.is_file():
            return candidate
    return path


def _builtin_sub(value: Any, builtins: dict[str, str]) -> Any:
    """``${run_id}``, ``${run_dir}``, ``${run_sock}`` in an arg's value (other ``${…}`` stay as they are)."""
    if not isinstance(value, str):
        return value
    return _ARG.sub(lambda m: builtins.get(m.group(1), m.group(0)), value)


def load_launch(path: str | Path, overrides: dict[str, str] | None = None, *,
                run_dir: Path | None = None) -> LaunchSpec:
    """Read and check a launch file; ``overrides`` are ``key=value`` args from the command line; ``run_dir``
    the run directory (default: a new name under :func:`~polarstripe.runtime.graph.runs_dir`), which the
    built-in args ``${run_id}``, ``${run_dir}``, ``${run_sock}`` name.

    Raises :class:`LaunchError` (one line) for a file that cannot be read or parsed, an unknown key, a value
    of the wrong type, an unknown arg, a duplicate node name, a missing module or class, or bad params.
    """
    path = find_launch_file(path)
    raw = _read_toml(path)
    where = path.name
    args, explicit = _args(raw.get("args", {}), overrides or {}, where)
    spec, builtins = _launch_spec(path, raw.get("launch", {}), args, explicit, run_dir)
    nodes = raw.get("node", [])
    if not isinstance(nodes, list) or not nodes:
        raise LaunchError(f"{where}: needs at least one [[node]]")
    seen: set[str] = set()
    for i, table in enumerate(nodes):
        node = _node_spec(table, f"{where}: node[{i}]", where, {**spec.args, **builtins}, seen)
        if node is not None:
            spec.nodes.append(node)
    return spec


def _read_toml(path: Path) -> dict:
    """The launch file's tables; only the top-level keys args, launch and node."""
    try:
        raw = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise LaunchError(f"launch file {path} does not exist") from None
    except tomllib.TOMLDecodeError as exc:
        raise LaunchError(f"{path}: not valid TOML: {exc}") from None
    for key in raw:
        if key not in _TOP_KEYS:
            raise LaunchError(f"{path.name}: unknown top-level key {key!r} (known: args, launch, node)")
    return raw


def _args(args: Any, overrides: dict[str, str], where: str) -> tuple[dict, set[str]]:
    """The declared ``[args]`` with the command line's ``overrides``, and the names the command line set."""
    if not isinstance(args, dict):
        raise LaunchError(f"{where}: [args] must be a table")
    for k, v in args.items():
        if not isinstance(v, str | int | float | bool):
            raise LaunchError(f"{where}: args.{k}: expected a string, number or bool, got {type(v).__name__}")
    args = dict(args)
    for k in BUILTIN_ARGS:
        if k in args:
            raise LaunchError(f"{where}: args.{k}: {k} is given by the launcher (one per run); "
                              "pick another name")
    for k, v in overrides.items():
        if k not in args:
            raise LaunchError(f"{where}: unknown arg {k!r} on the command line (declared: {_names(args)})")
        args[k] = v
    return args, set(overrides)


def _launch_spec(path: Path, launch_table: Any, args: dict, explicit: set[str],
                 run_dir: Path | None) -> tuple[LaunchSpec, dict[str, str]]:
    """The ``[launch]`` table checked, the run directory named and the built-in args substituted into the
    args: the spec (without nodes) and the built-ins."""
    where = path.name
    name = path.stem
    if isinstance(launch_table, dict) and "name" in launch_table:
        name = _coerce_typed(_substitute(launch_table["name"], args, f"{where}: [launch].name"), str,
                             f"{where}: [launch].name")
    if run_dir is None:
        run_dir = runs_dir() / f"{name}-{time.strftime('%Y%m%dT%H%M%S')}-{os.getpid()}"
    builtins = run_builtins(Path(run_dir))
    per_run = {k for k, v in args.items() if isinstance(v, str) and _ARG.search(v)
               and any(m.group(1) in builtins for m in _ARG.finditer(v))}
    args = {k: _builtin_sub(v, builtins) for k, v in args.items()}
    launch = _check_table(launch_table, _LAUNCH_KEYS, f"{where}: [launch]", {**args, **builtins})
    for key in ("exclusive", "prepare"):
        if not all(isinstance(x, str) for x in launch.get(key, [])):
            raise LaunchError(f"{where}: launch.{key} must be a list of strings")
    for k in launch.get("exclusive", []):
        if k not in args:
            raise LaunchError(f"{where}: launch.exclusive names {k!r}, not an arg (declared: {_names(args)})")
    for entry in launch.get("prepare", []):
        if ":" not in entry:
            raise LaunchError(f"{where}: launch.prepare: {entry!r} must be MODULE:FUNCTION")
    spec = LaunchSpec(
        path=path,
        run_dir=Path(run_dir),
        exclusive={k: str(args[k]) for k in launch.get("exclusive", [])
                   if str(args[k]) and (k in explicit or k not in per_run)},
        prepare=list(launch.get("prepare", [])),
        name=launch.get("name", path.stem),
        args=args,
        namespace=launch.get("namespace", ""),
        transport=launch.get("transport", "ipc"),
        host=launch.get("host", "127.0.0.1"),
        shutdown_timeout=launch.get("shutdown_timeout", 3.0),
        env=launch.get("env", {}),
    )
    if spec.transport not in ("ipc", "tcp"):
        raise LaunchError(f"{where}: launch.transport must be 'ipc' or 'tcp', got {spec.transport!r}")
    if not spec.shutdown_timeout > 0:
        raise LaunchError(f"{where}: launch.shutdown_timeout must be > 0, got {spec.shutdown_timeout}")
    return spec, builtins


def _node_spec(table: Any, nwhere: str, where: str, subs: dict, seen: set[str]) -> NodeSpec | None:
    """One ``[[node]]`` table checked (``subs``: the args and built-ins it may name), its class imported and
    its params built; None when it is not ``enabled``. ``seen``: the names so far (this one is added)."""
    if isinstance(table, dict):
        nwhere += f" ({table.get('name')!r})"
    t = _check_table(table, _NODE_KEYS, nwhere, subs)
    for req in ("name", "module"):
        if req not in t:
            raise LaunchError(f"{nwhere}: missing key {req!r}")
    name = t["name"]
    if not _NAME.match(name):
        raise LaunchError(
            f"{nwhere}: name {name!r} must be letters, digits, '_' or '-', starting with a letter"
        )
    if name in seen:
        raise LaunchError(f"{nwhere}: duplicate node name {name!r}")
    seen.add(name)
    if not t.pop("enabled", True):
        return None
    if t.get("respawn_delay", 0) < 0 or t.get("max_respawns", 0) < 0 or t.get("respawn_max_delay", 0) < 0:
        raise LaunchError(f"{nwhere}: respawn_delay, respawn_max_delay and max_respawns must be >= 0")
    try:
        cls = load_node_class(t["module"])
    except PolarstripeError as exc:
        raise LaunchError(f"{nwhere}: {exc}") from None
    try:
        params = build_params(cls.Params, t.get("params", {}), node=name).as_dict()
    except ParamError as exc:
        raise LaunchError(f"{where}: {exc}") from None
    t["params"] = {k: v for k, v in params.items() if k in t.get("params", {})}
    return NodeSpec(node_class=cls, **t)
