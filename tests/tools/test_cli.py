import subprocess
import sys


def _run(*args):
    return subprocess.run(
        [sys.executable, "-m", "polarstripe", *args], capture_output=True, text=True, timeout=60
    )


def test_help_lists_every_command():
    from polarstripe.tools.cli import COMMANDS

    out = _run("--help")
    assert out.returncode == 0
    for name in COMMANDS:
        assert name in out.stdout


def test_unknown_command_is_one_clear_line():
    out = _run("frobnicate")
    assert out.returncode == 2
    assert "unknown command 'frobnicate'" in out.stderr
    assert "Traceback" not in out.stderr
