"""Telling the sheets of a K-sheet frame apart (imaging/sheets.py): against projector columns computed here in
closed form from the default tank's rig (a pinhole projection of the wall's points)."""

import numpy as np
import pytest
from polarstripe.imaging.sheets import (
    SheetsOverlap,
    assign_positions,
    check_sheets,
    depth_range,
    epipolar_span,
    max_sheets,
    ray_columns,
)
from polarstripe.imaging.triangulation import RigGeometry, camera_rays
from polarstripe.sim.depth_truth import rig_geometry
from polarstripe.sim.scene import load_scene

G = rig_geometry(load_scene(None))
GEOM = RigGeometry.from_dict(G)


def _column(x, y, z):
    """Projector column of the camera-frame point (x, y, z): X_p = R·X + T, c = f·x_p/z_p + c_x + ½."""
    p = G["R"] @ np.array([x, y, z]) + G["T"]
    return G["K_proj"][0, 0] * p[0] / p[2] + G["K_proj"][0, 2] + 0.5


def test_a_pixel_ray_projects_where_its_points_do():
    rows, cols = np.array([0, 239, 479]), np.array([0, 320, 639])
    rays = camera_rays(GEOM, rows, cols)
    for z in (0.2, 0.38):
        want = [_column(r[0] * z, r[1] * z, z) for r in rays]
        np.testing.assert_allclose(ray_columns(GEOM, rays, z), want, rtol=1e-12)
    lo, hi = epipolar_span(GEOM, rays[1:2], (0.3, 0.45))
    assert lo[0] == pytest.approx(_column(rays[1][0] * 0.45, rays[1][1] * 0.45, 0.45))
    assert hi[0] == pytest.approx(_column(rays[1][0] * 0.3, rays[1][1] * 0.3, 0.3))


def test_every_pixel_of_a_wall_gets_the_position_that_lit_it():
    n, k, width = 30, 3, 1024
    rr, cc = np.mgrid[0:480:7, 0:640:7]
    rays = camera_rays(GEOM, rr, cc)
    z = 0.38
    col = np.vectorize(lambda r, c: _column(*(camera_rays(GEOM, r, c) * z)))(rr, cc)
    inside = (col >= 0) & (col < width)
    pos = np.floor(col * n / width).astype(int)               # position p: columns [⌊pW/N⌋, ⌊(p+1)W/N⌋)
    pos = np.where(np.floor((pos + 1) * width / n) <= col, pos + 1, pos)   # ⌊⌋ of the integer edges
    frame = pos % 10                                           # F = 10 frames: position p in frame p mod F
    lo, hi = epipolar_span(GEOM, rays, (0.3, 0.45))
    got = assign_positions(frame, n, k, width, lo, hi)
    assert inside.mean() > 0.5
    np.testing.assert_array_equal(got[inside], pos[inside])


def test_sheets_closer_than_a_ray_s_span_are_refused_with_the_number_that_fits():
    rays = camera_rays(GEOM, *np.mgrid[0:480:16, 0:640:16])
    lo, hi = epipolar_span(GEOM, rays, (0.3, 0.45))
    span = float(np.nanmax(hi - lo))
    # between 0.3 and 0.45 m a ray crosses some hundred columns (the centre ray: 604 at 0.3 m, above)
    assert 100 < span < 300
    check_sheets(30, 3, 1024, lo, hi, (0.3, 0.45))             # 10 frames: 9 stripes = 307 columns apart
    k = max_sheets(30, 1024, span)
    assert (np.ceil(30 / k) - 1) * 1024 / 30 > span >= (np.ceil(30 / (k + 1)) - 1) * 1024 / 30
    with pytest.raises(SheetsOverlap, match=rf"10 sheets of 30 stripes overlap .* use at most {k} sheets"):
        check_sheets(30, 10, 1024, lo, hi, (0.3, 0.45))
    lo2, hi2 = epipolar_span(GEOM, rays, (0.1, 0.45))
    with pytest.raises(SheetsOverlap, match="3 sheets"):
        check_sheets(30, 3, 1024, lo2, hi2, (0.1, 0.45))
    with pytest.raises(ValueError, match="near < far"):
        depth_range([0.5, 0.4])
