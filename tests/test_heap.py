"""heap.py: with keep_freed, large buffers freed together are reused (no page faults the
second time round); glibc's defaults give the freed memory back and fault it in again. Each case runs in a
fresh interpreter: the setting is process-wide."""

import subprocess
import sys

import pytest

PROBE = """
import resource, sys
import numpy as np
from polarstripe.heap import keep_freed
if sys.argv[1] == "keep":
    assert keep_freed(256 << 20)
def faults():
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt
def burst():  # 8 frames of 2.6 MB alive at once, written to, then freed together
    bufs = [np.empty(2_621_440, np.uint8) for _ in range(8)]
    for b in bufs:
        b.fill(1)
burst()
f0 = faults()
for _ in range(5):
    burst()
print((faults() - f0) / (5 * 8 * 2_621_440 / 4096))  # faults per page written
"""


def _faults_per_page(mode: str) -> float:
    out = subprocess.run([sys.executable, "-c", PROBE, mode], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    return float(out.stdout)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_freed_buffers_are_reused_only_when_kept():
    assert _faults_per_page("keep") < 0.01  # every page of the later bursts was already mapped
    assert _faults_per_page("default") > 0.5  # glibc trimmed or unmapped them: faulted in again
