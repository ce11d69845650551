"""docs/nodes.md is written from the node classes (tools/node_docs.py) and must be what the code says now."""

import tomllib
from pathlib import Path

from polarstripe.runtime.runner import load_node_class
from polarstripe.tools import node_docs
from polarstripe.tools.cli import main

ROOT = Path(__file__).resolve().parents[2]


def test_docs_nodes_md_is_the_generated_reference():
    text = (ROOT / "docs" / "nodes.md").read_text()
    assert text == node_docs.render(), "docs/nodes.md is stale: polarstripe docs nodes -o docs/nodes.md"


def test_the_command_writes_it(tmp_path):
    assert main(["docs", "nodes", "-o", str(tmp_path / "nodes.md")]) == 0
    assert (tmp_path / "nodes.md").read_text() == (ROOT / "docs" / "nodes.md").read_text()


def test_every_node_a_launch_file_starts_is_in_the_reference():
    listed = {cls for _, cls in node_docs.node_classes()}
    for f in sorted((ROOT / "launch").glob("*.toml")):
        for node in tomllib.loads(f.read_text()).get("node", []):
            assert load_node_class(node["module"]) in listed, (f.name, node["module"])


def test_a_param_is_listed_with_its_type_default_and_comment():
    rows = [line for line in node_docs.render().splitlines() if line.startswith("| `grab_timeout_s` ")]
    assert rows == ["| `grab_timeout_s` | `float` | `10.0` | a grab (and a service the camera calls) that "
                    "takes longer is a fault |"]
