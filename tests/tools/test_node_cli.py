"""``polarstripe node MODULE[:CLASS]`` (tools/node_cli.py): every bad input is one error line with exit 2
before any socket is bound; a good one runs the node with its parameters (``-p`` over ``--params-json``), name
and namespace on default or given ipc endpoints."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest
from polarstripe.tools.cli import main


def _one_error_line(capsys) -> str:
    cap = capsys.readouterr()
    lines = cap.err.strip().splitlines()
    assert len(lines) == 1, cap.err
    assert lines[0].startswith("polarstripe node: error: ")
    return lines[0].removeprefix("polarstripe node: error: ")


@pytest.mark.parametrize(
    "argv, error",
    [
        (["no_such_pkg.mod:X"], "node 'no_such_pkg.mod:X': module 'no_such_pkg' not found"),
        (["polarstripe.nodes.demo:Nope"],
         "node 'polarstripe.nodes.demo:Nope': module 'polarstripe.nodes.demo' has no class 'Nope' "
         "(a Node subclass)"),
        (["polarstripe.msgs:Frame"], "module 'polarstripe.msgs' has no class 'Frame' (a Node subclass)"),
        (["polarstripe.nodes.demo:Talker", "--params-json", "{rate: 1}"],
         "--params-json: not JSON (Expecting property name enclosed in double quotes: line 1 column 2"),
        (["polarstripe.nodes.demo:Talker", "-p", "rate_hz"], "param 'rate_hz': expected KEY=VALUE"),
        (["polarstripe.nodes.demo:Talker", "-p", "=3"], "param '=3': expected KEY=VALUE"),
        (["polarstripe.nodes.demo:Talker", "--service", "reset"], "service 'reset': expected KEY=VALUE"),
        (["polarstripe.nodes.demo:Talker", "-p", "rate_hz=fast"], "param 'rate_hz': bad value 'fast'"),
        (["polarstripe.nodes.demo:Talker", "-p", "speed=3"], "unknown param 'speed'"),
        (["polarstripe.nodes.demo:Talker", "--params-json", '{"count": -1}'], "count must be >= 0, got -1"),
    ],
)
def test_bad_input_is_one_line_before_anything_starts(argv, error, capsys, tmp_path, monkeypatch):
    monkeypatch.setenv("POLARSTRIPE_RUNS", str(tmp_path / "runs"))
    assert main(["node", *argv]) == 2
    assert error in _one_error_line(capsys)
    assert not (tmp_path / "standalone").exists()  # no socket was bound


def test_a_node_missing_from_the_graph_is_named(tmp_path, capsys):
    graph = tmp_path / "graph.json"
    graph.write_text(json.dumps({"namespace": "/rig", "nodes": {"listener": {"pub": "ipc:///nowhere"}}}))
    assert main(["node", "polarstripe.nodes.demo:Talker", "--graph", str(graph)]) == 2
    assert _one_error_line(capsys) == f"node 'talker' is not in graph {graph}"
    assert main(["node", "polarstripe.nodes.demo:Talker", "--graph", str(tmp_path / "none.json")]) == 2
    assert "does not exist" in _one_error_line(capsys)


def test_a_module_without_node_names_what_it_needs(capsys):
    assert main(["node", "polarstripe.nodes.demo"]) == 2
    assert "module 'polarstripe.nodes.demo' has no" in _one_error_line(capsys)


def test_a_module_without_node_reads_well(capsys):
    assert main(["node", "polarstripe.nodes.demo"]) == 2
    assert "has no NODE attribute naming its Node class" in _one_error_line(capsys)


@pytest.mark.parametrize("value", ["[1, 2]", '"x"', "3"])
def test_params_json_must_be_an_object(value, capsys):
    try:
        code = main(["node", "polarstripe.nodes.demo:Talker", "--params-json", value])
    except (TypeError, ValueError) as exc:
        pytest.fail(f"traceback: {type(exc).__name__}: {exc}")
    assert code == 2 and "--params-json" in _one_error_line(capsys)


def test_usage_errors(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["node"])
    assert exc.value.code == 2
    assert "the following arguments are required: MODULE[:CLASS]" in capsys.readouterr().err


def _run(tmp_path, *args):
    env = {**os.environ, "POLARSTRIPE_RUNS": str(tmp_path / "runs")}
    env.pop("POLARSTRIPE_CURVE_KEYS", None)
    return subprocess.run([sys.executable, "-m", "polarstripe", "node", *args], env=env, capture_output=True,
                          text=True, timeout=60)


def test_a_node_runs_with_its_params_name_and_default_endpoints(tmp_path):
    # -p wins over --params-json: the talker stops after 2 messages, not 50
    r = _run(tmp_path, "polarstripe.nodes.demo:Talker", "--name", "chatty", "--namespace", "/rig",
             "--params-json", '{"count": 50, "rate_hz": 200}', "-p", "count=2")
    assert r.returncode == 0, r.stderr
    assert "chatty: started (pid " in r.stderr
    assert f"pub ipc://{tmp_path}/standalone/chatty.pub)" in r.stderr  # <runs>/../standalone
    assert r.stderr.strip().endswith("chatty: stopped (sent 2 messages)")


def test_a_node_binds_the_given_endpoints(tmp_path):
    r = _run(tmp_path, "polarstripe.nodes.demo:Talker", "-p", "count=1", "-p", "rate_hz=100",
             "--pub", f"ipc://{tmp_path}/t.pub", "--srv", f"ipc://{tmp_path}/t.srv")
    assert r.returncode == 0, r.stderr
    assert "talker: started (pid " in r.stderr and f"pub ipc://{tmp_path}/t.pub)" in r.stderr
