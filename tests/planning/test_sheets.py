"""Sheets per frame for a frame budget (planning/sheets.py): the budget's arithmetic by hand, and the most
sheets a separation allows against a brute-force look at the scene's own projector: points sampled along each
camera ray through the objects' depth range, projected with the model's pinhole (sim/geometry.py), and the
sheets of each frame whose columns they fall in counted."""

import warnings

import numpy as np
import pytest
from polarstripe.msgs.patterns import frames_of
from polarstripe.planning.sheets import feasible, object_depth_range, sheet_limits, sheets_for_budget
from polarstripe.sim.depth_truth import camera_frame, projector_frame
from polarstripe.sim.geometry import pixel_rays, projector_coords
from polarstripe.sim.scene import SceneError, load_scene, with_separation


def test_the_fewest_sheets_that_fit_the_budget():
    assert sheets_for_budget(30, 60, 2) == 1            # 30 frames per pass
    assert sheets_for_budget(30, 59, 2) == 2            # 29 per pass: 15 frames of 2 sheets
    assert sheets_for_budget(30, 20, 2) == 3            # 10 per pass
    assert sheets_for_budget(30, 12, 1) == 3            # 12 per pass: ⌈30/3⌉ = 10 (⌈30/2⌉ = 15 > 12)
    assert sheets_for_budget(30, 2, 2) == 30
    with pytest.raises(SceneError, match="at least 2 frame"):
        sheets_for_budget(30, 1, 2)


def _brute_force_overlap(scene, n, k, near_far):
    """True when some pixel (on a coarse grid) sees, within near_far, two sheets of one frame."""
    cam, proj = camera_frame(scene), projector_frame(scene)
    rows, cols = np.mgrid[0:cam.h:16, 0:cam.w:16]
    dirs = pixel_rays(cam, np.stack([rows.ravel(), cols.ravel()], 1))
    z = np.linspace(*near_far, 200)
    t = z[None, :] / (dirs @ cam.f)[:, None]                   # depth along the camera axis
    pts = np.asarray(cam.position) + t[..., None] * dirs[:, None, :]
    col, _, depth = projector_coords(proj, pts.reshape(-1, 3))
    col = np.where(depth > 0, col, np.nan).reshape(t.shape)
    pos = np.floor(col * n / proj.w)                           # the position whose columns hold it (±1 px)
    f = frames_of(n, k)
    for frame in range(f):
        mine = np.where(np.isfinite(pos) & (pos % f == frame) & (pos >= 0) & (pos < n), pos, np.nan)
        with warnings.catch_warnings():                        # rays that see none of this frame
            warnings.simplefilter("ignore", RuntimeWarning)
            lo, hi = np.nanmin(mine, axis=1), np.nanmax(mine, axis=1)
        if np.any(hi - lo >= f):                               # two sheets of this frame on one ray
            return True
    return False


def test_the_most_sheets_a_separation_allows_is_what_a_brute_force_look_finds():
    scene = load_scene(None)
    near_far = object_depth_range(scene)
    assert near_far == pytest.approx((0.9 * 0.38, 1.1 * 0.38), rel=0.05)   # the chart on the back wall
    limits = sheet_limits(scene, 30, [0.1, 0.3])
    assert limits[0] >= limits[1] >= 1                          # a wider baseline, longer spans
    for d, k in zip([0.1, 0.3], limits, strict=True):
        sd = with_separation(scene, d, aim=True)
        assert not _brute_force_overlap(sd, 30, k, near_far)
        if k < 30:
            assert _brute_force_overlap(sd, 30, k + 1, near_far) or frames_of(30, k + 1) == frames_of(30, k)
    assert list(feasible(limits, 2)) == [bool(v >= 2) for v in limits]
