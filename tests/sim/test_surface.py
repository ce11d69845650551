"""Surface reflectance at hit points: the chart's bands and bars, a PNG texture's orientation, albedo."""

import cv2
import numpy as np
import pytest
from polarstripe.sim.geometry import Hits
from polarstripe.sim.scene import PlaneObject, SphereObject
from polarstripe.sim.surface import surface_info

# a chart at z = 0.38 facing the camera at the origin: image right is world −x, image up is world +y
CHART = PlaneObject(point=(0.0, 0.0, 0.38), normal=(0.0, 0.0, -1.0), size=(0.3, 0.2), albedo=0.6,
                    texture="chart")


def _hits(index, xy, z=0.38):
    xy = np.asarray(xy, float)
    pts = np.column_stack([xy, np.full(len(xy), z)])
    normals = np.tile([0.0, 0.0, -1.0], (len(xy), 1))
    return Hits(np.full(len(xy), 1.0), np.asarray(index, np.int64), normals, pts)


def _chart_point(band, bar):
    """World (x, y) of the middle of a band (0 top … 3 bottom) and bar (0 left … 15 right, seen from the
    front): fraction across = (bar + ½)/16 from the left (+x) edge, down = (band + ½)/4 from the top."""
    return 0.15 - 0.3 * (bar + 0.5) / 16, 0.1 - 0.2 * (band + 0.5) / 4


def test_chart_bands_have_the_documented_michelson_contrasts():
    pts = [_chart_point(b, k) for b in range(4) for k in (6, 7)]          # an even (high) and odd (low) bar
    info = surface_info((CHART,), _hits(np.zeros(len(pts)), pts))
    assert info.chart_band.tolist() == [0, 0, 1, 1, 2, 2, 3, 3]
    assert info.chart_high.tolist() == [True, False] * 4
    hi, lo = info.albedo[0::2], info.albedo[1::2]
    np.testing.assert_allclose(hi, 0.6, rtol=1e-15)
    np.testing.assert_allclose((hi - lo) / (hi + lo), [0.82, 0.54, 0.33, 0.18], atol=0.005)
    np.testing.assert_allclose(lo, [0.06, 0.18, 0.30, 0.42], rtol=1e-12)


def test_left_edge_of_the_chart_is_a_high_bar_on_the_plus_x_side():
    info = surface_info((CHART,), _hits([0, 0], [(0.149, 0.099), (-0.149, 0.099)]))
    assert info.chart_high.tolist() == [True, False]          # bar 0 (left, +x) high, bar 15 (right) low


def test_png_texture_top_row_at_the_up_edge_left_column_at_the_left_seen_from_the_front(tmp_path):
    img = np.array([[255, 0, 0, 51], [0, 0, 102, 0]], np.uint8)       # 4 wide, 2 high
    path = tmp_path / "tex.png"
    cv2.imwrite(str(path), img)
    plane = PlaneObject(point=(0.0, 0.0, 0.38), normal=(0.0, 0.0, -1.0), size=(0.4, 0.2), albedo=0.5,
                        texture=str(path))
    # texel (row r, col c) covers x ∈ 0.2 − 0.1·(c, c + 1), y ∈ 0.1 − 0.1·(r, r + 1)
    pts = [(0.15, 0.05), (-0.15, 0.05), (-0.05, -0.05)]               # texels (0, 0), (0, 3), (1, 2)
    info = surface_info((plane,), _hits([0, 0, 0], pts))
    np.testing.assert_allclose(info.albedo, [0.5, 0.5 * 0.2, 0.5 * 0.4], rtol=1e-12)
    assert info.chart_band.tolist() == [-1, -1, -1]


def test_plain_albedo_and_misses():
    sphere = SphereObject(center=(0.0, 0.0, 0.3), radius=0.05, albedo=0.35)
    info = surface_info((CHART, sphere), _hits([1, -1, 0], [(0.0, 0.0), (0.0, 0.0), _chart_point(0, 0)]))
    assert info.object_id.tolist() == [1, -1, 0]
    assert info.albedo.tolist() == [0.35, 0.0, pytest.approx(0.6)]
    assert info.chart_band.tolist() == [-1, -1, 0]
