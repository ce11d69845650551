"""Image-quality metrics: Michelson contrast over a chart's bars and the error of an estimate of S."""

from __future__ import annotations

import numpy as np
from polarstripe.imaging.validation import ImagingError, as_image, roi_slices


def _region_mean(name: str, image: np.ndarray, roi) -> float:
    index = roi_slices(name, roi, image.shape)
    values = image[index]
    if isinstance(values, np.ma.MaskedArray):
        values = values.compressed()
    values = np.asarray(values, np.float64)
    if values.size == 0:
        raise ImagingError(f"{name}: every pixel in the region is masked (saturated)")
    if not np.all(np.isfinite(values)):
        raise ImagingError(f"{name}: the region holds NaN or infinite values")
    return float(values.mean())


def michelson_contrast(image, bright, dark) -> float:
    """Michelson contrast (I_bright - I_dark)/(I_bright + I_dark) between the mean of the bright bars and the
    mean of the dark bars.

    Parameters
    ----------
    image : array (h, w), may be masked
        Any estimate of the scene (DN or radiance, offset subtracted); masked pixels are left out.
    bright, dark : (row0, row1, col0, col1) or bool mask (h, w)
        The chart's bright and dark bar regions.

    Returns
    -------
    float
        In [-1, 1] for non-negative images; 0 when both means are 0. An estimate whose dark bars come out
        negative (over-subtracted backscatter) can exceed 1; that is reported, not hidden.
    """
    img = as_image("image", image)
    hi, lo = _region_mean("bright", img, bright), _region_mean("dark", img, dark)
    total = hi + lo
    if total == 0.0:
        return 0.0
    return (hi - lo) / total


def signal_error(estimate, truth, mask=None, *, fit_gain: bool = False, masked: str = "lost") -> float:
    """Relative RMS error of an estimate of S against the ground truth: ||Ŝ - S|| / ||S|| over ``mask``.

    Parameters
    ----------
    estimate, truth : array (h, w)
        The method's estimate and the true S = D + A, in the same units.
    mask : bool array (h, w) or (row0, row1, col0, col1), optional
        Pixels to compare (e.g. those seeing the chart); all when None.
    fit_gain : bool
        First scale the estimate by the least-squares gain g = <Ŝ, S>/<Ŝ, Ŝ> (over its unmasked pixels), so
        a method that returns S up to a known factor (a crossed-analyzer frame is S/2) is judged on shape,
        not scale.
    masked : "lost" or "skip"
        Masked pixels of ``estimate`` (a saturated frame): ``lost`` (default) counts them as an estimate of 0,
        all their truth is error, so a method cannot score better by saturating; ``skip`` leaves them out.

    Returns
    -------
    float (0 = perfect; 1 when every compared pixel is lost)
    """
    if masked not in ("lost", "skip"):
        raise ImagingError(f"masked: 'lost' or 'skip', got {masked!r}")
    est, tru = as_image("estimate", estimate), as_image("truth", truth)
    if est.shape != tru.shape:
        raise ImagingError(f"estimate: shape {est.shape} does not match truth shape {tru.shape}")
    index = roi_slices("mask", mask, tru.shape)
    e, t = est[index], np.asarray(tru[index], np.float64)
    lost = np.zeros(0)
    if isinstance(e, np.ma.MaskedArray):
        keep = ~np.ma.getmaskarray(e)
        lost = t[~keep] if masked == "lost" else lost
        e, t = np.asarray(e.data, np.float64)[keep], t[keep]
    e = np.asarray(e, np.float64).ravel()
    t = t.ravel()
    if e.size == 0 and lost.size == 0:
        raise ImagingError("estimate: every compared pixel is masked")
    if not (np.all(np.isfinite(e)) and np.all(np.isfinite(t)) and np.all(np.isfinite(lost))):
        raise ImagingError("estimate: NaN or infinite values in the compared pixels")
    norm = float(np.sqrt(np.sum(t * t) + np.sum(lost * lost)))
    if norm == 0.0:
        raise ImagingError("truth: the signal is zero over the compared pixels")
    if fit_gain:
        ee = float(np.sum(e * e))
        e = e * (float(np.sum(e * t)) / ee if ee > 0 else 0.0)
    return float(np.sqrt(np.sum((e - t) ** 2) + np.sum(lost * lost)) / norm)
