"""Triangulation through flat ports: a camera pixel's water ray against the projector column's light, both
refracted at their ports (docs/physics.md §11, docs/depth.md "Through a port").

Behind a flat port a projector column no longer lights a plane and a camera pixel no longer looks along a line
through its pinhole, so :mod:`polarstripe.imaging.triangulation`'s ray–plane depth is biased. Here the
camera's pixel ray (:func:`~polarstripe.imaging.triangulation.camera_rays`, undistorted) is refracted through
the camera's port into its water ray O + x·w, and the depth is where the projector column of the point, the
column of the air ray that reaches it through the projector's port (:func:`polarstripe.sim.port.light_to`),
equals the decoded column c: a 1-D root along the ray, bracketed on a geometric grid of x and bisected. The
geometry is the rig's (:class:`~polarstripe.imaging.triangulation.RigGeometry`) plus each port as 8 numbers in
its device's OpenCV frame: normal (3), d, t, n_a, n_g, n_w (``port_cam``, ``port_proj`` of
:func:`polarstripe.sim.depth_truth.rig_geometry`); a missing port is the bare pinhole.
"""

from __future__ import annotations

import numpy as np
from polarstripe.imaging.triangulation import RigGeometry, camera_rays
from polarstripe.imaging.validation import ImagingError
from polarstripe.sim.port import PortGeometry, light_to, water_rays

_SAMPLES = 48
_BISECTIONS = 48


def port_of(numbers) -> PortGeometry | None:
    """A port's 8 numbers (normal in the device's frame, d, t, n_a, n_g, n_w) as a PortGeometry at the
    device's origin (None stays None). The triangulation needs no Fresnel term."""
    if numbers is None:
        return None
    a = np.asarray(numbers, float).ravel()
    if a.size != 8 or not np.all(np.isfinite(a)) or np.linalg.norm(a[:3]) < 1e-12 or min(a[5:]) < 1.0 or \
            min(a[3:5]) < 0.0:
        raise ImagingError(f"geometry: a port is 8 numbers (normal, d, t, n_a, n_g, n_w), got {numbers!r}")
    return PortGeometry(np.zeros(3), a[:3] / np.linalg.norm(a[:3]), float(a[3]), float(a[4]), float(a[5]),
                        float(a[6]), float(a[7]), False)


def water_rays_of(geom: RigGeometry, port_cam: PortGeometry | None, rows, cols):
    """Camera-frame origins and unit directions (n, 3) of pixel (row, col) rays in the water."""
    v = camera_rays(geom, np.asarray(rows, float).ravel(), np.asarray(cols, float).ravel())
    v = v / np.linalg.norm(v, axis=1, keepdims=True)
    if port_cam is None:
        return np.zeros_like(v), v
    origins, dirs, _, _ = water_rays(port_cam, v)
    return origins, dirs


def projector_columns(geom: RigGeometry, port_proj: PortGeometry | None, points: np.ndarray) -> np.ndarray:
    """Continuous pattern column of camera-frame ``points`` (n, 3) [m] lit through the projector's port
    (NaN where no light of the projector reaches the point)."""
    xp = points @ geom.R.T + geom.T
    if port_proj is None:
        a = xp
    else:
        a = light_to(port_proj, xp).air
    K = geom.K_proj
    with np.errstate(divide="ignore", invalid="ignore"):
        col = K[0, 0] * a[:, 0] / a[:, 2] + K[0, 1] * a[:, 1] / a[:, 2] + K[0, 2] + 0.5
    return np.where(a[:, 2] > 0, col, np.nan)


def depth_through_ports(geom: RigGeometry, port_cam: PortGeometry | None, port_proj: PortGeometry | None,
                        columns: np.ndarray, reach_m: tuple[float, float] = (1e-3, 5.0)) -> np.ndarray:
    """Depth map z [m] (h, w) along the camera axis from a map of continuous pattern columns (NaN stays NaN)
    through the ports (module docstring). ``reach_m``: the range of distances along a water ray searched."""
    columns = np.asarray(columns, float)
    h, w = columns.shape
    geom = geom.for_camera(w, h)
    out = np.full((h, w), np.nan)
    rows, cols = np.nonzero(np.isfinite(columns))
    if rows.size == 0:
        return out
    c = columns[rows, cols]
    origins, dirs = water_rays_of(geom, port_cam, rows, cols)
    xs = np.geomspace(reach_m[0], reach_m[1], _SAMPLES)

    def miss(x):           # the column at distance x along each ray minus the decoded one
        return projector_columns(geom, port_proj, origins + x[:, None] * dirs) - c

    f = np.stack([miss(np.full(c.size, x)) for x in xs], axis=1)           # (n, samples)
    change = np.isfinite(f[:, :-1]) & np.isfinite(f[:, 1:]) & (np.sign(f[:, :-1]) != np.sign(f[:, 1:]))
    ok = change.any(axis=1)
    k = np.argmax(change, axis=1)
    lo, hi = xs[k], xs[np.minimum(k + 1, xs.size - 1)]
    f_lo = f[np.arange(c.size), k]
    for _ in range(_BISECTIONS):
        mid = 0.5 * (lo + hi)
        f_mid = miss(mid)
        left = np.sign(f_mid) == np.sign(f_lo)
        lo, f_lo = np.where(left, mid, lo), np.where(left, f_mid, f_lo)
        hi = np.where(left, hi, mid)
    x = 0.5 * (lo + hi)
    z = origins[:, 2] + x * dirs[:, 2]
    out[rows[ok], cols[ok]] = z[ok]
    return out
