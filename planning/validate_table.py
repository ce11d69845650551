"""Plans against the end-to-end truth: the planner's pick per method, the error there, the best, the regret.

For one scene: the planner (:func:`polarstripe.planning.planner.plan` on a
:class:`~polarstripe.planning.scene_model.SceneModel`, once per objective variant, e.g. single scattering and
all orders) picks a separation per method; the end-to-end curves (:mod:`polarstripe.planning.validate`) are
computed on a grid of separations, at every pick, and at the geometric midpoints either side of each best
(``refine`` rounds of bisection). Per method and variant:

    regret = error(pick) / min(error over every separation scanned)    (≥ 1; 1: the pick is the best seen)

Each method is judged on the image the compositor publishes (eq. 7 for stripes, eq. 6's Ŝ for the polarized
methods) at the pick of the planner's curve for it (the polarized flood: the recommended reading's); the
polarized methods' best-polarized frame E_b is judged as well, at the E_b reading's pick. A best at either
end of the grid says the true best may lie beyond it (``best_at_edge``); a pick at either end of the
planner's range, the same of the plan (``pick_at_edge``).
"""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
from polarstripe.planning.planner import DEFAULT_SEARCH, default_separations, plan, plan_model, resolve_search
from polarstripe.planning.validate import METHODS, ScanSettings, scan_scene, score_scans
from polarstripe.sim.scene import Scene, SceneError, scene_to_dict

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


#: planner variants: name → (measure, orders of its model): the error measure (the default planner), the
#: paper's measures with all orders and with the paper's single scattering
VARIANTS = {"error": ("error", "all"), "all": ("paper", "all"), "single": ("paper", "single")}


def planner_picks(scene: Scene, *, orders: str, fidelity: str | None = None, n_stripes: int = 30,
                  separations_m=None, exposure: str = "scene", p_rule: str = "map",
                  width: int | None = None, search: str = DEFAULT_SEARCH) -> dict[str, dict]:
    """The planner's pick per planner curve key (``flood``, ``flood_polarized``, …): {"separation_m",
    "at_edge", "reading", "readings": {reading: separation_m}} with the planner's own defaults; ``orders``
    names the variant (:data:`VARIANTS`), ``p_rule`` eq. 6's p the error measure predicts with (the
    judge's), ``width`` its renders' width (the judge's camera: a 30-stripe composite at 3 px per stripe
    aliases, and its error moves by up to 15 % between 90 and 96 px, docs/planning.md §8), ``search`` the
    planner's (:data:`~polarstripe.planning.planner.SEARCHES`; ``separations_m`` replaces its grid)."""
    s = resolve_search(search)
    seps = default_separations(s.separations) if separations_m is None else \
        np.asarray(separations_m, np.float64)
    if orders not in VARIANTS:
        raise SceneError(f"planner variant must be one of {', '.join(VARIANTS)}, got {orders!r}")
    measure, model_orders = VARIANTS[orders]
    model = plan_model(scene, measure=measure, fidelity=fidelity, n_stripes=n_stripes, orders=model_orders,
                       p_rule=p_rule, width=width if measure == "error" else None)
    return picks_of(plan(model, seps, exposure=exposure, refine=s.refine, rivals=s.rivals))


def picks_of(plans: dict) -> dict[str, dict]:
    """The picks (:func:`planner_picks`) of plans made by :func:`polarstripe.planning.planner.plan`."""
    out = {}
    for key, mp in plans.items():
        i, n = mp.curve.best_index, len(mp.curve.separations_m)
        out[key] = {"separation_m": mp.curve.best_separation_m, "at_edge": i in (0, n - 1),
                    "reading": mp.reading,
                    "readings": {r: c.best_separation_m for r, c in mp.readings.items()}}
    return out


def _pick_of(picks: dict, key: str, reading: str | None) -> float:
    entry = picks[key]
    if reading is None or reading == entry["reading"] or reading not in entry["readings"]:
        return entry["separation_m"]
    return entry["readings"][reading]


def scan_key(scene: Scene, settings: ScanSettings, separation_m: float, method: str) -> str:
    """A text that names one scored scan: the scene, the settings, the separation and the method (what a
    cache of rows keys on; the model's code is the cache's to add)."""
    return json.dumps([scene_to_dict(scene), dataclasses.asdict(settings), round(float(separation_m), 9),
                       method], sort_keys=True)


def validate(scene: Scene, grid_m, settings: ScanSettings | None = None, *, plan_orders=("error",),
             plan_fidelity: str | None = None, n_plan: int | None = None, plan_range=(0.01, 0.6),
             progress=None, on_total=None, cache=None, picks: dict | None = None, refine: int = 1) -> dict:
    """The end-to-end table of one scene (module docstring).

    Parameters
    ----------
    scene : Scene
    grid_m : separations [m] of the end-to-end curves.
    settings : how the scans are rendered and exposed (:class:`~polarstripe.planning.validate.ScanSettings`).
    plan_orders : the planner variants (:data:`VARIANTS`: ``error``, ``all``, ``single``).
    plan_fidelity, n_plan, plan_range : the planner's fidelity and the separations of its search's grid
        (None: the default search's).
    progress : called once per separation scanned; ``on_total(n)`` first, with their number.
    cache : optional mapping-like store of scored rows by :func:`scan_key` (``get(key)``, ``put(key, row)``):
        a row found there is not scanned again.
    picks : optional {variant: :func:`picks_of` plans} already made (then ``plan_*`` are not used); the
        methods whose planner curves they lack are left out.
    refine : rounds of bisection: each scans, per method and image, the geometric midpoints between the best
        separation so far and its scanned neighbours (the grid's best is up to half a log step off).

    Returns
    -------
    {"grid_m", "curves": {method: [row per grid separation]}, "extra": {method: [rows off the grid: picks,
    bisections]}, "picks": {variant: {...}}, "scanned": rows scanned, "cached": rows from the cache,
    "rows": [one per (variant, method, image)]} (:func:`regret_rows`).
    """
    settings = settings or ScanSettings()
    settings.check()
    grid = sorted(float(d) for d in grid_m)
    if not grid or any(not (math.isfinite(d) and d > 0) for d in grid):
        raise SceneError("grid: need positive separations [m]")
    if picks is None:
        seps = default_separations(resolve_search(separations=n_plan).separations, *plan_range)
        picks = {o: planner_picks(scene, orders=o, fidelity=plan_fidelity, n_stripes=settings.n_stripes,
                                  separations_m=seps, p_rule=settings.p_rule, width=settings.width)
                 for o in plan_orders}
    methods = [m for m in METHODS if any(j[0] == m and j[2] in p for j in JUDGED for p in picks.values())]
    jobs: dict[float, set] = {round(d, 9): set(methods) for d in grid}
    for p in picks.values():  # a pick off the grid: only the methods picked there are scanned
        for method, _, key, reading in JUDGED:
            if key in p:
                jobs.setdefault(round(_pick_of(p, key, reading), 9), set()).add(method)
    if on_total is not None:
        on_total(len(jobs))
    small = scan_scene(scene, settings.width)
    at: dict[str, dict[float, dict]] = {m: {} for m in METHODS}
    counts = {"scanned": 0, "cached": 0}

    def run(jobs: dict[float, set]) -> None:
        for d in sorted(jobs):
            keys = {m: scan_key(scene, settings, d, m) for m in METHODS if m in jobs[d]}
            found = {m: cache.get(k) for m, k in keys.items()} if cache is not None else {}
            need = [m for m in keys if found.get(m) is None]
            made = score_scans(small, d, settings, need) if need else {}
            for m in keys:
                if m in made and cache is not None:
                    cache.put(keys[m], made[m])
                at[m][d] = made[m] if m in made else found[m]
            counts["scanned"] += len(made)
            counts["cached"] += len(keys) - len(made)
            if progress is not None:
                progress()

    run(jobs)
    for _ in range(refine):  # bisect (in log d) either side of each image's best so far
        more: dict[float, set] = {}
        for method, image in {(j[0], j[1]) for j in JUDGED if j[0] in methods}:
            for d in _bisections(at[method], image):
                more.setdefault(d, set()).add(method)
        if on_total is not None:
            on_total(len(more))
        run(more)
    on_grid = {round(d, 9) for d in grid}
    result = {"grid_m": grid,
              "curves": {m: [at[m][round(d, 9)] for d in grid] for m in methods},
              "extra": {m: [r for d, r in sorted(at[m].items()) if d not in on_grid] for m in methods},
              "picks": picks, **counts}
    result["rows"] = regret_rows(at, grid, picks)
    return result


def _bisections(scored: dict[float, dict], image: str) -> list[float]:
    """Geometric midpoints between the separation of the least ``image`` error and its scanned neighbours."""
    seps = sorted(d for d, r in scored.items() if r.get(image) is not None and math.isfinite(r[image]))
    if len(seps) < 2:
        return []
    i = min(range(len(seps)), key=lambda k: scored[seps[k]][image])
    return [round(math.sqrt(seps[j] * seps[i]), 9) for j in (i - 1, i + 1) if 0 <= j < len(seps)]


def regret_rows(at: dict[str, dict[float, dict]], grid: list[float], picks: dict) -> list[dict]:
    """One row per (planner variant, method, image): pick, its error, the best separation and error, regret.
    ``at`` maps method → {separation rounded to 1e-9: scored row}."""
    rows = []
    for variant, p in picks.items():
        for method, image, key, reading in JUDGED:
            if key not in p:
                continue
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
