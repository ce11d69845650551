"""The compositor's files from a small masked composite: PNG rounded and clipped to 16 bits, TIFF/NPY with NaN
where masked, metrics.json rewritten whole, the comparison figure."""

import json

import cv2
import numpy as np
from polarstripe.nodes.compositor_output import fmt, write_comparison, write_method


def _image():
    data = np.array([[-3.0, 0.4, 0.6], [1000.5, 70000.0, 12.0]])
    return np.ma.MaskedArray(data, [[False, False, False], [False, False, True]])


def test_png_is_rounded_and_clipped_and_tiff_keeps_floats_with_nan_where_masked(tmp_path):
    metrics = {"flood": {"contrast": 0.25, "error_vs_truth": None}}
    write_method(str(tmp_path), "flood", _image(), metrics)
    png = cv2.imread(str(tmp_path / "flood.png"), cv2.IMREAD_UNCHANGED)
    assert png.dtype == np.uint16
    # -3 -> 0, 0.4 -> 0, 0.6 -> 1, 1000.5 -> 1000 (round half to even), 70000 -> 65535, masked -> 0
    assert png.tolist() == [[0, 0, 1], [1000, 65535, 0]]
    tif = cv2.imread(str(tmp_path / "flood.tiff"), cv2.IMREAD_UNCHANGED)
    assert tif.dtype == np.float32 and np.isnan(tif[1, 2])
    np.testing.assert_array_equal(tif.ravel()[:5], np.float32([-3.0, 0.4, 0.6, 1000.5, 70000.0]))
    assert json.loads((tmp_path / "metrics.json").read_text()) == metrics
    assert not (tmp_path / "metrics.json.tmp").exists()  # written aside, then moved over


def test_npy_format_and_metrics_rewritten_whole(tmp_path):
    (tmp_path / "metrics.json").write_text('{"old": 1}')
    write_method(str(tmp_path), "stripes", _image(), {"stripes": {"frames": 30}}, image_format="npy")
    raw = np.load(tmp_path / "stripes.npy")
    assert raw.dtype == np.float32 and np.isnan(raw[1, 2]) and raw[1, 0] == np.float32(1000.5)
    assert not (tmp_path / "stripes.tiff").exists()
    assert json.loads((tmp_path / "metrics.json").read_text()) == {"stripes": {"frames": 30}}


def test_comparison_shows_the_methods_in_order(tmp_path):
    results = {"stripes": _image(), "flood": _image() * 2}
    metrics = {m: {"contrast": 0.5, "error_vs_truth": 0.1} for m in results}
    path = tmp_path / "comparison.png"
    write_comparison(str(path), results, metrics, ["flood", "polarized_flood", "stripes"])
    img = cv2.imread(str(path))
    assert img is not None and img.shape[1] == 2 * 320  # two methods, 3.2 in at 100 dpi each


def test_fmt():
    assert (fmt(None), fmt(0.12345), fmt(1)) == ("n/a", "0.123", "1.000")
