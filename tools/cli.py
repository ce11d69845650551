"""The ``polarstripe`` command: one entry point, subcommands imported lazily.

Each subcommand lives in its own module, which defines::

    HELP: str                                   # one line for ``polarstripe --help``
    def configure(parser: argparse.ArgumentParser) -> None
    def main(args: argparse.Namespace) -> int   # exit status

A user mistake raises :class:`polarstripe.errors.PolarstripeError` (or ``OSError`` for a file); it is printed
as one line, ``polarstripe <cmd>: error: …``, with exit status 2 and no traceback.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from polarstripe import __version__
from polarstripe.errors import PolarstripeError

# name -> (module, one-line help). Modules are imported only when their command runs.
COMMANDS: dict[str, tuple[str, str]] = {
    "launch": ("polarstripe.runtime.launch", "start a rig from a launch file"),
    "node": ("polarstripe.tools.node_cli", "run one node by itself"),
    "topic": ("polarstripe.tools.topic", "list, echo or time the topics of a running launch"),
    "render": ("polarstripe.tools.render_cli", "render one frame of a scene with the light-transport model"),
    "figure": ("polarstripe.planning.figures", "plot the model's curves (D/S vs τ, DOP vs angle)"),
    "plan": ("polarstripe.planning.plan_cli", "find the best camera-source separation and stripe scan"),
    "compare": ("polarstripe.planning.compare", "reproduce the paper's comparison of imaging methods"),
    "sweep": ("polarstripe.planning.sweep_cli", "run the planner over a grid of scenes (design studies)"),
    "record": ("polarstripe.tools.record", "record topics to an MCAP file"),
    "bag": ("polarstripe.tools.bag_cli", "inspect, recover, export (ROS 2, Foxglove) or import recordings"),
    "replay": ("polarstripe.tools.replay", "publish a recording on its original topics"),
    "view": ("polarstripe.tools.view", "contact sheet of the latest frames and composites"),
    "bench": ("polarstripe.bench.cli", "run a benchmark and print its table"),
    "calibrate": ("polarstripe.tools.calibrate_cli", "calibrate projector and camera (Gray code)"),
    "camera": ("polarstripe.tools.camera_cli", "list cameras, grab one frame, run a GigE Vision simulator"),
    "keys": ("polarstripe.tools.keys_cli", "make a host's CURVE certificates, print a key's fingerprint"),
    "ros2": ("polarstripe.tools.ros2_cli", "write the ROS 2 interface package polarstripe_msgs"),
    "docs": ("polarstripe.tools.node_docs", "write the node reference (params, topics, services)"),
}


def _top_parser() -> argparse.ArgumentParser:
    epilog = "commands:\n" + "\n".join(f"  {name:<9} {help_}" for name, (_, help_) in COMMANDS.items())
    parser = argparse.ArgumentParser(
        prog="polarstripe",
        description="Polarized light striping and optimal camera-source placement for poor visibility.",
        epilog=epilog + "\n\n'polarstripe COMMAND --help' describes one command.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"polarstripe {__version__}")
    parser.add_argument("command", choices=sorted(COMMANDS), metavar="COMMAND", help="a command listed below")
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    top = _top_parser()
    if not argv or argv[0].startswith("-"):
        top.parse_args(argv or ["--help"])
        return 0
    name, rest = argv[0], argv[1:]
    if name not in COMMANDS:
        top.error(f"unknown command {name!r} (choose from {', '.join(COMMANDS)})")
    module_name, help_ = COMMANDS[name]
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        if exc.name and module_name.startswith(exc.name):
            print(f"polarstripe {name}: error: this command is not available in this build", file=sys.stderr)
            return 2
        raise
    parser = argparse.ArgumentParser(prog=f"polarstripe {name}", description=getattr(module, "HELP", help_))
    module.configure(parser)
    args = parser.parse_args(rest)
    try:
        return int(module.main(args) or 0)
    except PolarstripeError as exc:
        print(f"polarstripe {name}: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"polarstripe {name}: error: {exc.strerror or exc}"
              + (f": {exc.filename}" if getattr(exc, "filename", None) else ""), file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    raise SystemExit(main())
