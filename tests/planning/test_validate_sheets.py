"""K sheets per frame through the planner's end-to-end judge (planning/validate.py ``sheets``): in clear water
a K-sheet scan lights every pixel of the chart once, so its composite is T up to the sensor's noise, as the
one-sheet scan's, in a K-th of the frames, and its depth is the wall's."""

import numpy as np
import pytest
from polarstripe.planning.validate import ScanSettings, curves
from polarstripe.sim.scene import load_scene


def test_a_two_sheet_scan_in_clear_water_is_the_one_sheet_scan_in_half_the_frames():
    tank = load_scene(None)
    clear = tank.replace(medium=tank.medium.replace(sigma_t=0.0))
    rows = {k: curves(clear, [0.1], ScanSettings(fidelity="preview", n_stripes=8, width=64, exposure="method",
                                                 sheets=k), methods=("stripes",))["stripes"][0]
            for k in (1, 2)}
    assert (rows[1]["frames"], rows[2]["frames"]) == (8, 4)
    assert rows[1]["error"] < 0.05
    assert rows[2]["error"] == pytest.approx(rows[1]["error"], rel=0.3)     # both the sensor's noise alone
    assert rows[2]["depth_valid_fraction"] > 0.5
    assert rows[2]["depth_valid_fraction"] == pytest.approx(rows[1]["depth_valid_fraction"], abs=0.05)
    assert rows[2]["depth_rms_mm"] == pytest.approx(rows[1]["depth_rms_mm"], rel=0.05)   # 64 px: ~6 mm both
    assert np.isfinite(rows[2]["depth_rms_mm"]) and rows[2]["depth_rms_mm"] < 10.0
