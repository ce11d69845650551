"""Which sheet of a K-sheet frame lit each pixel: the stripe position from the frame index and the geometry.

A scan of N stripe positions with K sheets per frame (``stripe:I/N:xK``, msgs/patterns.py) takes
F = ⌈N/K⌉ frames; frame I lights positions I, I + F, … (< N). The running argmax of the delineation
(:class:`~polarstripe.imaging.delineation.RunningArgmax`) gives each pixel its brightest frame I, not its
position: the position is I + j·F for one of the K sheets j. The geometry tells which: a camera pixel's ray,
between the near and far ends of the depth range [z_n, z_f] the objects lie in, projects onto the projector
columns between c(z_n) and c(z_f) (its epipolar segment; :func:`ray_columns`). Sheet j can have lit the pixel
only if its columns [⌊p·W/N⌋, ⌊(p + 1)·W/N⌋) meet that segment (:func:`assign_positions`); a pixel no sheet
of its frame meets, or (where the sheets are too close) two, gets none (−1) and the delineation leaves it
invalid. Behind flat ports the segment is that of the pixel's water ray and the columns those of the light
through the projector's port (docs/physics.md §11).

The sheets of one frame are ⌊F·W/N⌋ columns apart. Two of them can light the same pixel when its segment is
longer than the gap between them, (F − 1)·W/N columns: then the K sheets overlap in the image and the scan
cannot be delineated; :func:`check_sheets` says so, with the most sheets the depth range allows
(:func:`max_sheets`). Nearer objects or a wider baseline give longer segments (disparity ∝ baseline/z), so
fewer sheets. One sheet (K = 1) needs no depth range: every pixel's position is its frame index.
"""

from __future__ import annotations

import numpy as np
from polarstripe.imaging.refraction import port_of, projector_columns
from polarstripe.imaging.triangulation import RigGeometry
from polarstripe.imaging.validation import ImagingError, finite_param
from polarstripe.msgs.patterns import frames_of
from polarstripe.sim.port import water_rays


class SheetsOverlap(ImagingError):
    """The K sheets of a frame can light one pixel within the depth range: the scan cannot be delineated."""


def depth_range(values) -> tuple[float, float]:
    """A checked [near, far] depth range [m] (0 < near < far, finite)."""
    if len(values) != 2:
        raise ImagingError(f"depth_range_m: need [near, far] in metres, got {list(values)}")
    near, far = (finite_param("depth_range_m", v, low=0.0) for v in values)
    if not 0 < near < far:
        raise ImagingError(f"depth_range_m: need 0 < near < far, got [{near:g}, {far:g}]")
    return near, far


def ray_columns(geom: RigGeometry, rays: np.ndarray, z: float) -> np.ndarray:
    """Continuous projector column (msgs/patterns.py: c ∈ [j, j + 1) is column j) of the points z·v of
    camera rays v (..., 3) (z = 1 components, :func:`~.triangulation.camera_rays`): c = f_x·x_p/z_p + c_x + ½
    with X_p = R·(z v) + T; NaN where the point is behind the projector. A rig with ports takes the point at
    depth z on the pixel's water ray and the column of the light reaching it through the projector's port
    (imaging/refraction.py)."""
    if geom.has_ports:
        return _columns_through_ports(geom, rays, z)
    xp = z * (rays @ geom.R.T) + geom.T
    with np.errstate(divide="ignore", invalid="ignore"):
        c = geom.K_proj[0, 0] * xp[..., 0] / xp[..., 2] + geom.K_proj[0, 2] + 0.5
    return np.where(xp[..., 2] > 0, c, np.nan)


def _columns_through_ports(geom: RigGeometry, rays: np.ndarray, z: float) -> np.ndarray:
    v = np.asarray(rays, float).reshape(-1, 3)
    v = v / np.linalg.norm(v, axis=1, keepdims=True)
    port_cam = port_of(geom.port_cam)
    if port_cam is None:
        points = z * v / v[:, 2:3]
    else:
        origins, dirs, _, _ = water_rays(port_cam, v)
        with np.errstate(divide="ignore", invalid="ignore"):
            points = origins + ((z - origins[:, 2]) / dirs[:, 2])[:, None] * dirs
    return projector_columns(geom, port_of(geom.port_proj), points).reshape(np.shape(rays)[:-1])


def epipolar_span(geom: RigGeometry, rays: np.ndarray, near_far: tuple[float, float]):
    """Per ray, the projector columns (lo, hi) its points between depths near and far project to (the
    column is monotone along the ray in front of both pinholes)."""
    a, b = (ray_columns(geom, rays, z) for z in near_far)
    return np.fmin(a, b), np.fmax(a, b)


def max_sheets(count: int, width: int, span_cols: float) -> int:
    """The most sheets per frame (1 … count) whose neighbours stay more than ``span_cols`` projector columns
    apart ((F − 1)·W/N > span, F = ⌈N/K⌉ frames): what :func:`check_sheets` allows."""
    best = 1
    for k in range(2, count + 1):
        if (frames_of(count, k) - 1) * width / count > span_cols:
            best = k
    return best


def check_sheets(count: int, sheets: int, width: int, lo: np.ndarray, hi: np.ndarray,
                 near_far: tuple[float, float]) -> None:
    """Raise :class:`SheetsOverlap` when two sheets of one frame can light one pixel: some ray's span
    hi − lo (columns, NaN ignored) reaches the gap (F − 1)·W/N between neighbouring sheets."""
    if sheets <= 1:
        return
    span = float(np.nanmax(hi - lo)) if np.isfinite(hi - lo).any() else 0.0
    gap = (frames_of(count, sheets) - 1) * width / count
    if span >= gap:
        raise SheetsOverlap(
            f"{sheets} sheets of {count} stripes overlap in the image: over the depth range {near_far[0]:g}-"
            f"{near_far[1]:g} m a pixel's ray crosses {span:.0f} projector columns, the sheets are "
            f"{gap:.0f} columns apart; use at most {max_sheets(count, width, span)} sheets or a narrower "
            "depth range")


def assign_positions(frame_index: np.ndarray, count: int, sheets: int, width: int, lo: np.ndarray,
                     hi: np.ndarray) -> np.ndarray:
    """Stripe position (int32, −1 none) per pixel from its brightest frame ``frame_index`` of a scan of
    ``count`` positions with ``sheets`` sheets per frame: the one sheet I + j·F of the frame whose columns
    meet the pixel's epipolar span [lo, hi] (module docstring); −1 where none or more than one does."""
    frame_index = np.asarray(frame_index)
    f = frames_of(count, sheets)
    if sheets <= 1:
        return frame_index.astype(np.int32)
    out = np.full(frame_index.shape, -1, np.int32)
    hits = np.zeros(frame_index.shape, np.int32)
    ok = np.isfinite(lo) & np.isfinite(hi)
    for j in range(sheets):
        p = frame_index + j * f
        c0, c1 = (p * width) // count, ((p + 1) * width) // count
        meet = ok & (p < count) & (c0 <= hi) & (c1 > lo)
        out = np.where(meet, p, out)
        hits += meet
    return np.where(hits == 1, out, -1).astype(np.int32)
