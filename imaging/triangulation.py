"""Light-sheet planes and ray–plane triangulation: 3-D from a stripe scan, given the rig's geometry.

The geometry is plain numbers, as a projector–camera calibration gives them (``cv2.stereoCalibrate``
conventions): camera intrinsics ``K_cam`` (3×3, pixel centres at integer coordinates) and distortion
``dist_cam``, projector intrinsics ``K_proj``, image sizes ``cam_size``/``proj_size`` = [w, h], and the pose
``R`` (3×3), ``T`` (3,) [m] taking camera-frame points to the projector frame, X_p = R·X_c + T. Camera
frame: x image right, y image down, z forward (metres).

A projector column is a plane through the projector's centre. Pattern column coordinates follow the pattern
grammar (:mod:`polarstripe.msgs.patterns`): continuous c ∈ [j, j+1) is pattern column j, so stripe ``K/N``
of a W-wide pattern is the wedge c ∈ [⌊K·W/N⌋, ⌊(K+1)·W/N⌋) and its OpenCV pixel coordinate is x = c − ½.
In the projector frame the plane of c is x_p − a·z_p = 0 with a = (c − ½ − c_x)/f_x, i.e. normal
n_p = (1, 0, −a); in the camera frame n = Rᵀ·n_p, d = n_p·T (n·X + d = 0), normalised so |n| = 1.

A camera pixel (x, y) looks along v = ((x − c_x)/f_x, (y − c_y)/f_y, 1) (undistorted), so the point on the
plane is X = z·v with z = −d/(n·v): the depth along the camera axis. Projector lens distortion is not
modelled (a calibration with it would need the columns undistorted first).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit
from polarstripe.imaging.validation import ImagingError


@dataclass(frozen=True)
class RigGeometry:
    """A projector–camera rig (see the module docstring); build it with :meth:`from_dict`."""

    K_cam: np.ndarray
    K_proj: np.ndarray
    R: np.ndarray
    T: np.ndarray
    cam_size: tuple[int, int]
    proj_size: tuple[int, int]
    dist_cam: np.ndarray
    port_cam: np.ndarray | None = None      # a flat port: normal (device frame), d, t, n_a, n_g, n_w
    port_proj: np.ndarray | None = None

    @classmethod
    def from_dict(cls, d) -> RigGeometry:
        """From a mapping with ``K_cam``, ``K_proj``, ``R``, ``T``, ``cam_size``, ``proj_size`` and optionally
        ``dist_cam``; any missing or mis-shaped entry is one :class:`ImagingError` naming it."""
        out = {}
        for key, shape in (("K_cam", (3, 3)), ("K_proj", (3, 3)), ("R", (3, 3)), ("T", (3,)),
                           ("cam_size", (2,)), ("proj_size", (2,))):
            if key not in d:
                raise ImagingError(f"geometry: {key} is missing")
            a = np.asarray(d[key], float)
            if a.size != int(np.prod(shape)) or not np.all(np.isfinite(a)):
                raise ImagingError(f"geometry: {key} must be {shape} finite numbers, got {np.shape(d[key])}")
            out[key] = a.reshape(shape)
        if not np.allclose(out["R"] @ out["R"].T, np.eye(3), atol=1e-6):
            raise ImagingError("geometry: R is not a rotation")
        if min(out["cam_size"]) < 1 or min(out["proj_size"]) < 1 or out["K_cam"][0, 0] <= 0 or \
                out["K_proj"][0, 0] <= 0:
            raise ImagingError("geometry: sizes and focal lengths must be positive")
        dist = np.asarray(d.get("dist_cam", np.zeros(5)), float).ravel()
        ports = {}
        for key in ("port_cam", "port_proj"):
            if d.get(key) is not None:
                a = np.asarray(d[key], float).ravel()
                if a.size != 8 or not np.all(np.isfinite(a)) or np.linalg.norm(a[:3]) < 1e-12 or \
                        min(a[5:]) < 1.0 or min(a[3:5]) < 0.0:
                    raise ImagingError(f"geometry: {key} must be 8 numbers (normal, d, t, n_a, n_g, n_w), "
                                       f"got {np.shape(d[key])}")
                ports[key] = a
        return cls(out["K_cam"], out["K_proj"], out["R"], out["T"],
                   tuple(int(v) for v in out["cam_size"]), tuple(int(v) for v in out["proj_size"]), dist,
                   **ports)

    def to_dict(self) -> dict:
        out = {"K_cam": self.K_cam, "K_proj": self.K_proj, "R": self.R, "T": self.T,
               "cam_size": list(self.cam_size), "proj_size": list(self.proj_size), "dist_cam": self.dist_cam}
        for key in ("port_cam", "port_proj"):
            if getattr(self, key) is not None:
                out[key] = getattr(self, key)
        return out

    @property
    def has_ports(self) -> bool:
        """True when the camera or the projector looks through a flat port (imaging/refraction.py)."""
        return self.port_cam is not None or self.port_proj is not None

    def for_camera(self, w: int, h: int) -> RigGeometry:
        """The same rig with the camera binned/resized to w×h (the intrinsics scale with the pixel size)."""
        if (w, h) == tuple(self.cam_size):
            return self
        sx, sy = w / self.cam_size[0], h / self.cam_size[1]
        K = self.K_cam.copy()
        K[0, 0], K[0, 1], K[0, 2] = K[0, 0] * sx, K[0, 1] * sx, (K[0, 2] + 0.5) * sx - 0.5
        K[1, 1], K[1, 2] = K[1, 1] * sy, (K[1, 2] + 0.5) * sy - 0.5
        return RigGeometry(K, self.K_proj, self.R, self.T, (int(w), int(h)), self.proj_size, self.dist_cam,
                           self.port_cam, self.port_proj)

    @property
    def baseline_m(self) -> float:
        """Distance between the camera's and the projector's centres [m]."""
        return float(np.linalg.norm(self.T))


def stripe_edges(count: int, width: int) -> np.ndarray:
    """Continuous pattern column of the N + 1 stripe boundaries of a scan of ``count`` stripes on a pattern
    ``width`` pixels wide: ⌊k·W/N⌋, k = 0 … N (msgs.patterns.stripe_columns)."""
    if count < 1 or width < 1:
        raise ImagingError(f"stripes: need count >= 1 and width >= 1, got {count}, {width}")
    return (np.arange(count + 1) * int(width) // int(count)).astype(float)


def column_planes(geom: RigGeometry, columns) -> tuple[np.ndarray, np.ndarray]:
    """Planes of continuous pattern columns in the camera frame: unit normals (n, 3) and offsets (n,) with
    n·X + d = 0 for every point X [m] the column lights; the normal points toward increasing column."""
    c = np.asarray(columns, float).ravel()
    a = (c - 0.5 - geom.K_proj[0, 2]) / geom.K_proj[0, 0]
    n_p = np.stack([np.ones_like(a), np.zeros_like(a), -a], axis=1)
    n = n_p @ geom.R  # rows: Rᵀ·n_p
    d = n_p @ geom.T
    norm = np.linalg.norm(n, axis=1)
    return n / norm[:, None], d / norm


def sheet_planes(geom: RigGeometry, count: int, *, edges: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """The light sheets of a scan of ``count`` stripes (``stripe:K/N``, N = count) in the camera frame.

    Returns (normals, offsets): sheet k's centre plane (count of them), or with ``edges`` the count + 1
    boundary planes (plane k is the left edge of stripe k and the right edge of stripe k − 1)."""
    e = stripe_edges(count, geom.proj_size[0])
    return column_planes(geom, e if edges else 0.5 * (e[:-1] + e[1:]))


def camera_rays(geom: RigGeometry, rows, cols) -> np.ndarray:
    """Rays v = (x', y', 1) (z = 1, undistorted) of camera pixel coordinates (arrays of one shape);
    returns (..., 3)."""
    rows, cols = np.asarray(rows, float), np.asarray(cols, float)
    K = geom.K_cam
    if np.any(geom.dist_cam != 0):
        import cv2  # only with a distorted lens

        pts = np.stack([cols.ravel(), rows.ravel()], axis=1).reshape(-1, 1, 2)
        und = cv2.undistortPoints(pts, K, geom.dist_cam).reshape(-1, 2)
        x, y = und[:, 0].reshape(cols.shape), und[:, 1].reshape(rows.shape)
    else:
        y = (rows - K[1, 2]) / K[1, 1]
        x = (cols - K[0, 2] - K[0, 1] * y) / K[0, 0]
    return np.stack([x, y, np.ones_like(x)], axis=-1)


def intersect_planes(rays: np.ndarray, normals: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Depth z of rays X = z·v (v with z = 1, (..., 3)) on planes n·X + d = 0 (broadcast); NaN where the
    ray is parallel to its plane or meets it behind the camera."""
    den = np.sum(rays * normals, axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = -np.asarray(offsets) / den
    return np.where(np.isfinite(z) & (z > 0), z, np.nan)


def depth_from_columns(geom: RigGeometry, columns: np.ndarray, rays: np.ndarray | None = None) -> np.ndarray:
    """Depth map z [m] (h, w) from a map of continuous pattern columns (NaN: invalid, stays NaN).

    The per-pixel plane is x_p = a·z_p with a = (c − ½ − c_x)/f_x; for X = z·v this is
    z = −(T_x − a·T_z)/((R_x − a·R_z)·v), R_x, R_z the rows of R. ``rays``: :func:`camera_rays` of the
    whole image, precomputed (it depends only on the geometry)."""
    columns = np.asarray(columns, float)
    h, w = columns.shape
    if rays is None:
        rr, cc = np.mgrid[0:h, 0:w]
        rays = camera_rays(geom, rr, cc)
    a = (columns - 0.5 - geom.K_proj[0, 2]) / geom.K_proj[0, 0]
    R, T = geom.R, geom.T
    rx, rz = rays @ R[0], rays @ R[2]
    with np.errstate(divide="ignore", invalid="ignore"):
        z = -(T[0] - a * T[2]) / (rx - a * rz)
    return np.where(np.isfinite(z) & (z > 0), z, np.nan)


def points_from_depth(geom: RigGeometry, depth: np.ndarray, rays: np.ndarray | None = None) -> np.ndarray:
    """The valid (finite) pixels of a depth map as camera-frame points (n, 3) [m], row-major order."""
    depth = np.asarray(depth, float)
    ok = np.isfinite(depth)
    if rays is None:
        rr, cc = np.nonzero(ok)
        v = camera_rays(geom, rr, cc)
    else:
        v = rays[ok]
    return v * depth[ok][:, None]


class Triangulator:
    """Depth and points of column maps of one geometry and image shape, the per-pixel constants (rays,
    R_x·v, R_z·v) computed once: what the compositor keeps between scans (:func:`depth_from_columns` in one
    compiled pass). A rig with ports triangulates through them
    (:func:`polarstripe.imaging.refraction.depth_through_ports`) and its points lie on the water rays."""

    def __init__(self, geom: RigGeometry, shape: tuple[int, int]):
        h, w = shape
        self.geom, self.shape = geom.for_camera(w, h), (int(h), int(w))
        rr, cc = np.mgrid[0:h, 0:w]
        self.rays = np.ascontiguousarray(camera_rays(self.geom, rr, cc))
        self._rx = np.ascontiguousarray(self.rays @ self.geom.R[0])
        self._rz = np.ascontiguousarray(self.rays @ self.geom.R[2])
        self._water = None
        if self.geom.has_ports:
            from polarstripe.imaging.refraction import port_of, water_rays_of  # it builds on this module

            o, d = water_rays_of(self.geom, port_of(self.geom.port_cam), rr, cc)
            self._water = (o.reshape(h, w, 3), d.reshape(h, w, 3))

    def depth(self, columns: np.ndarray) -> np.ndarray:
        """z [m] (h, w) float32, NaN where the column is NaN or the plane is behind the camera."""
        columns = np.ascontiguousarray(columns, np.float64)
        if columns.shape != self.shape:
            raise ImagingError(f"columns: shape {columns.shape}, the triangulator's is {self.shape}")
        if self._water is not None:
            from polarstripe.imaging.refraction import depth_through_ports, port_of

            g = self.geom
            z = depth_through_ports(g, port_of(g.port_cam), port_of(g.port_proj), columns)
            return z.astype(np.float32)
        out = np.empty(self.shape, np.float32)
        K, T = self.geom.K_proj, self.geom.T
        _depth(columns, self._rx, self._rz, float(K[0, 2]), float(K[0, 0]), float(T[0]), float(T[2]), out)
        return out

    def points(self, depth: np.ndarray) -> np.ndarray:
        """The finite pixels of ``depth`` as camera-frame points (n, 3) float32 [m], row-major."""
        depth = np.ascontiguousarray(depth, np.float32)
        if self._water is not None:          # on the water ray O + x·w at its depth z
            ok = np.isfinite(depth)
            o, d = self._water[0][ok], self._water[1][ok]
            x = (depth[ok] - o[:, 2]) / d[:, 2]
            return (o + x[:, None] * d).astype(np.float32)
        return _points(depth, self.rays, int(np.count_nonzero(np.isfinite(depth))))


@njit(cache=True, nogil=True)
def _depth(columns, rx, rz, cx, fx, tx, tz, out):
    h, w = columns.shape
    for i in range(h):
        for j in range(w):
            c = columns[i, j]
            out[i, j] = np.nan
            if np.isfinite(c):
                a = (c - 0.5 - cx) / fx
                den = rx[i, j] - a * rz[i, j]
                if den != 0.0:
                    z = -(tx - a * tz) / den
                    if z > 0.0:
                        out[i, j] = z


@njit(cache=True, nogil=True)
def _points(depth, rays, n):
    out = np.empty((n, 3), np.float32)
    h, w = depth.shape
    k = 0
    for i in range(h):
        for j in range(w):
            z = depth[i, j]
            if np.isfinite(z):
                for c in range(3):
                    out[k, c] = rays[i, j, c] * z
                k += 1
    return out
