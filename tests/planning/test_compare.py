import json
import subprocess
import sys


def test_compare_command_small_and_fast(tmp_path):
    png = tmp_path / "cmp.png"
    out = subprocess.run([sys.executable, "-m", "polarstripe", "compare", "--resolution", "32x24",
                          "--stripes", "6", "--json", "--figure", str(png)],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    doc = json.loads(out.stdout)
    assert [lev["sigma_t"] for lev in doc["levels"]] == [5.0, 12.0]
    for lev in doc["levels"]:
        rows = lev["rows"]
        assert set(rows) >= {"flood", "polarized flood", "light striping", "polarized striping (eq. 6)",
                             "high-frequency 10px (direct)", "high-frequency 20px (direct)"}
        # band 0 of the chart alternates albedo 0.6 and 0.06: Michelson (1 - 0.1)/(1 + 0.1) = 0.818 in S
        assert abs(rows["ground truth S"]["contrast"] - 0.818) < 0.05
        # flood light adds the whole backscatter to S; eq. 6 removes most of it
        assert rows["polarized flood"]["error"] < rows["flood"]["error"]
        assert rows["flood"]["contrast"] < rows["ground truth S"]["contrast"]
    assert png.stat().st_size > 10_000


def test_compare_bad_resolution_is_one_line():
    out = subprocess.run([sys.executable, "-m", "polarstripe", "compare", "--resolution", "big"],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and "--resolution" in out.stderr and "Traceback" not in out.stderr
