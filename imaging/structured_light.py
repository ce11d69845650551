"""Decoding the calibration's structured light: Gray and XOR codes, each pattern against its inverse
(docs/depth.md "Calibration in the murk").

A camera pixel's bit of a pattern pair is 1 where the pattern is brighter than its inverse: the threshold is
per pixel and per pattern, the inverse's own value, so the medium's light and the board's albedo, alike
under both, cancel (Gupta, Agrawal, Veeraraghavan & Narasimhan, CVPR 2011, §3). A pattern with an XOR base
(msgs/patterns.py ``gray:BIT:AXIS:INV:xorBASE``) has the base pair's bit XORed back. The bits of each axis
are a Gray code g; the projector pixel is its binary j (j = g XOR g >> 1 XOR g >> 2 …).

The code's contrast, |P − P̄| / (P + P̄) above the dark level, is the share of a pixel's light that carries
the code: in murky water most of the light has been scattered (forward, onto and from the board, and back from
the medium) and is alike under both patterns; what is left to decode is the direct light.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from polarstripe.msgs.patterns import PatternSpec, gray_bits, gray_code, xor_code

XOR_RUNS = 16  # the XOR base's stripes: 1/XOR_RUNS of the projector's width


def xor_base(width: int) -> int:
    """The XOR base bit of a ``width``-column projector: runs of 2^(base+1) columns, 1/``XOR_RUNS`` of the
    width (64 columns on 1024, 16 on 256). A finer base splits the coarse bits' runs unevenly, where the
    light blurred by forward scattering onto and from the board, wider than the runs, takes the sign of the
    longer neighbours (the default tank at σ_t = 5, a 1024-column projector: base runs of 16 columns left
    the projector corners 12 px RMS off, runs of 64 columns 0.05 px; docs/depth.md)."""
    return max(0, gray_bits(width) - int(np.log2(XOR_RUNS)) - 1)


def calibration_code(width: int, height: int) -> list[PatternSpec]:
    """The patterns a calibration shows after ``flood`` and ``off``: the XOR code of :func:`xor_base`
    (msgs/patterns.py :func:`~polarstripe.msgs.patterns.xor_code`), or plain Gray code for a projector too
    narrow for a base (fewer than 4 column bits)."""
    if gray_bits(width) < 4:
        return gray_code(width, height)
    return xor_code(width, height, xor_base(width))


@dataclass
class Decoded:
    """Per camera pixel: projector column ``col`` and row ``row`` (int64, the pattern pixel [j, j+1), i.e.
    OpenCV's projector coordinate j; −1 where ``valid`` is False), ``valid`` (lit: white − black above the
    threshold, and inside the pattern), and ``contrast`` (the median over the pattern pairs of
    |P − P̄| / (P + P̄ − 2·dark), NaN where not lit)."""

    col: np.ndarray
    row: np.ndarray
    valid: np.ndarray
    contrast: np.ndarray


def decode(frames, code: list[PatternSpec], proj_size: tuple[int, int], white: np.ndarray,
           black: np.ndarray, *, lit_threshold: float) -> Decoded:
    """Decode the frames of ``code`` (a pattern then its inverse, in the order of ``code``) per pixel.

    Parameters
    ----------
    frames : sequence of (h, w) arrays, one per pattern of ``code``.
    code : :func:`calibration_code`, :func:`~polarstripe.msgs.patterns.gray_code` or
        :func:`~polarstripe.msgs.patterns.xor_code` of ``proj_size``.
    white, black : the flood and off frames; a pixel is lit where white − black > ``lit_threshold`` [the
        frames' unit].
    """
    white = np.asarray(white, float)
    dark = np.asarray(black, float)
    bits: dict[tuple[str, int], np.ndarray] = {}
    xors: dict[tuple[str, int], int] = {}
    ratios = []
    for k in range(0, len(code), 2):
        p, q = np.asarray(frames[k], float), np.asarray(frames[k + 1], float)
        spec = code[k]
        bits[(spec.axis, spec.index)] = (p > q).astype(np.int64)
        xors[(spec.axis, spec.index)] = spec.xor
        with np.errstate(invalid="ignore", divide="ignore"):
            ratios.append(np.abs(p - q) / (p + q - 2.0 * dark))
    lit = white - dark > lit_threshold
    out = {}
    for axis, n in (("col", proj_size[0]), ("row", proj_size[1])):
        g = np.zeros(white.shape, np.int64)
        for bit in range(gray_bits(n)):
            b = bits[(axis, bit)]
            if xors[(axis, bit)] >= 0:
                b = b ^ bits[("col", xors[(axis, bit)])]
            g |= b << bit
        j, shift = g.copy(), g >> 1
        while shift.any():
            j ^= shift
            shift >>= 1
        out[axis] = j
        lit &= j < n
    contrast = np.where(lit, np.median(np.stack(ratios), axis=0), np.nan)
    return Decoded(np.where(lit, out["col"], -1), np.where(lit, out["row"], -1), lit, contrast)
