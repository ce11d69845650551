"""Input checks shared by the imaging functions, and their one error class.

Every public imaging function validates its inputs here, once, and raises :class:`ImagingError` whose text
names the argument and the bad value (shape, dtype, region, parameter).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from polarstripe.errors import PolarstripeError


class ImagingError(PolarstripeError, ValueError):
    """Bad input to an imaging function: mismatched shapes or dtypes, a region outside the image, an empty
    stack, a NaN or out-of-range parameter. The text names the argument and the value."""


def as_image(name: str, value, *, ndim: int = 2) -> np.ndarray:
    """Return ``value`` (masks kept) as an array of ``ndim`` dimensions and a real numeric dtype, or raise."""
    arr = np.asanyarray(value)  # keeps a mask (saturated pixels)
    if arr.dtype.kind not in "uif":
        raise ImagingError(f"{name}: dtype {arr.dtype} is not a real numeric type")
    if arr.ndim != ndim:
        raise ImagingError(f"{name}: expected {ndim} dimensions, got shape {arr.shape}")
    if arr.size == 0:
        raise ImagingError(f"{name}: empty array of shape {arr.shape}")
    return arr


def same_shape(**arrays: np.ndarray) -> tuple[int, ...]:
    """Raise unless all named arrays share one shape; return it."""
    items = list(arrays.items())
    name0, a0 = items[0]
    for name, arr in items[1:]:
        if np.shape(arr) != np.shape(a0):
            raise ImagingError(f"{name}: shape {np.shape(arr)} does not match {name0} shape {np.shape(a0)}")
    return tuple(np.shape(a0))


def same_dtype(**arrays: np.ndarray) -> np.dtype:
    """Raise unless all named arrays share one dtype; return it."""
    items = list(arrays.items())
    name0, a0 = items[0]
    for name, arr in items[1:]:
        if np.asarray(arr).dtype != np.asarray(a0).dtype:
            raise ImagingError(f"{name}: dtype {np.asarray(arr).dtype} does not match {name0} dtype "
                               f"{np.asarray(a0).dtype}")
    return np.asarray(a0).dtype


def as_stack(name: str, frames) -> np.ndarray:
    """Return a (k, h, w) stack from an array or a sequence of equal frames, or raise."""
    if isinstance(frames, np.ndarray):
        stack = frames
    else:
        frames = list(frames)
        if not frames:
            raise ImagingError(f"{name}: empty stack (no frames)")
        first = as_image(f"{name}[0]", frames[0])
        for k, f in enumerate(frames[1:], start=1):
            f = np.asarray(f)
            if f.shape != first.shape:
                raise ImagingError(f"{name}[{k}]: shape {f.shape} does not match {name}[0] shape "
                                   f"{first.shape}")
            if f.dtype != first.dtype:
                raise ImagingError(f"{name}[{k}]: dtype {f.dtype} does not match {name}[0] dtype "
                                   f"{first.dtype}")
        stack = np.stack(frames)
    if stack.ndim != 3:
        raise ImagingError(f"{name}: expected a stack of 2-D frames (k, h, w), got shape {stack.shape}")
    if stack.shape[0] == 0:
        raise ImagingError(f"{name}: empty stack (no frames)")
    if stack.dtype.kind not in "uif":
        raise ImagingError(f"{name}: dtype {stack.dtype} is not a real numeric type")
    return stack


def finite_param(name: str, value, *, low: float | None = None, high: float | None = None,
                 low_open: bool = False, high_open: bool = False) -> float:
    """Return ``value`` as a finite float within [low, high] (open ends when asked), or raise."""
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ImagingError(f"{name}: {value!r} is not a number") from None
    if not math.isfinite(x):
        raise ImagingError(f"{name}: {x} is not finite")
    if low is not None and (x < low or (low_open and x == low)):
        raise ImagingError(f"{name}: {x} is below the allowed range ({'>' if low_open else '>='} {low})")
    if high is not None and (x > high or (high_open and x == high)):
        raise ImagingError(f"{name}: {x} is above the allowed range ({'<' if high_open else '<='} {high})")
    return x


def finite_array(name: str, value) -> np.ndarray:
    """Return ``value`` as a float64 array without NaN or inf, or raise."""
    arr = np.asarray(value, dtype=np.float64)
    if not np.all(np.isfinite(arr)):
        bad = int(np.count_nonzero(~np.isfinite(arr)))
        raise ImagingError(f"{name}: {bad} value(s) are NaN or infinite")
    return arr


Roi = tuple[int, int, int, int]


def roi_slices(name: str, roi: Sequence[int] | np.ndarray | None, shape: tuple[int, ...]):
    """Turn a region of interest into an index for an image of ``shape`` (h, w).

    ``roi`` is ``(row0, row1, col0, col1)`` (half-open, pixels), a boolean mask of ``shape``, or None for
    the whole image. Raises if the rectangle is empty or reaches outside the image, or the mask is empty.
    """
    h, w = shape[-2], shape[-1]
    if roi is None:
        return (slice(0, h), slice(0, w))
    arr = np.asarray(roi)
    if arr.dtype == bool:
        if arr.shape != (h, w):
            raise ImagingError(f"{name}: mask shape {arr.shape} does not match image shape {(h, w)}")
        if not arr.any():
            raise ImagingError(f"{name}: mask selects no pixels")
        return arr
    if arr.shape != (4,) or arr.dtype.kind not in "iu":
        raise ImagingError(f"{name}: expected (row0, row1, col0, col1) integers or a boolean mask, "
                           f"got {roi!r}")
    r0, r1, c0, c1 = (int(v) for v in arr)
    if not (0 <= r0 < r1 <= h and 0 <= c0 < c1 <= w):
        raise ImagingError(f"{name}: rectangle rows {r0}:{r1}, cols {c0}:{c1} is empty or outside the "
                           f"{h}x{w} image")
    return (slice(r0, r1), slice(c0, c1))
