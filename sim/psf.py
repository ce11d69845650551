"""Forward-scatter blur: how the light scattered inside the forward cone spreads on its way.

Jaffe (1990) and McGlamery (1980) write the forward-scattered image as the direct image convolved with a
point-spread function g = e^{−cR}δ + (e^{−GR} − e^{−cR})·h: an unscattered core and a spread halo, G ≤ c an
effective attenuation. Here c = σ_t, G = σ̃_t of the similarity-scaled medium, so along an in-medium path of
length ℓ the quasi-direct light keeps the fraction e^{−n} sharp, n = f σ_s ℓ (the mean number of scatterings
inside the forward cone, Poisson), and spreads the rest. The halo h follows from small-angle multiple
scattering (Fermi–Eyges): k scatterings at uniform positions along the path, each turning the ray by an angle
θ_i drawn from the cone's part of the phase function, move its end sideways by Σ θ_i u_i ℓ (u_i uniform in
[0, 1]); given at least one scattering (E[k | k ≥ 1] = n/(1 − e^{−n})) the per-axis variance is

    v = ⟨θ²_x⟩ ℓ² n / (3 (1 − e^{−n})).

That halo is far from Gaussian — most scatterings happen near the end of the path and the cone's angles are
themselves peaked, so it is cusped with a long tail (for one scattering in the paper's medium the median
radius is 0.65 of the rms, a Gaussian's 1.18). :func:`halo_table` draws it once per phase function
(deterministic Monte Carlo of the model just stated) at a ladder of n and fits it, per n, as a mixture of
Gaussians of widths (0.08, 0.2, 0.5, 1.2, 2.5) × its rms. It applies twice: to the pattern projected on the
object (source → object: the stripe widens and its edges soften) and to the object's radiance on its way to
the camera (camera → object: by reciprocity the footprint of a pixel on the object).

Whole frames are blurred in the image (:func:`blur_image`: one ladder of Gaussian blurs √2 apart, each on an
image downsampled to about half its width, weighted per pixel); requested pixels use a radial stencil of the
same halo (:mod:`polarstripe.sim.psf_stencil`).
"""

from __future__ import annotations

import math
from functools import lru_cache
from typing import NamedTuple

import cv2
import numpy as np
from polarstripe.sim.phase import tthg_parameters

WIDTHS = np.array([0.08, 0.2, 0.5, 1.2, 2.5])      # mixture widths, in units of the halo's per-axis rms
N_LADDER = np.array([0.03, 0.1, 0.3, 0.7, 1.5, 3.0, 6.0, 12.0])
_LEVEL_STEP = math.sqrt(2.0)
_MIN_PX = 0.3           # narrower halos than this (in pixels) are left sharp
_SAMPLES = 60000


class HaloTable(NamedTuple):
    """Per n of :data:`N_LADDER`: the halo's per-axis rms in units of the path length ℓ (m,), and the
    mixture weights (m, len(WIDTHS)) of Gaussians of widths WIDTHS × rms (each row sums to 1)."""

    rms: np.ndarray
    weights: np.ndarray


def _cone_angles(model: str, g: float, cos_c: float, size: int, rng) -> np.ndarray:
    """Polar angles [rad] drawn from the phase function restricted to the cone μ > cos_c."""
    if model == "isotropic" or (model != "hg" and tthg_parameters(g)[2] == 0.0):
        return np.arccos(1 - rng.random(size) * (1 - cos_c))
    if model == "hg":
        parts = [(1.0, g)]
    else:
        gf, gb, alpha = tthg_parameters(g)
        parts = [(alpha, gf), (1 - alpha, -gb)]
    out = np.zeros(0)
    for _ in range(200):
        lobe = rng.random(4 * size) < parts[0][0]
        gg = np.where(lobe, parts[0][1], parts[-1][1])
        gg = np.clip(gg, -1 + 1e-6, 1 - 1e-6)
        xi = rng.random(4 * size)
        s = (1 - gg * gg) / (1 - gg + 2 * gg * xi)
        mu = np.where(np.abs(gg) < 1e-9, 1 - 2 * xi, (1 + gg * gg - s * s) / (2 * np.where(gg == 0, 1, gg)))
        out = np.concatenate([out, mu[mu > cos_c]])
        if out.size >= size:
            break
    if out.size < size:                    # a cone the lobes hardly reach: spread uniformly in it
        out = np.concatenate([out, 1 - rng.random(size - out.size) * (1 - cos_c)])
    return np.arccos(np.clip(out[:size], -1.0, 1.0))


@lru_cache(maxsize=64)
def halo_table(model: str, g: float, cos_c: float) -> HaloTable:
    """The forward-cone halo of a phase function (module docstring), fitted once (seeded, deterministic)."""
    from scipy.optimize import nnls

    rng = np.random.default_rng(20080623)
    theta = _cone_angles(model, float(g), float(cos_c), _SAMPLES * 4, rng)
    rms, weights = [], []
    for n in N_LADDER:
        k = rng.poisson(n, _SAMPLES * 3)
        k = k[k >= 1][:_SAMPLES]
        x = np.zeros(k.size)
        y = np.zeros(k.size)
        for j in range(int(k.max())):
            on = k > j
            th = theta[rng.integers(0, theta.size, k.size)]
            ph = rng.random(k.size) * 2 * np.pi
            u = rng.random(k.size)
            x += np.where(on, th * np.cos(ph) * u, 0.0)
            y += np.where(on, th * np.sin(ph) * u, 0.0)
        s = math.sqrt(max(0.5 * float((x * x + y * y).mean()), 1e-30))
        r = np.sort(np.hypot(x, y)) / s
        edges = r[np.linspace(0, r.size - 1, 48).astype(int)]
        cdf = np.linspace(0, 1, 48)
        basis = 1 - np.exp(-edges[:, None] ** 2 / (2 * WIDTHS[None, :] ** 2))
        w, _ = nnls(np.vstack([basis, 30 * np.ones(WIDTHS.size), 30 * WIDTHS ** 2]),
                    np.concatenate([cdf, [30.0, 30.0]]))
        rms.append(s)
        weights.append(w / max(w.sum(), 1e-12))
    return HaloTable(np.array(rms), np.array(weights))


def spread(table: HaloTable, f_sigma_s: float, ell: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(n, rms, weights) after in-medium paths ℓ [m]: cone scatterings n = f σ_s ℓ, the halo's per-axis rms
    [m] and its mixture weights (…, len(WIDTHS)), interpolated in log n on the table's ladder."""
    ell = np.asarray(ell, float)
    n = f_sigma_s * ell
    pos = np.interp(np.log(np.maximum(n, 1e-12)), np.log(N_LADDER), np.arange(N_LADDER.size))
    i0 = np.clip(np.floor(pos).astype(int), 0, N_LADDER.size - 2)
    t = np.clip(pos - i0, 0.0, 1.0)[..., None]
    w = (1 - t) * table.weights[i0] + t * table.weights[i0 + 1]
    rms = ((1 - t[..., 0]) * table.rms[i0] + t[..., 0] * table.rms[i0 + 1]) * ell
    return n, rms, w


def blur_image(img: np.ndarray, rms_px: np.ndarray, mix: np.ndarray, weight: np.ndarray,
               mask: np.ndarray | None = None, step: float = _LEVEL_STEP) -> np.ndarray:
    """Mixture blur of an (h, w) image: each pixel keeps (1 − weight) of its value sharp and spreads the rest
    with the halo of rms ``rms_px`` (pixels) and mixture weights ``mix`` (h, w, len(WIDTHS)).

    out = img·(1 − weight) + Σ_j mix_j·G_{c_j·rms} ⊛ (weight·img), the widths and weights those of the
    *receiving* pixel. The Gaussians come from one ladder of blurs ``step`` apart in width (each on an image
    downsampled to keep about 2 of its pixels per standard deviation, upsampled once), each pixel taking
    its components' widths by interpolation in log width. With ``mask`` (one object's pixels) the blur is
    normalised over the mask — the light that lands beyond the object's edge stands for the light that
    would arrive from beyond it — and only masked pixels receive.
    """
    img = np.asarray(img, float)
    spread_part = weight * img
    out = img - spread_part
    recv = np.ones(img.shape, bool) if mask is None else mask
    h, w = img.shape
    sig = rms_px[..., None] * WIDTHS                             # (h, w, J)
    sharp_w = np.where(sig < _MIN_PX, mix, 0.0).sum(-1)
    out[recv] += (sharp_w * spread_part)[recv]
    wide = recv[..., None] & (sig >= _MIN_PX) & (mix > 0)
    if not wide.any():
        return out
    s_lo, s_hi = float(sig[wide].min()), float(sig[wide].max())
    levels = [s_lo]
    while levels[-1] < s_hi * (1 - 1e-9):
        levels.append(levels[-1] * step)
    pos = np.log(np.clip(sig, s_lo, levels[-1]) / s_lo) / math.log(step)
    src = np.where(recv, spread_part, 0.0).astype(np.float32)
    m32 = None if mask is None else mask.astype(np.float32)
    rows, cols = np.nonzero(recv)
    pos_r, mix_r = pos[rows, cols], np.where(wide[rows, cols], mix[rows, cols], 0.0)
    acc = np.zeros(rows.size)
    for i, s in enumerate(levels):
        hat = np.clip(1.0 - np.abs(pos_r - i), 0.0, 1.0) if len(levels) > 1 else 1.0
        lw = (mix_r * hat).sum(-1)
        use = lw > 0
        if not use.any():
            continue
        acc[use] += lw[use] * _level(src, m32, s)[rows[use], cols[use]]
    out[rows, cols] += acc
    return out


def _level(src: np.ndarray, m32: np.ndarray | None, s: float) -> np.ndarray:
    """Gaussian blur of width s [px] (normalised over the mask when given), on a downsampled image."""
    h, w = src.shape
    down = 1
    while s / (2 * down) >= 2.0 and min(h, w) // (2 * down) >= 8:
        down *= 2
    size = (max(1, w // down), max(1, h // down))
    small = cv2.resize(src, size, interpolation=cv2.INTER_AREA) if down > 1 else src
    b = cv2.GaussianBlur(small, (0, 0), sigmaX=s / down, sigmaY=s / down, borderType=cv2.BORDER_CONSTANT)
    if m32 is not None:
        ms = cv2.resize(m32, size, interpolation=cv2.INTER_AREA) if down > 1 else m32
        nrm = cv2.GaussianBlur(ms, (0, 0), sigmaX=s / down, sigmaY=s / down, borderType=cv2.BORDER_CONSTANT)
        b = np.where(nrm > 1e-6, b / np.maximum(nrm, 1e-6), 0.0).astype(np.float32)
    return cv2.resize(b, (w, h), interpolation=cv2.INTER_LINEAR) if down > 1 else b


def radial_stencil(mix: np.ndarray, rings: int = 4, spokes: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """Offsets (k, 2) in units of the halo's per-axis rms and equal weights (k,) sampling the 2-D mixture
    ``mix`` (len(WIDTHS),): radii at the mid-quantiles of ``rings`` equal-probability rings, ``spokes``
    angles each (staggered from ring to ring)."""
    r = np.linspace(0, 12, 2400)
    cdf = (mix[None, :] * (1 - np.exp(-r[:, None] ** 2 / (2 * WIDTHS[None, :] ** 2)))).sum(1)
    cdf /= max(cdf[-1], 1e-12)
    radii = np.interp((np.arange(rings) + 0.5) / rings, cdf, r)
    pts = []
    for i, rr in enumerate(radii):
        a = (np.arange(spokes) + 0.5 * (i % 2)) * 2 * np.pi / spokes
        pts.append(np.stack([rr * np.cos(a), rr * np.sin(a)], 1))
    pts = np.concatenate(pts)
    return pts, np.full(pts.shape[0], 1.0 / pts.shape[0])
