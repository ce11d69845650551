"""Projector patterns in the model: the analytic clipping of rays to the lit part of the projector's frustum.

The grammar (``flood``, ``stripe:K/N[:xSHEETS]``, ``checker:SIZE:SHIFT``, ``gray:BIT:AXIS:INV``) and the
pattern value are :mod:`polarstripe.msgs.patterns`; ``PatternSpec``, ``stripe_columns``, ``sheet_columns``,
``single_sheets`` and ``gray_lit`` here are those, imported for the model. Checkers and Gray code are cut at
every pattern-pixel boundary where their lit state can change (checker squares; Gray bit b changes at columns
2^b + m·2^(b+1), an XOR base bit too).
A lit pixel sends I0 [W/sr] through it; an unlit one b·I0 (``projector.black_level``), handled by linearity.
A stripe pattern of several sheets is the union of their pyramids: a ray's lit intervals are each sheet's
(disjoint, so every order of light adds up over the sheets; the surface term A sums them in
:mod:`polarstripe.sim.surface_field`).
Each clip is a set of half-spaces n·(P − L) ≥ 0 through the source, linear along a ray (docs/physics.md §2.3).
"""

from __future__ import annotations

import numpy as np
from polarstripe.msgs.patterns import (
    PatternError,
    PatternSpec,
    gray_lit,
    parse,
    sheet_columns,
    single_sheets,
    stripe_columns,
)
from polarstripe.sim.geometry import PinholeFrame, projector_coords
from polarstripe.sim.kernels import clip_rays
from polarstripe.sim.scene import SceneError

__all__ = ["PatternSpec", "clip_halfspaces", "column_order", "gray_lit", "lit_in_columns", "lit_intervals",
           "parse_pattern", "sheet_columns", "single_sheets", "stripe_columns"]

_PAR_EPS = 1e-13


def parse_pattern(spec: str | PatternSpec) -> PatternSpec:
    """Parse ``flood``, ``stripe:K/N`` (0 ≤ K < N; ``stripe:I/N:xS``: S sheets at once),
    ``checker:SIZE:SHIFT`` (SIZE ≥ 1, SHIFT ≥ 0 pixels) or ``gray:BIT:col|row:0|1`` with
    the grammar of :mod:`polarstripe.msgs.patterns`; a bad spec (or ``off``, which lights nothing to model)
    is a :class:`SceneError`."""
    try:
        pattern = parse(spec)
    except PatternError as exc:
        raise SceneError(str(exc)) from None
    if pattern.kind == "off":
        raise SceneError(f"pattern {spec!r} is not flood, stripe:K/N, checker:SIZE:SHIFT or "
                         "gray:BIT:AXIS:INV")
    return pattern


def _halfspaces(frame: PinholeFrame, c0: float, c1: float) -> np.ndarray:
    """Normals (4, 3) of the pyramid columns [c0, c1) × rows [0, H) through the projector centre."""
    a0, a1 = (c0 - frame.w / 2.0) * frame.s, (c1 - frame.w / 2.0) * frame.s
    b = frame.h / 2.0 * frame.s
    f, r, u = frame.f, frame.r, frame.u
    return np.stack([r - a0 * f, a1 * f - r, b * f - u, b * f + u])


def clip_halfspaces(origin: np.ndarray, dirs: np.ndarray, x0: np.ndarray, x1: np.ndarray, apex: np.ndarray,
                    normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Clip [x0, x1] of rays origin + x·dir to ∩ {n·(P − apex) ≥ 0}; a ray parallel to a plane is kept
    or dropped whole (|n·d| below 1e−13·|n|), so grazing rays give no 0/0."""

    lo, hi = np.empty(dirs.shape[0]), np.empty(dirs.shape[0])
    clip_rays(np.ascontiguousarray(origin, float).reshape(-1, 3), np.ascontiguousarray(dirs, float),
              np.ascontiguousarray(np.broadcast_to(x0, dirs.shape[:1]), float),
              np.ascontiguousarray(np.broadcast_to(x1, dirs.shape[:1]), float), np.asarray(apex, float),
              np.ascontiguousarray(normals, float), _PAR_EPS, lo, hi)
    return lo, hi


def lit_intervals(pattern: PatternSpec, frame: PinholeFrame | None, origin: np.ndarray, dirs: np.ndarray,
                  x0: np.ndarray, x1: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sub-intervals of each ray's [x0, x1] that the pattern lights.

    Parameters
    ----------
    pattern : PatternSpec
    frame : projector PinholeFrame, or None for the isotropic point source (everything lit).
    origin : (3,) or (n, 3); dirs (n, 3) unit; x0, x1 (n,) the in-medium interval.

    Returns
    -------
    ray : (m,) int index of the ray each interval belongs to; lo, hi : (m,) interval ends (lo < hi).
    """
    if frame is None:
        keep = x1 > x0
        return np.nonzero(keep)[0], x0[keep], x1[keep]
    if pattern.kind in ("flood", "stripe"):     # one pyramid per sheet; the sheets are disjoint
        out = []
        for c0, c1 in sheet_columns(pattern, frame.w):
            lo, hi = clip_halfspaces(origin, dirs, x0, x1, frame.position, _halfspaces(frame, c0, c1))
            keep = hi > lo
            out.append((np.nonzero(keep)[0], lo[keep], hi[keep]))
        if len(out) == 1:
            return out[0]
        return tuple(np.concatenate(parts) for parts in zip(*out, strict=True))
    # checker, gray: clip to the frustum, then split at every column/row boundary the ray crosses
    lo, hi = clip_halfspaces(origin, dirs, x0, x1, frame.position, _halfspaces(frame, 0, frame.w))
    keep = np.nonzero(hi > lo)[0]
    rays, los, his = [], [], []
    if pattern.kind == "gray":   # (axis, first boundary, period) of the pattern-pixel lines where it changes
        bounds = [(0 if pattern.axis == "col" else 1, 2 ** pattern.index, 2 ** (pattern.index + 1))]
        if pattern.xor >= 0:     # and where the column code's XOR base bit changes
            bounds.append((0, 2 ** pattern.xor, 2 ** (pattern.xor + 1)))
    else:
        size, shift = pattern.size, pattern.shift % (2 * pattern.size)
        bounds = [(0, shift % size, size), (1, 0, size)]
    rel_all = np.broadcast_to(origin - frame.position, dirs.shape)
    for start in range(0, keep.size, 8192):
        idx = keep[start:start + 8192]
        rel, d, a, b = rel_all[idx], dirs[idx], lo[idx], hi[idx]
        vf0, vr0, vu0 = rel @ frame.f, rel @ frame.r, rel @ frame.u
        df, dr, du = d @ frame.f, d @ frame.r, d @ frame.u
        # pattern coordinates at both ends; along a ray in front of the projector they are monotone,
        # so only the boundaries between the two ends can be crossed
        ends = []
        for x in (a, b):
            vf = np.maximum(vf0 + x * df, 1e-300)
            with np.errstate(over="ignore"):    # an end at the apex (vf → 0): clamp into the frustum's range
                ends.append((np.clip(frame.w / 2 + ((vr0 + x * dr) / vf) / frame.s, 0.0, frame.w),
                             np.clip(frame.h / 2 - ((vu0 + x * du) / vf) / frame.s, 0.0, frame.h)))
        cuts = [a[:, None], b[:, None]]
        for axis, off, size in bounds:
            lo_c = np.minimum(ends[0][axis], ends[1][axis])
            hi_c = np.maximum(ends[0][axis], ends[1][axis])
            k0 = np.ceil((lo_c - off) / size)
            k1 = np.floor((hi_c - off) / size)
            count = int(np.clip(k1 - k0 + 1, 0, None).max()) if idx.size else 0
            if count == 0:
                continue
            j = np.arange(count)[None, :]
            bound = off + (k0[:, None] + j) * size
            valid = j <= (k1 - k0)[:, None]
            if axis == 0:
                coef = (bound - frame.w / 2) * frame.s              # vr = coef·vf on a column boundary
                num, den = coef * vf0[:, None] - vr0[:, None], dr[:, None] - coef * df[:, None]
            else:
                coef = (frame.h / 2 - bound) * frame.s              # vu = coef·vf on a row boundary
                num, den = coef * vf0[:, None] - vu0[:, None], du[:, None] - coef * df[:, None]
            with np.errstate(divide="ignore", invalid="ignore"):
                xb = num / den
            cuts.append(np.where(valid & np.isfinite(xb), xb, b[:, None]))
        br = np.clip(np.concatenate(cuts, axis=1), a[:, None], b[:, None])
        br.sort(axis=1)
        s0, s1 = br[:, :-1], br[:, 1:]
        mid = 0.5 * (s0 + s1)
        pf = vf0[:, None] + mid * df[:, None]
        with np.errstate(divide="ignore", invalid="ignore"):
            col = frame.w / 2.0 + ((vr0[:, None] + mid * dr[:, None]) / pf) / frame.s
            row = frame.h / 2.0 - ((vu0[:, None] + mid * du[:, None]) / pf) / frame.s
        with np.errstate(invalid="ignore"):     # a mid-point at the apex (0/0) is not lit
            if pattern.kind == "gray":
                lit = gray_lit(pattern, col, row) & np.isfinite(col + row) & (s1 > s0)
            else:
                lit = ((np.floor((col - shift) / size) + np.floor(row / size)) % 2 == 0) & (s1 > s0)
        r_i, c_i = np.nonzero(lit)
        rays.append(idx[r_i])
        los.append(s0[r_i, c_i])
        his.append(s1[r_i, c_i])
    if not rays:
        return np.zeros(0, np.int64), np.zeros(0), np.zeros(0)
    return np.concatenate(rays), np.concatenate(los), np.concatenate(his)


def column_order(frame: PinholeFrame, coords) -> tuple[np.ndarray, np.ndarray]:
    """The points inside the projector's ``frame`` (given their
    :func:`~polarstripe.sim.geometry.projector_coords` ``coords``) sorted by pattern column: (their indices,
    their columns), for :func:`lit_in_columns`."""
    col, row, depth = coords
    inside = np.nonzero((depth > 0) & (row >= 0) & (row < frame.h) & (col >= 0) & (col < frame.w))[0]
    order = inside[np.argsort(col[inside], kind="stable")]
    return order, col[order]


def lit_in_columns(pattern: PatternSpec, width: int, order: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """Indices of the points a flood or stripe ``pattern`` lights, from their :func:`column_order`: those of
    :func:`pattern_lit`, found by bisection (a scan's frames share the order)."""
    index, col = order
    parts = [index[np.searchsorted(col, c0, "left"):np.searchsorted(col, c1, "left")]
             for c0, c1 in sheet_columns(pattern, width)]
    return parts[0] if len(parts) == 1 else np.concatenate(parts)


def pattern_lit(pattern: PatternSpec | None, frame, points: np.ndarray, coords=None) -> np.ndarray:
    """Which ``points`` (m, 3) the projector lights: inside its ``frame`` (a pinhole; None: everywhere, a
    point source) and, unless ``pattern`` is None, on a lit pixel of the stripe, checker or Gray pattern.
    ``coords``: the points' :func:`~polarstripe.sim.geometry.projector_coords` when already known (a scan's
    frames share them)."""
    if frame is None:
        return np.ones(points.shape[0], bool)
    col, row, depth = projector_coords(frame, points) if coords is None else coords
    ok = (depth > 0) & (row >= 0) & (row < frame.h) & (col >= 0) & (col < frame.w)
    if pattern is None:
        return ok
    if pattern.kind == "stripe":
        ok &= np.logical_or.reduce([(col >= c0) & (col < c1) for c0, c1 in sheet_columns(pattern, frame.w)])
    elif pattern.kind == "checker":
        shift = pattern.shift % (2 * pattern.size)
        ok &= (np.floor((col - shift) / pattern.size) + np.floor(row / pattern.size)) % 2 == 0
    elif pattern.kind == "gray":
        ok &= gray_lit(pattern, col, row)
    return ok
