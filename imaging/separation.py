"""High-frequency direct/global separation (Nayar, Krishnan, Grossberg & Raskar 2006), any lit fraction and
projector black level.

In a scattering medium "direct" is D and "global" is A + B (the paper's eq. 3), so the direct image carries
only D, which falls quickly with optical thickness (the paper's Fig. 5).
"""

from __future__ import annotations

import numpy as np
from polarstripe.imaging.validation import ImagingError, as_stack, finite_param, same_shape


def separate_direct_global(l_max, l_min, *, lit_fraction: float = 0.5, black_level: float = 0.0,
                           clip: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Direct and global images from the per-pixel max and min over shifted high-frequency patterns.

    Parameters
    ----------
    l_max, l_min : array (h, w)
        L⁺ = max and L⁻ = min over the shifted patterns (dark offset subtracted). Masked arrays propagate.
    lit_fraction : float
        α, the fraction of projector pixels lit, in (0, 1).
    black_level : float
        b, the brightness of an "off" projector pixel relative to "on", in [0, 1).
    clip : bool
        Where noise makes L_g < 0, set L_g = 0 and L_d = L⁺ (the usual fallback); also L_d >= 0.

    Returns
    -------
    (direct, global) : float64 arrays (h, w)

    Notes
    -----
    L⁺ = L_d + α L_g + b(1 - α) L_g and L⁻ = b L_d + (1 - α) L_g + α b L_g, solved:
    L_g = (L⁻ - b L⁺) / ((1 - α)(1 - b²)),
    L_d = [(1 - α + α b) L⁺ - (α + b - α b) L⁻] / ((1 - α)(1 - b²)).
    α = ½, b = 0 gives L_d = L⁺ - L⁻, L_g = 2 L⁻.
    """
    for name, v in (("l_max", l_max), ("l_min", l_min)):
        if np.asarray(v).dtype.kind not in "uif" or np.size(v) == 0:
            raise ImagingError(f"{name}: expected a non-empty numeric image, got {np.asarray(v).dtype} "
                               f"{np.shape(v)}")
    same_shape(l_max=l_max, l_min=l_min)
    a = finite_param("lit_fraction", lit_fraction, low=0.0, high=1.0, low_open=True, high_open=True)
    b = finite_param("black_level", black_level, low=0.0, high=1.0, high_open=True)
    masked = isinstance(l_max, np.ma.MaskedArray) or isinstance(l_min, np.ma.MaskedArray)
    lp = np.ma.asarray(l_max).astype(np.float64) if masked else np.asarray(l_max, np.float64)
    lm = np.ma.asarray(l_min).astype(np.float64) if masked else np.asarray(l_min, np.float64)
    den = (1.0 - a) * (1.0 - b * b)
    glob = (lm - b * lp) / den
    direct = ((1.0 - a + a * b) * lp - (a + b - a * b) * lm) / den
    if clip:
        neg = glob < 0
        direct = np.where(neg, lp, np.maximum(direct, 0.0))
        glob = np.where(neg, 0.0, glob)
        if masked:
            mask = np.ma.getmaskarray(lp) | np.ma.getmaskarray(lm)
            direct, glob = np.ma.MaskedArray(direct, mask), np.ma.MaskedArray(glob, mask)
    return direct, glob


def separate_stack(frames, *, lit_fraction: float = 0.5, black_level: float = 0.0,
                   saturation: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Direct and global images from a stack of frames under shifted patterns (max/min, then
    :func:`separate_direct_global`). Pixels saturated in any frame are masked."""
    stack = as_stack("frames", frames)
    l_max, l_min = stack.max(axis=0), stack.min(axis=0)
    if saturation is not None:
        mask = l_max >= finite_param("saturation", saturation)
        l_max, l_min = np.ma.MaskedArray(l_max, mask), np.ma.MaskedArray(l_min, mask)
    return separate_direct_global(l_max, l_min, lit_fraction=lit_fraction, black_level=black_level)
