"""Decoding the calibration's codes (imaging/structured_light.py) on synthetic frames: a plane seen through a
known homography, lit by each pattern (msgs/patterns.py ``gray_lit``) under scattered light that no per-image
threshold survives; the decoded projector pixel is the homography's."""

from __future__ import annotations

import numpy as np
import pytest
from polarstripe.imaging.structured_light import calibration_code, decode, xor_base
from polarstripe.msgs.patterns import gray_code, gray_lit, xor_code

W, H = 256, 192               # projector
CAM = (120, 160)              # camera (h, w)


def _truth():
    """Projector coordinates (col, row) of every camera pixel: a homography of a tilted plane."""
    Hm = np.array([[1.35, 0.12, 20.0], [-0.05, 1.1, 15.0], [2e-4, -1e-4, 1.0]])
    v, u = np.mgrid[0:CAM[0], 0:CAM[1]].astype(float)
    q = Hm @ np.stack([u.ravel(), v.ravel(), np.ones(u.size)])
    return (q[0] / q[2]).reshape(CAM), (q[1] / q[2]).reshape(CAM)


def _frames(code, col, row, *, direct=100.0, veil=None, noise=0.0, seed=0):
    """Each pattern: ``direct`` where lit plus a scattered ``veil`` (same under a pattern and its inverse)."""
    rng = np.random.default_rng(seed)
    veil = np.zeros(CAM) if veil is None else veil
    out = [direct * gray_lit(p, col, row) + veil + noise * rng.standard_normal(CAM) for p in code]
    return out, direct + veil, np.zeros(CAM)


@pytest.mark.parametrize("make", [gray_code, calibration_code], ids=["gray", "xor"])
def test_every_pixel_decodes_to_its_projector_pixel_under_a_veil_ten_times_the_code(make):
    col, row = _truth()
    veil = np.broadcast_to(1000.0 * (1.0 + 0.5 * np.sin(np.arange(CAM[1]) / 17.0)), CAM)  # 10× the code
    code = make(W, H)
    frames, white, black = _frames(code, col, row, veil=veil)
    d = decode(frames, code, (W, H), white, black, lit_threshold=10.0)
    inside = (col >= 0) & (col < W) & (row >= 0) & (row < H)
    assert inside.mean() > 0.9 and np.array_equal(d.valid, inside)
    np.testing.assert_array_equal(d.col[inside], np.floor(col[inside]))
    np.testing.assert_array_equal(d.row[inside], np.floor(row[inside]))
    assert np.all(d.col[~inside] == -1)
    np.testing.assert_allclose(np.nanmedian(d.contrast), 100.0 / (100.0 + 2 * np.median(veil)), rtol=0.05)


def test_the_xor_base_is_taken_out_again():
    col, row = _truth()
    code = xor_code(W, H, 2)
    frames, white, black = _frames(code, col, row)
    d = decode(frames, code, (W, H), white, black, lit_threshold=10.0)
    np.testing.assert_array_equal(d.col[d.valid], np.floor(col[d.valid]))
    np.testing.assert_array_equal(d.row[d.valid], np.floor(row[d.valid]))


def test_unlit_pixels_are_not_decoded():
    col, row = _truth()
    code = calibration_code(W, H)
    frames, white, black = _frames(code, col, row)
    white = white.copy()
    white[:, :40] = 5.0                                        # a shadow: white − black below the threshold
    d = decode(frames, code, (W, H), white, black, lit_threshold=10.0)
    assert not d.valid[:, :40].any() and np.all(d.col[:, :40] == -1) and np.isnan(d.contrast[:, :40]).all()


def test_the_base_makes_runs_of_a_sixteenth_of_the_width():
    assert [xor_base(w) for w in (64, 256, 1024, 1920)] == [1, 3, 5, 6]
    assert calibration_code(8, 8) == gray_code(8, 8)           # too narrow for a base
