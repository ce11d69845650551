"""Orders of wide-angle scattering beyond the first, in the similarity-scaled medium, on a grid over the tank.

After the forward cone is folded into the quasi-direct light (:mod:`polarstripe.sim.similarity`), the light
that is scattered at wide angles twice or more is smooth in space and direction, so it is carried on a
coarse cell grid over the medium box by successive orders in the P1 form of the integral equation of
transfer. A cell emits (1/4π)(s₀ + 3 s₁·ω) [W m⁻³ sr⁻¹]; its fluence and flux at Y are

    φ(Y) = ∫ e^{−σ̃_t r}/(4π r²) (s₀(X) + 3 s₁(X)·ω̂) dV_X,
    F(Y) = ∫ e^{−σ̃_t r}/(4π r²) (s₀(X) + 3 s₁(X)·ω̂) ω̂ dV_X,        ω̂ = (Y − X)/r, r = |Y − X|,

and scattering by P̃ (mean cosine g̃) turns a field (φ, F) into the next emission (σ̃_s φ, σ̃_s g̃ F). Paths
between two points of the convex box stay inside it, so the kernel is exact for the tank: light that leaves
is lost, as it is at a real tank's walls. The three kernels K₀ = e^{−σr}/(4πr²), K₁ = ω̂K₀, K₂ = ω̂ω̂ᵀK₀ are
integrated over each cell (sub-sampled next to the receiving cell, the self-cell's r⁻² radially in closed
form) and applied by FFT (zero-padded, so the convolution is linear, not circular).

The first emission is the quasi-direct light's (s₀ = σ̃_s φ₀, s₁ = σ̃_s g̃ F₀; :func:`solve_orders`); orders
are added one by one up to a fixed count, and the rest by the geometric tail φ_K r/(1 − r) with r the ratio
of successive orders of a uniform emission in the same grid (≤ 0.98), so the map stays linear in the source
and albedo 1 at τ = 100 ends, finite. Compared with Monte
Carlo in the scaled medium (the paper's tank, TTHG 0.8, σ_t = 2.5–8 m⁻¹): within 3 % for g̃ ≈ 0, 5–10 % for
g̃ ≈ 0.2–0.3, up to 25 % (light too low) for g̃ ≈ 0.5 (HG 0.95, where these orders are < 10 % of B).
Isotropic scattering keeps exactly (g̃ = 0 the P1 form is exact for the emission).
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numba import njit
from polarstripe.sim import tally
from polarstripe.sim.grid_kernels import GridArgs
from polarstripe.sim.threads import blas_one_thread, fft_workers
from scipy import fft as sfft

_PAIRS = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))
_NEAR = 2            # cells within this offset (per axis) are sub-sampled
_SUB = 5             # sub-samples per axis of a near cell
_MAX_RATIO = 0.98    # the geometric tail's largest ratio
_BATCH_BYTES = 1 << 20   # a batch's transforms in pieces of about this size (they stay in the cache)


@dataclass(frozen=True)
class Grid:
    """A cell-centred grid over the box [lo, hi] with n (3,) cells of size h (3,) [m]."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    n: tuple[int, int, int]

    @property
    def h(self) -> np.ndarray:
        return (np.asarray(self.hi) - np.asarray(self.lo)) / np.asarray(self.n)

    def args(self) -> GridArgs:
        return GridArgs(np.asarray(self.lo, float), self.h.astype(float), np.asarray(self.n, np.int64))

    def centres(self) -> np.ndarray:
        """Cell centres (nx, ny, nz, 3)."""
        h = self.h
        axes = [self.lo[a] + (np.arange(self.n[a]) + 0.5) * h[a] for a in range(3)]
        return np.stack(np.meshgrid(*axes, indexing="ij"), -1)


def make_grid(lo, hi, cells: int) -> Grid:
    """A grid of about ``cells`` cells along the box's longest side, cubic-ish cells, at least 2 per axis."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    ext = hi - lo
    n = tuple(int(max(2, round(cells * e / ext.max()))) for e in ext)
    return Grid(tuple(float(x) for x in lo), tuple(float(x) for x in hi), n)


@dataclass(frozen=True)
class Field:
    """A scattered-light field on a grid: fluence φ (nx, ny, nz) [W/m²] and flux F (nx, ny, nz, 3)."""

    phi: np.ndarray
    flux: np.ndarray

    def __add__(self, other: Field) -> Field:
        return Field(self.phi + other.phi, self.flux + other.flux)

    def __sub__(self, other: Field) -> Field:
        return Field(self.phi - other.phi, self.flux - other.flux)


def zero_field(grid: Grid) -> Field:
    return Field(np.zeros(grid.n), np.zeros((*grid.n, 3)))


@dataclass(frozen=True)
class Orders:
    """The solution: ``first`` the once-scattered field (light scattered once at a wide angle), ``total``
    the field of all orders ≥ 1, ``count`` the orders summed before the tail, ``ratio`` the tail's ratio."""

    first: Field
    total: Field
    count: int
    ratio: float


def _fibonacci(n: int) -> np.ndarray:
    k = np.arange(n) + 0.5
    z = 1 - 2 * k / n
    r = np.sqrt(1 - z * z)
    a = math.pi * (1 + 5 ** 0.5) * k
    return np.stack([r * np.cos(a), r * np.sin(a), z], 1)


def _kernel_values(off: np.ndarray, sigma: float, vol: float):
    r = np.linalg.norm(off, axis=-1)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore", under="ignore"):
        k0 = np.exp(-sigma * r) / (4 * np.pi * r * r) * vol
        w = off / r[..., None]
    k1 = w * k0[..., None]
    k2 = np.stack([w[..., a] * w[..., b] * k0 for a, b in _PAIRS], -1)
    return k0, k1, k2


def kernel_tables(n: tuple[int, int, int], h: tuple[float, float, float], sigma: float):
    """Cell-integrated kernels over offsets (2n − 1) per axis (offset 0 at index n − 1): K₀ (…), K₁ (…, 3),
    K₂ (…, 6) with the pairs (xx, yy, zz, xy, xz, yz) — ∫_cell(o) e^{−σr}/(4πr²)·(1, ω̂, ω̂ω̂) dV."""
    h = np.asarray(h, float)
    vol = float(h.prod())
    axes = [np.arange(-(n[a] - 1), n[a]) * h[a] for a in range(3)]
    off = np.stack(np.meshgrid(*axes, indexing="ij"), -1)
    k0, k1, k2 = _kernel_values(off, sigma, vol)
    sub = (np.arange(_SUB) + 0.5) / _SUB - 0.5
    pts = np.stack(np.meshgrid(*(sub * h[a] for a in range(3)), indexing="ij"), -1).reshape(-1, 3)
    c = [n[a] - 1 for a in range(3)]
    rng = [range(-min(_NEAR, n[a] - 1), min(_NEAR, n[a] - 1) + 1) for a in range(3)]
    for i in rng[0]:
        for j in rng[1]:
            for k in rng[2]:
                if i == j == k == 0:
                    continue
                a, b, e = _kernel_values(np.array([i, j, k]) * h + pts, sigma, vol)
                k0[c[0] + i, c[1] + j, c[2] + k] = a.mean()
                k1[c[0] + i, c[1] + j, c[2] + k] = b.mean(0)
                k2[c[0] + i, c[1] + j, c[2] + k] = e.mean(0)
    # the own cell: (1/4π)∫dΩ ∫_0^{R(Ω)} e^{−σr} dr (1, ω, ωω), R the centre's distance to the cell wall
    u = _fibonacci(4096)
    R = np.min(0.5 * h[None, :] / np.maximum(np.abs(u), 1e-12), axis=1)
    radial = -np.expm1(-sigma * R) / sigma if sigma > 0 else R
    k0[tuple(c)] = radial.mean()
    k1[tuple(c)] = 0.0
    k2[tuple(c)] = [float((radial * u[:, a] * u[:, b]).mean()) for a, b in _PAIRS]
    return k0, k1, k2


@njit(cache=True, nogil=True)
def kernel_product(f0, f1, f2, t, out):
    """The P1 kernels' product in Fourier space, per frequency and per field of a batch: out₀ = K̂₀ŝ₀ +
    3(K̂₁·ŝ₁) and outₐ = K̂₁ₐŝ₀ + 3(K̂₂ₐ·ŝ₁) (t (m, 4, …) = m × (ŝ₀, ŝ₁ₓ, ŝ₁ᵧ, ŝ₁_z), f1 (3, …), f2 (3, 3, …);
    in one pass that reads each frequency's kernels once for the whole batch; all in single precision, as the
    transforms are: the factor 3 a float32, not an integer that would promote the sums to double)."""
    a_, b_, c_ = f0.shape
    three = np.float32(3.0)
    for q in range(t.shape[0]):
        for i in range(a_):
            for j in range(b_):
                for k in range(c_):
                    s0, sx, sy, sz = t[q, 0, i, j, k], t[q, 1, i, j, k], t[q, 2, i, j, k], t[q, 3, i, j, k]
                    out[q, 0, i, j, k] = f0[i, j, k] * s0 + three * (f1[0, i, j, k] * sx + f1[1, i, j, k] * sy
                                                                 + f1[2, i, j, k] * sz)
                    for a in range(3):
                        out[q, 1 + a, i, j, k] = f1[a, i, j, k] * s0 + three * (
                            f2[a, 0, i, j, k] * sx + f2[a, 1, i, j, k] * sy + f2[a, 2, i, j, k] * sz)


@lru_cache(maxsize=16)
def _transforms(n: tuple[int, int, int], h: tuple[float, float, float], sigma: float):
    k0, k1, k2 = kernel_tables(n, h, sigma)
    shape = tuple(sfft.next_fast_len(2 * m - 1, real=True) for m in n)
    f0 = sfft.rfftn(k0, shape)
    f1 = [sfft.rfftn(k1[..., a], shape) for a in range(3)]
    f2 = [sfft.rfftn(k2[..., p], shape) for p in range(6)]
    index = {}
    for p, (a, b) in enumerate(_PAIRS):
        index[(a, b)] = index[(b, a)] = p
    f2 = np.stack([np.stack([f2[index[(a, b)]] for b in range(3)]) for a in range(3)])
    return shape, f0, np.stack(f1), f2


@lru_cache(maxsize=16)
def _transforms32(n: tuple[int, int, int], h: tuple[float, float, float], sigma: float):
    shape, f0, f1, f2 = _transforms(n, h, sigma)
    return shape, f0.astype(np.complex64), f1.astype(np.complex64), f2.astype(np.complex64)


def propagate(grid: Grid, sigma: float, s0: np.ndarray, s1: np.ndarray, rank_tol: float = 0.0) -> Field:
    """The field (φ, F) of the emission (1/4π)(s₀ + 3 s₁·ω) [W m⁻³ sr⁻¹] of every cell, with extinction σ.

    In Fourier space φ̂ = K̂₀ŝ₀ + 3 K̂₁·ŝ₁ and F̂_a = K̂₁ₐŝ₀ + 3 Σ_b K̂₂ₐᵦŝ₁ᵦ: the four inputs go through one
    batched transform each way (:func:`polarstripe.sim.threads.fft_workers` threads), one axis at a time,
    in single precision (half the memory traffic; ~10⁻⁷ of the largest value, docs/physics.md §10.3), the
    field returned in double. ``s0`` (…, nx, ny, nz) and ``s1`` (…, nx, ny, nz, 3) may carry leading batch
    axes (the frames of a scan, :mod:`polarstripe.sim.scan_render`): each field of the batch is transformed
    line by line as it would be alone (the same numbers, ``tests/sim/test_scan_render.py``).

    ``rank_tol`` > 0 (a batch): the batch's sources X (m × 4N) are replaced by their truncated singular
    value decomposition X ≈ Σ_{i<r} u_i s_i v_iᵀ, keeping s_i > rank_tol·s_0; only the r basis sources v_i are
    transformed and each field is Σ u_i s_i P(v_i) (the map P is linear). The error of a field is at most
    the dropped part of its source (docs/physics.md §10.6, "A scan's solves in low rank")."""
    since = tally.start()
    n = tuple(int(m) for m in grid.n)
    shape, f0, f1, f2 = _transforms32(n, tuple(float(x) for x in grid.h), float(sigma))
    lead = s0.shape[:-3]
    m = math.prod(lead)
    src = np.empty((m, 4) + n, np.float32)
    src[:, 0] = s0.reshape((m,) + n)
    src[:, 1:] = np.moveaxis(s1.reshape((m,) + n + (3,)), -1, 1)
    low = rank_tol > 0.0 and m > 2
    with blas_one_thread() if low else contextlib.nullcontext():
        basis, coef = _low_rank(src, rank_tol) if low else (src, None)
        res = np.empty(basis.shape, np.float32)
        step = max(1, _BATCH_BYTES // (32 * math.prod(shape[:2]) * (shape[2] // 2 + 1)))   # complex64, 4 in
        for a in range(0, len(basis), step):
            res[a:a + step] = _convolve(basis[a:a + step], n, shape, f0, f1, f2)
        if coef is not None:
            res = np.tensordot(coef, res, 1).astype(np.float32)
    phi = np.maximum(res[:, 0], 0.0).astype(float).reshape(lead + n)
    out = Field(phi, np.moveaxis(res[:, 1:], 1, -1).astype(float).reshape(lead + n + (3,)))
    tally.add(len(basis), since)                                   # for benches (sim/tally.py)
    return out


def _low_rank(src: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray | None]:
    """(basis (r, …), coefficients (m, r)) with src ≈ coefficients · basis: the singular vectors of the
    batch (m, …) whose singular values exceed ``tol`` times the largest, from the eigenvectors of the m × m
    Gram matrix (cheap for m ≪ N; accurate for the values kept, all ≥ tol·s₀ ≫ √ε·s₀). (src, None) when
    nothing would be saved."""
    m = src.shape[0]
    x = src.reshape(m, -1).astype(np.float64)
    lam, u = np.linalg.eigh(x @ x.T)
    lam, u = lam[::-1], u[:, ::-1]
    if not lam[0] > 0.0:
        return src, None
    r = int(np.count_nonzero(lam > (tol * tol) * lam[0]))
    if r >= m - 1:
        return src, None
    s = np.sqrt(lam[:r])
    basis = ((u[:, :r].T @ x) / s[:, None]).astype(np.float32).reshape((r,) + src.shape[1:])
    return basis, u[:, :r] * s


def _convolve(src: np.ndarray, n, shape, f0, f1, f2) -> np.ndarray:
    """:func:`propagate`'s transforms of a batch (m, 4, nx, ny, nz): rfftn and irfftn axis by axis in their
    own order (the same numbers), skipping the lines that are zero padding on the way in and the ones
    sliced away on the way out."""
    workers = fft_workers()
    t = sfft.rfft(src, shape[2], axis=4, workers=workers)
    t = sfft.fft(sfft.fft(t, shape[0], axis=2, workers=workers), shape[1], axis=3, workers=workers)
    out = np.empty_like(t)
    kernel_product(f0, f1, f2, t, out)
    res = sfft.ifft(out, axis=2, workers=workers)[:, :, n[0] - 1:2 * n[0] - 1]
    res = sfft.ifft(res, axis=3, workers=workers)[:, :, :, n[1] - 1:2 * n[1] - 1]
    return sfft.irfft(res, shape[2], axis=4, workers=workers)[..., n[2] - 1:2 * n[2] - 1]


def _emission(field: Field, sigma_s: float, g: float) -> tuple[np.ndarray, np.ndarray]:
    """(s₀, s₁) = (σ̃_s φ, σ̃_s g̃ F), s₁ shortened where |3 s₁| > s₀ so the emission is nowhere negative."""
    s0 = sigma_s * field.phi
    s1 = sigma_s * g * field.flux
    norm = 3.0 * np.linalg.norm(s1, axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        cut = np.where(norm > s0, s0 / np.where(norm > 0, norm, 1.0), 1.0)
    return s0, s1 * cut[..., None]


@lru_cache(maxsize=32)
def tail_ratio(grid: Grid, sigma_t: float, sigma_s: float, g: float, orders: int) -> float:
    """The ratio of successive orders after ``orders`` of them, from a uniform emission (the medium's and the
    grid's alone, so :func:`solve_orders` stays one linear operator for every source); ≤ 0.98."""
    z = Field(np.ones(grid.n), np.zeros((*grid.n, 3)))
    prev = float(z.phi.sum())
    ratio = 0.0
    for _ in range(max(int(orders), 2)):
        s0, s1 = _emission(z, sigma_s, g)
        z = propagate(grid, sigma_t, s0, s1)
        cur = float(z.phi.sum())
        ratio = cur / prev if prev > 0 else 0.0
        prev = cur
    return float(min(max(ratio, 0.0), _MAX_RATIO))


def solve_orders(grid: Grid, quasi: Field, sigma_t: float, sigma_s: float, g: float, *,
                 orders: int = 6, rank_tol: float = 0.0) -> Orders:
    """All orders ≥ 1 of wide-angle scattering of the quasi-direct field ``quasi`` (φ₀, F₀).

    Parameters
    ----------
    grid : the cell grid; quasi : the unscattered (quasi-direct) light's fluence and flux on it, or a batch
        of them (leading axes: each solved as it would be alone, :func:`solve_each`).
    sigma_t, sigma_s, g : σ̃_t, σ̃_s [1/m] and g̃ of the scaled medium.
    orders : orders computed one by one; the rest is the geometric tail φ_K r/(1 − r) with r from
        :func:`tail_ratio`. A fixed count and ratio keep the map from ``quasi`` to the result linear (the
        stripes of a scan add up to the flood frame).
    rank_tol : a batch's sources in low rank at each order (:func:`propagate`); 0: exact.

    Returns
    -------
    Orders: the once-scattered field and the sum of all orders (φ, F), in W/m².
    """
    if int(orders) < 1:
        raise ValueError(f"solve_orders: orders must be >= 1, got {orders!r}")
    if sigma_s <= 0.0 or not np.any(quasi.phi > 0):
        z = Field(np.zeros_like(quasi.phi), np.zeros_like(quasi.flux))
        return Orders(z, z, 0, 0.0)
    s0, s1 = _emission(quasi, sigma_s, g)
    first = propagate(grid, sigma_t, s0, s1, rank_tol)
    total, last = first, first
    for _ in range(int(orders) - 1):
        s0, s1 = _emission(last, sigma_s, g)
        last = propagate(grid, sigma_t, s0, s1, rank_tol)
        total = total + last
    ratio = tail_ratio(grid, float(sigma_t), float(sigma_s), float(g), int(orders))
    tail = ratio / (1.0 - ratio)
    total = Field(total.phi + tail * last.phi, total.flux + tail * last.flux)
    return Orders(first, total, int(orders), ratio)


def solve_polarized(grid: Grid, quasi: Field, sigma_p: float, sigma_s: float, g: float, *, kappa: float,
                    orders: int = 6, rank_tol: float = 0.0) -> Field:
    """The polarized part Σ_k κ^k φ_p^(k) of the orders ≥ 1 (docs/physics.md §10.4).

    ``quasi`` is the quasi-direct field's polarized part (deposited with the polarized extinction σ_p),
    propagated with σ_p between wide-angle scatterings (each cone scattering on the way keeps r_c of the
    polarization) and each order k weighted by κ^k (the fraction of the polarization a wide-angle scattering
    keeps). Orders after ``orders`` are the geometric tail with ratio κ·r, r from :func:`tail_ratio` at σ_p.
    """
    if int(orders) < 1:
        raise ValueError(f"solve_polarized: orders must be >= 1, got {orders!r}")
    if not 0.0 <= kappa <= 1.0:
        raise ValueError(f"solve_polarized: kappa must be in [0, 1], got {kappa!r}")
    if sigma_s <= 0.0 or kappa == 0.0 or not np.any(quasi.phi > 0):
        return Field(np.zeros_like(quasi.phi), np.zeros_like(quasi.flux))
    last, weight = quasi, 1.0
    pol = Field(np.zeros_like(quasi.phi), np.zeros_like(quasi.flux))
    for _ in range(int(orders)):
        s0, s1 = _emission(last, sigma_s, g)
        last = propagate(grid, sigma_p, s0, s1, rank_tol)
        weight *= kappa
        pol = Field(pol.phi + weight * last.phi, pol.flux + weight * last.flux)
    ratio = kappa * tail_ratio(grid, float(sigma_p), float(sigma_s), float(g), int(orders))
    tail = weight * ratio / (1.0 - ratio)
    return Field(pol.phi + tail * last.phi, pol.flux + tail * last.flux)


@dataclass(frozen=True, eq=False)
class GridSolve:
    """One grid solve a frame asks for: :func:`solve_orders` of ``quasi`` (``kappa`` None) or
    :func:`solve_polarized` with ``kappa``. A frame's computation yields these and takes the answers
    (:func:`answer`), so that a scan's frames can hand theirs over together (:func:`solve_each`)."""

    grid: Grid
    quasi: Field
    sigma: float
    sigma_s: float
    g: float
    orders: int
    kappa: float | None = None

    def key(self) -> tuple:
        """Requests with the same key are solved as one batch."""
        return (self.grid, float(self.sigma), float(self.sigma_s), float(self.g), int(self.orders),
                self.kappa, self.quasi.phi.shape)

    def solve(self, quasi: Field, rank_tol: float = 0.0):
        if self.kappa is None:
            return solve_orders(self.grid, quasi, self.sigma, self.sigma_s, self.g, orders=self.orders,
                                rank_tol=rank_tol)
        return solve_polarized(self.grid, quasi, self.sigma, self.sigma_s, self.g, kappa=self.kappa,
                               orders=self.orders, rank_tol=rank_tol)


def answer(steps):
    """Run a frame's steps (a generator yielding :class:`GridSolve`), answering each request on its own;
    returns what the generator returns."""
    try:
        request = next(steps)
        while True:
            request = steps.send(request.solve(request.quasi))
    except StopIteration as done:
        return done.value


def solve_each(requests: list[GridSolve], rank_tol: float = 0.0) -> list:
    """The answers to requests of one :meth:`GridSolve.key`, solved as one batch along a leading axis (the
    map is the same for each; every field comes out as its own solve gives it). A request whose source is
    zero gets the zero answer its own solve gives (no orders counted). ``rank_tol`` > 0: the batch in low
    rank (:func:`propagate`), each field then within that tolerance of its own solve, not equal to it."""
    first = requests[0]
    live = [k for k, r in enumerate(requests) if np.any(r.quasi.phi > 0)]
    out = [first.solve(r.quasi) if k not in live else None for k, r in enumerate(requests)]
    if not live:
        return out
    both = first.solve(Field(np.stack([requests[k].quasi.phi for k in live]),
                             np.stack([requests[k].quasi.flux for k in live])), rank_tol)
    for j, k in enumerate(live):
        if first.kappa is not None:
            out[k] = Field(both.phi[j], both.flux[j])
        else:
            out[k] = Orders(Field(both.first.phi[j], both.first.flux[j]),
                            Field(both.total.phi[j], both.total.flux[j]), both.count, both.ratio)
    return out
