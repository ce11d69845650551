"""The ground truth a recovered image is scored against: the object as the medium would show it if it only
attenuated the light (docs/physics.md §10.8).

Under single scattering S = D + A is a fair truth: A is small and follows the object. Under all orders it is
not: the forward-scattered light that reaches the object and the light scattered on the way back blur and
dim the chart (its bar contrast falls from 0.82 to 0.07 at σ_t = 10 m⁻¹ in the paper's tank), so a method
that recovers the object better than the water shows it would be scored as wrong. The truth is therefore
the *unscattered* object radiance under flood light:

    T = (ρ cos φ / π) · I0 · e^{−σ_t (ℓ_LO + ℓ_CO)} / (d_LO² + r_s²)

at every pixel that sees a lit object (0 elsewhere): eq. 11 of the paper (docs/physics.md §0.3) with the
whole projector lit, the object's albedo times the irradiance that reaches it unscattered, attenuated on its
way to the camera. It holds no scattered light: it is what every render gives when σ_s = 0 (albedo 0),
for the same σ_t. It does not depend on the pattern a frame uses or on the orders modelled.

Its scale is that of the unscattered light alone, while every method returns the light that reached the
object by every path (forward scatter roughly doubles it at σ_t = 5), so errors against T are taken after
fitting the estimate's gain (:func:`polarstripe.imaging.metrics.signal_error` with ``fit_gain``): a method
is judged on the object's shape (albedo pattern, edges, the source's fall-off), not on a brightness that no
method can know.
"""

from __future__ import annotations

import numpy as np
from polarstripe.sim.geometry import intersect, occluded, pinhole_frame, pixel_rays
from polarstripe.sim.patterns import parse_pattern, pattern_lit
from polarstripe.sim.scene import Scene, SceneError
from polarstripe.sim.surface import SurfaceInfo, surface_info
from polarstripe.sim.transport import direct, make_source


def unscattered_radiance(scene: Scene, pixels: np.ndarray | None = None) -> np.ndarray:
    """T = (ρ cos φ/π)·I0·e^{−σ_t(ℓ_LO + ℓ_CO)}/(d_LO² + r_s²) per pixel under flood light [W sr⁻¹ m⁻²].

    Parameters
    ----------
    scene : Scene
        Its camera sets the image size; its projector (pinhole or point) is fully lit (the black level
        does not matter: flood lights every pixel).
    pixels : optional (n, 2) int array of (row, col): only these.

    Returns
    -------
    (h, w) array, or (n,) for ``pixels``: 0 where the pixel sees no object or the object is in shadow, outside
    a pinhole projector's frustum or facing away from the source.
    """
    return unscattered_object(scene, pixels)[0]


def unscattered_object(scene: Scene, pixels: np.ndarray | None = None) -> tuple[np.ndarray, SurfaceInfo]:
    """(T of :func:`unscattered_radiance`, the :class:`SurfaceInfo` of the same pixels: which object, albedo,
    chart band and bar), both shaped (h, w), or (n,) for ``pixels``."""
    if not isinstance(scene, Scene):
        raise SceneError(f"scene must be a Scene (see load_scene), got {type(scene).__name__}")
    cam = pinhole_frame(scene.camera.position, scene.camera.look_at, scene.camera.up, scene.camera.fov_deg,
                        scene.camera.resolution)
    flood = parse_pattern("flood")
    src = make_source(scene, flood)
    dirs = pixel_rays(cam, pixels)
    hits = intersect(scene.objects, cam.position, dirs)
    surf = surface_info(scene.objects, hits)
    out = np.zeros(dirs.shape[0])
    hit = np.nonzero(surf.object_id >= 0)[0]
    if hit.size:
        lit = hit[pattern_lit(flood, src.frame, hits.point[hit])]       # inside a pinhole's frustum
        lit = lit[~occluded(scene.objects, src.position, hits.point[lit])]
        out[lit] = direct(src, scene.objects, cam.position, hits.point[lit], hits.normal[lit],
                          surf.albedo[lit], np.ones(lit.size, bool))
    shape = (cam.h, cam.w) if pixels is None else (dirs.shape[0],)
    parts = (surf.object_id, surf.albedo, surf.chart_band, surf.chart_high)
    return out.reshape(shape), SurfaceInfo(*(a.reshape(shape) for a in parts))
