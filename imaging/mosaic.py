"""Frames of a polarization camera (2×2 micro-polarizer mosaic): demosaicing, linear Stokes per pixel, and
the frames eqs. 4–6 need, E_b and E_w, from one exposure (docs/physics.md §4.4).

Demosaicing (bilinear) and the Stokes solve are polanalyser's (``demosaicing``, ``calcStokes``). The
analyzer of each pixel class is the sensor's, extinction ratio and crosstalk included (sim/mosaic.py), so
the Stokes are those of the light, not of the filters.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
import polanalyser as pa
from polarstripe.imaging.validation import ImagingError, as_image, finite_param
from polarstripe.sim.mosaic import SONY_EXTINCTION_RATIO, SONY_LAYOUT, check_layout

#: what a derived pixel is set to where a raw pixel it was made from is saturated (≥ this counts as saturated)
SATURATED = 1e30
#: E_b/E_w rules: the angle crossed per pixel from the locally smoothed Stokes, one global angle, or the
#: per-pixel extremes of the Malus curve (I_min, I_max)
RULES = ("local", "global", "pixel")
# polanalyser's demosaicing returns the images of these 2x2 positions (row, col), in this order
_PA_POSITIONS = ((1, 1), (0, 1), (0, 0), (1, 0))


@dataclass(frozen=True)
class MosaicCalibration:
    """What the demosaicing knows of the sensor: its layout (4 angles [deg], row-major 2×2 from the top-left
    pixel), the micro-polarizers' extinction ratio and the crosstalk into each edge / diagonal neighbour."""

    layout: tuple[float, float, float, float] = SONY_LAYOUT
    extinction_ratio: float = SONY_EXTINCTION_RATIO
    crosstalk_edge: float = 0.0
    crosstalk_diagonal: float = 0.0

    def __post_init__(self):
        try:
            object.__setattr__(self, "layout", check_layout(self.layout))
        except ValueError as exc:
            raise ImagingError(str(exc)) from None
        finite_param("extinction_ratio", self.extinction_ratio, low=1.0, low_open=True)
        finite_param("crosstalk_edge", self.crosstalk_edge, low=0.0, high=0.25)
        finite_param("crosstalk_diagonal", self.crosstalk_diagonal, low=0.0, high=0.25)

    @property
    def a0(self) -> float:
        """The sensor's transmission of unpolarized light, ½(1 + 1/ER) (crosstalk keeps it)."""
        return 0.5 * (1.0 + 1.0 / self.extinction_ratio)

    def rows(self) -> np.ndarray:
        """(4, 3): each 2×2 position's response to (S0, S1, S2), row-major, crosstalk included.

        A polarizer at φ: ½(k1 + k2), ½(k1 − k2) cos 2φ, ½(k1 − k2) sin 2φ with k1 = 1, k2 = 1/ER; a
        position's row is (1 − 4c_e − 4c_d)·own + c_e·(2 horizontal + 2 vertical neighbours) + 4c_d·diagonal.
        """
        k2 = 1.0 / self.extinction_ratio
        phi = np.radians(np.asarray(self.layout, float))
        own = np.stack([np.full(4, 0.5 * (1 + k2)), 0.5 * (1 - k2) * np.cos(2 * phi),
                        0.5 * (1 - k2) * np.sin(2 * phi)], 1)
        ce, cd = self.crosstalk_edge, self.crosstalk_diagonal
        out = np.empty_like(own)
        for i in range(4):
            r, c = divmod(i, 2)
            horizontal, vertical, diagonal = r * 2 + (1 - c), (1 - r) * 2 + c, (1 - r) * 2 + (1 - c)
            out[i] = ((1 - 4 * ce - 4 * cd) * own[i] + 2 * ce * (own[horizontal] + own[vertical])
                      + 4 * cd * own[diagonal])
        return out


def demosaic(raw, layout=SONY_LAYOUT) -> tuple[np.ndarray, tuple[float, ...]]:
    """The four analyzer images of a mosaic frame, each at full size (bilinear; polanalyser).

    Parameters
    ----------
    raw : (h, w) uint8 or uint16 mosaic frame (h, w even).
    layout : the 2×2 angles [deg], row-major from the top-left pixel.

    Returns
    -------
    images : (4, h, w) float64, the interpolated image of each 2×2 position, row-major
    angles : the 4 angles [deg] of those positions (``layout``)
    """
    img = as_image("raw", raw)
    if img.dtype not in (np.uint8, np.uint16):
        raise ImagingError(f"raw: a mosaic frame is uint8 or uint16, got {img.dtype}")
    if img.shape[0] % 2 or img.shape[1] % 2 or min(img.shape) < 4:
        raise ImagingError(f"raw: a 2x2 mosaic needs an even size of at least 4x4, got {img.shape}")
    try:
        angles = check_layout(layout)
    except ValueError as exc:
        raise ImagingError(str(exc)) from None
    images = pa.demosaicing(np.ascontiguousarray(img), pa.COLOR_PolarMono)
    out = np.empty((4, *img.shape))
    for (r, c), image in zip(_PA_POSITIONS, images, strict=True):
        out[2 * r + c] = image
    return out, angles


def mosaic_stokes(raw, calibration: MosaicCalibration = MosaicCalibration()) -> np.ndarray:
    """(h, w, 3) linear Stokes (S0, S1, S2) of the light per pixel, in the raw frame's units, from a mosaic
    frame: the demosaiced images solved against the calibrated analyzer rows (least squares, polanalyser's
    ``calcStokes``). A dark offset o in every raw pixel shows as o/a0 in S0 (a0 = ½(1 + 1/ER)), never in
    S1, S2."""
    images, _ = demosaic(raw, calibration.layout)
    return pa.calcStokes(images, calibration.rows())


def _saturated(raw: np.ndarray, saturation: float | None) -> np.ndarray | None:
    """Pixels whose 3×3 neighbourhood (what bilinear demosaicing reads) holds a saturated raw pixel."""
    if saturation is None:
        return None
    hit = (raw >= saturation).astype(np.uint8)
    if not hit.any():
        return None
    return cv2.dilate(hit, np.ones((3, 3), np.uint8)).astype(bool)


def crossed_pair(raw, calibration: MosaicCalibration = MosaicCalibration(), *,
                 rule: Literal["local", "global", "pixel"] = "local", angle_sigma_px: float = 6.0,
                 polarized_sigma_px: float = 0.0,
                 saturation: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    r"""E_b and E_w from one mosaic frame: the frames through an ideal analyzer crossed to and along the
    light's polarization, with the sensor's own transmission a0 = ½(1 + 1/ER).

    Parameters
    ----------
    raw : (h, w) uint16 mosaic frame, DN (dark offset o included).
    calibration : the sensor's layout, extinction ratio and crosstalk.
    rule : how the crossed angle ψ_b is chosen per pixel:

        * ``local``: ψ = AoLP of the Stokes around the pixel, smoothed by a Gaussian of ``angle_sigma_px``
          without the pixel's own 5×5 neighbourhood (the backscatter's angle varies slowly; the angle
          holds none of the pixel's own noise, so the projection is unbiased);
        * ``global``: one ψ for the frame, the AoLP of the summed S1, S2 (what one rotating analyzer does);
        * ``pixel``: each pixel's own AoLP: E_b = a0(S0 − √(S1² + S2²)), the minimum of its Malus curve
          (biased low under noise: √(S1² + S2²) is Rician).

    angle_sigma_px : the ``local`` rule's smoothing [px].
    polarized_sigma_px : smooth the polarized part S1 cos 2ψ + S2 sin 2ψ by a Gaussian of this σ [px] before
        it is added and subtracted (0: not): the object's light is unpolarized, so the polarized part is the
        backscatter's, smooth, while the demosaicing's false polarization at edges and the noise are not.
    saturation : raw level [DN] at which a pixel is saturated; derived pixels reading one are
        :data:`SATURATED`.

    Returns
    -------
    (E_b, E_w) : float64 (h, w), in DN with the dark offset o exactly once (as a raw frame)

    Notes
    -----
    .. math:: E_{b,w} = a_0\,\bigl(S_0 \mp (S_1 \cos 2ψ + S_2 \sin 2ψ)\bigr)

    With unpolarized object light S and backscatter B of DOP p at angle χ (ψ = χ), E_b = a0(S + B(1 − p)),
    E_w = a0(S + B(1 + p)): eqs. 4–5 up to the gain 2a0. Under noise of std σ in each of S1 and S2 and no
    polarized light, the ``pixel`` rule's E_b is low by a0·σ√(π/2) on average (the mean of a Rayleigh
    variable); ``local`` and ``global`` are unbiased.
    """
    e_b, e_w = crossed_from_stokes(mosaic_stokes(raw, calibration), calibration.a0, rule=rule,
                                   angle_sigma_px=angle_sigma_px, polarized_sigma_px=polarized_sigma_px)
    hit = _saturated(np.asarray(raw), saturation)
    if hit is not None:
        e_b[hit] = e_w[hit] = SATURATED
    return e_b, e_w


def crossed_from_stokes(stokes, a0: float = 0.5, *, rule: Literal["local", "global", "pixel"] = "local",
                        angle_sigma_px: float = 6.0,
                        polarized_sigma_px: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """E_b, E_w = a0·(S0 ∓ (S1 cos 2ψ + S2 sin 2ψ)) from (h, w, 3) Stokes, ψ chosen by ``rule``
    (:func:`crossed_pair`)."""
    if rule not in RULES:
        raise ImagingError(f"rule: {rule!r} is not one of {', '.join(RULES)}")
    finite_param("angle_sigma_px", angle_sigma_px, low=0.0, low_open=True)
    finite_param("polarized_sigma_px", polarized_sigma_px, low=0.0)
    stokes = np.asarray(stokes, float)
    if stokes.ndim != 3 or stokes.shape[-1] != 3:
        raise ImagingError(f"stokes: expected (h, w, 3), got {stokes.shape}")
    s0, s1, s2 = stokes[..., 0], stokes[..., 1], stokes[..., 2]
    if rule == "pixel":
        proj = np.hypot(s1, s2)
    else:
        if rule == "global":
            two_psi = np.arctan2(s2.sum(), s1.sum())
        else:
            two_psi = np.arctan2(_surround(s2, float(angle_sigma_px)), _surround(s1, float(angle_sigma_px)))
        proj = s1 * np.cos(two_psi) + s2 * np.sin(two_psi)
    if polarized_sigma_px > 0:
        proj = cv2.GaussianBlur(proj, (0, 0), float(polarized_sigma_px), borderType=cv2.BORDER_REFLECT)
    return a0 * (s0 - proj), a0 * (s0 + proj)


def _surround(image: np.ndarray, sigma_px: float) -> np.ndarray:
    """``image`` smoothed by a Gaussian of ``sigma_px`` with its central 5×5 left out (unnormalised: only the
    angle of the result is used). Those are the pixels whose demosaiced Stokes share raw pixels with the
    centre's (bilinear reads ±1 raw pixel), so the angle holds none of the centre's own noise and the
    projection on it stays unbiased. The full Gaussian is separable (fast); its central 5×5 is taken off."""
    r = max(3, int(np.ceil(3.0 * sigma_px)))
    g = cv2.getGaussianKernel(2 * r + 1, sigma_px)
    full = cv2.sepFilter2D(image, -1, g, g, borderType=cv2.BORDER_REFLECT)
    core = g[r - 2:r + 3]
    return full - cv2.sepFilter2D(image, -1, core, core, borderType=cv2.BORDER_REFLECT)


def mosaic_intensity(raw, calibration: MosaicCalibration = MosaicCalibration(), *,
                     saturation: float | None = None) -> np.ndarray:
    """a0·S0 per pixel [DN, dark offset o once]: the frame of an unpolarized method through the mosaic (half
    the light of a camera without micro-polarizers; a0 = ½(1 + 1/ER))."""
    stokes = mosaic_stokes(raw, calibration)
    out = calibration.a0 * stokes[..., 0]
    hit = _saturated(np.asarray(raw), saturation)
    if hit is not None:
        out[hit] = SATURATED
    return out
