"""``polarstripe bench NAME``: each benchmark is a module in this package with ``configure`` and ``main``.

Benchmarks print a table for people (ratios to the physical limit and the best peer, measured in the
same run) and, with ``--json``, one JSON object for machines.
"""

from __future__ import annotations

import argparse
import importlib

from polarstripe.errors import PolarstripeError

HELP = "run a benchmark and print its table (--json for machines)"

BENCHES: dict[str, str] = {
    "transport": "bus throughput and latency vs raw pyzmq and memcpy",
    "fidelity": "model time and error per fidelity level",
    "compositor": "per-frame cost of the running reductions",
    "planner": "time per full plan and optimum error per fidelity",
    "sweep": "design-study sweep: scenes per second with 1 and 2 workers",
    "pipeline": "a full simulated scan: simulation, transport, compositing",
    "record": "recorder sustained frame rate vs a plain file write",
    "depth": "triangulation time per stripe scan (and --accuracy: depth error vs truth)",
    "soak": "the sim rig scanning for N minutes, a node killed every M s: losses, memory, recovery",
    "light": "linear against circular light end to end over σ_t and g, and the planner's pick",
    "motion": "the composite's loss with the rig's speed: rotating analyzer, polarization camera, K sheets",
    "sheets": "K light sheets per stripe frame end to end over σ_t: error vs T, depth, frames",
    "ros2": "the live ROS 2 bridge's cost per camera frame against a plain Zenoh put and memcpy",
}


def configure(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="bench", required=True, metavar="NAME")
    for name, help_ in BENCHES.items():
        p = sub.add_parser(name, help=help_, description=help_)
        p.add_argument("--json", action="store_true", help="print one JSON object instead of a table")
        try:
            module = importlib.import_module(f"polarstripe.bench.{name}")
        except ModuleNotFoundError:
            continue
        module.configure(p)


def main(args: argparse.Namespace) -> int:

    try:
        module = importlib.import_module(f"polarstripe.bench.{args.bench}")
    except ModuleNotFoundError as exc:
        raise PolarstripeError(f"benchmark {args.bench!r} is not available in this build") from exc
    return int(module.main(args) or 0)
