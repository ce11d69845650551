"""A of a stripe frame on a plane, interpolated on a grid in the projector's pattern coordinates.

A stripe's surface term varies fastest across the stripe: it peaks inside the lit footprint and has a kink
at each edge (the 1/r peak of the point's own pattern pixel enters or leaves the lit columns), and elsewhere
it falls off roughly exponentially with the distance from the stripe. On a plane the map from camera pixel
to pattern coordinates (κ column, ϱ row) is a homography, so the field is sampled on a tensor grid in
(κ, ϱ): uniform nodes over the plane's visible κ range, plus nodes graded geometrically toward both stripe
edges (a node on each edge, so the kink falls between cells, never inside one), and a few uniform rows.
Each pixel interpolates log(A/ρ) (smooth where A falls off exponentially; plain values where a node is 0)
with monotone cubics (PCHIP) in κ broken at the stripe edges and 4-point Lagrange in ϱ, and multiplies by
its albedo. Nodes lie on the plane's infinite continuation, so pixels at the plane's edge interpolate instead
of extrapolating. A flood frame is the stripe [0, W) (its edges are the frustum's).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from polarstripe.sim.geometry import PinholeFrame, projector_coords
from scipy.interpolate import PchipInterpolator

# graded nodes, in stripe widths from each edge: outward (where A falls off fastest), inward, and the uniform
# cells across the stripe; a grid narrower than _DENSE_FROM uniform columns (preview) uses the sparse set
_DENSE = ((1 / 16, 1 / 4, 1.0, 2.5), (1 / 16,), 4)
_SPARSE = ((1 / 8, 1 / 2, 2.0), (1 / 8,), 3)
_DENSE_FROM = 12


def kappa_nodes(k_min: float, k_max: float, c0: float, c1: float, n_uniform: int) -> np.ndarray:
    """Pattern-column nodes: ``n_uniform`` over [k_min, k_max], the stripe edges, graded nodes about both
    edges and uniform cells across the stripe (only those within [k_min, k_max])."""
    width = max(c1 - c0, 1.0)
    outward, inward, inside = _DENSE if n_uniform >= _DENSE_FROM else _SPARSE
    graded = [c0 - g * width for g in outward] + [c1 + g * width for g in outward]
    graded += [c0 + g * width for g in inward] + [c1 - g * width for g in inward]
    special = np.concatenate([graded, np.linspace(c0, c1, inside + 1)])
    special = special[(special >= k_min) & (special <= k_max)]
    uniform = np.linspace(k_min, k_max, max(n_uniform, 2))
    gap = 0.3 * (k_max - k_min) / max(n_uniform - 1, 1)       # uniform nodes give way to nearby special ones
    if special.size:
        near = np.abs(uniform[:, None] - special[None, :]).min(axis=1) < gap
        near[[0, -1]] = False
        uniform = uniform[~near]
    nodes = np.unique(np.concatenate([uniform, special]))
    keep = np.concatenate([[True], np.diff(nodes) > 1e-6 * max(width, k_max - k_min)])
    return nodes[keep]


def plane_stripe_field(frame: PinholeFrame, plane, points: np.ndarray, c0: float, c1: float, n_kappa: int,
                       n_rho: int, a_at) -> np.ndarray | None:
    """A/ρ at ``points`` (m, 3) on ``plane`` for the stripe of pattern columns [c0, c1), or None when the
    pattern coordinates are not usable (a point behind the projector, the plane seen edge-on from it).

    ``a_at(points, normals, albedo)`` evaluates A at surface points; n_kappa uniform columns (plus the graded
    ones) × n_rho rows of nodes are evaluated.
    """
    kap, rho, depth = projector_coords(frame, points)
    if points.shape[0] == 0 or (depth <= 0).any():
        return None
    k_lo, k_hi = float(kap.min()), float(kap.max())
    k_hi = max(k_hi, k_lo + 1.0)
    r_lo, r_hi = float(rho.min()), float(rho.max())
    kn = kappa_nodes(k_lo, k_hi, float(c0), float(c1), n_kappa)
    rn = np.linspace(r_lo, r_hi, max(n_rho, 2)) if r_hi > r_lo else np.array([r_lo, r_lo + 1.0])
    K, R = np.meshgrid(kn, rn, indexing="ij")
    d = (frame.f[None, :] + ((K.ravel() - frame.w / 2) * frame.s)[:, None] * frame.r[None, :]
         - ((R.ravel() - frame.h / 2) * frame.s)[:, None] * frame.u[None, :])
    n = np.asarray(plane.normal, float)
    dn = d @ n
    with np.errstate(divide="ignore", invalid="ignore"):
        t = ((np.asarray(plane.point, float) - frame.position) @ n) / dn
    if not (np.isfinite(t) & (t > 0)).all():
        return None
    nodes = frame.position + t[:, None] * d
    vals = a_at(nodes, np.broadcast_to(n, nodes.shape), np.ones(nodes.shape[0])).reshape(K.shape)
    return _interpolate(kn, rn, vals, kap, rho, (float(c0), float(c1)))


def _interpolate(kn, rn, vals, kap, rho, breaks):
    """Interpolate log(vals) (vals where a node is 0): monotone cubics (PCHIP) in κ, one per piece between
    the stripe edges (the kinks sit on piece ends, so no cubic crosses one), then 4-point Lagrange in ϱ."""
    positive = (vals > 0).all()
    y = np.log(vals) if positive else vals
    cut = [0] + [int(np.searchsorted(kn, b)) for b in breaks if kn[0] < b < kn[-1]] + [kn.size - 1]
    coef = np.concatenate([PchipInterpolator(kn[i:j + 1], y[i:j + 1], axis=0).c
                           for i, j in zip(cut[:-1], cut[1:], strict=True) if j > i], axis=1)
    out = np.empty(kap.size)
    interpolate_kernel(kn, rn, np.ascontiguousarray(coef), np.ascontiguousarray(kap, float),
                       np.ascontiguousarray(rho, float), out)
    return np.exp(out) if positive else np.maximum(out, 0.0)


@njit(cache=True, nogil=True)
def interpolate_kernel(kn, rn, coef, kap, rho, out):
    """Piecewise cubic in κ (coefficients (4, intervals, rows), as scipy's PPoly) on every node row, then
    Lagrange in ϱ through the 4 (or 2) nearest rows; κ and ϱ are clamped to the node ranges."""
    n, nr = kn.size, rn.size
    order = 4 if nr >= 4 else 2
    h = rn[1] - rn[0]
    for p in range(kap.size):
        k = min(max(kap[p], kn[0]), kn[n - 1])
        i = min(max(np.searchsorted(kn, k, side="right") - 1, 0), n - 2)
        dk = k - kn[i]
        r = min(max(rho[p], rn[0]), rn[nr - 1])
        j0 = min(max(int(math.floor((r - rn[0]) / h)) - (order // 2 - 1), 0), nr - order)
        t = (r - rn[j0]) / h
        acc = 0.0
        for a in range(order):
            w = 1.0
            for b in range(order):
                if b != a:
                    w *= (t - b) / (a - b)
            c = coef[:, i, j0 + a]
            acc += w * (((c[0] * dk + c[1]) * dk + c[2]) * dk + c[3])
        out[p] = acc
