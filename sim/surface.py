"""Surface reflectance at hit points: constant albedo, the procedural contrast chart, or a PNG texture.

The chart (``texture = "chart"``) fills the plane's ``size``: 4 horizontal bands (top to bottom), each with 16
vertical bars alternating between the plane's ``albedo`` (high) and albedo × (0.1, 0.3, 0.5, 0.7) (low), so
the bands have Michelson contrasts 0.82, 0.54, 0.33, 0.18. A PNG maps grey level / full scale to
albedo × level, its top row at the plane's ``up`` edge, its left column at the plane's left seen from
the front.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import NamedTuple

import cv2
import numpy as np
from numba import njit
from polarstripe.sim.geometry import Hits, plane_axes
from polarstripe.sim.scene import PlaneObject, SceneError

CHART_BANDS = 4
CHART_BARS = 16
CHART_LOW = (0.1, 0.3, 0.5, 0.7)


@dataclass
class SurfaceInfo:
    """Per pixel: object index (−1 = none), albedo, chart band (−1 off-chart), chart bar high (bool)."""

    object_id: np.ndarray
    albedo: np.ndarray
    chart_band: np.ndarray
    chart_high: np.ndarray


class Chart(NamedTuple):
    """A chart plane as :func:`_chart_kernel` takes it: centre, texture axes (right, up), size [m], high
    albedo ρ, the bands' low factors, and the band and bar counts."""

    origin: np.ndarray
    right: np.ndarray
    up: np.ndarray
    width: float
    height: float
    rho: float
    low: np.ndarray
    bands: int
    bars: int


@lru_cache(maxsize=8)
def _png(path: str) -> np.ndarray:

    img = cv2.imread(path, cv2.IMREAD_UNCHANGED)
    if img is None:
        raise SceneError(f"object texture {path!r} cannot be read as an image")
    if img.ndim == 3:
        img = img[..., :3].mean(axis=2)
    full = 65535.0 if img.dtype == np.uint16 else 255.0 if img.dtype == np.uint8 else float(img.max() or 1)
    return np.clip(img.astype(float) / full, 0.0, 1.0)


def surface_info(objects, hits: Hits) -> SurfaceInfo:
    """Albedo and chart labels at each hit point."""
    n = hits.t.size
    albedo = np.zeros(n)
    band = np.full(n, -1, dtype=np.int64)
    high = np.zeros(n, dtype=bool)
    for k, obj in enumerate(objects):
        sel = hits.index == k
        if not sel.any():
            continue
        tex = getattr(obj, "texture", None)
        if tex is None:
            albedo[sel] = obj.albedo
            continue
        assert isinstance(obj, PlaneObject) and obj.size is not None
        ra, ua = plane_axes(obj)
        if tex == "chart":
            chart = Chart(np.asarray(obj.point, float), ra, ua, float(obj.size[0]), float(obj.size[1]),
                          float(obj.albedo), np.asarray(CHART_LOW, float), CHART_BANDS, CHART_BARS)
            _chart_kernel(hits.index, k, np.ascontiguousarray(hits.point), chart, (albedo, band, high))
            continue
        rel = hits.point[sel] - np.asarray(obj.point)
        fx = np.clip((rel @ ra) / obj.size[0] + 0.5, 0.0, 1.0 - 1e-12)      # 0 left … 1 right
        fy = np.clip(0.5 - (rel @ ua) / obj.size[1], 0.0, 1.0 - 1e-12)      # 0 top … 1 bottom
        img = _png(tex)
        r = (fy * img.shape[0]).astype(np.int64)
        c = (fx * img.shape[1]).astype(np.int64)
        albedo[sel] = obj.albedo * img[r, c]
    return SurfaceInfo(hits.index.copy(), albedo, band, high)


@njit(cache=True, nogil=True)
def _chart_kernel(index, k, points, chart, out):
    """The chart's albedo, band and bar high into ``out`` = (albedo, band, high) at the hits on object k."""
    origin, ra, ua, width, height, rho, low, bands, bars = chart
    albedo, band, high = out
    for i in range(index.size):
        if index[i] != k:
            continue
        rx, ry, rz = points[i, 0] - origin[0], points[i, 1] - origin[1], points[i, 2] - origin[2]
        fx = min(max((rx * ra[0] + ry * ra[1] + rz * ra[2]) / width + 0.5, 0.0), 1.0 - 1e-12)
        fy = min(max(0.5 - (rx * ua[0] + ry * ua[1] + rz * ua[2]) / height, 0.0), 1.0 - 1e-12)
        b = int(fy * bands)
        hi = int(fx * bars) % 2 == 0
        albedo[i] = rho * (1.0 if hi else low[b])
        band[i], high[i] = b, hi
