"""``polarstripe bench motion`` on a tiny rig: the scan's timing, a one-frame scan that motion cannot touch, a
two-pass scan that it does, and the tolerated speed's interpolation."""

import json

import pytest
from polarstripe.bench.motion import tolerated_speed
from polarstripe.tools.cli import main


def test_tolerated_speed_is_linear_between_the_speeds_measured():
    # at rest 0.2: +10 % is 0.22, reached between 0.1 (0.21) and 0.2 (0.25 m/s): 0.1 + 0.1·(0.01/0.04)
    assert tolerated_speed([0.0, 0.1, 0.2], [0.2, 0.21, 0.25]) == pytest.approx(0.125)
    assert tolerated_speed([0.0, 0.1], [0.2, 0.21]) is None


def test_bench_motion_table(capsys):
    assert main(["bench", "motion", "--resolution", "32x24", "--stripes", "2", "--speeds", "0", "0.05",
                 "--directions", "along", "--only", "1", "2", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    rotating, camera = doc["rows"]
    # 2 passes of 2 frames at 30 fps, the stage's 90 deg at 200 deg/s plus 0.02 s settle between them
    assert rotating["frames"] == 4
    assert rotating["scan_s"] == pytest.approx(3 / 30 + 90 / 200 + 0.02, rel=1e-12)
    errors = rotating["directions"]["along"]["error"]
    assert errors[1] > 1.1 * errors[0]  # E_b and E_w, their passes 0.5 s apart (2.5 cm), no longer register
    # one frame, taken mid-scan at the scene's pose: the same composite at any speed
    assert camera["frames"] == 1 and camera["scan_s"] == 0.0
    flood = camera["directions"]["along"]
    assert flood["error"][0] == flood["error"][1] and flood["tolerated_m_s"] is None


def test_a_three_sheet_stripe_scan_is_a_third_of_the_frames_and_time(capsys):
    assert main(["bench", "motion", "--resolution", "32x24", "--stripes", "6", "--speeds", "0",
                 "--directions", "along", "--only", "4", "5", "--json"]) == 0
    one, three = json.loads(capsys.readouterr().out)["rows"]
    assert (one["sheets"], one["frames"], three["sheets"], three["frames"]) == (1, 6, 3, 2)
    assert one["scan_s"] == pytest.approx(5 / 30, rel=1e-12)       # the last frame at (frames − 1)/fps
    assert three["scan_s"] == pytest.approx(1 / 30, rel=1e-12)
