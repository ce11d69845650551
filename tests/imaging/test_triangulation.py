"""Light-sheet planes, delineation and triangulation against closed-form geometry (no renderer).

The rig is written down by hand (not read from the scene code): camera K with f = 500 px, the projector 0.2 m
to the camera's right, turned 25° toward it about the camera's y axis. Planes and depths are checked against
ray–plane geometry done independently here.
"""

from __future__ import annotations

import numpy as np
import pytest
from polarstripe.imaging.delineation import NoiseModel, RunningArgmax, delineate
from polarstripe.imaging.triangulation import (
    RigGeometry,
    Triangulator,
    column_planes,
    depth_from_columns,
    sheet_planes,
    stripe_edges,
)
from polarstripe.imaging.validation import ImagingError

W, H, PW, PH = 160, 120, 1024, 768
ANG = np.radians(25.0)
C_PROJ = np.array([0.2, 0.0, 0.0])  # projector centre in the camera frame
# projector axes (rows) in camera coordinates: turned -25° about y, so it looks back toward the camera axis
R_PC = np.array([[np.cos(ANG), 0.0, np.sin(ANG)], [0.0, 1.0, 0.0], [-np.sin(ANG), 0.0, np.cos(ANG)]])


def _geom() -> RigGeometry:
    K = [[500.0, 0, W / 2 - 0.5], [0, 500.0, H / 2 - 0.5], [0, 0, 1]]
    Kp = [[900.0, 0, PW / 2 - 0.5], [0, 900.0, PH / 2 - 0.5], [0, 0, 1]]
    return RigGeometry.from_dict({"K_cam": K, "K_proj": Kp, "R": R_PC, "T": -R_PC @ C_PROJ,
                                  "cam_size": [W, H], "proj_size": [PW, PH]})


def _proj_col(points):
    """Continuous pattern column of camera-frame points (c ∈ [j, j+1) is column j)."""
    p = (points - C_PROJ) @ R_PC.T
    return 900.0 * p[..., 0] / p[..., 2] + PW / 2


def test_sheet_planes_contain_the_projector_centre_and_their_column_rays():
    g = _geom()
    n, d = sheet_planes(g, 8, edges=True)
    assert n.shape == (9, 3) and d.shape == (9,)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0)
    np.testing.assert_allclose(n @ C_PROJ + d, 0.0, atol=1e-12)  # every sheet passes through the projector
    edges = np.arange(9) * PW // 8
    for k, c in enumerate(edges):
        for row in (0.0, 300.0, 767.0):  # rays through the edge column at several pattern rows
            v_p = np.array([(c - PW / 2) / 900.0, (row + 0.5 - PH / 2) / 900.0, 1.0])
            X = C_PROJ + 0.4 * (R_PC.T @ v_p)
            assert abs(n[k] @ X + d[k]) < 1e-12
    centre_n, centre_d = sheet_planes(g, 8)
    X = C_PROJ + R_PC.T @ np.array([((edges[2] + edges[3]) / 2 - PW / 2) / 900.0, 0.0, 1.0])
    assert abs(centre_n[2] @ X + centre_d[2]) < 1e-12


def test_depth_of_known_columns_is_the_ray_plane_intersection():
    g = _geom()
    rr, cc = np.mgrid[0:H, 0:W]
    v = np.stack([(cc - (W / 2 - 0.5)) / 500.0, (rr - (H / 2 - 0.5)) / 500.0, np.ones((H, W))], -1)
    # a tilted plane n·X = 0.3: X = z v, z = 0.3/(n·v)
    n = np.array([0.3, -0.1, 1.0])
    z_true = 0.3 / (v @ n)
    cols = _proj_col(v * z_true[..., None])
    np.testing.assert_allclose(depth_from_columns(g, cols), z_true, rtol=1e-9)
    np.testing.assert_allclose(Triangulator(g, (H, W)).depth(cols), z_true, rtol=1e-6)
    planes_n, planes_d = column_planes(g, cols[60:61, 80])  # one pixel the explicit way
    X = z_true[60, 80] * v[60, 80]
    assert abs(planes_n[0] @ X + planes_d[0]) < 1e-9
    half = g.for_camera(W // 2, H // 2)  # binned 2×2: binned pixel (i, j) is centred at (2i + ½, 2j + ½)
    hr, hc = np.mgrid[0:H // 2, 0:W // 2]
    vh = np.stack([(2 * hc + 0.5 - (W / 2 - 0.5)) / 500.0, (2 * hr + 0.5 - (H / 2 - 0.5)) / 500.0,
                   np.ones(hr.shape)], -1)
    zh = 0.3 / (vh @ n)
    np.testing.assert_allclose(depth_from_columns(half, _proj_col(vh * zh[..., None])), zh, rtol=1e-9)


def _scan(z_true, v, stripes, *, signal=2000.0, back=100.0, noise=3.0, seed=0):
    """Stripe frames of a surface at depth z_true, area-sampled (4×4 sub-pixels) so edges fall between
    pixels."""
    rng = np.random.default_rng(seed)
    edges = stripe_edges(stripes, PW)
    sub = np.linspace(-0.375, 0.375, 4)
    cols = []
    for dy in sub:
        for dx in sub:
            vv = v + np.array([dx / 500.0, dy / 500.0, 0.0])
            n = np.array([0.3, -0.1, 1.0])
            cols.append(_proj_col(vv * (0.3 / (vv @ n))[..., None]))
    cols = np.stack(cols)
    ra = RunningArgmax((H, W), np.uint16)
    for k in range(stripes):
        lit = ((cols >= edges[k]) & (cols < edges[k + 1])).mean(axis=0)
        img = 64 + back + signal * lit + rng.normal(0, noise, (H, W))
        ra.add(np.clip(np.round(img), 0, 4095).astype(np.uint16), k)
    return ra.result()


def test_delineated_scan_triangulates_a_plane_to_sub_millimetre():
    g = _geom()
    rr, cc = np.mgrid[0:H, 0:W]
    v = np.stack([(cc - (W / 2 - 0.5)) / 500.0, (rr - (H / 2 - 0.5)) / 500.0, np.ones((H, W))], -1)
    z_true = 0.3 / (v @ np.array([0.3, -0.1, 1.0]))
    votes = _scan(z_true, v, 40)
    cols = delineate(votes, stripe_edges(40, PW), NoiseModel(dark_dn=64.0, read_noise_dn=3.0))
    z = depth_from_columns(g, cols)
    ok = np.isfinite(z)
    assert ok.mean() > 0.7  # all but the first/last stripe and the frame border
    err = z[ok] - z_true[ok]
    assert np.sqrt(np.mean(err ** 2)) < 0.5e-3  # metres


def test_undelineable_pixels_are_nan_not_guessed():
    g = _geom()
    rr, cc = np.mgrid[0:H, 0:W]
    v = np.stack([(cc - (W / 2 - 0.5)) / 500.0, (rr - (H / 2 - 0.5)) / 500.0, np.ones((H, W))], -1)
    z_true = 0.3 / (v @ np.array([0.3, -0.1, 1.0]))
    votes = _scan(z_true, v, 40)
    best = votes.best.copy()
    best[:, :40] = 4095  # saturated
    best[:20, 40:] = 64  # dark (at the dark offset)
    sat = type(votes)(best, votes.second, votes.index, votes.n_frames)
    z = depth_from_columns(g, delineate(sat, stripe_edges(40, PW),
                                        NoiseModel(dark_dn=64.0, read_noise_dn=3.0, saturation_dn=4095)))
    assert np.isnan(z[:, :40]).all() and np.isnan(z[:20]).all()
    assert np.isfinite(z[40:, 60:140]).mean() > 0.8
    flat = type(votes)(np.full((H, W), 1000, np.uint16), np.full((H, W), 999, np.uint16), votes.index, 40)
    assert np.isnan(delineate(flat, stripe_edges(40, PW), NoiseModel(dark_dn=64.0))).all()  # no margin


def test_running_argmax_matches_a_stack():
    rng = np.random.default_rng(3)
    stack = rng.integers(0, 4096, (7, 9, 11)).astype(np.uint16)
    ra = RunningArgmax((9, 11), np.uint16)
    for k, f in enumerate(stack):
        ra.add(f, k, 45.0)
    r = ra.result(45.0)
    srt = np.sort(stack, axis=0)
    np.testing.assert_array_equal(r.best, srt[-1])
    np.testing.assert_array_equal(r.second, srt[-2])
    np.testing.assert_array_equal(stack[r.index, *np.indices((9, 11))], srt[-1])
    with pytest.raises(ImagingError):
        ra.result(0.0)


def test_bad_geometry_is_one_error():
    d = _geom().to_dict()
    with pytest.raises(ImagingError, match="R is not a rotation"):
        RigGeometry.from_dict({**d, "R": np.eye(3) * 2})
    with pytest.raises(ImagingError, match="K_proj is missing"):
        RigGeometry.from_dict({k: v for k, v in d.items() if k != "K_proj"})
