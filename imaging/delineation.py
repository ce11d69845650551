"""Stripe delineation for triangulation: which light sheet lit each pixel, and where exactly its edges are.

Over a stripe scan, :class:`RunningArgmax` keeps per pixel the brightest value, the index of the sheet that
gave it (the argmax over the scan's frames) and the second-brightest value, one set per analyzer angle:
memory does not grow with the number of stripes (like the running max of eq. 7).

:func:`delineate` turns them into a map of continuous projector (pattern) columns, the per-pixel input of
the triangulation (:func:`polarstripe.imaging.triangulation.depth_from_columns`):

* along each camera row, where the sheet index steps by one between pixels j and j + 1 (sheets a and a + 1),
  the edge between them (the projector column ⌊(a + 1)·W/N⌋, known exactly) crosses the row. Its sub-pixel
  position is the zero of the normalized difference of the two sheets' images, y = (I_a − I_{a+1})/(I_a +
  I_{a+1}) (albedo cancels): at a pixel of sheet a next to the edge y = (best − second)/(best + second −
  2·dark) (the second best there is sheet a + 1), at one of sheet a + 1 it is the negative of that. The
  edge is the zero x = −α/β of the least-squares line y = α + β·x through m pixels of each stripe on either
  side (fewer where the stripe ends or a pixel is invalid) — the paper's gradient edge (§2) from the
  running values alone. m = 1 first (the two-pixel zero x = j + n_j/(n_j + n_{j+1})); only an edge that
  fails the test below on m pixels is fitted again on m + 1, up to ``edge_window``. That is what finds
  the edges when all orders of scattering widen the stripes into ramps many pixels wide (docs/depth.md,
  "Why the demo's depth was 4–30 % valid"), while a sharp edge keeps its two-pixel zero;
* a pixel between the two edges of its own stripe (the columns ⌊k·W/N⌋ and ⌊(k + 1)·W/N⌋ of its sheet k,
  in either order) gets the column interpolated linearly between them;
* a pixel is **invalid** (NaN), not guessed, when it has no sheet (index −1: of a frame of several sheets
  none or two can have lit it, :mod:`polarstripe.imaging.sheets`), saturated (best ≥ saturation), dark (best
  − dark below ``k_sigma`` noise σ), its margin is below ``k_sigma`` σ of the margin (unless it is within
  the window its edge was fitted over, where a small margin is expected), or it is not bracketed by two good
  edges on its row (the first and last stripe, an object's silhouette, a shadow, a jump of more than one
  sheet). An edge is good when the line falls (β < 0) and the sum of the two sides' mean margins exceeds
  ``k_sigma`` σ of that sum and ``min_contrast`` times the mean signal over the window (a stripe seen on a
  surface is sharp; backscatter of the sheets in the water is not).

Noise model (DN): σ²(v) = read_noise_dn² + (v − dark)·dn_per_electron (shot noise, EMVA 1288).
Stripes are assumed to cross camera rows (a horizontal camera–projector baseline, vertical stripes).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numba import njit
from polarstripe.imaging.validation import ImagingError, finite_param

EDGE_WINDOW = 3  # most pixels per side an edge's sub-pixel zero is fitted over (module docstring)


@dataclass(frozen=True)
class SheetVotes:
    """Per pixel over one angle's frames: ``best`` and ``second`` values (frame units), ``index`` (int32,
    sheet of the best), ``n_frames``."""

    best: np.ndarray
    second: np.ndarray
    index: np.ndarray
    n_frames: int


class RunningArgmax:
    """Running argmax and second-best value per pixel, one set per analyzer angle (``None``: no analyzer).

    ``add(frame, sheet, angle)``: O(1) memory in the number of stripes; buffers are reused after
    :meth:`reset`."""

    def __init__(self, shape: tuple[int, int], dtype=np.uint16):
        self.shape = (int(shape[0]), int(shape[1]))
        self.dtype = np.dtype(dtype)
        self._bufs: dict = {}
        self._count: dict = {}

    @staticmethod
    def _key(angle_deg):
        return None if angle_deg is None else round(float(angle_deg) % 180.0, 6)

    def reset(self) -> None:
        self._count.clear()

    def add(self, frame: np.ndarray, sheet: int, angle_deg: float | None = None) -> None:
        if frame.shape != self.shape or frame.dtype != self.dtype:
            raise ImagingError(f"frame: {frame.dtype} {frame.shape}, expected {self.dtype} {self.shape}")
        key = self._key(angle_deg)
        if key not in self._bufs:
            self._bufs[key] = tuple(np.empty(self.shape, t) for t in (self.dtype, self.dtype, np.int32))
        best, second, index = self._bufs[key]
        if self._count.get(key, 0) == 0:
            np.copyto(best, frame)
            second.fill(-np.inf if self.dtype.kind == "f" else np.iinfo(self.dtype).min)
            index.fill(sheet)
        else:  # one compiled pass: a new best pushes the old best down to second
            _fold(np.ascontiguousarray(frame).reshape(-1), best.reshape(-1), second.reshape(-1),
                  index.reshape(-1), np.int32(sheet))
        self._count[key] = self._count.get(key, 0) + 1

    @property
    def angles(self) -> list:
        return [k for k, n in self._count.items() if n > 0]

    def result(self, angle_deg: float | None = None) -> SheetVotes:
        key = self._key(angle_deg)
        if not self._count.get(key):
            raise ImagingError(f"angle_deg: no frames at {angle_deg!r} (have {self.angles})")
        best, second, index = self._bufs[key]
        return SheetVotes(best, second, index, self._count[key])


@njit(cache=True, nogil=True)
def _fold(frame, best, second, index, sheet):
    for p in range(frame.size):
        v, b = frame[p], best[p]
        if v > b:
            second[p] = b
            best[p] = v
            index[p] = sheet
        elif v > second[p]:
            second[p] = v


@dataclass(frozen=True)
class NoiseModel:
    """The sensor noise the validity tests use, in DN (see the module docstring)."""

    dark_dn: float = 0.0
    read_noise_dn: float = 1.0
    dn_per_electron: float = 1.0 / 12.0
    saturation_dn: float | None = None


def delineate(votes: SheetVotes, edges, noise: NoiseModel = NoiseModel(), *, k_sigma: float = 4.0,
              min_contrast: float = 0.15, edge_window: int = EDGE_WINDOW) -> np.ndarray:
    """Continuous pattern column per pixel (h, w) float64, NaN where the stripe cannot be delineated.

    Parameters
    ----------
    votes : SheetVotes
        Of one analyzer angle (for polarized striping: the crossed one, E_b).
    edges : (N + 1,) array
        Pattern column of the stripe boundaries (:func:`~.triangulation.stripe_edges`); sheet k spans
        [edges[k], edges[k + 1]).
    noise : NoiseModel
    k_sigma, min_contrast : float
        The validity thresholds (module docstring).
    edge_window : int
        Most pixels per side an edge's sub-pixel zero is fitted over (module docstring); 1: two pixels.
    """
    best = np.ascontiguousarray(votes.best)
    second = np.ascontiguousarray(votes.second, best.dtype)
    index = np.ascontiguousarray(votes.index, np.int32)
    edges = np.ascontiguousarray(edges, np.float64)
    if best.ndim != 2 or best.shape != index.shape or best.shape != second.shape:
        raise ImagingError(f"votes: shapes {best.shape}, {second.shape}, {index.shape} differ or are not 2-D")
    if edges.ndim != 1 or edges.size < 2:
        raise ImagingError(f"edges: need N + 1 >= 2 boundaries, got {edges.shape}")
    if index.size and (index.min() < -1 or index.max() >= edges.size - 1):
        raise ImagingError(f"votes: sheet index outside 0 … {edges.size - 2} (−1: none)")
    if isinstance(edge_window, bool) or not isinstance(edge_window, (int, np.integer)) or edge_window < 1:
        raise ImagingError(f"edge_window: need an integer >= 1 (pixels per side), got {edge_window!r}")
    sat = np.inf if noise.saturation_dn is None else finite_param("saturation", noise.saturation_dn)
    out = np.empty(best.shape)
    tests = _Tests(float(noise.dark_dn), float(noise.read_noise_dn) ** 2, float(noise.dn_per_electron),
                   float(sat), finite_param("k_sigma", k_sigma, low=0.0),
                   finite_param("min_contrast", min_contrast, low=0.0), int(edge_window))
    _delineate_rows(best, second, index, edges, tests, out)
    return out


class _Tests(NamedTuple):
    """The noise model and the validity thresholds, one record for the kernel (numba takes a NamedTuple)."""

    dark: float  # [DN]
    read_var: float  # read noise variance [DN²]
    dn_per_electron: float  # [DN/e⁻]
    saturation: float  # [DN]; inf: none
    k_sigma: float
    min_contrast: float
    edge_window: int  # most pixels per side of an edge's fit


@njit(cache=True, nogil=True)
def _delineate_rows(best, second, index, edges, tests, out):
    dark, read_var, g, sat = tests.dark, tests.read_var, tests.dn_per_electron, tests.saturation
    k, min_contrast, m_win = tests.k_sigma, tests.min_contrast, tests.edge_window
    h, w = best.shape
    ok = np.empty(w, np.bool_)
    kind = np.empty(w + 1, np.int8)  # gap p sits between pixels p − 1 and p: 0 same stripe, 1 edge, 2 break
    xs = np.empty(w + 1)
    cs = np.empty(w + 1)
    ws = np.ones(w + 1, np.int64)  # the window an edge was fitted over
    var = np.empty(w)
    left = np.empty(w, np.int64)
    bf = np.empty(w)  # the row's best and second as float64 (frames may be unsigned integers)
    sf = np.empty(w)
    for i in range(h):
        for j in range(w):
            bf[j], sf[j] = best[i, j], second[i, j]
            b, s = bf[j], sf[j]
            sb = b - dark if b > dark else 0.0
            ss = s - dark if s > dark else 0.0
            var[j] = 2.0 * read_var + g * (sb + ss)
            ok[j] = b < sat and sb >= k * np.sqrt(read_var + g * sb) and index[i, j] >= 0
        kind[0] = 2
        kind[w] = 2
        for p in range(1, w):
            a, c = p - 1, p
            if not (ok[a] and ok[c]):
                kind[p] = 2
                continue
            ia, ic = index[i, a], index[i, c]
            if ia == ic:
                kind[p] = 0
                continue
            if abs(ia - ic) != 1:
                kind[p] = 2
                continue
            # the window grows a pixel per side at a time (up to m_win, while the pixels are ok and of their
            # stripe) until the edge passes: a sharp edge keeps its two-pixel zero, a ramp gets a wider fit
            s1 = s_x = s_y = s_xx = s_xy = 0.0
            mar_l = mar_r = var_l = var_r = sig = 0.0
            n_l = n_r = 0
            open_l = open_r = True
            kind[p] = 2
            for t in range(m_win):
                for side in range(2):
                    j = a - t if side == 0 else c + t
                    if (open_l if side == 0 else open_r) and (
                            j < 0 or j >= w or not ok[j] or index[i, j] != (ia if side == 0 else ic)):
                        if side == 0:
                            open_l = False
                        else:
                            open_r = False
                    if not (open_l if side == 0 else open_r):
                        continue
                    mj = bf[j] - sf[j]
                    y = mj / max(bf[j] + sf[j] - 2.0 * dark, 1e-9)  # (I_a − I_a+1)/(I_a + I_a+1)
                    if side == 1:
                        y = -y
                        mar_r += mj
                        var_r += var[j]
                        n_r += 1
                    else:
                        mar_l += mj
                        var_l += var[j]
                        n_l += 1
                    sig += bf[j] - dark
                    s1 += 1.0
                    s_x += j
                    s_y += y
                    s_xx += j * j
                    s_xy += j * y
                if not (open_l or open_r) and t > 0:
                    break
                tot = mar_l / n_l + mar_r / n_r  # the mean margins of the two sides
                sd = np.sqrt(var_l / (n_l * n_l) + var_r / (n_r * n_r))
                det = s1 * s_xx - s_x * s_x
                slope = (s1 * s_xy - s_x * s_y) / det if det > 0 else 0.0
                if tot > 0 and slope < 0 and tot >= k * sd and tot >= min_contrast * sig / s1:
                    kind[p] = 1  # the zero of the least-squares line through the window: albedo-free
                    x0 = -(s_y - slope * s_x) / s1 / slope
                    xs[p] = min(max(x0, a), c)
                    cs[p] = edges[max(ia, ic)]
                    ws[p] = t + 1
                    break
        last = 0
        for j in range(w):
            if kind[j] != 0:
                last = j
            left[j] = last
        nxt = w
        for j in range(w - 1, -1, -1):
            if kind[j + 1] != 0:
                nxt = j + 1
            pl = left[j]
            out[i, j] = np.nan
            if not ok[j] or kind[pl] != 1 or kind[nxt] != 1:
                continue
            m = bf[j] - sf[j]
            if m < k * np.sqrt(var[j]) and j - pl >= ws[pl] and nxt - j - 1 >= ws[nxt]:
                continue
            xl, xr = xs[pl], xs[nxt]
            lo, hi = edges[index[i, j]], edges[index[i, j] + 1]  # its own stripe's two edges, either way
            if xr <= xl or not ((cs[pl] == lo and cs[nxt] == hi) or (cs[pl] == hi and cs[nxt] == lo)):
                continue
            out[i, j] = cs[pl] + (j - xl) * (cs[nxt] - cs[pl]) / (xr - xl)
