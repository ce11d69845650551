"""``polarstripe node MODULE[:CLASS]``: run one node by itself (the launcher starts its children this way)."""

from __future__ import annotations

import argparse
import json

from polarstripe.runtime.params import ParamError, parse_assignments
from polarstripe.runtime.runner import run_node

HELP = "run one node by itself"


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "spec",
        metavar="MODULE[:CLASS]",
        help="the node class, e.g. polarstripe.nodes.demo:Talker (a module's NODE if no class)",
    )
    parser.add_argument("--name", help="node name (default: the class name, lower case)")
    parser.add_argument("--namespace", default="", help="namespace of relative topic names, e.g. /rig")
    parser.add_argument(
        "--param",
        "-p",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="set a parameter (repeatable); the value is coerced to the declared type",
    )
    parser.add_argument("--params-json", default=None, metavar="JSON", help="parameters as one JSON object")
    parser.add_argument(
        "--graph", default=None, metavar="FILE", help="a launch's graph.json (endpoints, peers)"
    )
    parser.add_argument("--pub", default=None, metavar="ENDPOINT", help="bind the PUB socket here")
    parser.add_argument("--srv", default=None, metavar="ENDPOINT", help="bind the service socket here")
    parser.add_argument(
        "--connect",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="also subscribe from this PUB endpoint (repeatable)",
    )
    parser.add_argument(
        "--service",
        action="append",
        default=[],
        metavar="NAME=ENDPOINT",
        help="where a service the node calls is served (repeatable)",
    )


def main(args: argparse.Namespace) -> int:

    params: dict = {}
    if args.params_json:
        try:
            given = json.loads(args.params_json)
        except json.JSONDecodeError as exc:
            raise ParamError(f"--params-json: not JSON ({exc})") from None
        if not isinstance(given, dict):
            raise ParamError(f"--params-json: must be one JSON object {{name: value}}, "
                             f"got {args.params_json!r}")
        params.update(given)
    params.update(parse_assignments(args.param))
    services = parse_assignments(args.service, what="service")
    return run_node(
        args.spec,
        name=args.name,
        namespace=args.namespace,
        params=params,
        graph_file=args.graph,
        pub=args.pub,
        srv=args.srv,
        connect=args.connect,
        services=services,
    )
