"""The objects' glow on the higher orders' grid (docs/physics.md §10.3), for :mod:`polarstripe.sim.higher`.

Each object patch is a Lambertian source of exitance M = ρ(E_quasi + E_grid). Its first wide-angle scattering
toward the camera is summed over the patches at every cell with the exact P̃ (the glow's first flight is too
directional for P1); the orders after it come from the grid.

Both are linear in the patches' exitance, and everything else in them — the patches, their beams through
the grid, the phase, solid angle and attenuation between each patch and each cell — is the same for every
frame of a scan. Where it is small (:data:`BASIS_VALUES`) that part is kept per scene: the once-scattered
emission is then one matrix–vector product with the exitance, the first flight a weighted sum of each
patch's field (:func:`glow_basis`); equal to computing them anew to rounding (the products are associated
differently), ``tests/sim/test_glow_basis.py``.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit
from polarstripe.sim.backscatter import geo
from polarstripe.sim.geometry import Hits
from polarstripe.sim.grid_kernels import deposit_beams, glow_emission, patch_glow, unit_toward
from polarstripe.sim.grid_patches import (
    glow_beams,
    glow_field,
    object_patches,
    patch_irradiance,
    quasi_irradiance,
)
from polarstripe.sim.grid_patches import patch_light as light_of
from polarstripe.sim.grid_sources import surface_irradiance
from polarstripe.sim.kernel_records import PhaseArgs
from polarstripe.sim.multiple import Field, Grid, GridSolve, answer, zero_field
from polarstripe.sim.similarity import truncated_code
from polarstripe.sim.surface import surface_info
from polarstripe.sim.threads import in_bands

BASIS_VALUES = 2_000_000     # cells × patches × 4 above which nothing is kept (16 MB; `reference`'s grid)


@njit(cache=True, nogil=True)
def glow_weights(points, eye, patches, phase, sigma, out):
    """out[m, p] = P̃(μ_p) Ω_p e^{−σ̃ r_p} of :func:`~polarstripe.sim.grid_kernels.glow_emission` (its terms
    without the patch's radiance; 0 where it adds nothing), ``patches`` (k, 7): centre, normal, area."""
    for m in range(points.shape[0]):
        yx, yy, yz = points[m, 0], points[m, 1], points[m, 2]
        ex, ey, ez = unit_toward(eye, yx, yy, yz)
        for p in range(patches.shape[0]):
            out[m, p] = patch_glow(patches, p, yx, yy, yz, ex, ey, ez, phase, sigma)


@njit(cache=True, nogil=True)
def weighted_rows(weights, values, scale, out):
    """out[m] = scale·Σ_p weights[m, p]·values[p]."""
    for m in range(weights.shape[0]):
        acc = 0.0
        for p in range(weights.shape[1]):
            acc += weights[m, p] * values[p]
        out[m] = scale * acc


class GlowBasis(NamedTuple):
    """Per scene: the patches and their albedo, which of them have area (``keep``), the emission weights
    (cells, kept patches) of :func:`glow_weights`, and each kept patch's first-flight field at unit
    exitance, φ (cells, kept patches) and F (cells·3, kept patches) (None: too large to keep)."""

    patches: object
    albedo: np.ndarray
    keep: np.ndarray
    weights: np.ndarray | None
    phi: np.ndarray | None
    flux: np.ndarray | None


def glow_basis(scene, grid: Grid, cells: np.ndarray, eye: np.ndarray, sigma: float, phase: PhaseArgs,
               spacing: float, directions: int) -> GlowBasis:
    """The patches ``spacing`` apart and, where cells × patches × 4 ≤ :data:`BASIS_VALUES`, the emission
    weights toward ``eye`` at ``cells`` (m, 3) and the unit-exitance field of each patch's beams."""
    patches = object_patches(scene.objects, grid.lo, grid.hi, spacing)
    hits = Hits(np.ones(patches.area.size), patches.index, patches.normal, patches.point)
    albedo = surface_info(scene.objects, hits).albedo
    keep = np.nonzero(patches.area > 0)[0]
    if keep.size == 0 or cells.shape[0] * keep.size * 4 > BASIS_VALUES:
        return GlowBasis(patches, albedo, keep, None, None, None)
    packed = np.ascontiguousarray(np.column_stack([patches.point, patches.normal, patches.area]))
    weights = np.empty((cells.shape[0], patches.area.size))
    in_bands(cells.shape[0], lambda a, b: glow_weights(cells[a:b], eye, packed, phase, sigma, weights[a:b]),
             min_size=256)
    beams = glow_beams(grid, patches, keep, scene.objects, directions)
    k = beams.dirs.shape[0] // keep.size
    phi, flux = np.zeros((keep.size, *grid.n)), np.zeros((keep.size, *grid.n, 3))
    for i in range(keep.size):
        one = slice(i * k, (i + 1) * k)
        deposit_beams(grid.args(), type(beams)(*(x[one] for x in beams)), float(sigma),
                      0.5 * float(grid.h.min()), phi[i], flux[i])
    return GlowBasis(patches, albedo, keep, np.ascontiguousarray(weights[:, keep]),
                     np.ascontiguousarray(phi.reshape(keep.size, -1).T),
                     np.ascontiguousarray(flux.reshape(keep.size, -1).T))


def glow_fields(view, ssrc, plan, st, grid: Grid, total: Field, patch_light=None) -> tuple[Field, Field]:
    """The objects' glow on the grid: the field to view (its emission toward the camera) and the scattered
    glow field (whose irradiance lights the objects again); module docstring. ``patch_light(patches)``, where
    given, is the patches' quasi-direct irradiance (a projector behind a port); else the pinhole source's."""
    return answer(glow_steps(view, ssrc, plan, st, grid, total, patch_light))


def glow_steps(view, ssrc, plan, st, grid: Grid, total: Field, patch_light=None):
    """:func:`glow_fields` as steps that yield its grid solve (a
    :class:`~polarstripe.sim.multiple.GridSolve`)."""
    scene, sc = view.scene, plan.scaled
    eye = np.asarray(view.cam.position, float)
    phase = PhaseArgs(*truncated_code(sc.phase))
    spacing = st.patch_cells * float(grid.h.min())
    basis = geo(view, ("glow", grid, spacing, st.glow_dirs, float(sc.sigma_t), tuple(phase)),
                lambda: glow_basis(scene, grid, grid.centres().reshape(-1, 3), eye, float(sc.sigma_t), phase,
                                   spacing, st.glow_dirs), camera_only=True)
    patches = basis.patches
    if patches.area.size == 0:
        return zero_field(grid), zero_field(grid)
    if patch_light is not None:
        e = patch_light(patches)
    elif ssrc.frame is not None:            # area-averaged; what the pattern does not change, per scene
        e = patch_irradiance(ssrc, geo(view, ("patch_light", spacing, float(ssrc.sigma_t)), lambda: light_of(
            ssrc, scene.objects, patches.point, patches.normal, patches.du, patches.dv)))
    else:
        e = quasi_irradiance(ssrc, scene.objects, patches.point, patches.normal)
    exitance = basis.albedo * (e + surface_irradiance(grid, total, patches.point, patches.normal))
    j1 = np.empty(int(np.prod(grid.n)))
    keep = basis.keep
    if basis.weights is not None and np.array_equal(np.nonzero(exitance * patches.area > 0)[0], keep):
        radiance = np.ascontiguousarray(exitance[keep] / np.pi)
        in_bands(j1.size, lambda a, b: weighted_rows(basis.weights[a:b], radiance, float(sc.sigma_s),
                                                     j1[a:b]), min_size=256)
        ex = np.ascontiguousarray(exitance[keep])
        phi, flux = np.empty(basis.phi.shape[0]), np.empty(basis.flux.shape[0])
        for out, rows in ((phi, basis.phi), (flux, basis.flux)):
            in_bands(out.size, lambda a, b, o=out, r=rows: weighted_rows(r[a:b], ex, 1.0, o[a:b]),
                     min_size=256)
        first = Field(phi.reshape(grid.n), flux.reshape(*grid.n, 3))
    else:
        packed = np.ascontiguousarray(np.column_stack([patches.point, patches.normal, patches.area,
                                                       exitance / np.pi]))
        cells = grid.centres().reshape(-1, 3)
        in_bands(j1.size, lambda a, b: glow_emission(cells[a:b], eye, packed, phase, float(sc.sigma_t),
                                                     float(sc.sigma_s), j1[a:b]), min_size=256)
        first = glow_field(grid, patches, exitance, sc.sigma_t, scene.objects, st.glow_dirs)
    more = yield GridSolve(grid, first, sc.sigma_t, sc.sigma_s, sc.g_tilde, st.glow_orders)
    c = sc.sigma_s / (4 * np.pi)
    return Field(more.total.phi + j1.reshape(grid.n) / c, more.total.flux), more.total
