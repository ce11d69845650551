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

Whole frames are blurred in the image (:func:`blur_image`: the mixture's Gaussians at the object's smallest
and largest halo width, interpolated per pixel, each on an image downsampled to about two pixels per standard
deviation); requested pixels use a radial stencil of the same halo (:mod:`polarstripe.sim.psf_stencil`).
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
_MIN_PX = 0.3           # narrower halos than this (in pixels) are left sharp
_LEVEL_RATIO = 1.4      # whole frames: the halo at rms levels this far apart, interpolated in log rms
_SAMPLES = 60000
_LOG_LADDER = np.log(N_LADDER)


class HaloTable(NamedTuple):
    """Per n of :data:`N_LADDER`: the halo's per-axis rms in units of the path length ℓ (m,), and the
    mixture weights (m, len(WIDTHS)) of Gaussians of widths WIDTHS × rms (each row sums to 1)."""

    rms: np.ndarray
    weights: np.ndarray


def _hg_cdf(mu, g):
    """P(μ' < μ) of HG(g) (|g| ≥ 1e-9)."""
    return (1 - g * g) / (2 * g) * (1 / np.sqrt(1 + g * g - 2 * g * mu) - 1 / (1 + g))


def _hg_cone(g: float, cos_c: float, size: int, rng) -> np.ndarray:
    """μ drawn from HG(g) restricted to μ > cos_c, by inverting the closed-form CDF."""
    if abs(g) < 1e-9:
        return 1 - rng.random(size) * (1 - cos_c)
    lo = float(_hg_cdf(cos_c, g))
    u = lo + rng.random(size) * (1 - lo)
    q = u * 2 * g / (1 - g * g) + 1 / (1 + g)
    return np.clip((1 + g * g - 1 / (q * q)) / (2 * g), cos_c, 1.0)


def _cone_angles(model: str, g: float, cos_c: float, size: int, rng) -> np.ndarray:
    """Polar angles [rad] drawn from the phase function restricted to the cone μ > cos_c (each HG lobe by
    its closed-form inverse CDF, the lobes in proportion to their mass inside the cone)."""
    if model == "isotropic" or (model != "hg" and tthg_parameters(g)[2] == 0.0):
        return np.arccos(1 - rng.random(size) * (1 - cos_c))
    if model == "hg":
        lobes = [(1.0, g)]
    else:
        gf, gb, alpha = tthg_parameters(g)
        lobes = [(alpha, gf), (1 - alpha, -gb)]
    lobes = [(w, min(max(gg, -1 + 1e-6), 1 - 1e-6)) for w, gg in lobes]
    mass = np.array([w * (1 - float(_hg_cdf(cos_c, gg))) if abs(gg) >= 1e-9 else w * (1 - cos_c) / 2
                     for w, gg in lobes])
    if mass.sum() <= 0:
        return np.arccos(1 - rng.random(size) * (1 - cos_c))
    pick = rng.random(size) < mass[0] / mass.sum()
    mu = np.where(pick, _hg_cone(lobes[0][1], cos_c, size, rng), _hg_cone(lobes[-1][1], cos_c, size, rng))
    return np.arccos(np.clip(mu, -1.0, 1.0))


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


def spread(table: HaloTable, f_sigma_s: float, ell: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(n, rms) after in-medium paths ℓ [m]: cone scatterings n = f σ_s ℓ and the halo's per-axis rms [m]
    (interpolated in log n on the table's ladder; :func:`mixture` gives its mixture weights)."""
    ell = np.asarray(ell, float)
    n = f_sigma_s * ell
    pos = np.interp(np.log(np.maximum(n, 1e-12)), _LOG_LADDER, np.arange(N_LADDER.size))
    return n, np.interp(pos, np.arange(N_LADDER.size), table.rms) * ell


def mixture(table: HaloTable, n: float) -> np.ndarray:
    """The halo's mixture weights (len(WIDTHS),) after n cone scatterings."""
    pos = float(np.interp(math.log(max(n, 1e-12)), _LOG_LADDER, np.arange(N_LADDER.size)))
    i0 = min(int(pos), N_LADDER.size - 2)
    t = min(max(pos - i0, 0.0), 1.0)
    return (1 - t) * table.weights[i0] + t * table.weights[i0 + 1]


def blur_levels(rms_px: np.ndarray, mask: np.ndarray | None = None) -> tuple:
    """The rms levels at which :func:`blur_image` blurs, from the receiving pixels' rms [px] (``mask``: one
    object's pixels, else all): ((rms, None),) when the smallest and largest are at most 1.4× apart, else
    ((rms_i, hat_i), …), rms_i spaced evenly in log rms from the smallest to the largest and hat_i (float32
    (h, w)) each pixel's weight of level i (linear in log rms; levels no pixel weighs are left out). They
    depend on the rms and the mask alone, so a scan's frames share them. () when no pixel receives."""
    recv = np.ones(rms_px.shape, bool) if mask is None else mask
    if not recv.any():
        return ()
    r = rms_px[recv]
    r_lo, r_hi = float(r.min()), float(r.max())
    if r_hi <= _LEVEL_RATIO * r_lo:
        return ((math.sqrt(r_lo * r_hi), None),)
    count = int(math.ceil(math.log(r_hi / r_lo) / math.log(_LEVEL_RATIO))) + 1
    pos = np.clip(np.log(np.maximum(rms_px, r_lo) / r_lo) / math.log(r_hi / r_lo) * (count - 1), 0,
                  count - 1).astype(np.float32)
    levels = []
    for i in range(count):
        hat = np.clip(1.0 - np.abs(pos - i), 0.0, 1.0)
        if hat.any():
            levels.append((r_lo * (r_hi / r_lo) ** (i / (count - 1)), hat))
    return tuple(levels)


def blur_image(spread_part: np.ndarray, rms_px: np.ndarray, mix: np.ndarray,
               mask: np.ndarray | None = None, norms: dict | None = None,
               levels: tuple | None = None) -> np.ndarray:
    """The halo of an (h, w) image's spread part: Σ_j mix_j·G_{c_j·rms} ⊛ spread_part (float32 (h, w)).

    ``spread_part`` is what each pixel spreads (weight·image, 0 where nothing is spread), ``rms_px`` the
    halo's per-axis rms [pixels] of each *receiving* pixel, ``mix`` the mixture weights. The halo is blurred
    at rms levels at most 1.4× apart from the smallest to the largest rms of the receiving pixels and each
    pixel interpolates between the two around its own in log rms (:func:`blur_levels`; ``levels``: those
    of this ``rms_px`` and ``mask``, made before); each Gaussian runs on an image downsampled
    to about two pixels per standard deviation, the components summed coarse to fine; the frame's edges
    reflect (the scene goes on beyond them). With ``mask`` (one object's pixels) every Gaussian is normalised
    over the mask — the light that lands beyond the object's edge stands for the light that would arrive from
    beyond it — and the halo is returned on the mask only. ``norms``: a dict that keeps those normalisations
    (the mask's blurs) for the next call with the same mask, as a scan's frames have it.
    """
    src = np.asarray(spread_part, np.float32)
    if mask is not None:
        src = np.where(mask, src, np.float32(0.0))          # only the object's own light
    if levels is None:
        levels = blur_levels(rms_px, mask)
    if not levels:
        return np.zeros(src.shape, np.float32)
    m32 = None if mask is None else mask.astype(np.float32)
    pyramid: dict = {}
    if norms is not None:
        pyramid["norms"] = norms
    if levels[0][1] is None:
        out = _halo(src, m32, levels[0][0], mix, pyramid)
    else:
        out = np.zeros(src.shape, np.float32)
        for rms, hat in levels:
            out += hat * _halo(src, m32, rms, mix, pyramid)
    return out if mask is None else np.where(mask, out, np.float32(0.0))


def _down(pyramid: dict, key: str, img: np.ndarray, down: int) -> np.ndarray:
    """``img`` downsampled by ``down`` (area average), cached per (key, down): from the level of half its
    ``down`` when that is exactly twice its size (the same average), else from ``img``."""
    if down == 1:
        return img
    if (key, down) not in pyramid:
        h, w = img.shape
        size = (max(1, w // down), max(1, h // down))
        finer = _down(pyramid, key, img, down // 2) if down % 2 == 0 else img
        if finer.shape != (2 * size[1], 2 * size[0]):
            finer = img
        pyramid[key, down] = cv2.resize(finer, size, interpolation=cv2.INTER_AREA)
    return pyramid[key, down]


def _mask_norm(pyramid: dict, m32: np.ndarray, s: float, down: int) -> np.ndarray:
    """max(G_s ⊛ mask, 1e-6) on the image downsampled by ``down`` (kept in ``pyramid["norms"]`` if given)."""
    keep = pyramid.get("norms")
    key = (float(s), down)
    if keep is not None and key in keep:
        return keep[key]
    m_small = _down(pyramid, "mask", m32, down)
    nrm = np.maximum(cv2.GaussianBlur(m_small, (0, 0), sigmaX=s / down, sigmaY=s / down,
                                      borderType=cv2.BORDER_CONSTANT), 1e-6)
    if keep is not None:
        keep[key] = nrm
    return nrm


def _halo(src: np.ndarray, m32: np.ndarray | None, rms: float, mix: np.ndarray, pyramid: dict) -> np.ndarray:
    """Σ_j mix_j G_{c_j·rms} ⊛ src, each Gaussian normalised over the mask when given, widest first."""
    h, w = src.shape
    acc, acc_size, sharp = None, None, 0.0
    for c, m in sorted(zip(WIDTHS.tolist(), mix.tolist(), strict=True), reverse=True):   # floats keep float32
        s = c * rms
        if m <= 0:
            continue
        if s < _MIN_PX:
            sharp += m
            continue
        down = 1
        while s / (2 * down) >= 2.0 and min(h, w) // (2 * down) >= 8:
            down *= 2
        small = _down(pyramid, "src", src, down)
        border = cv2.BORDER_CONSTANT if m32 is not None else cv2.BORDER_REFLECT
        b = cv2.GaussianBlur(small, (0, 0), sigmaX=s / down, sigmaY=s / down, borderType=border)
        if m32 is not None:
            b = b / _mask_norm(pyramid, m32, s, down)
        size = (b.shape[1], b.shape[0])
        if acc is None:
            acc, acc_size = m * b, size
        else:
            if acc_size != size:
                acc = cv2.resize(acc, size, interpolation=cv2.INTER_LINEAR)
                acc_size = size
            acc += m * b
    if acc is None:
        return (sharp * src).astype(np.float32)
    if acc_size != (w, h):
        acc = cv2.resize(acc, (w, h), interpolation=cv2.INTER_LINEAR)
    return acc + sharp * src if sharp else acc


def radial_stencil(mix: np.ndarray, rings: int = 8, spokes: int = 12) -> tuple[np.ndarray, np.ndarray]:
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
