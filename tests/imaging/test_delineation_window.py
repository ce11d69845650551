"""The windowed sub-pixel edge (imaging/delineation.py): stripes blurred into ramps many pixels wide, as all
orders of scattering make them, drawn in closed form (a box convolved with a Gaussian is a difference of two
error functions), on a pedestal three times the stripe's own peak."""

from __future__ import annotations

import numpy as np
import pytest
from polarstripe.imaging.delineation import NoiseModel, SheetVotes, delineate
from polarstripe.imaging.validation import ImagingError
from scipy.special import erf

W, N, PITCH, X0 = 96, 8, 12.0, 0.37  # stripe k spans [X0 + k·PITCH, X0 + (k + 1)·PITCH) in pixels


def _votes(blur_px: float, seed: int = 0, rows: int = 40) -> SheetVotes:
    """Each sheet's image: the box of its columns blurred by a Gaussian of ``blur_px``, plus a broad
    pedestal (a Gaussian of 3 pitches, 3× the peak, the wide-angle light); 12-bit-like noise."""
    x = np.arange(W, dtype=float)
    s = blur_px * np.sqrt(2.0)
    rng = np.random.default_rng(seed)
    frames = []
    for k in range(N):
        a, b = X0 + k * PITCH, X0 + (k + 1) * PITCH  # sampled at the pixel centres j
        sharp = 0.5 * (erf((x - a) / s) - erf((x - b) / s))
        wide = 3.0 * np.exp(-0.5 * ((x - 0.5 * (a + b)) / (3 * PITCH)) ** 2)
        row = 64 + 400 * (sharp + wide)
        frames.append(row + rng.normal(0.0, 2.0, (rows, W)))
    st = np.sort(np.stack(frames), axis=0)
    return SheetVotes(st[-1], st[-2], np.argmax(np.stack(frames), axis=0).astype(np.int32), N)


def _edges():
    return X0 + np.arange(N + 1) * PITCH  # the stripe boundaries' true pixel positions, as "columns"


def test_windowed_edge_finds_blurred_ramps_that_two_pixels_cannot():
    v, noise = _votes(blur_px=3.0), NoiseModel(64.0, 2.0, 0.0)
    two = delineate(v, _edges(), noise, edge_window=1)
    win = delineate(v, _edges(), noise)  # the default window (3 pixels per side)
    truth = np.broadcast_to(np.arange(W, dtype=float), v.best.shape)  # column map = pixel position
    inner = (truth > X0 + PITCH) & (truth < X0 + (N - 1) * PITCH - 1)
    assert np.isfinite(two[inner]).mean() < 0.2  # the per-pixel step is below 4 sigma: rejected
    assert np.isfinite(win[inner]).mean() > 0.9
    err = (win - truth)[inner & np.isfinite(win)]
    assert np.sqrt(np.mean(err ** 2)) < 0.05 and abs(np.mean(err)) < 0.02  # pixels (symmetric: unbiased)


def test_window_of_one_is_the_two_pixel_zero():
    """Sharp stripes, ``edge_window`` 1: a pixel's column is the linear interpolation between the two-pixel
    zeros x = j + n_j/(n_j + n_{j+1}) of its stripe's edges, computed here by hand."""
    v = _votes(blur_px=0.6)
    one = delineate(v, _edges(), NoiseModel(64.0, 2.0, 0.0), edge_window=1)
    i = 5
    steps = np.nonzero(np.diff(v.index[i]) == 1)[0]
    n = (v.best[i] - v.second[i]) / (v.best[i] + v.second[i] - 128.0)
    zeros = steps + n[steps] / (n[steps] + n[steps + 1])
    np.testing.assert_allclose(zeros, _edges()[v.index[i, steps + 1]], atol=0.3)  # near the truth
    j0, j1 = steps[2] + 1, steps[3]  # the pixels of one stripe between two edges
    k = v.index[i, j0]
    expect = _edges()[k] + (np.arange(j0, j1 + 1) - zeros[2]) * PITCH / (zeros[3] - zeros[2])
    np.testing.assert_allclose(one[i, j0:j1 + 1], expect, rtol=1e-12)
    # the default window only widens an edge that fails on two pixels: sharp stripes come out the same
    np.testing.assert_array_equal(delineate(v, _edges(), NoiseModel(64.0, 2.0, 0.0)), one)


@pytest.mark.parametrize("bad", [0, -2, 1.5, True])
def test_bad_edge_window_is_one_error(bad):
    with pytest.raises(ImagingError, match="edge_window"):
        delineate(_votes(1.0, rows=2), _edges(), edge_window=bad)


def test_pixel_between_edges_not_of_its_stripe_is_nan():
    """An island of sheet 3 inside sheet 2 (2 → 3 → 2 along the row): both its edges are the one column
    ⌊3·W/N⌋, so its pixels' columns cannot be interpolated: NaN, not that column."""
    index = np.array([[1, 1, 1, 1, 2, 2, 2, 3, 3, 3, 2, 2, 2, 3, 3, 3, 3]], np.int32)
    w = index.shape[1]
    best, second = np.full((1, w), 1000.0), np.full((1, w), 400.0)
    cols = delineate(SheetVotes(best, second, index, 5), np.arange(6) * 10.0, NoiseModel(0.0, 1.0, 0.0))
    assert np.all(np.isnan(cols[0, 7:10]))  # the island
    assert np.all(np.isfinite(cols[0, 4:7])) and np.all((cols[0, 4:7] >= 20) & (cols[0, 4:7] <= 30))
