"""Which orders of scattering a render models, decided from the scene, and the error to expect.

``orders="single"`` is the paper's model: D plus once-scattered A and B (docs/physics.md §2), bit-identical to
the renderer before the higher orders existed. ``orders="all"`` (the default) adds every higher order
*where the scene needs them* (docs/physics.md §10): single scattering misses the light scattered more than
once, whose share of the image is about

    η = 1 − e^{−σ_s ℓ},   ℓ = ℓ_C + ℓ_L

with ℓ_C the in-medium length of the camera's central ray (to the first object or out of the medium) and ℓ_L
the source's in-medium distance to that ray's end: η is the chance that light on the main path scatters at
all, and for B the ratio of double to single scattering is of the same order. Below η = 1 % single
scattering is within 1 % and the higher orders are skipped (clear water in a tank, σ_t = 0, albedo 0).
Otherwise they are computed, and the expected error is that of the higher-order model measured against Mitsuba
(``polarstripe bench fidelity``): see :func:`expected_error`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from polarstripe.sim.geometry import box_interval, intersect, segment_length_in_box
from polarstripe.sim.scene import Scene, SceneError
from polarstripe.sim.similarity import Scaled, scaled_medium

ORDERS = ("all", "single")
SKIP_BELOW = 0.01        # η below which single scattering is used (its error is then below η)


@dataclass(frozen=True)
class OrdersPlan:
    """What a render models: ``requested`` (all | single), ``modelled`` (True: higher orders computed),
    ``tau_s`` = σ_s ℓ along the main path, ``single_error`` η (single scattering's expected relative error),
    ``expected_error`` (relative, of what is rendered), ``reason`` (one line) and the ``scaled`` medium."""

    requested: str
    modelled: bool
    tau_s: float
    single_error: float
    expected_error: float
    reason: str
    scaled: Scaled | None = None

    def as_dict(self) -> dict:
        """JSON-able summary (``polarstripe render`` writes it into meta.json)."""
        kind = "all orders" if self.modelled else "single scattering"
        out = {"requested": self.requested, "modelled": kind,
               "tau_s": self.tau_s, "single_scattering_error": self.single_error,
               "expected_error": self.expected_error, "reason": self.reason}
        if self.scaled is not None:
            sc = self.scaled
            out["similarity"] = {"theta_c_deg": math.degrees(math.acos(sc.phase.cos_c)), "f": sc.f,
                                 "sigma_t_scaled": sc.sigma_t, "sigma_s_scaled": sc.sigma_s,
                                 "g_scaled": sc.g_tilde,
                                 "cone_rms_deg": math.degrees(math.sqrt(2 * sc.theta2_x))}
            out["terms"] = ["D (unscattered)",
                            "quasi-direct (forward-scattered) light on the object, blurred",
                            "single wide-angle scattering (A, B; Mueller polarization)",
                            "orders >= 2 on a grid (A, B; unpolarized)", "the object's glow",
                            "blur of the object's radiance on its way to the camera"]
        return out


def main_path(scene: Scene) -> float:
    """ℓ = ℓ_C + ℓ_L [m]: the camera's central ray in the medium and the source's in-medium distance to its
    end."""
    c, m = scene.camera, scene.medium
    lo, hi = np.asarray(m.extent.min), np.asarray(m.extent.max)
    pos = np.asarray(c.position, float)
    d = np.subtract(c.look_at, c.position)
    d = (d / np.linalg.norm(d))[None, :]
    t0, t1 = box_interval(pos, d, lo, hi)
    t_hit = intersect(scene.objects, pos, d).t[0]
    if not t1[0] > t0[0]:
        return 0.0
    end = pos + min(t1[0], t_hit) * d[0]
    ell_c = max(min(t1[0], t_hit) - max(t0[0], 0.0), 0.0)
    ell_l = float(segment_length_in_box(np.asarray(scene.projector.position, float), end, lo, hi))
    return float(ell_c + ell_l)


TAU_VALIDATED = 8.0      # σ_s ℓ up to which the all-orders model was validated against Mitsuba
BOUND = {"preview": 0.25, "standard": 0.10, "reference": 0.10}


def expected_error(tau_s: float, fidelity_name: str) -> float:
    """Relative error to expect of the all-orders model (image halves and centre) at σ_s ℓ = ``tau_s``: the
    bound it was validated to against Mitsuba (docs/physics.md §10.6) — 10 % at ``standard`` and ``reference``
    (and explicit counts), 25 % at ``preview`` — for σ_s ℓ ≤ 8, growing by 10 % per unit of σ_s ℓ beyond,
    where the grid no longer resolves the first mean free path (capped at 100 %)."""
    bound = BOUND.get(fidelity_name, BOUND["standard"])
    return float(min(bound + 0.1 * max(tau_s - TAU_VALIDATED, 0.0), 1.0))


def plan_orders(scene: Scene, orders: str = "all", fidelity_name: str = "standard") -> OrdersPlan:
    """Decide the orders of scattering to model (module docstring).

    Raises
    ------
    SceneError
        ``orders`` not one of ``all``, ``single``.
    """
    if not isinstance(orders, str) or orders not in ORDERS:
        raise SceneError(f"orders must be one of {', '.join(ORDERS)}, got {orders!r}")
    return _plan(scene, orders, str(fidelity_name))


@lru_cache(maxsize=32)
def _plan(scene: Scene, orders: str, fidelity_name: str) -> OrdersPlan:
    """:func:`plan_orders` of a checked ``orders``, kept per scene (every frame of a scan asks the same)."""
    tau_s = scene.medium.sigma_s * main_path(scene)
    eta = float(-math.expm1(-tau_s))
    if orders == "single":
        return OrdersPlan("single", False, tau_s, eta, eta, "single scattering requested (the paper's model)")
    if eta < SKIP_BELOW:
        return OrdersPlan("all", False, tau_s, eta, eta,
                          f"higher orders skipped: sigma_s*l = {tau_s:.3g} < {SKIP_BELOW} (single scattering "
                          f"within {100 * eta:.2g} %)")
    err = expected_error(tau_s, fidelity_name)
    return OrdersPlan("all", True, tau_s, eta, err, f"sigma_s*l = {tau_s:.3g}: single scattering would miss "
                      f"~{100 * eta:.0f} % of the light", scaled_medium(scene.medium))
