"""The compositor's files from a small masked composite: an 8-bit display PNG, TIFF/NPY with NaN where masked,
metrics.json rewritten whole, the comparison figure with the truth and the best method marked."""

import json

import cv2
import numpy as np
from polarstripe.nodes.compositor_output import (
    LEGEND,
    best_method,
    fmt,
    to_display,
    write_comparison,
    write_method,
)


def _image():
    data = np.array([[-3.0, 0.4, 0.6], [1000.5, 70000.0, 12.0]])
    return np.ma.MaskedArray(data, [[False, False, False], [False, False, True]])


def test_png_is_8_bit_for_a_person_and_tiff_keeps_floats_with_nan_where_masked(tmp_path):
    metrics = {"flood": {"contrast": 0.25, "error_vs_truth": None}}
    write_method(str(tmp_path), "flood", _image(), metrics)
    png = cv2.imread(str(tmp_path / "flood.png"), cv2.IMREAD_UNCHANGED)
    # stretched from the 1st to the 99.5th percentile: the darkest pixel black, the brightest white, order
    # kept; a masked (saturated) pixel white
    assert png.dtype == np.uint8 and png.shape == (2, 3)
    assert png[0, 0] == 0 and png[1, 1] == 255 and png[1, 2] == 255
    assert png[0, 0] <= png[0, 1] <= png[0, 2] <= png[1, 0] <= png[1, 1]
    tif = cv2.imread(str(tmp_path / "flood.tiff"), cv2.IMREAD_UNCHANGED)
    assert tif.dtype == np.float32 and np.isnan(tif[1, 2])
    np.testing.assert_array_equal(tif.ravel()[:5], np.float32([-3.0, 0.4, 0.6, 1000.5, 70000.0]))
    assert json.loads((tmp_path / "metrics.json").read_text()) == metrics
    assert not (tmp_path / "metrics.json.tmp").exists()  # written aside, then moved over


def test_a_dim_composite_fills_the_8_bits():
    """Raw DN of ~3500 of 65535 were black in a viewer; the display PNG spans the whole range."""
    ramp = np.ma.MaskedArray(np.linspace(60.0, 3500.0, 200).reshape(10, 20))
    png = to_display(ramp)
    assert png.min() == 0 and png.max() == 255 and np.all(np.diff(png.ravel().astype(int)) >= 0)


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


def test_comparison_puts_the_ground_truth_first_and_marks_the_best(tmp_path):
    results = {"flood": _image(), "stripes": _image() * 2}
    metrics = {"flood": {"contrast": 0.2, "error_vs_truth": 0.4},
               "stripes": {"contrast": 0.3, "error_vs_truth": 0.2}}
    path = tmp_path / "comparison.png"
    write_comparison(str(path), results, metrics, ["flood", "stripes"], truth=np.arange(6.0).reshape(2, 3))
    img = cv2.imread(str(path))
    assert img.shape[1] == 3 * 320  # the truth and two methods
    green = (img[..., 1].astype(int) - img[..., 0] > 60) & (img[..., 1].astype(int) - img[..., 2] > 60)
    cols = np.flatnonzero(green.any(axis=0))
    assert cols.size and cols.min() >= 2 * 320 - 10  # the frame around the best: the third panel


def test_the_truth_panel_and_legend_name_the_unscattered_radiance_t(tmp_path, monkeypatch):
    """The truth is T, the unscattered object radiance (sim/truth.py), not the object light S = D + A."""
    import polarstripe.nodes.compositor_output as out

    figures = []
    monkeypatch.setattr(out.plt, "close", figures.append)
    write_comparison(str(tmp_path / "c.png"), {"flood": _image()}, {"flood": {"contrast": 0.2}}, ["flood"],
                     truth=np.ones((2, 3)))
    titles = [ax.get_title() for ax in figures[0].axes]
    legend = " ".join(t.get_text() for t in figures[0].texts)
    assert titles[0].splitlines()[0] == "ground truth T (unscattered)" and titles[1].startswith("flood")
    assert "ground truth T, the unscattered object radiance" in legend and "truth S" not in legend
    out.plt.close(figures[0])


def test_the_best_method_is_the_lowest_error_else_the_highest_real_contrast():
    assert best_method({"a": {"error_vs_truth": 0.5}, "b": {"error_vs_truth": 0.2}}, ["a", "b"]) == "b"
    no_truth = {"a": {"contrast": 0.4, "error_vs_truth": None},
                "b": {"contrast": 3.58, "error_vs_truth": None}}
    assert best_method(no_truth, ["a", "b"]) == "a"  # 3.58 is not a contrast
    assert best_method({"a": {}}, ["a"]) is None
    assert "contrast" in LEGEND and "error" in LEGEND and "\n" not in LEGEND  # one line


def test_fmt():
    assert (fmt(None), fmt(0.12345), fmt(1)) == ("n/a", "0.123", "1.000")


def _depth_figure(tmp_path, monkeypatch, results, metrics, depth):
    """Draw the comparison and keep its figure open: (the figure, the PNG as read back)."""
    import polarstripe.nodes.compositor_output as out

    figures = []
    monkeypatch.setattr(out.plt, "close", figures.append)
    path = tmp_path / "comparison.png"
    write_comparison(str(path), results, metrics, ["flood", "stripes", "polarized_stripes", "hf_separation"],
                     truth=np.ones((24, 32)), depth=depth)
    assert not (tmp_path / "comparison.png.tmp").exists()  # drawn aside, then renamed
    return figures[0], cv2.imread(str(path))


def _depth_map(method, scan_id, z, **metrics):
    from polarstripe.msgs import DepthMap

    return DepthMap(depth_m=np.float32(z), points_m=None, method=method, scan_id=scan_id, metrics=metrics)


def test_the_stripe_methods_depth_maps_sit_in_a_second_row_titled_with_valid_fraction_and_rms(
        tmp_path, monkeypatch):
    import polarstripe.nodes.compositor_output as out

    h, w = 24, 32
    z = np.full((h, w), np.nan)
    z[:, w // 2:] = np.linspace(0.30, 0.40, w // 2)  # the left half invalid: 50 % of the pixels valid
    z_pol = np.full((h, w), 0.35)
    z_pol[: 3 * h // 4] = np.nan  # 25 % valid
    results = {m: np.ma.MaskedArray(np.ones((h, w))) for m in ("flood", "stripes", "polarized_stripes")}
    metrics = {"flood": {"scan_id": 1, "contrast": 0.2}, "stripes": {"scan_id": 2, "contrast": 0.3},
               "polarized_stripes": {"scan_id": 3, "contrast": 0.3}}
    depth = {"stripes": _depth_map("stripes", 2, z, depth_rms_mm=4.62, valid_fraction_of_objects=0.8),
             "polarized_stripes": _depth_map("polarized_stripes", 3, z_pol)}  # no depth truth
    fig, img = _depth_figure(tmp_path, monkeypatch, results, metrics, depth)
    assert img.shape[:2] == (2 * 330, 4 * 320)  # two rows of 3.3 in: the truth and three methods
    titles = {ax.get_title(): ax for ax in fig.axes if ax.get_title()}
    stripes = titles["stripes: depth (grey: none)\nvalid 50 % of pixels (80 % of objects)\n"
                     "RMS 4.6 mm vs depth truth"]
    assert "polarized_stripes: depth (grey: none)\nvalid 25 % of pixels\nno depth truth: no RMS" in titles
    flood = next(ax for t, ax in titles.items() if t.startswith("flood"))
    # the depth panel is under its composite (the second row, the same column)
    assert stripes.get_position().y1 < flood.get_position().y0
    assert sum(1 for ax in fig.axes if ax.get_label() == "<colorbar>") == 2  # a colour bar each
    # invalid pixels are masked, and drawn in a grey that is no colour of the depth map
    drawn = stripes.images[0].get_array()
    np.testing.assert_array_equal(np.ma.getmaskarray(drawn), np.isnan(z))
    lut = out.plt.get_cmap(out.DEPTH_CMAP)(np.linspace(0, 1, 256))[:, :3]
    assert np.min(np.abs(lut - out.INVALID_GREY).max(axis=1)) > 0.1
    # ... and so in the PNG: the centre of the left (invalid) half grey, the right half coloured
    box = stripes.get_window_extent()
    scale = 100 / fig.dpi  # savefig at 100 dpi
    row = int(img.shape[0] - scale * (box.y0 + box.y1) / 2)
    left, right = (int(scale * (box.x0 + f * box.width)) for f in (0.25, 0.75))
    grey = np.uint8(np.round(255 * np.array(out.INVALID_GREY)))[::-1]
    assert np.abs(img[row, left].astype(int) - grey).max() <= 2
    assert np.ptp(img[row, right].astype(int)) > 40  # a viridis colour, not a grey
    out.plt.close(fig)


def test_no_stripe_method_no_depth_row_and_a_stale_map_is_not_shown(tmp_path, monkeypatch):
    import polarstripe.nodes.compositor_output as out

    z = np.full((24, 32), 0.3)
    results = {m: np.ma.MaskedArray(np.ones((24, 32))) for m in ("flood", "hf_separation")}
    metrics = {"flood": {"scan_id": 1, "contrast": 0.2}, "hf_separation": {"scan_id": 2, "contrast": 0.3}}
    stale = {"stripes": _depth_map("stripes", 0, z)}
    fig, img = _depth_figure(tmp_path, monkeypatch, results, metrics, stale)
    assert img.shape[:2] == (330, 3 * 320) and len(fig.axes) == 3  # one row, no colour bar
    assert not any("depth" in ax.get_title() for ax in fig.axes)
    out.plt.close(fig)
    # a stripe scan that published no depth (its map is of an earlier scan): said so, nothing drawn
    results["stripes"] = np.ma.MaskedArray(np.ones((24, 32)))
    metrics["stripes"] = {"scan_id": 5, "contrast": 0.3}
    fig, _ = _depth_figure(tmp_path, monkeypatch, results, metrics, stale)
    panel = next(ax for ax in fig.axes if ax.get_title().startswith("stripes: depth"))
    assert panel.get_title() == "stripes: depth\nnone for this scan (see the log)" and not panel.images
    out.plt.close(fig)


def test_published_depth_forwards_and_keeps_the_last_map_of_each_method():
    from polarstripe.nodes.compositor_output import PublishedDepth

    sent = []
    pub = PublishedDepth(type("P", (), {"publish": staticmethod(sent.append)})())
    a, b = _depth_map("stripes", 1, np.ones((2, 2))), _depth_map("stripes", 2, np.ones((2, 2)))
    pub.publish(a)
    pub.publish(b)
    assert sent == [a, b] and pub.maps == {"stripes": b}
