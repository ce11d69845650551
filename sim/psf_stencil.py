"""The forward-cone blurs of :mod:`polarstripe.sim.psf` at requested pixels: radial stencils of the halo.

For a pixel that sees an object, the camera-side blur averages the object radiance over neighbouring rays
whose footprints lie at the nodes δ_i of the camera path's halo on the object, and each of those radiances
averages the quasi-direct irradiance over the nodes ε_j of the source path's halo on the tangent plane of
the point it hits:

    L = e^{−n_C} R(O) + (1 − e^{−n_C}) Σ_i w_i R(O + δ_i),
    R(O) = ρ(O)·([e^{−n_L} E(O) + (1 − e^{−n_L}) Σ_j w_j E(O + ε_j)]·e^{−σ̃_t ℓ_CO}/π + Ã/ρ),

(:func:`polarstripe.sim.psf.radial_stencil`: equal weights at the mid-quantiles of equal-probability rings),
with the requested pixel's halos for its whole stencil and Ã/ρ (smooth) taken at that pixel. Whole frames blur
in the image instead (:func:`polarstripe.sim.psf.blur_image`).
"""

from __future__ import annotations

import numpy as np
from polarstripe.sim.geometry import intersect, pixel_rays, segment_length_in_box
from polarstripe.sim.grid_patches import quasi_irradiance
from polarstripe.sim.psf import radial_stencil
from polarstripe.sim.surface import surface_info


def _tangents(nrm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    helper = np.where(np.abs(nrm[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
    e1 = np.cross(nrm, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    return e1, np.cross(nrm, e1)


def stencil_blur(view, ssrc, legs, rest_unit: np.ndarray, depth: np.ndarray, rays_of=None,
                 light=None) -> np.ndarray:
    """Object radiance per requested pixel after both blurs (module docstring).

    Parameters
    ----------
    view : the render's View (pixels given); ssrc : the similarity-scaled Source.
    legs : ((n_L, rms_L, mix_L), (n_C, rms_C, mix_C)) per pixel (:func:`polarstripe.sim.psf.spread`) of the
        source → object and camera → object paths; n_C = 0 skips a pixel. A pixel beside the objects
        carries a nearby object point's halos (it receives only the halo).
    rest_unit : (n,) the wide-angle object radiance Ã per unit albedo per pixel.
    depth : (n,) camera distance [m] of the object point a pixel beside the objects takes its halo from.
    rays_of : (origins, directions) of camera pixels (a camera behind a port,
        :func:`~polarstripe.sim.grid_sources.camera_rays`); None: the pinhole's rays.
    light : ``light(points, normals)``, the quasi-direct irradiance there (a projector behind a port); None:
        :func:`~polarstripe.sim.grid_patches.quasi_irradiance`.
    """
    scene, _, _, cam, dirs, hits, surf, pixels = view
    (n_l, rms_l, mix_l), (n_c, rms_c, mix_c) = legs
    out = np.zeros(dirs.shape[0])
    for i in np.nonzero(n_c > 0)[0]:
        cam_nodes, cam_w = radial_stencil(mix_c[i])
        ill_nodes, ill_w = radial_stencil(mix_l[i])
        own = surf.object_id[i] >= 0
        dist = float(np.linalg.norm(hits.point[i] - cam.position)) if own else float(depth[i])
        step = rms_c[i] / max(dist * cam.s, 1e-12)                       # pixels per rms
        px = np.vstack([np.asarray(pixels[i], float), np.asarray(pixels[i], float) + step * cam_nodes])
        origin, rays = (cam.position, pixel_rays(cam, px)) if rays_of is None else rays_of(px)
        h2 = intersect(scene.objects, origin, rays)
        s2 = surface_info(scene.objects, h2)
        ok = s2.object_id >= 0
        if not ok.any():
            continue
        first = int(np.argmax(ok))
        nrm = np.where(ok[:, None], h2.normal, h2.normal[first])
        pnt = np.where(ok[:, None], h2.point, h2.point[first])
        e1, e2 = _tangents(nrm)
        offs = rms_l[i] * (ill_nodes[None, :, :1] * e1[:, None, :] + ill_nodes[None, :, 1:] * e2[:, None, :])
        pts = np.concatenate([pnt[:, None, :], pnt[:, None, :] + offs], axis=1).reshape(-1, 3)
        k = ill_w.size + 1
        nrm_k = np.repeat(nrm, k, axis=0)
        e = quasi_irradiance(ssrc, scene.objects, pts, nrm_k) if light is None else light(pts, nrm_k)
        e = e.reshape(-1, k)
        ill = np.exp(-n_l[i]) * e[:, 0] + (-np.expm1(-n_l[i])) * (e[:, 1:] * ill_w).sum(1)
        att = np.exp(-ssrc.sigma_t * segment_length_in_box(origin, pnt, ssrc.box_lo, ssrc.box_hi))
        rad = np.where(ok, s2.albedo * (ill * att / np.pi + rest_unit[i]), 0.0)
        if not own:                    # a pixel beside an object: only the halo reaches it
            rad[0] = 0.0
        out[i] = np.exp(-n_c[i]) * rad[0] + (-np.expm1(-n_c[i])) * float((rad[1:] * cam_w).sum())
    return out
