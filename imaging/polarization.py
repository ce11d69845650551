"""Polarization descattering on frames: eqs. 4-6, partially polarized objects, Stokes, DoLP/AoLP, p.

Conventions: E_b is the frame through the analyzer crossed to the backscatter polarization (least
backscatter), E_w the co-polarized one. p is the backscatter's degree of polarization. Angles in degrees at
the boundary of :func:`least_backscatter_angle` and :func:`stokes`, radians for AoLP.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from polarstripe.imaging.validation import (
    ImagingError,
    as_stack,
    finite_array,
    finite_param,
    roi_slices,
    same_shape,
)


def _p_value(p, shape: tuple[int, ...]) -> np.ndarray | float:
    """Validate p: a scalar or an array broadcastable to ``shape``, finite, in (0, 1]."""
    if np.ndim(p) == 0:
        return finite_param("p", p, low=0.0, high=1.0, low_open=True)
    arr = finite_array("p", p)
    try:
        np.broadcast_shapes(arr.shape, shape)
    except ValueError:
        raise ImagingError(f"p: shape {arr.shape} does not broadcast to the frames' shape {shape}") from None
    if np.any(arr <= 0.0) or np.any(arr > 1.0):
        raise ImagingError(f"p: values must lie in (0, 1], got min {arr.min()} max {arr.max()}")
    return arr


def polarized_pair(signal, backscatter, p) -> tuple[np.ndarray, np.ndarray]:
    """Frames through the crossed and co-polarized analyzer (eqs. 4-5).

    E_b = S/2 + B(1 - p)/2,  E_w = S/2 + B(1 + p)/2.

    Parameters
    ----------
    signal, backscatter : array (h, w) or (n,)
        S = D + A and B (any radiance or DN units, before the analyzer).
    p : float or array
        Backscatter degree of polarization in [0, 1].

    Returns
    -------
    (E_b, E_w) : float64 arrays, same shape
    """
    s, b = finite_array("signal", signal), finite_array("backscatter", backscatter)
    same_shape(signal=s, backscatter=b)
    pp = finite_param("p", p, low=0.0, high=1.0) if np.ndim(p) == 0 else finite_array("p", p)
    return 0.5 * s + 0.5 * b * (1.0 - pp), 0.5 * s + 0.5 * b * (1.0 + pp)


def _pair(e_b, e_w):
    for name, e in (("e_b", e_b), ("e_w", e_w)):
        if np.asarray(e).dtype.kind not in "uif":
            raise ImagingError(f"{name}: dtype {np.asarray(e).dtype} is not a real numeric type")
        if np.size(e) == 0:
            raise ImagingError(f"{name}: empty array")
    same_shape(e_b=e_b, e_w=e_w)
    if isinstance(e_b, np.ma.MaskedArray) or isinstance(e_w, np.ma.MaskedArray):
        return np.ma.asarray(e_b).astype(np.float64), np.ma.asarray(e_w).astype(np.float64)
    return np.asarray(e_b, np.float64), np.asarray(e_w, np.float64)


def recover_signal(e_b, e_w, p, *, p_object: float = 0.0):
    """Estimate of the signal S from the two polarized frames (eq. 6 and its partially polarized form).

    Parameters
    ----------
    e_b, e_w : array (h, w) or (n,), or masked arrays
        Best- and worst-polarized frames, dark offset already subtracted. Masks (saturation) propagate.
    p : float or array
        Backscatter DOP in (0, 1] (clamp an estimate away from 0 first, see :func:`estimate_p`).
    p_object : float
        DOP of the object's own light, in [0, p); 0 (unpolarized, the paper's assumption) gives eq. 6.

    Returns
    -------
    float64 array (masked when an input was masked), same shape
        Ŝ = [E_b (p + 1) + E_w (p - 1)] / (p - p_object); with p_object = 0 this is eq. 6,
        Ŝ = E_b (1 + 1/p) + E_w (1 - 1/p).

    Notes
    -----
    Treibitz & Schechner (2009) give the p_object form; it amplifies noise without bound as p_object -> p,
    and independent per-frame noise σ grows to σ·sqrt(2(1 + 1/p²)) for p_object = 0 (see
    :func:`recovered_signal_variance`).
    """
    eb, ew = _pair(e_b, e_w)
    pp = _p_value(p, np.shape(eb))
    po = finite_param("p_object", p_object, low=0.0)
    if np.any(np.asarray(pp) <= po):
        raise ImagingError(f"p_object: {po} must be below p (min p = {np.min(pp)})")
    if po == 0.0:
        return eb * (1.0 + 1.0 / pp) + ew * (1.0 - 1.0 / pp)  # eq. 6
    return (ew * (pp - 1.0) + eb * (pp + 1.0)) / (pp - po)


def recover_backscatter(e_b, e_w, p, *, p_object: float = 0.0):
    """Estimate of the backscatter B: (E_w - E_b)/p, or [E_w(1 - p_obj) - E_b(1 + p_obj)]/(p - p_obj)."""
    eb, ew = _pair(e_b, e_w)
    pp = _p_value(p, np.shape(eb))
    po = finite_param("p_object", p_object, low=0.0)
    if np.any(np.asarray(pp) <= po):
        raise ImagingError(f"p_object: {po} must be below p (min p = {np.min(pp)})")
    return (ew * (1.0 - po) - eb * (1.0 + po)) / (pp - po)


def recovered_signal_variance(var_b, var_w, p, *, p_object: float = 0.0):
    """Variance of Ŝ for independent noise in E_b and E_w (docs/physics.md §4.2).

    Var Ŝ = [(p + 1)² Var E_b + (p - 1)² Var E_w] / (p - p_object)²; with equal variance σ² and p_object = 0
    the noise gain is σ_Ŝ/σ = sqrt(2 (1 + 1/p²)).
    """
    vb, vw = finite_array("var_b", var_b), finite_array("var_w", var_w)
    pp = _p_value(p, np.broadcast_shapes(vb.shape, vw.shape))
    po = finite_param("p_object", p_object, low=0.0)
    if np.any(np.asarray(pp) <= po):
        raise ImagingError(f"p_object: {po} must be below p (min p = {np.min(pp)})")
    return ((pp + 1.0) ** 2 * vb + (pp - 1.0) ** 2 * vw) / (pp - po) ** 2


def stokes(frames, angles_deg: Sequence[float], *, transmittances: tuple[float, float] = (1.0, 0.0)):
    """Linear Stokes parameters per pixel from frames at three or more analyzer angles (Malus's law).

    Least squares on I(θ) = ½(k1 + k2) S0 + ½(k1 - k2)(S1 cos 2θ + S2 sin 2θ).

    Parameters
    ----------
    frames : array (k, h, w) or sequence of k (h, w) arrays
        Frames through the analyzer, dark offset subtracted.
    angles_deg : sequence of k floats
        Analyzer angles in degrees; at least three distinct values modulo 180.
    transmittances : (k1, k2)
        Principal transmittances of the polarizer (ideal: 1, 0).

    Returns
    -------
    (S0, S1, S2) : float64 arrays (h, w)
    """
    stack = as_stack("frames", frames)
    ang = finite_array("angles_deg", angles_deg).ravel()
    if ang.size != stack.shape[0]:
        raise ImagingError(f"angles_deg: {ang.size} angles for {stack.shape[0]} frames")
    if np.unique(np.round(np.mod(ang, 180.0), 9)).size < 3:
        raise ImagingError(f"angles_deg: need at least three distinct angles modulo 180, got {list(ang)}")
    k1 = finite_param("transmittances[0]", transmittances[0], low=0.0)
    k2 = finite_param("transmittances[1]", transmittances[1], low=0.0)
    if k1 <= k2:
        raise ImagingError(f"transmittances: k1 = {k1} must exceed k2 = {k2}")
    th = np.deg2rad(ang) * 2.0
    a = np.column_stack([0.5 * (k1 + k2) * np.ones_like(th), 0.5 * (k1 - k2) * np.cos(th),
                         0.5 * (k1 - k2) * np.sin(th)])
    y = stack.reshape(stack.shape[0], -1).astype(np.float64)
    coef, *_ = np.linalg.lstsq(a, y, rcond=None)
    s0, s1, s2 = (c.reshape(stack.shape[1:]) for c in coef)
    return s0, s1, s2


def dolp(s0, s1, s2, *, noise_std: float | None = None) -> np.ndarray:
    """Degree of linear polarization sqrt(S1² + S2²)/S0 (0 where S0 <= 0), optionally debiased.

    With ``noise_std`` = σ, the per-frame noise of 4 equally spaced frames, the Rician bias is removed:
    DoLP² <- max(0, DoLP² - 2·(2σ²)/S0²) (docs/physics.md §4.3).
    """
    s0, s1, s2 = (np.asarray(x, np.float64) for x in (s0, s1, s2))
    same_shape(s0=s0, s1=s1, s2=s2)
    pol2 = s1 * s1 + s2 * s2
    if noise_std is not None:
        sig = finite_param("noise_std", noise_std, low=0.0)
        pol2 = np.maximum(0.0, pol2 - 4.0 * sig * sig)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.where(s0 > 0, np.sqrt(pol2) / np.where(s0 > 0, s0, 1.0), 0.0)
    return out


def aolp(s1, s2) -> np.ndarray:
    """Angle of linear polarization ½ atan2(S2, S1) in radians, in (-π/2, π/2]."""
    s1, s2 = np.asarray(s1, np.float64), np.asarray(s2, np.float64)
    same_shape(s1=s1, s2=s2)
    return 0.5 * np.arctan2(s2, s1)


def _usable(e_b, e_w, roi, dark_offset: float, saturation: float | None):
    """(E_b, E_w) offset subtracted (float, whole frames) and the mask of the region's pixels below
    ``saturation`` in both raw frames, for :func:`estimate_p` and :func:`p_bootstrap_std`."""
    eb_raw, ew_raw = np.asarray(e_b), np.asarray(e_w)
    for name, e in (("e_b", eb_raw), ("e_w", ew_raw)):
        if e.dtype.kind not in "uif" or e.ndim != 2 or e.size == 0:
            raise ImagingError(f"{name}: expected a non-empty 2-D numeric frame, got {e.dtype} {e.shape}")
    same_shape(e_b=eb_raw, e_w=ew_raw)
    use = np.zeros(eb_raw.shape, bool)
    use[roi_slices("roi", roi, eb_raw.shape)] = True
    off = finite_param("dark_offset", dark_offset)
    if saturation is not None:
        sat = finite_param("saturation", saturation)
        use &= (eb_raw < sat) & (ew_raw < sat)
    return eb_raw.astype(np.float64) - off, ew_raw.astype(np.float64) - off, use


def _object_free_pixels(e_b, e_w, roi, dark_offset: float, saturation: float | None):
    """(E_w − E_b, E_w + E_b) at the region's usable pixels (1-D, row-major): the ``median`` rule's."""
    eb, ew, use = _usable(e_b, e_w, roi, dark_offset, saturation)
    return (ew - eb)[use], (ew + eb)[use]


BLOCK_PX = 5
"""Side of the blocks :func:`estimate_p` reads the measured DOP in [pixels]."""
TOP_FRACTION = 0.2
"""The fraction of blocks, those of highest measured DOP, whose mean is p̂."""


def _block_dops(e_b, e_w, roi, dark_offset: float, saturation: float | None):
    """The measured DOP Σ(E_w − E_b) / Σ(E_w + E_b) of each ``BLOCK_PX``² block of the region (its pixels
    below ``saturation`` in both frames, offset subtracted; blocks with at least half the pixels the fullest
    block has, and light above the offset), each one's standard error, and the number of pixels used; for
    :func:`estimate_p` and :func:`p_bootstrap_std`."""
    eb, ew, use = _usable(e_b, e_w, roi, dark_offset, saturation)
    h, w = use.shape
    k = BLOCK_PX
    pad = ((0, -h % k), (0, -w % k))

    def block_sums(x):
        x = np.pad(np.where(use, x, 0.0), pad)
        return x.reshape(x.shape[0] // k, k, x.shape[1] // k, k).sum(axis=(1, 3)).ravel()

    d, t = ew - eb, ew + eb
    n, diff, total = block_sums(np.ones_like(eb)), block_sums(d), block_sums(t)
    if not n.any():
        return np.empty(0), np.empty(0), 0
    keep = (n >= 0.5 * n.max()) & (total > 0)
    if not keep.any():
        raise ImagingError("roi: no backscatter above the dark offset (E_w + E_b <= 0 in every block)")
    m = diff[keep] / total[keep]
    # the ratio's standard error from its pixels' residuals: Σ(d − m t)² / (Σt)² (delta method)
    resid = block_sums(d * d)[keep] - 2 * m * block_sums(d * t)[keep] + m * m * block_sums(t * t)[keep]
    return m, np.sqrt(np.maximum(resid, 0.0)) / total[keep], int(n.sum())


def _upper_mean(dops: np.ndarray) -> float:
    """The mean of the highest ``TOP_FRACTION`` of ``dops`` (at least one): :func:`estimate_p`'s ``upper``
    p̂ from its block DOPs."""
    dops = np.asarray(dops, np.float64).ravel()
    top = max(1, int(np.ceil(TOP_FRACTION * dops.size)))
    return float(np.mean(np.sort(dops)[-top:]))


RULES = ("median", "upper")


def estimate_p(e_b, e_w, roi=None, *, dark_offset: float = 0.0, saturation: float | None = None,
               p_min: float | None = 0.05, min_pixels: int = 1, rule: str = "median") -> float:
    """Backscatter DOP p from a region's analyzer pair, robust to noise, offset and saturation.

    ``median``: p̂ = median(E_w − E_b) / median(E_w + E_b) over the region's valid pixels, for an
    object-free region (S ≈ 0); ``upper``: the mean of the highest ``TOP_FRACTION`` of the region's block
    DOPs Σ(E_w − E_b) / Σ(E_w + E_b) (blocks of ``BLOCK_PX``² pixels), for a region with object light.
    Clipped to [p_min, 1].

    Parameters
    ----------
    e_b, e_w : array (h, w)
        Crossed and co-polarized frames (raw DN or radiance).
    roi : (row0, row1, col0, col1) or bool mask (h, w), optional
        The region; whole frame when None.
    dark_offset : float
        Black level subtracted from both frames first (an offset left in biases p̂ low).
    saturation : float, optional
        Pixels at or above this level in either frame are left out (E_w saturates first).
    p_min : float or None
        Lower clamp, in (0, 1]: eq. 6 divides by p. None: no clamp, a p̂ outside (0, 1] raises (a
        published estimate, planning/medium_fit.py).
    min_pixels : int
        The fewest valid pixels to estimate from.
    rule : ``median`` or ``upper`` (above).

    Returns
    -------
    float

    Raises
    ------
    ImagingError
        Bad input, fewer than ``min_pixels`` valid pixels, no backscatter above the offset, or (``p_min``
        None) p̂ outside (0, 1]; the text says which.

    Notes
    -----
    Where S = 0, eqs. 4–5 give E_w − E_b = p (E_w + E_b) at every pixel, so both rules are exact without
    noise even when B varies over the region; medians ignore outliers. Unpolarized object light S lowers
    the measured DOP to p·B/(B + S), so the ratio of medians reads low where the region has object light
    (the simulated tank's wall is lit everywhere by forward-scattered light: 0.32 where the backscatter's
    DOP is 0.48, docs/physics.md §4.2); the blocks of highest DOP are those with the least, so ``upper``
    reads closer (0.40), and about one block standard deviation high from noise. Eq. 6 with either
    over-subtracts there; the compositor divides by the medium model's p map instead (imaging/p_map.py,
    planning/medium_p.py) and keeps these as its ``median`` and ``upper`` rules.
    """
    if rule not in RULES:
        raise ImagingError(f"rule: {rule!r} is not one of {', '.join(RULES)}")
    pmin = None if p_min is None else finite_param("p_min", p_min, low=0.0, high=1.0, low_open=True)
    if rule == "upper":
        dops, _, used = _block_dops(e_b, e_w, roi, dark_offset, saturation)
    else:
        diff, total_px = _object_free_pixels(e_b, e_w, roi, dark_offset, saturation)
        used = diff.size
    if used == 0:
        raise ImagingError("roi: no unsaturated pixels left to estimate p from")
    if used < min_pixels:
        raise ImagingError(f"roi: only {used} unsaturated pixels to estimate p from (need {min_pixels})")
    if rule == "upper":
        p = _upper_mean(dops)
    else:
        total = float(np.median(total_px))
        if total <= 0.0:
            raise ImagingError(f"roi: no backscatter above the dark offset (median E_w + E_b = {total:.3g})")
        p = np.median(diff) / total
    if pmin is not None:
        return float(np.clip(p, pmin, 1.0))
    if not 0.0 < p <= 1.0:
        raise ImagingError(f"p = {p:.3g} from the analyzer pair is outside (0, 1]")
    return float(p)


def p_bootstrap_std(e_b, e_w, roi=None, *, dark_offset: float = 0.0, saturation: float | None = None,
                    n_boot: int = 200, seed: int = 0, rule: str = "median") -> float:
    """The spread (standard deviation) of :func:`estimate_p`'s unclamped estimate under the frames' noise
    (arguments as there; ``seed`` seeds the draws). ``median``: a bootstrap of the region's pixels.
    ``upper``: a parametric bootstrap: the blocks' DOPs shrunk toward their mean until their spread is
    what remains after their noise, then each redrawn with its own standard error (from its pixels'
    residuals); resampling blocks would understate the spread of a mean of the highest ones, and redrawing
    the noisy DOPs as they are would count the noise twice."""
    rng = np.random.default_rng(seed)
    if rule == "upper":
        dops, err, used = _block_dops(e_b, e_w, roi, dark_offset, saturation)
        if used == 0:
            raise ImagingError("roi: no unsaturated pixels left to estimate p from")
        # the blocks' true spread without their noise (shrunk toward the mean), then their noise redrawn
        spread = float(np.var(dops))
        shrink = math.sqrt(max(spread - float(np.mean(err ** 2)), 0.0) / spread) if spread > 0 else 0.0
        base = dops.mean() + shrink * (dops - dops.mean())
        draws = base + rng.standard_normal((n_boot, dops.size)) * err
        return float(np.std([_upper_mean(x) for x in draws]))
    diff, total = _object_free_pixels(e_b, e_w, roi, dark_offset, saturation)
    if diff.size == 0:
        raise ImagingError("roi: no unsaturated pixels left to estimate p from")
    idx = rng.integers(0, total.size, size=(n_boot, total.size))
    return float(np.std(np.median(diff[idx], axis=1) / np.median(total[idx], axis=1)))


def least_backscatter_angle(angles_deg: Sequence[float], frames, roi=None, *, dark_offset: float = 0.0,
                            saturation: float | None = None) -> float:
    """Analyzer angle (degrees, [0, 180)) that transmits the least backscatter over an object-free region.

    Fits Malus's law I(θ) = ½(S0 + S1 cos 2θ + S2 sin 2θ) to the region's mean intensity (pixels saturated
    in any frame left out) and returns the angle of its minimum, AoLP + 90°. Called by the polarizer's
    calibrate service. Raises when the region's light shows no measurable polarization.

    Parameters
    ----------
    angles_deg : sequence of k floats
        Analyzer angles, at least three distinct modulo 180.
    frames : array (k, h, w) or sequence of k (h, w) arrays
    roi : (row0, row1, col0, col1) or bool mask (h, w), optional
    dark_offset : float
        Black level subtracted first.
    saturation : float, optional
    """
    stack = as_stack("frames", frames)
    index = roi_slices("roi", roi, stack.shape[1:])
    off = finite_param("dark_offset", dark_offset)
    region = stack[(slice(None),) + (index if isinstance(index, tuple) else (index,))]
    region = region.reshape(stack.shape[0], -1).astype(np.float64)
    valid = np.ones(region.shape[1], bool)
    if saturation is not None:
        valid &= np.all(region < finite_param("saturation", saturation), axis=0)
    if not valid.any():
        raise ImagingError("roi: every pixel is saturated in some frame")
    means = region[:, valid].mean(axis=1) - off
    s0, s1, s2 = stokes(means.reshape(-1, 1, 1), angles_deg)
    s0, s1, s2 = float(s0[0, 0]), float(s1[0, 0]), float(s2[0, 0])
    if s0 <= 0.0 or np.hypot(s1, s2) <= 1e-6 * s0:
        raise ImagingError(f"frames: the region's light is unpolarized (S0 = {s0:.3g}, "
                           f"|S1, S2| = {np.hypot(s1, s2):.3g}); no least-backscatter angle")
    return float(np.mod(np.rad2deg(0.5 * np.arctan2(s2, s1)) + 90.0, 180.0))
