"""The layers of docs/architecture.md hold: import-linter's contracts in pyproject.toml all pass."""

import shutil
import subprocess
import sys
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
    cfg = tmp_path / "contracts.toml"
    cfg.write_text((ROOT / "pyproject.toml").read_text())
    r = subprocess.run([shutil.which("lint-imports") or "lint-imports", "--no-cache", "--config", str(cfg)],
                       cwd=tmp_path, capture_output=True, text=True, timeout=120,
                       env={"PYTHONPATH": str(tmp_path), "PATH": str(Path(sys.executable).parent)})
    assert r.returncode != 0
    assert "polarstripe.sim.backward -> polarstripe.runtime.bus" in r.stdout
