import json
import subprocess
import sys


def test_compare_command_small_and_fast(tmp_path):
    png = tmp_path / "cmp.png"
    out = subprocess.run([sys.executable, "-m", "polarstripe", "compare", "--resolution", "32x24",
                          "--stripes", "6", "--orders", "all", "--sigma-t", "2", "5", "10", "--json",
                          "--figure", str(png)],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    doc = json.loads(out.stdout)
    assert [lev["sigma_t"] for lev in doc["levels"]] == [2.0, 5.0, 10.0]
    for lev in doc["levels"]:
        rows = lev["rows"]
        assert set(rows) >= {"flood", "polarized flood", "light striping", "polarized striping (eq. 6)",
                             "high-frequency 10px (direct)", "high-frequency 20px (direct)"}
        truth, water = rows["ground truth (unscattered)"], rows["object light S = D + A"]
        # the truth is the unscattered chart: band 0 alternates albedo 0.6 and 0.06, Michelson
        # (1 - 0.1)/(1 + 0.1) = 0.818 (up to the source's fall-off across a bar pair)
        assert abs(truth["contrast"] - 0.818) < 0.05 and truth["error"] < 1e-12
        # what the water delivers to the camera is blurred: lower contrast, an error against the truth
        assert water["contrast"] < truth["contrast"] - 0.2 and water["error"] > 0.1
        assert water["error_vs_S"] < 1e-12
        assert rows["flood"]["contrast"] < water["contrast"]
    # flood light adds the whole backscatter; eq. 6 removes most of it where the medium is moderate
    for lev in doc["levels"][:2]:
        assert lev["rows"]["polarized flood"]["error"] < lev["rows"]["flood"]["error"]
    assert png.stat().st_size > 10_000


def test_compare_bad_resolution_is_one_line():
    out = subprocess.run([sys.executable, "-m", "polarstripe", "compare", "--resolution", "big"],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and "--resolution" in out.stderr and "Traceback" not in out.stderr
