"""``preview``'s half → full resolution pass (sim/frame_kernels.py ``half_up``) against independent numbers:
OpenCV's bilinear resize for the smooth fields, and the within-object rule of docs/physics.md §10.6 written
out pixel by pixel (the neighbours that see the pixel's object, renormalised; else the nearest coarse pixel
of it within two) for A = ρ·P↑ + H↑."""

import cv2
import numpy as np
import pytest
from polarstripe.sim.frame_kernels import half_fix, half_up


def _objects(hs, ws):
    """Coarse and fine object ids: a disc (1) on a wall (0) beside empty water (−1), edges at odd places."""
    def ids(h, w, scale):
        y, x = np.mgrid[0:h, 0:w] / scale
        out = np.where(x < 0.7 * ws, 0, -1)
        out[(y - 0.45 * hs) ** 2 + (x - 0.4 * ws) ** 2 < (0.23 * hs) ** 2] = 1
        return out.astype(np.int64)
    return ids(hs, ws, 1.0), ids(2 * hs, 2 * ws, 2.0)


def _a_by_the_rule(p_small, ids_small, ids, albedo, h_up):
    """A pixel by pixel: the bilinear weights of the coarse neighbours of the pixel's own object."""
    hs, ws = p_small.shape
    h, w = ids.shape
    a = np.empty(h * w)
    for i in range(h):
        fy = min(max(i / 2 - 0.25, 0.0), hs - 1.0)
        y0 = min(int(fy), hs - 2)
        for j in range(w):
            m, k = i * w + j, ids[i, j]
            if k < 0:
                a[m] = h_up[m]
                continue
            fx = min(max(j / 2 - 0.25, 0.0), ws - 1.0)
            x0 = min(int(fx), ws - 2)
            acc = wsum = 0.0
            for yy in (y0, y0 + 1):
                for xx in (x0, x0 + 1):
                    wq = (1 - abs(fy - yy)) * (1 - abs(fx - xx))
                    if ids_small[yy, xx] == k:
                        acc, wsum = acc + wq * p_small[yy, xx], wsum + wq
            if wsum > 1e-9:
                p = acc / wsum
            else:
                near = [((yy - fy) ** 2 + (xx - fx) ** 2, p_small[yy, xx])
                        for yy in range(max(int(fy) - 1, 0), min(int(fy) + 3, hs))
                        for xx in range(max(int(fx) - 1, 0), min(int(fx) + 3, ws)) if ids_small[yy, xx] == k]
                p = min(near)[1] if near else 0.0
            a[m] = albedo[m] * p + h_up[m]
    return a


@pytest.mark.parametrize("fields", [4, 5])
def test_half_up_is_the_bilinear_and_the_within_object_rule(fields):
    hs, ws = 18, 26
    rng = np.random.default_rng(3)
    ids_small, ids = _objects(hs, ws)
    smooth = tuple(rng.uniform(-1, 2, (hs, ws)) * 10.0 ** rng.uniform(-3, 1) for _ in range(fields))
    p_small = np.where(ids_small >= 0, rng.uniform(0.1, 3, (hs, ws)), 0.0)
    albedo = np.where(ids >= 0, rng.uniform(0.05, 0.9, ids.shape), 0.0).ravel()
    fix, start = half_fix(ids, ids_small, albedo)
    assert 0 < fix.size < ids.size // 4 and start[-1] == fix.size
    a, out = np.empty(ids.size), np.full((fields - 1, ids.size), np.nan)
    half_up(smooth, p_small, ids_small, ids.ravel(), albedo, fix, start, a, out, 0, 7)   # two bands of rows
    half_up(smooth, p_small, ids_small, ids.ravel(), albedo, fix, start, a, out, 7, -1)
    ups = [cv2.resize(s, (2 * ws, 2 * hs), interpolation=cv2.INTER_LINEAR).ravel() for s in smooth]
    for got, want in zip(out, ups[1:], strict=True):
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-13 * np.abs(want).max())
    want_a = _a_by_the_rule(p_small, ids_small, ids, albedo, ups[0])
    np.testing.assert_allclose(a, want_a, rtol=0, atol=1e-13 * np.abs(want_a).max())
    # edges matter
    assert not np.array_equal(a, albedo * cv2.resize(p_small, (2 * ws, 2 * hs)).ravel() + ups[0])
