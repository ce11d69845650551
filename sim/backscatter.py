"""B of the all-orders model beyond the grid: its single wide-angle scattering, the forward cone toward the
camera, and its polarization through every order (docs/physics.md §10.3, §10.4); used by
:mod:`polarstripe.sim.higher`.

Polarization: each scattering inside the forward cone keeps r_c of the linear polarization and each further
wide-angle scattering κ (:mod:`polarstripe.sim.similarity`), so the polarized part travels with the
extinction σ_p = σ̃_t + (1 − r_c)·f·σ_s: single wide-angle scattering's Stokes sums take it in the line
integral (a source with ``sigma_pol``), orders ≥ 2 come from a grid chain with σ_p and κ per order, in the
orientation of the single wide-angle scattering at the pixel.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import numpy as np
from polarstripe.sim.frame_kernels import polarized_gain
from polarstripe.sim.geometry import Hits, box_interval
from polarstripe.sim.geometry_cache import cached
from polarstripe.sim.geometry_cache import camera_only as pose_free
from polarstripe.sim.grid_kernels import coarse_silhouettes, upsample_grid
from polarstripe.sim.grid_sources import source_field
from polarstripe.sim.multiple import Field, Grid, GridSolve, answer
from polarstripe.sim.orders import OrdersPlan
from polarstripe.sim.similarity import pair_retention_of, polarized_extinction
from polarstripe.sim.surface_field import View, single_parts
from polarstripe.sim.threads import in_bands
from polarstripe.sim.transport import Source

if TYPE_CHECKING:
    from polarstripe.sim.higher import HigherSettings


def scaled_source(src: Source, plan: OrdersPlan) -> Source:
    sc = plan.scaled
    return dataclasses.replace(src, sigma_t=sc.sigma_t, sigma_s=sc.sigma_s, phase=sc.phase)


def geo(view: View, name, make, camera_only: bool = False):
    """``make()`` once per scene and frame size for whole frames (:mod:`polarstripe.sim.geometry_cache`),
    every time for requested pixels; ``camera_only``: the value does not depend on the projector, kept once
    for every projector pose (:func:`polarstripe.sim.geometry_cache.camera_only`)."""
    if view.pixels is not None:
        return make()
    return cached(pose_free(view.scene) if camera_only else view.scene, (name, view.cam.w, view.cam.h), make)


def b_single(view: View, ssrc: Source, need, div: int, x_end: np.ndarray):
    """B's single wide-angle scattering and its Stokes (B, Bq, Bu, Bv), every pixel or (``div`` > 1, whole
    frames) on a grid of every div-th pixel, bilinear in between (B is continuous across the image except
    at silhouettes: pixels whose coarse neighbours end their rays (``x_end`` per pixel) more than 1 cm or
    1 % away from their own are computed exactly)."""
    keys = tuple(k for k in ("B", "p") if k in need)
    if div <= 1 or view.pixels is not None:
        return single_parts(view, ssrc, keys)[2:]
    cam = view.cam
    gh, gw = -(-(cam.h - 1) // div) + 1, -(-(cam.w - 1) // div) + 1      # every div-th pixel, past the last

    def coarse_rays():      # the same for every pattern
        gr, gc = np.arange(gh) * div, np.arange(gw) * div                  # (rays of real pixels only)
        px = np.stack([a.ravel() for a in np.meshgrid(gr, gc, indexing="ij")], 1)
        return px, *rays(view.scene, cam, px)

    px, dirs, hits = geo(view, ("coarse", div), coarse_rays, camera_only=True)
    coarse = view._replace(dirs=dirs, hits=hits, pixels=px)
    parts = np.stack(single_parts(coarse, ssrc, keys)[2:]).reshape(4, gh, gw)

    def silhouettes():       # the same for every pattern
        t_c = np.minimum(hits.t, box_interval(cam.position, dirs, ssrc.box_lo, ssrc.box_hi)[1])
        t_c = t_c.reshape(gh, gw)
        bad = np.empty(cam.h * cam.w, bool)
        own = np.ascontiguousarray(x_end, float)
        in_bands(own.size, lambda a, b: coarse_silhouettes(t_c, own, cam.w, float(div), bad, a, b))
        idx = np.nonzero(bad)[0]
        return idx, view.dirs[idx], take(view.hits, idx)

    idx, sub_dirs, sub_hits = geo(view, ("silhouettes", div), silhouettes, camera_only=True)
    made = 4 if parts[3].any() else 3                   # V is 0 for linear light: left at 0, not upsampled
    out = np.empty((4, cam.h * cam.w))
    if made < 4:
        out[3] = 0.0
    in_bands(cam.h, lambda a, b: upsample_grid(parts[:made], cam.w, float(div), out[:made], a, b),
             min_size=16)
    if idx.size:       # this frame's pattern on the silhouettes' rays
        sub = view._replace(dirs=sub_dirs, hits=sub_hits, pixels=np.zeros((idx.size, 2), int))
        out[:, idx] = np.stack(single_parts(sub, ssrc, keys)[2:])
    return out[0], out[1], out[2], out[3]


def b_cone(view: View, src: Source, plan: OrdersPlan, need, x0: np.ndarray):
    """B of light scattered once inside the forward cone toward the camera (a view ray that looks toward
    the source: its halo), with σ̃_t both ways; only rays whose smallest scattering angle (at their entry
    x0: θ_s grows along a ray) is below θ_c, so the paper's rig (source beside the camera) costs nothing
    (None: no ray is in the cone; which rays are is the same for every pattern, kept per scene)."""
    sc = plan.scaled

    def in_cone():
        lv = np.asarray(src.position, float) - np.asarray(view.cam.position, float)
        xc = view.dirs @ lv
        h2 = np.maximum((lv * lv).sum() - xc * xc, 0.0) + src.radius ** 2
        u0 = x0 - xc
        with np.errstate(invalid="ignore", divide="ignore"):
            cos0 = -u0 / np.sqrt(u0 * u0 + h2)
        return np.nonzero(cos0 > sc.phase.cos_c)[0]

    idx = geo(view, ("cone", float(sc.phase.cos_c)), in_cone)
    n = view.dirs.shape[0]
    if idx.size == 0:
        return None
    cone = dataclasses.replace(src, sigma_t=sc.sigma_t, phase=dataclasses.replace(sc.phase, cone=True))
    sub = view._replace(dirs=view.dirs[idx], hits=take(view.hits, idx), pixels=np.zeros((idx.size, 2), int))
    out = np.zeros((4, n))
    out[:, idx] = np.stack(single_parts(sub, cone, tuple(k for k in ("B", "p") if k in need))[2:])
    return out[0], out[1], out[2], out[3]


def rays(scene, cam, pixels=None):
    """Ray directions of ``cam`` (all pixels or ``pixels``) and their hits."""
    from polarstripe.sim.geometry import intersect, pixel_rays

    dirs = pixel_rays(cam, pixels)
    return dirs, intersect(scene.objects, cam.position, dirs)


def take(hits: Hits, idx: np.ndarray) -> Hits:
    return Hits(hits.t[idx], hits.index[idx], hits.normal[idx], hits.point[idx])


def polarized_source(src: Source, plan: OrdersPlan, scene) -> Source:
    """The scaled source whose Stokes sums give the polarized part the extinction σ_p, the circular part
    σ_pV (docs/physics.md §10.4, §5.1); its intensity keeps σ̃_t."""
    ph, dop = scene.medium.phase, scene.medium.dop
    args = (plan.scaled, scene.medium.sigma_s, ph.model, float(ph.g), float(dop.depolarization))
    return dataclasses.replace(scaled_source(src, plan), sigma_pol=polarized_extinction(*args),
                               sigma_pol_v=polarized_extinction(*args, circular=True))


def polarized_field(psrc: Source, plan: OrdersPlan, scene, st: HigherSettings, grid: Grid,
                    circular: bool = False, port=None) -> Field:
    """The polarized part of the grid's orders ≥ 1, Σ_k κ^k φ_p^(k): the quasi-direct light deposited and
    carried with σ_p, each order weighted by κ^k (docs/physics.md §10.4); ``circular``: the circular part,
    with σ_pV and κ_V (§5.1); ``port``: the source's flat port (:func:`source_field`)."""
    return answer(polarized_steps(psrc, plan, scene, st, grid, circular, port))


def polarized_steps(psrc: Source, plan: OrdersPlan, scene, st: HigherSettings, grid: Grid,
                    circular: bool = False, port=None, beams=None):
    """:func:`polarized_field` as steps that yield its grid solve (a
    :class:`~polarstripe.sim.multiple.GridSolve`); ``beams``: the source's beams where the caller keeps them
    (:func:`~polarstripe.sim.grid_sources.source_field`)."""
    ph, dop = scene.medium.phase, scene.medium.dop
    kappa = pair_retention_of(ph.model, float(ph.g), float(dop.depolarization), circular)
    sigma = psrc.sigma_pol_v if circular else psrc.sigma_pol
    deposit = dataclasses.replace(psrc, sigma_t=sigma)
    quasi = source_field(grid, deposit, scene.objects, st.oversample, port, beams)
    return (yield GridSolve(grid, quasi, sigma, plan.scaled.sigma_s, plan.scaled.g_tilde, st.orders, kappa))


def add_polarized_orders(bq: np.ndarray, bu: np.ndarray, seen: np.ndarray, dop: float):
    """B's Stokes plus the orders ≥ 2: the polarized grid field seen along the view rays (``seen``, σ_p on the
    way) carries κ^(k−1) of once-backscattered light's DOP, ``dop`` = (1 − δ)·DOP_L (κ's reference, docs/
    physics.md §10.4), in the orientation of the single wide-angle scattering at the pixel. ``bq``, ``bu``
    are updated in place and returned."""
    polarized_gain(bq, bu, np.ascontiguousarray(seen, float), float(dop))
    return bq, bu


KAPPA_MADE = 0.3    # fitted to the polarized truth of circular light (docs/physics.md §5.1)


def add_made_orders(bq: np.ndarray, bu: np.ndarray, b_one: np.ndarray, q_one: np.ndarray, u_one: np.ndarray,
                    seen: np.ndarray, share: float):
    """B's linear Stokes plus what orders ≥ 2 make of light that is not linearly polarized (circular or
    unpolarized, ``share`` of the source's intensity): m21 of the last scattering polarizes it as it does
    once-scattered light, but the grid's P1 field (docs/physics.md §10.3) carries no such polarization
    (a P1 radiance makes none, by symmetry). A fitted law stands in: the grid's orders ≥ 2 (``seen``) carry
    KAPPA_MADE of the linear DOP of single wide-angle scattering at the pixel (``b_one``, ``q_one``,
    ``u_one``), in its orientation (docs/physics.md §5.1)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        f = np.where(b_one > 0, KAPPA_MADE * share * seen / np.where(b_one > 0, b_one, 1.0), 0.0)
    return bq + f * q_one, bu + f * u_one


def add_circular_orders(bv: np.ndarray, seen: np.ndarray, v_back: float) -> np.ndarray:
    """B's V plus the orders ≥ 2: the circular grid field seen along the view rays (σ_pV on the way) carries
    κ_V^(k−1) of once-backscattered light's V, ``v_back`` = m44/m11(π)·V_L = −(1 − 2δ)·V_L (κ_V's
    reference, docs/physics.md §5.1); every twice-backscattered path flips the helicity as once-
    backscattered light does, so the sign is v_back's."""
    return bv + v_back * seen
