"""Linear or circular light: the planner's recommendation (docs/physics.md §5.1, docs/planning.md §10).

The polarized modalities are planned twice, once with the rig's linear polarizers and once with quarter-wave
plates making the light circular (:func:`polarstripe.sim.scene.with_light`), with the planner's own
end-to-end-predicting objective (the ``error`` measure: 1 − the composite's expected error against T,
planning/predicted_error.py). Per polarized modality the light whose best separation predicts the lower
error is recommended; within ``TIE`` of each other the linear rig is kept (no plates to mount).
"""

from __future__ import annotations

import numpy as np
from polarstripe.planning.planner import plan, plan_model
from polarstripe.sim.scene import LIGHTS, Scene, with_light

TIE = 0.005          # objectives (1 − expected error) this close: keep the linear rig


def compare_lights(scene: Scene, separations_m: np.ndarray, *, modalities=("flood", "stripes"),
                   fidelity: str | None = None, n_stripes: int = 30, orders: str = "all",
                   stripe_step: int = 3, width: int | None = None, refine: int = 0, rivals: float = 0.0,
                   progress=None) -> dict:
    """Plan the polarized modalities with each light (``width``: the renders', None: the camera's;
    ``refine`` and ``rivals``: the search's, as :func:`~polarstripe.planning.planner.plan`'s).

    Returns
    -------
    {"recommended": {"flood_polarized": "linear" | "circular", ...},
     "lights": {light: {plan key: {"separation_m", "objective", "expected_error", "p"}}}, "tie": TIE}
    ``p`` is the backscatter DOP the analyzer sees at the pick (linear: the DoLP; circular: |V| and the
    plate's linear axis, docs/physics.md §5.1), the mean over the image.
    """
    lights: dict[str, dict] = {}
    for light in LIGHTS:
        lit = with_light(scene, light)
        model = plan_model(lit, measure="error", fidelity=fidelity, n_stripes=n_stripes, orders=orders,
                           stripe_step=stripe_step, width=width)
        plans = plan(model, separations_m, modalities=modalities, refine=refine, rivals=rivals,
                     progress=progress)
        entry = {}
        for key, mp in plans.items():
            if not mp.polarized:
                continue
            c = mp.curve
            at = model.flood(c.best_separation_m)
            best = float(c.objective[c.best_index])
            p = float(np.sum(at.dop * at.backscatter) / max(float(np.sum(at.backscatter)), 1e-300))
            entry[key] = {"separation_m": c.best_separation_m, "objective": best,
                          "expected_error": 1.0 - best, "p": p}
        lights[light] = entry
    recommended = {}
    for key in lights["linear"]:
        lin, circ = lights["linear"][key]["objective"], lights["circular"][key]["objective"]
        recommended[key] = "circular" if circ > lin + TIE else "linear"
    return {"recommended": recommended, "lights": lights, "tie": TIE}
