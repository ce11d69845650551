"""Telling the sheets of a K-sheet frame apart (imaging/sheets.py): against projector columns computed here in
closed form from the default tank's rig (a pinhole projection of the wall's points), and behind the glass
wall against the columns the model's ports give."""

import numpy as np
import pytest
from polarstripe.bench.depth import depth_scene
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
from polarstripe.sim.depth_truth import column_truth, depth_truth, rig_geometry
from polarstripe.sim.scene import glass_tank, load_scene

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


def test_behind_ports_every_pixel_gets_the_position_that_lit_it():
    """The paper's glass wall (docs/physics.md §11): the column that lit each object pixel, computed in the
    world through the model's ports (sim/depth_truth.py ``column_truth``), lies in the pixel's span through
    the ports, and 2 sheets a frame (the most this depth range allows) are told apart on every object pixel;
    through the pinholes the span misses it on nearly half of them and the position is wrong or none."""
    scene = glass_tank(depth_scene(2.0, 64))
    rig = rig_geometry(scene)
    geom = RigGeometry.from_dict(rig)
    n, k, width = 30, 2, 1024
    col = column_truth(scene)
    z = depth_truth(scene)
    obj = np.isfinite(col) & (col >= 0) & (col < width)
    assert obj.mean() > 0.5
    near_far = (float(np.nanmin(z)) - 0.01, float(np.nanmax(z)) + 0.01)
    rays = camera_rays(geom, *np.mgrid[0:col.shape[0], 0:col.shape[1]])
    lo, hi = epipolar_span(geom, rays, near_far)
    assert np.all((lo[obj] <= col[obj]) & (col[obj] <= hi[obj]))
    check_sheets(n, k, width, lo, hi, near_far)
    pos = np.floor(col * n / width).astype(int)
    pos = np.where(np.floor((pos + 1) * width / n) <= col, pos + 1, pos)
    got = assign_positions(pos % 15, n, k, width, lo, hi)          # F = 15 frames
    np.testing.assert_array_equal(got[obj], pos[obj])
    pinhole = RigGeometry.from_dict({key: v for key, v in rig.items() if not key.startswith("port")})
    plo, phi = epipolar_span(pinhole, rays, near_far)
    assert np.mean((plo[obj] <= col[obj]) & (col[obj] <= phi[obj])) < 0.6
    assert np.mean(assign_positions(pos % 15, n, k, width, plo, phi)[obj] != pos[obj]) > 0.3
