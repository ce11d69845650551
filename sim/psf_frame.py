"""The forward-cone blurs of :mod:`polarstripe.sim.psf` on whole frames.

The object's quasi-direct irradiance E (per unit albedo) keeps e^{−n_L} sharp and spreads the rest with the
source path's halo on the object (normalised over each object's pixels); its radiance R = ρ·E_blurred + Ã
then keeps e^{−n_C} sharp and spreads the rest with the camera path's halo in the image (into pixels beside
the object as well). Widths are converted to pixels with each pixel's footprint d·s/√|cos| on the object.
The per-pixel arithmetic is one compiled pass per leg (:func:`leg_inputs`).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit
from polarstripe.sim.geometry_cache import cached
from polarstripe.sim.psf import N_LADDER, HaloTable, blur_image, mixture
from polarstripe.sim.threads import in_bands

_LOG_LADDER = np.log(N_LADDER)


@njit(cache=True, nogil=True)
def footprints(hit, points, dirs, normals, cam, pitch, out):
    """A pixel's footprint on the object [m]: distance·pitch/√max(|cos|, 0.05) (1 where nothing is hit)."""
    for i in range(hit.size):
        if not hit[i]:
            out[i] = 1.0
            continue
        dx, dy, dz = points[i, 0] - cam[0], points[i, 1] - cam[1], points[i, 2] - cam[2]
        c = abs(dirs[i, 0] * normals[i, 0] + dirs[i, 1] * normals[i, 1] + dirs[i, 2] * normals[i, 2])
        out[i] = math.sqrt(dx * dx + dy * dy + dz * dz) * pitch / math.sqrt(max(c, 0.05))


class Ladder(NamedTuple):
    """The halo table for the compiled pass: log n of the ladder (m,) and the rms per unit path (m,)."""

    log_n: np.ndarray
    rms: np.ndarray


class LegOut(NamedTuple):
    """Per pixel: what it spreads (float32), its halo rms [px] (float32), what it keeps sharp."""

    spread: np.ndarray
    rms: np.ndarray
    keep: np.ndarray


@njit(cache=True, nogil=True)
def leg_inputs(hit, value, ell, footprint, f_sigma_s, ladder, out):
    """Per pixel that sees an object: n = fσ_sℓ, w = 1 − e^{−n}, the halo rms [px] (the table's rms per unit
    path, interpolated in log n, times ℓ over the pixel's footprint); out.spread = w·value,
    out.keep = (1 − w)·value. Other pixels: 0 (out.rms left as it is)."""
    log_ladder, rms_table = ladder
    spread_out, rms_out, keep_out = out
    m = log_ladder.size
    for i in range(hit.size):
        if not hit[i]:
            spread_out[i] = 0.0
            keep_out[i] = 0.0
            continue
        n = f_sigma_s * ell[i]
        w = -math.expm1(-n)
        ln = math.log(max(n, 1e-12))
        if ln <= log_ladder[0]:
            r = rms_table[0]
        elif ln >= log_ladder[m - 1]:
            r = rms_table[m - 1]
        else:
            j = 0
            while log_ladder[j + 1] < ln:
                j += 1
            t = (ln - log_ladder[j]) / (log_ladder[j + 1] - log_ladder[j])
            r = (1 - t) * rms_table[j] + t * rms_table[j + 1]
        rms_out[i] = r * ell[i] / footprint[i]
        spread_out[i] = w * value[i]
        keep_out[i] = (1.0 - w) * value[i]


def _legs(hit, value, ell, footprint, f_sigma_s, ladder, out: LegOut) -> None:
    """:func:`leg_inputs` over bands of pixels (:func:`polarstripe.sim.threads.in_bands`)."""
    in_bands(hit.size, lambda a, b: leg_inputs(hit[a:b], value[a:b], ell[a:b], footprint[a:b], f_sigma_s,
                                               ladder, LegOut(*(x[a:b] for x in out))))


def object_radiance(view, table: HaloTable, f_sigma_s: float, quasi: np.ndarray, rest_unit: np.ndarray,
                    ells: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """The object light beyond D, per pixel (flat (h·w,)), after both blurs (module docstring): A = ρ·P + H.

    Parameters
    ----------
    view : the render's View (whole frame); table : the phase function's halo table.
    f_sigma_s : f σ_s [1/m], the rate of forward-cone scatterings.
    quasi : (h·w,) quasi-direct object radiance per unit albedo; rest_unit : (h·w,) Ã per unit albedo.
    ells : (h·w,) in-medium path lengths source → hit and camera → hit [m].

    Returns
    -------
    P : (h·w,) what stays on the pixel, per unit albedo: e^{−n_C}(halo_L + Ã/ρ) (its e^{−n_C}e^{−n_L}·quasi is
        exactly D/ρ and is left out);
    H : (h·w,) the camera path's halo of the object radiance (albedo included), also beside the objects.
    """
    cam, dirs, hits, surf = view.cam, view.dirs, view.hits, view.surf
    hit = surf.object_id >= 0
    shape, npx = (cam.h, cam.w), cam.h * cam.w
    def footprint_of():
        out = np.empty(npx)
        footprints(hit, hits.point, dirs, hits.normal, np.asarray(cam.position, float), float(cam.s), out)
        return out

    footprint = cached(view.scene, ("footprint", cam.w, cam.h), footprint_of)    # the same every pattern
    ladder = Ladder(_LOG_LADDER, np.ascontiguousarray(table.rms, float))
    spread_l, rms_l, keep_l = np.zeros(npx, np.float32), np.zeros(npx, np.float32), np.zeros(npx)
    _legs(hit, quasi, ells[0], footprint, f_sigma_s, ladder, LegOut(spread_l, rms_l, keep_l))
    halo_l = np.zeros(npx)
    ids = surf.object_id
    for k in range(len(view.scene.objects)):
        mask = ids == k
        if not mask.any():
            continue
        n_med = f_sigma_s * float(np.median(ells[0][mask][::7]))
        norms = cached(view.scene, ("mask_norms", cam.w, cam.h, k), dict)  # the object's mask, every pattern
        halo = blur_image(spread_l.reshape(shape), rms_l.reshape(shape), mixture(table, n_med),
                          mask.reshape(shape), norms)
        halo_l += halo.ravel()
    extra = np.where(hit, halo_l + rest_unit, 0.0)
    rad = surf.albedo * (keep_l + extra)
    spread_c, rms_c, keep_c = np.zeros(npx, np.float32), np.zeros(npx, np.float32), np.zeros(npx)
    _legs(hit, rad, ells[1], footprint, f_sigma_s, ladder, LegOut(spread_c, rms_c, keep_c))
    if hit.any():
        rms_c[~hit] = float(np.median(rms_c[hit][::7]))                # pixels beside the object receive too
    n_med = f_sigma_s * float(np.median(ells[1][hit][::7])) if hit.any() else 0.0
    halo = blur_image(spread_c.reshape(shape), rms_c.reshape(shape), mixture(table, n_med))
    keep = cached(view.scene, ("keep_c", cam.w, cam.h, f_sigma_s), lambda: np.exp(-f_sigma_s * ells[1]))
    return keep * extra, halo.ravel().astype(float)
