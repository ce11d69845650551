"""Plans against the end-to-end truth: the planner's pick per method, the error there, the best, the regret.

For one scene: the planner (:func:`polarstripe.planning.planner.plan` on a
:class:`~polarstripe.planning.scene_model.SceneModel`, once per objective variant, e.g. single scattering and
all orders) picks a separation per method; the end-to-end curves (:mod:`polarstripe.planning.validate`) are
computed on a grid of separations and at every pick. Per method and variant:

    regret = error(pick) / min(error over the grid and the picks)    (≥ 1; 1: the pick is the best seen)

Each method is judged on the image the compositor publishes (eq. 7 for stripes, eq. 6's Ŝ for the polarized
methods) at the pick of the planner's curve for it (the polarized flood: the recommended reading's); the
polarized methods' best-polarized frame E_b is judged as well, at the E_b reading's pick. A best at either
end of the grid says the true best may lie beyond it (``best_at_edge``); a pick at either end of the
planner's range, the same of the plan (``pick_at_edge``).
"""

from __future__ import annotations

import math

import numpy as np
from polarstripe.planning.planner import default_separations, plan
from polarstripe.planning.scene_model import SceneModel
from polarstripe.planning.validate import METHODS, ScanSettings, curves, scan_scene, score_scans
from polarstripe.sim.scene import Scene, SceneError

#: (method, image scored, planner curve key, reading of that curve or None for the plan's choice)
JUDGED = (("flood", "error", "flood", None),
          ("polarized_flood", "error", "flood_polarized", None),
          ("polarized_flood", "error_e_b", "flood_polarized", "E_b"),
          ("stripes", "error", "stripes", None),
          ("polarized_stripes", "error", "stripes_polarized", None),
          ("polarized_stripes", "error_e_b", "stripes_polarized", "E_b"))
IMAGE_NAMES = {"error": "composite", "error_e_b": "E_b"}
EDGE_TOL = 1e-9


def default_grid(n: int = 10, d_min_m: float = 0.02, d_max_m: float = 0.6) -> np.ndarray:
    """n separations [m] spaced evenly in log d from ``d_min_m`` to ``d_max_m`` (the optima cluster at the
    small end, where the curves also change fastest)."""
    if n < 2 or not (0.0 < d_min_m < d_max_m) or not math.isfinite(d_max_m):
        raise SceneError(f"grid: need n >= 2 and 0 < d_min < d_max, got n={n}, d_min={d_min_m}, "
                         f"d_max={d_max_m}")
    return np.geomspace(d_min_m, d_max_m, int(n))


def planner_picks(scene: Scene, *, orders: str, fidelity: str = "standard", n_stripes: int = 30,
                  separations_m=None, exposure: str = "scene") -> dict[str, dict]:
    """The planner's pick per planner curve key (``flood``, ``flood_polarized``, …): {"separation_m",
    "at_edge", "reading", "readings": {reading: separation_m}} with the planner's own defaults."""
    seps = default_separations() if separations_m is None else np.asarray(separations_m, np.float64)
    model = SceneModel(scene, fidelity=fidelity, n_stripes=n_stripes, orders=orders)
    out = {}
    for key, mp in plan(model, seps, exposure=exposure).items():
        i = mp.curve.best_index
        out[key] = {"separation_m": mp.curve.best_separation_m, "at_edge": i in (0, len(seps) - 1),
                    "reading": mp.reading,
                    "readings": {r: c.best_separation_m for r, c in mp.readings.items()}}
    return out


def _pick_of(picks: dict, key: str, reading: str | None) -> float:
    entry = picks[key]
    if reading is None or reading == entry["reading"] or reading not in entry["readings"]:
        return entry["separation_m"]
    return entry["readings"][reading]


def validate(scene: Scene, grid_m, settings: ScanSettings | None = None, *, plan_orders=("all",),
             plan_fidelity: str = "standard", n_plan: int = 60, plan_range=(0.01, 0.6), progress=None,
             on_total=None) -> dict:
    """The end-to-end table of one scene (module docstring).

    Parameters
    ----------
    scene : Scene
    grid_m : separations [m] of the end-to-end curves.
    settings : how the scans are rendered and exposed (:class:`~polarstripe.planning.validate.ScanSettings`).
    plan_orders : the planner variants, each an ``orders`` of its SceneModel.
    plan_fidelity, n_plan, plan_range : the planner's fidelity and separation grid.
    progress : called once per separation scanned; ``on_total(n)`` first, with their number.

    Returns
    -------
    {"grid_m", "curves": {method: [row per grid separation]}, "picks": {variant: {...}},
    "rows": [one per (variant, method, image)]} (:func:`regret_rows`).
    """
    settings = settings or ScanSettings()
    grid = sorted(float(d) for d in grid_m)
    seps = default_separations(n_plan, *plan_range)
    picks = {o: planner_picks(scene, orders=o, fidelity=plan_fidelity, n_stripes=settings.n_stripes,
                              separations_m=seps) for o in plan_orders}
    on_grid = {round(d, 9) for d in grid}
    extra: dict[float, set] = {}  # a pick off the grid: only the methods picked there are scanned
    for p in picks.values():
        for method, _, key, reading in JUDGED:
            d = round(_pick_of(p, key, reading), 9)
            if d not in on_grid:
                extra.setdefault(d, set()).add(method)
    if on_total is not None:
        on_total(len(grid) + len(extra))
    made = curves(scene, grid, settings, METHODS, progress=progress)
    at = {m: {round(r["separation_m"], 9): r for r in rows} for m, rows in made.items()}
    scans = {m: [] for m in METHODS}
    small = scan_scene(scene, settings.width)
    for d in sorted(extra):
        for m, row in score_scans(small, d, settings, [m for m in METHODS if m in extra[d]]).items():
            at[m][d] = row
            scans[m].append(row)
        if progress is not None:
            progress()
    result = {"grid_m": grid, "curves": made, "extra": scans, "picks": picks}
    result["rows"] = regret_rows(at, grid, picks)
    return result


def regret_rows(at: dict[str, dict[float, dict]], grid: list[float], picks: dict) -> list[dict]:
    """One row per (planner variant, method, image): pick, its error, the best separation and error, regret.
    ``at`` maps method → {separation rounded to 1e-9: scored row}."""
    rows = []
    for variant, p in picks.items():
        for method, image, key, reading in JUDGED:
            scored = at[method]
            d_pick = _pick_of(p, key, reading)
            errors = {d: r.get(image) for d, r in scored.items()}
            valid = {d: e for d, e in errors.items() if e is not None and math.isfinite(e)}
            e_pick = errors.get(round(d_pick, 9))
            row = {"plan": variant, "method": method, "image": IMAGE_NAMES[image],
                   "reading": reading or p[key]["reading"], "pick_m": d_pick, "pick_error": e_pick,
                   "pick_at_edge": p[key]["at_edge"], "best_m": None, "best_error": None, "regret": None,
                   "best_at_edge": None}
            if valid:
                d_best = min(valid, key=valid.get)
                row.update(best_m=d_best, best_error=valid[d_best],
                           best_at_edge=abs(d_best - grid[0]) < EDGE_TOL or abs(d_best - grid[-1]) < EDGE_TOL)
                if e_pick is not None and valid[d_best] > 0:
                    row["regret"] = e_pick / valid[d_best]
            rows.append(row)
    return rows
