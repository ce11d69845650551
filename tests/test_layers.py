"""The layers of docs/architecture.md hold: import-linter's contracts in pyproject.toml all pass, they name
every node module, and they can fail."""

import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_import_linter_contracts_are_kept():
    exe = shutil.which("lint-imports")
    if exe is None:  # the test extra installs it; a missing tool must fail, not skip
        pytest.fail("lint-imports not found: pip install -e '.[test]'")
    r = subprocess.run([exe, "--no-cache"], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stdout[-4000:] + r.stderr[-2000:]
    assert "BROKEN" not in r.stdout and r.stdout.count("KEPT") >= 5


def test_a_backward_import_is_caught(tmp_path):
    """The contracts can fail: a copy of the package whose model imports the runtime breaks the layers."""
    pkg = tmp_path / "polarstripe"
    shutil.copytree(ROOT, pkg, ignore=shutil.ignore_patterns(".git", ".venv", "tests", "out", "*.egg-info",
                                                              "__pycache__", "docs"))
    (pkg / "sim" / "backward.py").write_text("from polarstripe.runtime import bus\n")
    estimator = pkg / "nodes" / "estimator.py"  # a node reaching into another node's helper
    estimator.write_text(estimator.read_text() + "\nfrom polarstripe.nodes import compositor_output\n")
    cfg = tmp_path / "contracts.toml"
    cfg.write_text((ROOT / "pyproject.toml").read_text())
    r = subprocess.run([shutil.which("lint-imports") or "lint-imports", "--no-cache", "--config", str(cfg)],
                       cwd=tmp_path, capture_output=True, text=True, timeout=120,
                       env={"PYTHONPATH": str(tmp_path), "PATH": str(Path(sys.executable).parent)})
    assert r.returncode != 0
    assert "polarstripe.sim.backward -> polarstripe.runtime.bus" in r.stdout
    assert "polarstripe.nodes.estimator -> polarstripe.nodes.compositor_output" in r.stdout


def test_the_node_contracts_name_every_node_module():
    """A node module (or a node's helper) left out of the contracts could import any other node unseen."""
    contracts = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"]
    modules = {p.stem for p in (ROOT / "nodes").glob("*.py")} - {"__init__"}
    (independent,) = [c for c in contracts if c["type"] == "independence"]
    assert {m.removeprefix("polarstripe.nodes.") for m in independent["modules"]} == modules
    (drivers,) = [c for c in contracts if c.get("containers") == ["polarstripe.nodes"]]
    assert {m.strip() for m in drivers["layers"][0].split(":")} == modules
