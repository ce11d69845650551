"""The medium's DOP model from a measured p: what the planner plans with after an in-situ estimate.

The estimator reports p, the model's backscatter-weighted DOP over a flood frame scaled by the factor κ that
fits the analyzer pair (planning/medium_p.py): one number. The DOP itself varies across the image with the
scattering angle (docs/physics.md §5: depolarized Rayleigh, δ the depolarization), and that variation is what
eq. 6 with one analyzer angle cannot undo near the camera (planning/predicted_error.py). A constant DOP p
would erase it and make the polarized methods look better near the camera than they are. So a scene whose
medium has the Rayleigh model keeps it, with δ chosen so that the model's weighted DOP is the measured p:

    p_model(δ) = Σ p_m(x; δ) B(x) / Σ B(x)  over a flood frame at the scanned separation,   p_model(δ) = p

(p_model falls monotonically with δ: 0.97, 0.35, 0.13 at δ = 0, 0.2, 0.4 in the tank at σ_t 8.5, 23 cm);
solved by Brent's method on δ ∈ [0, δ_max]. A p beyond p_model(0) or p_model(δ_max) takes that end. A scene
with a ``constant`` DOP model gets p itself.
"""

from __future__ import annotations

from polarstripe.planning.image_model import ImageModel
from polarstripe.sim.scene import DopModel, Scene
from scipy.optimize import brentq

DELTA_MAX = 0.499          # the Rayleigh model's depolarization stays below 0.5 (sim/scene_parts.py)


def model_p(scene: Scene, d_lc_m: float, *, fidelity: str = "preview", width: int | None = None) -> float:
    """The scene's backscatter-weighted DOP over a flood frame with the source at ``d_lc_m`` [m]."""
    return ImageModel(scene, fidelity=fidelity, width=width).backscatter_dop(d_lc_m)


def with_measured_p(scene: Scene, p: float, d_lc_m: float, *, fidelity: str = "preview",
                    width: int | None = 96) -> Scene:
    """``scene`` with its DOP model set to give the measured ``p`` (clamped to [0, 1]) at ``d_lc_m``: the
    Rayleigh model's δ solved for p_model(δ) = p (module docstring), or a constant p."""
    p = min(max(float(p), 0.0), 1.0)
    medium = scene.medium
    if medium.dop.model != "rayleigh":
        return scene.replace(medium=medium.replace(dop=DopModel(model="constant", p=p)))

    def at(delta: float) -> Scene:
        return scene.replace(medium=medium.replace(dop=medium.dop.replace(depolarization=delta)))

    def gap(delta: float) -> float:
        return model_p(at(delta), d_lc_m, fidelity=fidelity, width=width) - p

    lo, hi = gap(0.0), gap(DELTA_MAX)
    if lo <= 0.0:
        return at(0.0)
    if hi >= 0.0:
        return at(DELTA_MAX)
    return at(float(brentq(gap, 0.0, DELTA_MAX, xtol=1e-4)))    # a root: gap changes sign in between
