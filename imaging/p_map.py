"""The p that eq. 6 divides by, and the medium's backscatter DOP beside it (docs/physics.md §4.2).

Eq. 6 removes the backscatter exactly where it divides by the DOP the analyzer pair sees at the pixel,
E_w − E_b = p_e(x)·B(x) with p_e = p(x)·cos 2(χ(x) − ψ) (p, χ the backscatter's DOP and angle, ψ the pair's
co-polarized angle). With one p̂ below p_e the backscatter is over-subtracted, Ŝ = S − B(p_e/p̂ − 1); above
it, under-subtracted. A :class:`PEstimate` carries both numbers a polarized composite needs: ``eq6``, a
scalar or a per-pixel map, and ``p``, the medium's backscatter DOP that the compositor publishes.

* :func:`global_p`: one p̂ from the frames (``median`` or ``upper`` rule of
  :func:`~.polarization.estimate_p`).
* :func:`regional_p_map`: a map from the frames alone, the ``upper`` p̂ of each tile of the region, shrunk
  toward the whole region's by its noise and interpolated between the tiles' centres. The frames alone
  read p_e·B/(S + B) (object light lowers the measured DOP), so this map is low where the region's light
  holds object light; the model's map (planning/medium_p.py) is not.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from polarstripe.imaging.polarization import RULES, estimate_p, p_bootstrap_std
from polarstripe.imaging.validation import ImagingError, finite_param, roi_slices

P_RULES = ("map", *RULES)
"""Eq. 6's p: ``map`` per pixel, ``median`` or ``upper`` one p̂ for the frame."""


@dataclass(frozen=True)
class PEstimate:
    """Eq. 6's p and the medium's DOP from one analyzer pair.

    Attributes
    ----------
    eq6 : float or numpy.ndarray (h, w)
        What eq. 6 divides by, in [p_min, 1]: one p̂, or per pixel p_e(x) = p(x)·cos 2(χ(x) − ψ).
    p : float
        The medium's backscatter DOP (the B-weighted mean over the region), published as the medium's p.
    p_std : float
        Its standard deviation under the frames' noise (NaN when unknown).
    source : str
        ``model`` (the medium's model, planning/medium_p.py), ``frames`` (:func:`regional_p_map`),
        ``median`` or ``upper`` (:func:`global_p`).
    note : str
        Why a better source was not used; "" when none was skipped.
    """

    eq6: float | np.ndarray
    p: float
    p_std: float = math.nan
    source: str = "median"
    note: str = ""

    def summary(self) -> dict:
        """The numbers the compositor's metrics carry: eq. 6's p (a map's median, 5th and 95th percentile)
        and the medium's."""
        out = {"p_source": self.source, "p_backscatter": self.p,
               "p_backscatter_std": None if math.isnan(self.p_std) else self.p_std}
        if np.ndim(self.eq6) == 0:
            out["p"] = float(self.eq6)
        else:
            lo, mid, hi = np.percentile(self.eq6, [5, 50, 95])
            out["p"], out["p_map_range"] = float(mid), [float(lo), float(hi)]
        if self.note:
            out["p_note"] = self.note
        return out


def global_p(e_b, e_w, region=None, *, dark_offset: float = 0.0, saturation: float | None = None,
             p_min: float = 0.05, rule: str = "median") -> PEstimate:
    """One p̂ for eq. 6 by ``rule`` (``median`` or ``upper``, :func:`~.polarization.estimate_p`) and, as the
    medium's p, the ``upper`` p̂ with its bootstrap spread (the blocks with the least object light).
    Arguments as :func:`~.polarization.estimate_p`'s; raises its ImagingError."""
    if rule not in RULES:
        raise ImagingError(f"rule: {rule!r} is not one of {', '.join(RULES)}")
    kw = dict(dark_offset=dark_offset, saturation=saturation)
    upper = estimate_p(e_b, e_w, region, p_min=p_min, rule="upper", **kw)
    eq6 = upper if rule == "upper" else estimate_p(e_b, e_w, region, p_min=p_min, rule=rule, **kw)
    return PEstimate(eq6, upper, p_bootstrap_std(e_b, e_w, region, rule="upper", **kw), rule)


def regional_p_map(e_b, e_w, region=None, *, dark_offset: float = 0.0, saturation: float | None = None,
                   p_min: float = 0.05, tiles: tuple[int, int] = (3, 4), min_pixels: int = 50,
                   seed: int = 0) -> PEstimate:
    """Eq. 6's p per pixel from the frames alone: the ``upper`` p̂ per tile, its noise accounted.

    Parameters
    ----------
    e_b, e_w : array (h, w)
        Crossed and co-polarized frames (raw DN).
    region : (row0, row1, col0, col1) or bool mask (h, w), optional
        The pixels p is read from (object-free where known); the whole frame when None.
    dark_offset, saturation, p_min
        As :func:`~.polarization.estimate_p`.
    tiles : (rows, cols)
        The frame is cut into this grid; each tile with at least ``min_pixels`` region pixels gets its own
        p̂_k and its bootstrap standard deviation s_k (:func:`~.polarization.p_bootstrap_std`).
    seed : int
        Seeds the bootstraps.

    Returns
    -------
    PEstimate
        ``eq6`` the map, ``p`` and ``p_std`` the whole region's ``upper`` p̂, ``source`` ``frames``.

    Notes
    -----
    Each tile's p̂_k is shrunk toward the region's p̂ by its noise (empirical Bayes):
    p̃_k = p̂ + w_k (p̂_k − p̂), w_k = τ² / (τ² + s_k²), τ² = max(0, var_k p̂_k − mean_k s_k²) the tiles' spread
    beyond their noise; a tile without enough pixels takes p̂. The tiles' values are then interpolated
    bilinearly between their centres (constant beyond the outer ones) and clamped to [p_min, 1], so the map
    is smooth and its noise no larger than a tile's: where the frames cannot tell the tiles apart the map is
    the one p̂, and Ŝ's noise does not grow beyond the global rule's.
    """
    pmin = finite_param("p_min", p_min, low=0.0, high=1.0, low_open=True)
    rows, cols = (int(t) for t in tiles)
    if rows < 1 or cols < 1:
        raise ImagingError(f"tiles: need at least 1 x 1, got {tiles}")
    shape = np.shape(e_b)
    if len(shape) != 2:
        raise ImagingError(f"e_b: expected a 2-D frame, got shape {shape}")
    mask = np.zeros(shape, bool)
    mask[roi_slices("region", region, shape)] = True
    kw = dict(dark_offset=dark_offset, saturation=saturation)
    whole = global_p(e_b, e_w, mask, p_min=pmin, rule="upper", **kw)
    r_edges = np.linspace(0, shape[0], rows + 1).astype(int)
    c_edges = np.linspace(0, shape[1], cols + 1).astype(int)
    vals, stds = np.full((rows, cols), np.nan), np.full((rows, cols), np.nan)
    for i in range(rows):
        for j in range(cols):
            tile = np.zeros(shape, bool)
            tile[r_edges[i]:r_edges[i + 1], c_edges[j]:c_edges[j + 1]] = True
            tile &= mask
            if tile.sum() < min_pixels:
                continue
            try:
                vals[i, j] = estimate_p(e_b, e_w, tile, p_min=None, rule="upper", **kw)
                stds[i, j] = p_bootstrap_std(e_b, e_w, tile, rule="upper", seed=seed, **kw)
            except ImagingError:
                vals[i, j] = np.nan
    have = np.isfinite(vals) & np.isfinite(stds)
    grid = np.full((rows, cols), whole.p)
    if have.any():
        spread = float(np.var(vals[have])) if have.sum() > 1 else 0.0
        tau2 = max(0.0, spread - float(np.mean(stds[have] ** 2)))
        w = tau2 / (tau2 + stds[have] ** 2) if tau2 > 0 else np.zeros(int(have.sum()))
        grid[have] = whole.p + w * (vals[have] - whole.p)
    # bilinear between tile centres: cv2's resize maps pixel centres, so the tiles' centres land on theirs
    # (for tiles of equal size; the edges' rounding moves them by under a pixel)
    smooth = cv2.resize(grid.astype(np.float64), (shape[1], shape[0]), interpolation=cv2.INTER_LINEAR)
    return PEstimate(np.clip(smooth, pmin, 1.0), whole.p, whole.p_std, "frames")
