"""Compiled (numba) ray geometry: pinhole rays, the box slab test and nearest object hits.

Same conventions and arithmetic as the numpy definitions in :mod:`polarstripe.sim.geometry`, which call
these; objects are packed once into arrays by ``geometry.pack_objects`` (kind 0 plane, 1 sphere, 2 box).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

_BIG = 1e30


class Pinhole(NamedTuple):
    """A pinhole's pose as the kernels take it (geometry.PinholeFrame): position, unit f, r, u, pitch s, w,
    h."""

    position: np.ndarray
    f: np.ndarray
    r: np.ndarray
    u: np.ndarray
    s: float
    w: int
    h: int


class HitArrays(NamedTuple):
    """Per-ray outputs of :func:`intersect_kernel`: t (n,), object index (n,), normal (n, 3), point (n, 3)."""

    t: np.ndarray
    index: np.ndarray
    normal: np.ndarray
    point: np.ndarray


@njit(cache=True, nogil=True)
def pixel_rays_kernel(frame, rows, cols, out):
    """Unit directions normalize(f + ((j + 0.5) − w/2)·s·r − ((i + 0.5) − h/2)·s·u) (docs/scene-format.md)
    of a :class:`Pinhole` at pixel coordinates (rows, cols)."""
    f, r, u, s, w, h = frame.f, frame.r, frame.u, frame.s, frame.w, frame.h
    for k in range(rows.size):
        a = ((cols[k] + 0.5) - w / 2.0) * s
        b = ((rows[k] + 0.5) - h / 2.0) * s
        x, y, z = f[0] + a * r[0] - b * u[0], f[1] + a * r[1] - b * u[1], f[2] + a * r[2] - b * u[2]
        n = math.sqrt(x * x + y * y + z * z)
        out[k, 0], out[k, 1], out[k, 2] = x / n, y / n, z / n


@njit(cache=True, nogil=True)
def box_interval_kernel(origin, dirs, lo, hi, t0_out, t1_out):
    """Slab test [t0, t1] (t0 ≥ 0) of rays origin + t·dir in the box; origin (1, 3) shared or (n, 3)."""
    per = origin.shape[0] > 1
    for i in range(dirs.shape[0]):
        ko = i if per else 0
        tmin, tmax = -math.inf, math.inf
        for k in range(3):
            o, d = origin[ko, k], dirs[i, k]
            if d == 0.0:
                inside = lo[k] <= o <= hi[k]
                a, b = (-_BIG, _BIG) if inside else (_BIG, -_BIG)
            else:
                inv = 1.0 / d
                ta, tb = (lo[k] - o) * inv, (hi[k] - o) * inv
                a, b = min(ta, tb), max(ta, tb)
            tmin, tmax = max(tmin, a), min(tmax, b)
        t0_out[i], t1_out[i] = max(tmin, 0.0), tmax


@njit(cache=True, nogil=True)
def intersect_kernel(kinds, params, origin, dirs, out):
    """Nearest hit per ray into ``out`` (:class:`HitArrays`; t = inf, index −1, normal 0, point = origin when
    none), as geometry.intersect; objects packed by ``geometry.pack_objects``."""
    t_out, idx_out, n_out, p_out = out
    per = origin.shape[0] > 1
    for i in range(dirs.shape[0]):
        ko = i if per else 0
        ox, oy, oz = origin[ko, 0], origin[ko, 1], origin[ko, 2]
        dx, dy, dz = dirs[i, 0], dirs[i, 1], dirs[i, 2]
        best, bidx = math.inf, -1
        bnx = bny = bnz = 0.0
        for k in range(kinds.size):
            p = params[k]
            t = math.inf
            nx = ny = nz = 0.0
            if kinds[k] == 0:                  # one-sided plane, optional rectangle
                nx, ny, nz = p[3], p[4], p[5]
                dn = dx * nx + dy * ny + dz * nz
                if dn < 0:
                    tt = ((p[0] - ox) * nx + (p[1] - oy) * ny + (p[2] - oz) * nz) / dn
                    if tt > 1e-12:
                        rx, ry, rz = ox + tt * dx - p[0], oy + tt * dy - p[1], oz + tt * dz - p[2]
                        if (abs(rx * p[8] + ry * p[9] + rz * p[10]) <= p[6]
                                and abs(rx * p[11] + ry * p[12] + rz * p[13]) <= p[7]):
                            t = tt
            elif kinds[k] == 1:                # sphere, seen from outside
                cx, cy, cz = ox - p[0], oy - p[1], oz - p[2]
                b = cx * dx + cy * dy + cz * dz
                disc = b * b - (cx * cx + cy * cy + cz * cz - p[3] * p[3])
                tt = -b - math.sqrt(max(disc, 0.0))
                if disc > 0 and tt > 1e-12:
                    t = tt
                    nx = (ox + tt * dx - p[0]) / p[3]
                    ny = (oy + tt * dy - p[1]) / p[3]
                    nz = (oz + tt * dz - p[2]) / p[3]
            else:                              # box, seen from outside
                tmin, tmax, axis = -math.inf, math.inf, 0
                for a in range(3):
                    o = ox if a == 0 else (oy if a == 1 else oz)
                    d = dx if a == 0 else (dy if a == 1 else dz)
                    if d == 0.0:
                        inside = p[a] <= o <= p[a + 3]
                        lo_, hi_ = (-_BIG, _BIG) if inside else (_BIG, -_BIG)
                    else:
                        ta, tb = (p[a] - o) / d, (p[a + 3] - o) / d
                        lo_, hi_ = min(ta, tb), max(ta, tb)
                    if lo_ > tmin:
                        tmin, axis = lo_, a
                    tmax = min(tmax, hi_)
                if tmin <= tmax and tmin > 1e-12:
                    t = tmin
                    d = dx if axis == 0 else (dy if axis == 1 else dz)
                    sgn = -1.0 if d > 0 else (1.0 if d < 0 else 0.0)
                    nx, ny, nz = (sgn, 0.0, 0.0) if axis == 0 else ((0.0, sgn, 0.0) if axis == 1 else
                                                                     (0.0, 0.0, sgn))
            if t < best:
                best, bidx = t, k
                bnx, bny, bnz = nx, ny, nz
        t_out[i], idx_out[i] = best, bidx
        n_out[i, 0], n_out[i, 1], n_out[i, 2] = bnx, bny, bnz
        tt = best if bidx >= 0 else 0.0
        p_out[i, 0], p_out[i, 1], p_out[i, 2] = ox + tt * dx, oy + tt * dy, oz + tt * dz


@njit(cache=True, nogil=True)
def projector_coords_kernel(frame, points, col, row, depth):
    """Pattern coordinates (col, row) and depth of points in a :class:`Pinhole`; (−1, −1) behind it
    (depth ≤ 0)."""
    position, f, r, u, s, w, h = frame
    for i in range(points.shape[0]):
        vx, vy, vz = points[i, 0] - position[0], points[i, 1] - position[1], points[i, 2] - position[2]
        vf = vx * f[0] + vy * f[1] + vz * f[2]
        depth[i] = vf
        if vf <= 0:
            col[i] = row[i] = -1.0
            continue
        col[i] = w / 2.0 + ((vx * r[0] + vy * r[1] + vz * r[2]) / vf) / s
        row[i] = h / 2.0 - ((vx * u[0] + vy * u[1] + vz * u[2]) / vf) / s
