"""How many light sheets per stripe frame, for a frame budget (docs/planning.md §12).

A stripe scan of N positions with K sheets per frame (``stripe:I/N:xK``, msgs/patterns.py) takes ⌈N/K⌉
frames per analyzer pass (two passes for polarized striping with a rotating analyzer, one with a
polarization camera or without a polarizer). Each frame then carries the backscatter of K sheets, so more
sheets cost quality: the fewest sheets that fit the budget are the choice (:func:`sheets_for_budget`), and
the planner's ``error`` measure renders those K-sheet frames (:class:`~polarstripe.planning.image_model.
ImageModel`), so the separation it picks accounts for the K-fold backscatter.

The sheets must also be told apart in the image (:mod:`polarstripe.imaging.sheets`): over the depth range
of the scene's objects a camera ray crosses more projector columns the wider the baseline, so each
separation allows at most some number of sheets (:func:`sheet_limits`); separations that allow fewer than K
are not eligible (:func:`feasible`).
"""

from __future__ import annotations

import numpy as np
from polarstripe.imaging.sheets import epipolar_span, max_sheets
from polarstripe.imaging.triangulation import RigGeometry, camera_rays
from polarstripe.msgs.patterns import frames_of
from polarstripe.sim.depth_truth import depth_truth, rig_geometry
from polarstripe.sim.scene import Scene, SceneError, with_separation

RANGE_MARGIN = 0.1  # the objects' depth range widened by this fraction each way (as the compositor's default)


def sheets_for_budget(n_stripes: int, max_frames: int, passes: int) -> int:
    """The fewest sheets per frame K with ⌈n_stripes/K⌉·passes ≤ max_frames; SceneError when even one
    sheet per position of the scan at once (K = N) does not fit."""
    if max_frames < passes:
        raise SceneError(f"max_frames={max_frames}: a scan takes at least {passes} frame(s) "
                         f"({passes} analyzer pass(es) of one frame of all {n_stripes} sheets)")
    per_pass = max_frames // passes
    return next(k for k in range(1, n_stripes + 1) if frames_of(n_stripes, k) <= per_pass)


def object_depth_range(scene: Scene) -> tuple[float, float]:
    """The depth range [m] (along the camera axis) of the scene's objects, widened by RANGE_MARGIN each way:
    the working range a rig's operator states (the compositor's ``depth_range_m``)."""
    z = depth_truth(scene)
    z = z[np.isfinite(z)]
    if z.size == 0:
        raise SceneError("the camera sees no object: no depth range to tell the sheets apart by")
    return (1.0 - RANGE_MARGIN) * float(z.min()), (1.0 + RANGE_MARGIN) * float(z.max())


def sheet_limits(scene: Scene, n_stripes: int, separations_m, *, step_px: int = 8) -> np.ndarray:
    """Per separation d_LC (the source moved and aimed as the planner moves it), the most sheets per frame
    that stay apart in the image over the objects' depth range (:func:`~polarstripe.imaging.sheets.
    max_sheets` of the longest epipolar span over a grid of pixels ``step_px`` apart)."""
    near_far = object_depth_range(scene)
    out = []
    for d in np.asarray(separations_m, float):
        geom = RigGeometry.from_dict(rig_geometry(with_separation(scene, float(d), aim=True)))
        w, h = geom.cam_size
        rays = camera_rays(geom, *np.mgrid[0:h:step_px, 0:w:step_px])
        lo, hi = epipolar_span(geom, rays, near_far)
        span = float(np.nanmax(hi - lo)) if np.isfinite(hi - lo).any() else 0.0
        out.append(max_sheets(n_stripes, geom.proj_size[0], span))
    return np.array(out, int)


def feasible(limits: np.ndarray, sheets: int) -> np.ndarray:
    """Which separations allow ``sheets`` sheets (bool per separation)."""
    return np.asarray(limits) >= sheets


def restrict(plans: dict, allowed: np.ndarray) -> None:
    """Score 0 at the separations where the sheets overlap in the image (as a saturated point scores 0), in
    every stripe plan's curves (the chosen reading's, every reading's and each location's), in place."""
    for key, mp in plans.items():
        if not key.startswith("stripes"):
            continue
        for c in [mp.curve, *mp.readings.values(), *mp.location_curves]:
            c.objective = np.where(allowed, c.objective, 0.0)
            c.objective_noise_free = np.where(allowed, c.objective_noise_free, 0.0)
