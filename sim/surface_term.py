"""The surface term A from the source side: integrate over the lit projector pixels, then along each beam.

For a pinhole projector the lit volume is a union of beams from L. With X = L + t·k, dV = t² dt dΩ_k cancels
the 1/d_LX² of eq. 12, so (physical form; docs/physics.md §0, §2.4)

    A(O) = (ρ/π) e^{−σ_t ℓ_CO} ∫_lit dΩ_k ∫ σ_s P(α) I0 e^{−σ_t (ℓ_LX + ℓ_XO)} max(0, n·(X − O))/d_XO³ dt

The inner integral is the eq. 13 line integral with O in the role of the source (ξ-substitution about O's foot
on the beam, :func:`transport.line_radiance` with ``facing``). The outer domain is a rectangle in pattern
pixels (the flood frame or one stripe), where the integrand is smooth except for a 1/r peak at O's own pattern
pixel: the rectangle is split at that point (clamped into it) into four, each into two triangles, and each
triangle gets the Duffy map (u, v) → p + u(a − p) + uv(b − a) whose Jacobian u cancels the 1/r, graded
u = s² toward p (a peak just outside the stripe), then Gauss–Legendre in s and v. The source radius r_s is
not applied to A (the point source's 1/r peak is integrable). Unlike the hemisphere rule it has no kinks at
the stripe's edges.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import numpy as np
from numba import njit
from polarstripe.sim.geometry import box_interval, intersect, segment_length_in_box
from polarstripe.sim.patterns import stripe_columns
from polarstripe.sim.transport import Source, gauss_legendre, line_radiance

_GRADE = 2
# forward-lobe splits of A's beams at 5–8 ξ nodes (standard): the pattern-pixel rule's error dominates there
_SPLITS_FEW = (1.0, 4.0)
_CUTS = (0.0, 1.0, 4.0, 16.0)   # side cuts from the foot of p, in units of p's distance


class TriangleRule(NamedTuple):
    """Side cuts (in units of the apex's distance) and the graded Duffy rule's nodes (u, v) and weights w."""

    cuts: np.ndarray
    u: np.ndarray
    v: np.ndarray
    w: np.ndarray


class BeamNodes(NamedTuple):
    """Per point (m, k): the nodes' pattern column, row and solid-angle weight [sr]."""

    col: np.ndarray
    row: np.ndarray
    weight: np.ndarray


def _rect(src: Source) -> tuple[float, float, float, float]:
    fr = src.frame
    if src.pattern.kind == "stripe":
        c0, c1 = stripe_columns(src.pattern, fr.w)
        return float(c0), float(c1), 0.0, float(fr.h)
    return 0.0, float(fr.w), 0.0, float(fr.h)


def beam_nodes(src: Source, points: np.ndarray, n_side: int):
    """Pattern-pixel nodes and solid-angle weights per surface point: (m, k) col, row, weight [sr].

    The rectangle is cut into triangles (p, a, b) with apex at the point's own pattern pixel p (clamped into
    the rectangle) and bases on the rectangle's sides; each side is cut, from the foot of p outward, at
    distances δ·(1, 4, 16) (δ: the side's distance from p), so every triangle but the last of a side
    is about as wide as it is far from p and the 1/r peak is resolved near a stripe edge too. Sides through p
    weigh nothing (det = 0) and are dropped by the caller.
    """
    fr = src.frame
    c_lo, c_hi, r_lo, r_hi = _rect(src)
    v = points - fr.position
    vf, vr, vu = v @ fr.f, v @ fr.r, v @ fr.u
    with np.errstate(divide="ignore", invalid="ignore"):
        col = np.where(vf > 0, fr.w / 2 + (vr / vf) / fr.s, 0.5 * (c_lo + c_hi))
        row = np.where(vf > 0, fr.h / 2 - (vu / vf) / fr.s, 0.5 * (r_lo + r_hi))
    pc, pr = np.clip(col, c_lo, c_hi), np.clip(row, r_lo, r_hi)
    t, w = gauss_legendre(n_side)
    uu, ww = 0.5 * (t + 1), 0.5 * w
    U, V = np.meshgrid(uu, uu, indexing="ij")
    W = np.outer(ww, ww) * _GRADE * U ** (2 * _GRADE - 1)      # u = s^q (grading) times the Duffy Jacobian u
    U = U ** _GRADE
    k = 8 * len(_CUTS) * n_side * n_side
    out = BeamNodes(*(np.empty((pc.size, k)) for _ in range(3)))
    _beam_nodes_kernel(np.ascontiguousarray(pc, float), np.ascontiguousarray(pr, float),
                       (float(c_lo), float(c_hi), float(r_lo), float(r_hi)),
                       TriangleRule(np.array(_CUTS), U.ravel(), V.ravel(), W.ravel()),
                       (float(fr.w), float(fr.h), float(fr.s)), out)
    return out


@njit(cache=True, nogil=True)
def _beam_nodes_kernel(pc, pr, rect, rule, pattern, out):
    """The triangles of :func:`beam_nodes`, side by side (left, right, top, bottom; up then down each):
    apexes (pc, pr), the rectangle (c_lo, c_hi, r_lo, r_hi), a :class:`TriangleRule`, the pattern's
    (width, height, pitch), the nodes into ``out`` (:class:`BeamNodes`)."""
    c_lo, c_hi, r_lo, r_hi = rect
    cuts, uu, vv, ww = rule
    fw, fh, fs = pattern
    cols, rows, wts = out
    tol = 1e-9 * max(c_hi - c_lo, r_hi - r_lo)
    nk = cuts.size
    for m in range(pc.size):
        px, py = pc[m], pr[m]
        q = 0
        for side in range(4):
            vertical = side < 2
            fixed = (c_lo, c_hi, r_lo, r_hi)[side]
            dist = abs((px if vertical else py) - fixed)
            foot = py if vertical else px
            lo_e, hi_e = (r_lo, r_hi) if vertical else (c_lo, c_hi)
            for half in range(2):
                sign, end = (1.0, hi_e) if half == 0 else (-1.0, lo_e)
                reach = abs(end - foot)
                for j in range(nk):
                    e0 = min(dist * cuts[j], reach)
                    e1 = min(dist * cuts[j + 1], reach) if j + 1 < nk else reach
                    s0, s1 = foot + sign * e0, foot + sign * e1
                    if vertical:
                        ac, ar, bc, br = fixed, s0, fixed, s1
                    else:
                        ac, ar, bc, br = s0, fixed, s1, fixed
                    det = abs((ac - px) * (br - ar) - (ar - py) * (bc - ac)) if dist > tol else 0.0
                    for i in range(uu.size):
                        cc = px + uu[i] * (ac - px) + (uu[i] * vv[i]) * (bc - ac)
                        rr = py + uu[i] * (ar - py) + (uu[i] * vv[i]) * (br - ar)
                        a = (cc - fw / 2) * fs
                        b = (rr - fh / 2) * fs
                        cols[m, q], rows[m, q] = cc, rr
                        wts[m, q] = ww[i] * det * fs * fs * (1 + a * a + b * b) ** -1.5
                        q += 1


def surface_scatter_beams(src: Source, objects, camera_pos: np.ndarray, points: np.ndarray,
                          normals: np.ndarray, albedo: np.ndarray, nodes: int, n_side: int) -> np.ndarray:
    """A at surface points (m, 3) lit by a pinhole projector with a flood or stripe pattern.

    Returns (m,) radiance [W sr⁻¹ m⁻²] toward the camera, before the analyzer (paper eq. 12, physical form).
    """
    m = points.shape[0]
    out = np.zeros(m)
    if m == 0 or src.sigma_s <= 0.0 or src.intensity <= 0.0:
        return out
    fr = src.frame
    k = 8 * len(_CUTS) * n_side * n_side
    per = max(1, 200000 // k)
    for s in range(0, m, per):
        sl = slice(s, s + per)
        pts, nrm = points[sl], normals[sl]
        cols, rows, wts = beam_nodes(src, pts, n_side)
        owner, node = np.nonzero(wts > 0)                     # degenerate triangles weigh nothing
        cols, rows, wts = cols[owner, node], rows[owner, node], wts[owner, node]
        dirs = (fr.f[None, :] + ((cols - fr.w / 2) * fr.s)[:, None] * fr.r
                - ((rows - fr.h / 2) * fr.s)[:, None] * fr.u)
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        t0, t1 = box_interval(fr.position, dirs, src.box_lo, src.box_hi)
        t1 = np.minimum(t1, intersect(objects, fr.position, dirs).t)
        o, n = pts[owner], nrm[owner]
        a = ((fr.position - o) * n).sum(1)                    # n·(L + t k − O) = a + b t ≥ 0
        b = (dirs * n).sum(1)
        with np.errstate(divide="ignore", invalid="ignore"):
            root = -a / b
        t0 = np.where(b > 0, np.maximum(t0, root), t0)
        t1 = np.where(b < 0, np.minimum(t1, root), np.where((b == 0) & (a < 0), -np.inf, t1))
        ray = np.nonzero(t1 > t0)[0]
        beam_src = dataclasses.replace(src, position=o, radius=0.0, inside=True)
        val = line_radiance(beam_src, fr.position, dirs, t0, (ray, t0[ray], t1[ray]), nodes, facing=n,
                            splits=_SPLITS_FEW if 5 <= nodes <= 8 else (0.3, 1.0, 3.0, 9.0))
        out[sl] = np.bincount(owner, val * wts, minlength=pts.shape[0])
    view = src.sigma_t * segment_length_in_box(camera_pos, points, src.box_lo, src.box_hi)
    with np.errstate(under="ignore"):
        return albedo / np.pi * np.exp(-view) * out
