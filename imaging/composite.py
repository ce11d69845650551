"""Light-stripe compositing: running per-pixel max/min (eq. 7) and stripe delineation with mosaicing.

The running reductions keep one max and one min image per analyzer angle, so memory does not grow with the
number of stripes. Saturation needs no per-frame work: a pixel's maximum is saturated exactly when it
reached the sensor's saturation level in at least one frame, so the mask is read off the maximum at the end.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from polarstripe.imaging.validation import ImagingError, as_image, as_stack, finite_param


@dataclass(frozen=True)
class CompositeImage:
    """The reductions over the frames seen at one analyzer angle.

    ``maximum`` is the composite CI of eq. 7 and ``minimum`` the per-pixel minimum (both masked where the
    value is saturated, so they are never silently mixed into later steps); ``n_frames`` frames were reduced.
    """

    maximum: np.ma.MaskedArray
    minimum: np.ma.MaskedArray
    n_frames: int
    argmax: np.ndarray | None = None


class RunningComposite:
    """Per-pixel running max and min over stripe frames, one pair per analyzer angle (eq. 7).

    Parameters
    ----------
    shape : (h, w)
        Frame shape in pixels.
    dtype : numpy dtype
        Frame dtype (uint16 DN for camera frames); the reductions stay in it, no conversion per frame.
    saturation : float or None
        Values >= this (DN) are saturated and masked in the results; None means no level (float frames).
    track_argmax : bool
        Also keep, per pixel, the index of the frame that gave the maximum (the stripe number); costs about
        as much again per frame.

    Notes
    -----
    Eq. 7 of the paper: CI(x, y) = max_k SI_k(x, y). Angles are keyed in degrees rounded to 1e-6;
    ``angle_deg=None`` means no analyzer.
    """

    def __init__(self, shape: tuple[int, int], dtype=np.uint16, *, saturation: float | None = None,
                 track_argmax: bool = False):
        if len(shape) != 2 or min(shape) <= 0:
            raise ImagingError(f"shape: expected (h, w) with positive sizes, got {shape!r}")
        self.shape = (int(shape[0]), int(shape[1]))
        self.dtype = np.dtype(dtype)
        if self.dtype.kind not in "uif":
            raise ImagingError(f"dtype: {self.dtype} is not a real numeric type")
        self.saturation = None if saturation is None else finite_param("saturation", saturation)
        self.track_argmax = bool(track_argmax)
        self._max: dict[float | None, np.ndarray] = {}
        self._min: dict[float | None, np.ndarray] = {}
        self._argmax: dict[float | None, np.ndarray] = {}
        self._count: dict[float | None, int] = {}

    @staticmethod
    def _key(angle_deg: float | None) -> float | None:
        if angle_deg is None:
            return None
        return round(finite_param("angle_deg", angle_deg) % 180.0, 6)

    def reset(self) -> None:
        """Forget all frames; the buffers are kept and reused by the next scan (no new allocation)."""
        self._count.clear()

    def add(self, frame: np.ndarray, angle_deg: float | None = None) -> None:
        """Fold one frame (shape ``self.shape``, dtype ``self.dtype``) into the reductions for its angle."""
        if not isinstance(frame, np.ndarray) or frame.shape != self.shape:
            raise ImagingError(f"frame: shape {np.shape(frame)} does not match the composite shape "
                               f"{self.shape}")
        if frame.dtype != self.dtype:
            raise ImagingError(f"frame: dtype {frame.dtype} does not match the composite dtype {self.dtype}")
        key = self._key(angle_deg)
        k = self._count.get(key, 0)
        if k == 0:
            if key not in self._max:
                self._max[key] = np.empty(self.shape, self.dtype)
                self._min[key] = np.empty(self.shape, self.dtype)
                if self.track_argmax:
                    self._argmax[key] = np.empty(self.shape, np.int32)
            np.copyto(self._max[key], frame)
            np.copyto(self._min[key], frame)
            if self.track_argmax:
                self._argmax[key].fill(0)
            self._count[key] = 1
            return
        mx = self._max[key]
        if self.track_argmax:
            np.copyto(self._argmax[key], k, where=frame > mx)
        np.maximum(mx, frame, out=mx)
        np.minimum(self._min[key], frame, out=self._min[key])
        self._count[key] = k + 1

    @property
    def angles(self) -> list[float | None]:
        """Analyzer angles (degrees, or None) that have frames."""
        return [key for key, n in self._count.items() if n > 0]

    def result(self, angle_deg: float | None = None) -> CompositeImage:
        """The max/min composite for one angle; saturated pixels are masked."""
        key = self._key(angle_deg)
        if self._count.get(key, 0) == 0:
            raise ImagingError(f"angle_deg: no frames were added at {angle_deg!r} (have {self.angles})")
        mx, mn = self._max[key].copy(), self._min[key].copy()
        if self.saturation is None:
            mask_max = mask_min = np.zeros(self.shape, bool)
        else:
            mask_max, mask_min = mx >= self.saturation, mn >= self.saturation
        arg = self._argmax[key].copy() if self.track_argmax else None
        return CompositeImage(np.ma.MaskedArray(mx, mask_max), np.ma.MaskedArray(mn, mask_min),
                              self._count[key], arg)


def max_composite(frames, saturation: float | None = None) -> np.ma.MaskedArray:
    """Light-stripe composite CI = max_k SI_k (eq. 7) of a stack, saturated pixels masked.

    Parameters
    ----------
    frames : array (k, h, w) or sequence of (h, w) arrays
        Stripe images SI_k, one dtype and shape.
    saturation : float, optional
        Saturation level (DN); pixels whose maximum reaches it are masked.

    Returns
    -------
    numpy.ma.MaskedArray, shape (h, w)
    """
    stack = as_stack("frames", frames)
    comp = RunningComposite(stack.shape[1:], stack.dtype, saturation=saturation)
    for f in stack:
        comp.add(np.ascontiguousarray(f))
    return comp.result().maximum


def _edge_gradient(frame: np.ndarray, axis: int) -> np.ndarray:
    """Sobel derivative along ``axis`` (smoothing [1, 2, 1] across it), float64, same shape."""
    f = np.asarray(frame, np.float64)
    if axis == 0:
        f = f.T
    p = np.pad(f, ((1, 1), (0, 0)), mode="edge")
    low = p.min(axis=1, keepdims=True)  # beyond the border the line is dark: a stripe touching it has an edge
    p = np.concatenate([low, p, low], axis=1)
    smooth = p[:-2, :] + 2.0 * p[1:-1, :] + p[2:, :]
    g = (smooth[:, 2:] - smooth[:, :-2]) / 8.0
    return g.T if axis == 0 else g


def delineate_stripe(frame: np.ndarray, *, axis: int = 1, min_gradient: float | None = None,
                     saturation: float | None = None) -> np.ndarray:
    """Pixels of the object stripe in one stripe frame, found with a gradient operator.

    Along each line across the stripe (rows for ``axis=1``, i.e. stripes running down the image), the
    stripe is the run between the strongest rising edge and the strongest falling edge after it (Sobel
    derivative). A line is kept only when both edges are at least ``min_gradient`` strong.

    Parameters
    ----------
    frame : array (h, w)
        One stripe image SI_k (DN or radiance).
    axis : {0, 1}
        Image axis across the stripe: 1 when the stripe runs vertically (projector columns), 0 otherwise.
    min_gradient : float, optional
        Edge threshold in frame units per pixel. Default: 6 × the robust (MAD) noise of the gradient.
    saturation : float, optional
        Pixels at or above it are left out of the stripe.

    Returns
    -------
    numpy.ndarray of bool, shape (h, w)
    """
    img = as_image("frame", frame)
    if axis not in (0, 1):
        raise ImagingError(f"axis: expected 0 or 1, got {axis!r}")
    g = _edge_gradient(img, axis)
    if axis == 0:
        g = g.T
    if min_gradient is None:
        med = np.median(g)
        thr = 6.0 * 1.4826 * float(np.median(np.abs(g - med))) + 1e-12
    else:
        thr = finite_param("min_gradient", min_gradient, low=0.0)
    n_lines, n = g.shape
    left = np.argmax(g, axis=1)
    cols = np.arange(n)
    after = np.where(cols[None, :] > left[:, None], g, np.inf)
    right = np.argmin(after, axis=1)
    rows = np.arange(n_lines)
    ok = (g[rows, left] >= thr) & (-after[rows, right] >= thr) & (right > left)
    mask = (cols[None, :] >= left[:, None]) & (cols[None, :] <= right[:, None]) & ok[:, None]
    if axis == 0:
        mask = mask.T
    if saturation is not None:
        mask &= img < finite_param("saturation", saturation)
    return mask


class StripeMosaic:
    """Mosaic of delineated stripes: each pixel takes its value from the stripe frame that delineated it with
    the strongest edges (the paper's alternative to eq. 7). Memory is independent of the number of stripes.
    Pixels no stripe claimed, or saturated, are masked in :meth:`result`."""

    def __init__(self, shape: tuple[int, int], *, axis: int = 1, min_gradient: float | None = None,
                 saturation: float | None = None):
        self.shape = (int(shape[0]), int(shape[1]))
        self.axis, self.min_gradient, self.saturation = axis, min_gradient, saturation
        self._value = np.zeros(self.shape, np.float64)
        self._strength = np.full(self.shape, -np.inf)
        self.n_frames = 0

    def add(self, frame: np.ndarray) -> np.ndarray:
        """Delineate the stripe in ``frame``, paste it into the mosaic, and return its mask."""
        img = as_image("frame", frame)
        if img.shape != self.shape:
            raise ImagingError(f"frame: shape {img.shape} does not match the mosaic shape {self.shape}")
        mask = delineate_stripe(img, axis=self.axis, min_gradient=self.min_gradient,
                                saturation=self.saturation)
        strength = np.abs(_edge_gradient(img, self.axis)).max(axis=self.axis, keepdims=True)
        strength = np.broadcast_to(strength, self.shape)
        take = mask & (strength > self._strength)
        self._value[take] = img[take]
        self._strength[take] = strength[take]
        self.n_frames += 1
        return mask

    def result(self) -> np.ma.MaskedArray:
        """The mosaic (float64, frame units), masked where no stripe was delineated."""
        return np.ma.MaskedArray(self._value.copy(), ~np.isfinite(self._strength))
