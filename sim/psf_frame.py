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
from polarstripe.sim.geometry_cache import cached, camera_only
from polarstripe.sim.psf import N_LADDER, HaloTable, blur_image, blur_levels, mixture
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


class Leg(NamedTuple):
    """One leg's per-pixel factors, the same for every pattern (kept per scene): the fraction spread
    w = 1 − e^{−n} and the fraction kept sharp 1 − w (both 0 off the objects), and the halo rms [px]
    (float32)."""

    spread: np.ndarray
    keep: np.ndarray
    rms: np.ndarray


@njit(cache=True, nogil=True)
def leg_factors(hit, ell, footprint, f_sigma_s, ladder, spread_out, keep_out, rms_out):
    """Per pixel that sees an object: n = fσ_sℓ, w = 1 − e^{−n}, the halo rms [px] (the table's rms per unit
    path, interpolated in log n, times ℓ over the pixel's footprint); spread_out = w, keep_out = 1 − w.
    Other pixels: 0 (rms_out left as it is)."""
    log_ladder, rms_table = ladder
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
        spread_out[i] = w
        keep_out[i] = 1.0 - w


@njit(cache=True, nogil=True)
def leg_split(spread, keep, value, spread_out, keep_out):
    """A frame's value split by its leg: spread_out = w·value (float32), keep_out = (1 − w)·value."""
    for i in range(value.size):
        spread_out[i] = spread[i] * value[i]
        keep_out[i] = keep[i] * value[i]


@njit(cache=True, nogil=True)
def camera_input(hit, halo_l, rest_unit, keep_l, albedo, spread_c, extra_out, spread_out):
    """The camera leg's input: extra = halo_L + Ã/ρ on the objects (0 beside them), the radiance
    R = ρ·(keep_L + extra) and its spread part w_C·R (float32)."""
    for i in range(hit.size):
        e = halo_l[i] + rest_unit[i] if hit[i] else 0.0
        extra_out[i] = e
        spread_out[i] = spread_c[i] * (albedo[i] * (keep_l[i] + e))


def _leg(hit, ell, footprint, f_sigma_s, ladder) -> Leg:
    """:func:`leg_factors` over bands of pixels (:func:`polarstripe.sim.threads.in_bands`)."""
    out = Leg(np.empty(hit.size), np.empty(hit.size), np.zeros(hit.size, np.float32))
    in_bands(hit.size, lambda a, b: leg_factors(hit[a:b], ell[a:b], footprint[a:b], f_sigma_s, ladder,
                                                *(x[a:b] for x in out)))
    return out


class Legs(NamedTuple):
    """What the blurs of a whole frame share with every pattern: both legs' factors, each object's mask
    and its source-leg halo mixture, the camera leg's mixture and e^{−n_C}; the blur levels of
    :func:`polarstripe.sim.psf.blur_levels` per object (``levels``) and for the camera leg."""

    source: Leg
    camera: Leg
    masks: tuple
    mixtures: tuple
    levels: tuple
    camera_mixture: np.ndarray
    camera_levels: tuple
    keep_c: np.ndarray


def _legs(view, table: HaloTable, f_sigma_s: float, ells) -> Legs:
    cam, dirs, hits, surf = view.cam, view.dirs, view.hits, view.surf
    hit = surf.object_id >= 0
    shape = (cam.h, cam.w)
    footprint = np.empty(hit.size)
    footprints(hit, hits.point, dirs, hits.normal, np.asarray(cam.position, float), float(cam.s), footprint)
    ladder = Ladder(_LOG_LADDER, np.ascontiguousarray(table.rms, float))
    source, camera = (_leg(hit, ell, footprint, f_sigma_s, ladder) for ell in ells)
    masks, mixtures, levels = [], [], []
    for k in range(len(view.scene.objects)):
        mask = surf.object_id == k
        if not mask.any():
            continue
        masks.append((k, mask.reshape(shape)))
        mixtures.append(mixture(table, f_sigma_s * float(np.median(ells[0][mask][::7]))))
        levels.append(blur_levels(source.rms.reshape(shape), mask.reshape(shape)))
    if hit.any():
        camera.rms[~hit] = float(np.median(camera.rms[hit][::7]))      # pixels beside the object receive too
    n_med = f_sigma_s * float(np.median(ells[1][hit][::7])) if hit.any() else 0.0
    return Legs(source, camera, tuple(masks), tuple(mixtures), tuple(levels), mixture(table, n_med),
                blur_levels(camera.rms.reshape(shape)), np.exp(-f_sigma_s * ells[1]))


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
    cam, surf = view.cam, view.surf
    hit = surf.object_id >= 0
    shape, npx = (cam.h, cam.w), cam.h * cam.w
    legs = cached(view.scene, ("legs", cam.w, cam.h, f_sigma_s), lambda: _legs(view, table, f_sigma_s, ells))
    spread_l, keep_l = np.empty(npx, np.float32), np.empty(npx)
    in_bands(npx, lambda a, b: leg_split(legs.source.spread[a:b], legs.source.keep[a:b], quasi[a:b],
                                         spread_l[a:b], keep_l[a:b]))
    halo_l = np.zeros(npx)
    for (k, mask), mix, levels in zip(legs.masks, legs.mixtures, legs.levels, strict=True):
        norms = cached(camera_only(view.scene), ("mask_norms", cam.w, cam.h, k), dict)   # any pose's
        halo_l += blur_image(spread_l.reshape(shape), legs.source.rms.reshape(shape), mix, mask, norms,
                             levels).ravel()
    extra, spread_c = np.empty(npx), np.empty(npx, np.float32)
    in_bands(npx, lambda a, b: camera_input(hit[a:b], halo_l[a:b], rest_unit[a:b], keep_l[a:b],
                                            surf.albedo[a:b], legs.camera.spread[a:b], extra[a:b],
                                            spread_c[a:b]))
    halo = blur_image(spread_c.reshape(shape), legs.camera.rms.reshape(shape), legs.camera_mixture,
                      levels=legs.camera_levels)
    extra *= legs.keep_c                                      # P, in place
    return extra, halo.ravel().astype(float)
