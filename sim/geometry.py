"""Geometry: pinhole rays exactly as docs/scene-format.md "Geometry" states, box clipping, object hits,
projector pixel coordinates.

Conventions (right-handed metres): forward f = normalize(look_at − position), right r = normalize(f × up),
image up u = r × f. Pixel (row i, column j) of a w×h image looks along
normalize(f + ((j + 0.5) − w/2)·s·r − ((i + 0.5) − h/2)·s·u), s = 2·tan(fov_deg/2)/w (horizontal fov).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from polarstripe.sim.ray_kernels import (
    HitArrays,
    Pinhole,
    box_interval_kernel,
    intersect_kernel,
    pixel_rays_kernel,
    projector_coords_kernel,
)
from polarstripe.sim.scene import BoxObject, PlaneObject, SphereObject


@dataclass(frozen=True)
class PinholeFrame:
    """A pinhole's pose: position (3,), orthonormal f, r, u (3,), pixel pitch s [1/px] and size (w, h)."""

    position: np.ndarray
    f: np.ndarray
    r: np.ndarray
    u: np.ndarray
    s: float
    w: int
    h: int

    def kernel_args(self) -> Pinhole:
        """The frame as the compiled kernels take it."""
        return Pinhole(np.asarray(self.position, float), self.f, self.r, self.u, float(self.s), int(self.w),
                       int(self.h))


def pinhole_frame(position, look_at, up, fov_deg: float, resolution) -> PinholeFrame:
    """The pinhole frame of a camera or projector (docs/scene-format.md "Geometry"); of a scene's tuples
    kept (read-only arrays: every frame of a scan asks for the same two)."""
    args = (position, look_at, up, fov_deg, resolution)
    if all(isinstance(a, tuple) for a in (position, look_at, up, resolution)):
        return _kept_frame(*args)
    return _pinhole(*args)


@lru_cache(maxsize=64)
def _kept_frame(position, look_at, up, fov_deg, resolution) -> PinholeFrame:
    frame = _pinhole(position, look_at, up, fov_deg, resolution)
    for a in (frame.position, frame.f, frame.r, frame.u):
        a.flags.writeable = False
    return frame


def _pinhole(position, look_at, up, fov_deg: float, resolution) -> PinholeFrame:
    p = np.asarray(position, dtype=float)
    f = np.asarray(look_at, dtype=float) - p
    f /= np.linalg.norm(f)
    r = np.cross(f, np.asarray(up, dtype=float))
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    w, h = int(resolution[0]), int(resolution[1])
    return PinholeFrame(p, f, r, u, 2.0 * np.tan(np.radians(fov_deg) / 2.0) / w, w, h)


def pixel_rays(frame: PinholeFrame, pixels: np.ndarray | None = None) -> np.ndarray:
    """Unit ray directions through pixel centres.

    Parameters
    ----------
    frame : PinholeFrame
    pixels : (n, 2) int array of (row, col), or None for the whole image.

    Returns
    -------
    (n, 3) float64 directions; n = h·w in row-major order when ``pixels`` is None.
    """
    if pixels is None:
        rows = np.repeat(np.arange(frame.h, dtype=float), frame.w)
        cols = np.tile(np.arange(frame.w, dtype=float), frame.h)
    else:                                        # integer or continuous (row, col)
        pixels = np.asarray(pixels)
        rows, cols = (np.ascontiguousarray(pixels[:, k], float) for k in (0, 1))
    out = np.empty((rows.size, 3))
    pixel_rays_kernel(frame.kernel_args(), rows, cols, out)
    return out


def box_interval(origin: np.ndarray, dirs: np.ndarray, lo, hi) -> tuple[np.ndarray, np.ndarray]:
    """Slab test: parameter interval [t0, t1] (t0 ≥ 0) of rays origin + t·dir inside the box.

    origin (3,) or (n, 3), dirs (n, 3) unit. Empty intervals have t1 < t0 (no NaN for axis-parallel rays).
    """
    dirs = np.ascontiguousarray(dirs, float)
    t0, t1 = np.empty(dirs.shape[0]), np.empty(dirs.shape[0])
    box_interval_kernel(np.ascontiguousarray(origin, float).reshape(-1, 3), dirs, np.asarray(lo, float),
                        np.asarray(hi, float), t0, t1)
    return t0, t1


def segment_length_in_box(a: np.ndarray, b: np.ndarray, lo, hi) -> np.ndarray:
    """Length [m] of each segment a→b (arrays (..., 3)) inside the box."""
    shape = np.broadcast_shapes(np.shape(a), np.shape(b))
    a3 = np.broadcast_to(a, shape).reshape(-1, 3)
    b3 = np.broadcast_to(b, shape).reshape(-1, 3)
    v = b3 - a3
    length = np.linalg.norm(v, axis=1)
    d = v / np.where(length > 0, length, 1.0)[:, None]
    t0, t1 = box_interval(a3, d, lo, hi)
    out = np.clip(np.minimum(t1, length) - t0, 0.0, None)
    return out.reshape(shape[:-1])


def point_in_box(p: np.ndarray, lo, hi, tol: float = 1e-12) -> np.ndarray:
    p = np.asarray(p, float)
    return np.all((p >= np.asarray(lo) - tol) & (p <= np.asarray(hi) + tol), axis=-1)


@dataclass
class Hits:
    """Nearest surface hit per ray: t [m] (inf = none), object index (−1), unit normal (3,), point (3,)."""

    t: np.ndarray
    index: np.ndarray
    normal: np.ndarray
    point: np.ndarray


def plane_axes(obj: PlaneObject) -> tuple[np.ndarray, np.ndarray]:
    """Texture axes (right, up) of a plane as seen from its front (looking along −normal)."""
    n = np.asarray(obj.normal)
    right = np.cross(-n, np.asarray(obj.up))
    right /= np.linalg.norm(right)
    return right, np.cross(right, -n)


def intersect(objects, origin: np.ndarray, dirs: np.ndarray) -> Hits:
    """Nearest hit of rays origin + t·dir (origin (3,) or (n, 3)) with the scene objects."""
    n = dirs.shape[0]
    t_best = np.empty(n)
    idx = np.empty(n, dtype=np.int64)
    normal = np.empty((n, 3))
    point = np.empty((n, 3))
    kinds, params = _packed(tuple(objects))
    intersect_kernel(kinds, params, np.ascontiguousarray(origin, float).reshape(-1, 3),
                     np.ascontiguousarray(dirs, float), HitArrays(t_best, idx, normal, point))
    return Hits(t_best, idx, normal, point)


def pack_objects(objects) -> tuple[np.ndarray, np.ndarray]:
    """Objects → (kinds (k,), params (k, 14)): plane P, n, w/2, h/2 (inf: unbounded), right, up axes;
    sphere centre, radius; box min, max."""
    kinds = np.zeros(len(objects), np.int64)
    params = np.zeros((len(objects), 14))
    for k, o in enumerate(objects):
        if isinstance(o, PlaneObject):
            ra, ua = plane_axes(o)
            half = (np.inf, np.inf) if o.size is None else (o.size[0] / 2, o.size[1] / 2)
            params[k] = [*o.point, *o.normal, *half, *ra, *ua]
        elif isinstance(o, SphereObject):
            kinds[k] = 1
            params[k, :4] = [*o.center, o.radius]
        elif isinstance(o, BoxObject):
            kinds[k] = 2
            params[k, :6] = [*o.min, *o.max]
        else:
            raise TypeError(f"unknown object type {type(o).__name__}")
    return kinds, params


@lru_cache(maxsize=64)
def _packed(objects: tuple):
    return pack_objects(objects)


def occluded(objects, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """True where the segment a (3,) → b (n, 3) is blocked by an object before reaching b."""
    v = b - a
    dist = np.linalg.norm(v, axis=1)
    d = v / np.where(dist > 0, dist, 1.0)[:, None]
    hits = intersect(objects, a, d)
    return hits.t < dist * (1.0 - 1e-9) - 1e-9


def projector_coords(frame: PinholeFrame, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Continuous pattern coordinates (col, row) of 3-D points and the depth along the projector axis.

    col ∈ [j, j+1) is pattern column j (row likewise); depth ≤ 0 means behind the projector.
    """
    points = np.ascontiguousarray(points, float).reshape(-1, 3)
    col, row, depth = (np.empty(points.shape[0]) for _ in range(3))
    projector_coords_kernel(frame.kernel_args(), points, col, row, depth)
    return col, row, depth
