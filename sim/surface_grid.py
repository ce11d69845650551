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

import numpy as np
from polarstripe.sim.geometry import Frame, projector_coords
from scipy.interpolate import PchipInterpolator, make_interp_spline

# graded nodes, in stripe widths from each edge: outward (where A falls off fastest) and inward
_OUTWARD = (1 / 32, 1 / 8, 1 / 3, 1.0, 2.0, 4.0)
_INWARD = (1 / 32, 1 / 8)
_INSIDE = 6           # uniform cells across the stripe


def kappa_nodes(k_min: float, k_max: float, c0: float, c1: float, n_uniform: int) -> np.ndarray:
    """Pattern-column nodes: ``n_uniform`` over [k_min, k_max], the stripe edges, graded nodes about both
    edges and ``_INSIDE`` uniform cells across the stripe (only those within [k_min, k_max])."""
    width = max(c1 - c0, 1.0)
    graded = [c0 - g * width for g in _OUTWARD] + [c1 + g * width for g in _OUTWARD]
    graded += [c0 + g * width for g in _INWARD] + [c1 - g * width for g in _INWARD]
    special = np.concatenate([graded, np.linspace(c0, c1, _INSIDE + 1)])
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


def plane_stripe_field(frame: Frame, plane, points: np.ndarray, c0: float, c1: float, n_kappa: int,
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
    """Interpolate log(vals) (vals where a node is 0): cubic splines in κ, one per piece between the stripe
    edges (the kinks sit on piece ends, so no spline crosses one), then 4-point Lagrange in ϱ (uniform)."""
    positive = (vals > 0).all()
    y = np.log(vals) if positive else vals
    along = np.empty((kap.size, rn.size))              # each pixel's κ-interpolated value on every row
    edges = np.concatenate([[-np.inf], [b for b in breaks if kn[0] < b < kn[-1]], [np.inf]])
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        sel = (kap >= lo) & (kap < hi) if hi < np.inf else kap >= lo
        if not sel.any():
            continue
        nodes = (kn >= max(lo, kn[0])) & (kn <= min(hi, kn[-1]))
        x = kn[nodes]
        k = min(3, x.size - 1)
        xs = np.clip(kap[sel], x[0], x[-1])
        along[sel] = (PchipInterpolator(x, y[nodes], axis=0)(xs) if k == 3 else
                      make_interp_spline(x, y[nodes], k=k, axis=0)(xs))
    n = rn.size
    if n < 4:
        j = np.clip(np.searchsorted(rn, rho, side="right") - 1, 0, n - 2)
        t = np.clip((rho - rn[j]) / (rn[j + 1] - rn[j]), 0.0, 1.0)
        rows = np.arange(kap.size)
        out = (1 - t) * along[rows, j] + t * along[rows, j + 1]
    else:
        h = rn[1] - rn[0]
        j0 = np.clip(np.floor((rho - rn[0]) / h).astype(np.int64) - 1, 0, n - 4)
        t = (rho - rn[j0]) / h                         # position in node spacings from node j0
        rows = np.arange(kap.size)
        out = np.zeros(kap.size)
        for a in range(4):
            w = np.ones(kap.size)
            for b in range(4):
                if b != a:
                    w *= (t - b) / (a - b)
            out += w * along[rows, j0 + a]
    return np.exp(out) if positive else np.maximum(out, 0.0)
