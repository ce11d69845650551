"""``polarstripe bench planner``: the planner's ladder, per fidelity level the CPU time of a full plan and the
regret of its picks against the end-to-end truth.

A full plan is the planner issue's: 60 separations (``--separations``), flood and stripes, each with and
without a polarizer (one model evaluation per separation and modality serves every reading), every order of
scattering the scene needs, on one core (one model thread, :mod:`polarstripe.sim.threads`), timed as process
CPU. Each level's picks are then judged end to end on the default tank at σ_t = 5 m⁻¹
(``bench/scenes/tank_sigma5.toml``; ``--scenes`` or the positional scene for others): full scans through the
compositor's pipeline on a log grid of separations, at every pick and one bisection round around each best
(:mod:`polarstripe.planning.validate_table`), scanned once for every level and kept in ``--end-to-end``'s
cache, so a second run only plans; the scans keep the scene's exposure, as the plan assumes
(``--scan-exposure``). ``regret = error at the level's pick / least error seen``, per method on
the image the compositor publishes. The plans render at the scans' width (``--width``): a stripe plan's pick
depends on the camera's pixel grid (docs/planning.md §8).

Targets: ≤ 2 s CPU per full plan at ``standard``, regret ≤ 1.05. ``--quick`` plans 12 separations (the time
scaled to 60) at 96 px against a 4-separation grid without bisection: about a minute instead of several.
``--end-to-end`` judges the planner variants on every scene instead (:mod:`polarstripe.bench.planner_e2e`).
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np
from polarstripe.bench import planner_e2e
from polarstripe.errors import PolarstripeError
from polarstripe.planning.image_model import plan_fidelity
from polarstripe.planning.planner import REFINE, default_separations, plan, plan_model
from polarstripe.planning.validate import ScanSettings
from polarstripe.planning.validate_table import VARIANTS, default_grid, picks_of, validate
from polarstripe.sim.scene import load_scene
from polarstripe.sim.threads import set_threads, threads

FULL_PLAN = 60                      # separations of the full plan
TARGET_CPU_S = 2.0                  # per full plan at standard, one core
DEFAULT_SCENE = "tank_sigma5"
METHOD_NAMES = ("flood", "polarized_flood", "stripes", "polarized_stripes")
QUICK = {"separations": 12, "grid": 4, "refine": 0, "width": 96}


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scene", nargs="?", default=None,
                        help="scene TOML (default: the tank at sigma_t 5, bench/scenes/tank_sigma5.toml)")
    parser.add_argument("--separations", type=int, default=None,
                        help=f"separations per plan (default {FULL_PLAN}, the full plan; --quick "
                             f"{QUICK['separations']}, its time scaled to {FULL_PLAN})")
    parser.add_argument("--fidelities", default="draft,preview,standard",
                        help="comma-separated fidelity levels of the planner's model (default "
                             "draft,preview,standard; draft: the planner's own, below preview; reference: "
                             "whole frames with A at every pixel, minutes per separation)")
    parser.add_argument("--quick", action="store_true",
                        help=f"a short ladder: {QUICK['separations']} separations at {QUICK['width']} px, "
                             f"the truth on {QUICK['grid']} separations without bisection")
    parser.add_argument("--exposure", choices=["scene", "auto"], default="scene",
                        help="exposure rule of the plan (see `polarstripe plan --help`)")
    planner_e2e.configure(parser)


def _levels(text: str) -> list[str]:
    fids = [f.strip() for f in text.split(",") if f.strip()]
    if not fids:
        raise PolarstripeError("--fidelities: no fidelity given")
    for f in fids:
        plan_fidelity(f)                # a bad name: one line naming the choices
    return fids


def _variants(text: str | None) -> list[str]:
    variants = [v.strip() for v in (text or "error").split(",") if v.strip()]
    if not variants or any(v not in VARIANTS for v in variants):
        raise PolarstripeError(f"--plan-orders: comma-separated {', '.join(VARIANTS)}, got {text!r}")
    return variants


def _settings(args) -> tuple[ScanSettings, int, int, int]:
    """The scans' settings, the plan's separations, the grid and the bisection rounds (``--quick``'s where
    the user left an option at its default)."""
    quick = args.quick
    width = QUICK["width"] if quick and args.width is None else args.width or planner_e2e.DEFAULT_WIDTH
    n_sep = args.separations or (QUICK["separations"] if quick else FULL_PLAN)
    grid = QUICK["grid"] if quick and args.grid is None else args.grid or planner_e2e.DEFAULT_GRID
    refine = QUICK["refine"] if quick and args.refine is None else (
        planner_e2e.DEFAULT_REFINE if args.refine is None else args.refine)
    settings = ScanSettings(fidelity=args.fidelity, orders=args.orders, n_stripes=args.stripes, width=width,
                            exposure=args.scan_exposure or "scene", seed=args.seed, p_rule=args.p_rule)
    settings.check()
    if n_sep < 2:
        raise PolarstripeError(f"--separations: need at least 2, got {n_sep}")
    return settings, n_sep, grid, refine


class _Bisections:
    """The plan's model, timing the evaluations off the grid (the planner's bisections, planner.REFINE): a
    plan timed on fewer separations than a full plan's scales its grid part, not these."""

    def __init__(self, model, grid):
        self._model, self._grid = model, {round(float(d), 9) for d in grid}
        self.cpu = self.wall = 0.0
        self.n = 0

    def __getattr__(self, name):
        return getattr(self._model, name)

    def _timed(self, fn, d):
        if round(d, 9) in self._grid:
            return fn(d)
        t0, c0 = time.perf_counter(), time.process_time()
        try:
            return fn(d)
        finally:
            self.cpu += time.process_time() - c0
            self.wall += time.perf_counter() - t0
            self.n += 1

    def flood(self, d):
        return self._timed(self._model.flood, d)

    def stripes(self, d):
        return self._timed(self._model.stripes, d)


def _timed_plan(scene, variant: str, fidelity: str, settings: ScanSettings, seps, exposure: str, tick,
                scale: float):
    """The plans and (CPU s, wall s, grid evaluations, bisection evaluations) of one full plan on one model
    thread: the grid's part times ``scale`` (a full plan's separations over ``seps``), the bisections' as
    they are (their scoring is in the grid's part)."""
    measure, orders = VARIANTS[variant]
    model = plan_model(scene, measure=measure, fidelity=fidelity, orders=orders, n_stripes=settings.n_stripes,
                       p_rule=settings.p_rule, width=settings.width if measure == "error" else None)
    timed = _Bisections(model, seps)
    count = {"n": 0}

    def progress():
        count["n"] += 1
        tick()

    before = threads()
    set_threads(1)
    try:
        warm = plan_model(scene, measure=measure, fidelity=fidelity, orders=orders, n_stripes=4,
                          width=16 if measure == "error" else None)
        plan(warm, seps[:2])            # load the kernels, warm the caches (phase tables, quadrature nodes)
        t0, c0 = time.perf_counter(), time.process_time()
        plans = plan(timed, seps, exposure=exposure, refine=REFINE, progress=progress)
        cpu, wall = time.process_time() - c0, time.perf_counter() - t0
    finally:
        set_threads(before)
    cpu = (cpu - timed.cpu) * scale + timed.cpu
    wall = (wall - timed.wall) * scale + timed.wall
    return plans, cpu, wall, count["n"] - timed.n, timed.n


def run(args) -> dict:
    fids, variants = _levels(args.fidelities), _variants(args.plan_orders)
    settings, n_sep, n_grid, refine = _settings(args)
    seps = default_separations(n_sep)
    scale = FULL_PLAN / n_sep
    paths = planner_e2e.scene_paths(args) if (args.scenes or args.scene) else \
        planner_e2e.scene_paths(argparse.Namespace(scenes=[DEFAULT_SCENE], scene=None))
    scenes = [(os.path.splitext(os.path.basename(p))[0], load_scene(p)) for p in paths]
    levels = [(v, f) for v in variants for f in fids]
    skipped = [(v, f) for v, f in levels if VARIANTS[v][0] == "error" and f == "reference"]
    levels = [lv for lv in levels if lv not in skipped]
    if not levels:
        raise PolarstripeError("--fidelities: the error measure is not run at reference (whole frames with A "
                               "at every pixel: minutes per separation); name another level")
    cache = None if args.no_cache else planner_e2e.ScanCache(args.cache or planner_e2e.default_cache_dir())
    bar = None
    if not args.no_progress:
        from tqdm import tqdm
        bar = tqdm(total=len(levels) * len(scenes) * 2 * n_sep, unit="eval", desc="plans", leave=False)

    def tick():
        if bar is not None:
            bar.update(1)

    out = {"separations": n_sep, "full_plan": FULL_PLAN, "time_scale": scale, "threads": 1,
           "exposure": args.exposure, "settings": vars(settings), "grid_m": default_grid(n_grid).tolist(),
           "refine": refine, "plan_refine": REFINE, "target_cpu_seconds": TARGET_CPU_S,
           "target_regret": planner_e2e.TARGET_REGRET,
           "skipped": [f"{v}/{f}" for v, f in skipped], "load_average_start": list(os.getloadavg()),
           "truth": {}, "levels": []}
    rows = {lv: {"variant": lv[0], "fidelity": lv[1], "cpu": [], "wall": [], "evaluations": 0,
                 "bisections": [], "picks_m": {}, "regret": {}} for lv in levels}
    c_all = time.process_time()
    try:
        for name, scene in scenes:
            picks = {}
            for lv in levels:
                if bar is not None:
                    bar.set_description(f"plan {name} {lv[0]}/{lv[1]}")
                plans, cpu, wall, evals, bisections = _timed_plan(scene, *lv, settings, seps, args.exposure,
                                                                  tick, scale)
                r = rows[lv]
                r["cpu"].append(cpu)
                r["wall"].append(wall)
                r["evaluations"] = evals
                r["bisections"].append(bisections)
                picks[f"{lv[0]}/{lv[1]}"] = picks_of(plans)
            if bar is not None:
                bar.set_description(f"truth {name}")
            res = validate(scene, out["grid_m"], settings, picks=picks, cache=cache, refine=refine,
                           progress=tick, on_total=(lambda n: setattr(bar, "total", bar.total + n))
                           if bar is not None else None)
            if cache is not None:
                cache.save()
            best = {}
            for row in res["rows"]:
                if row["image"] != "composite":
                    continue
                lv = tuple(row["plan"].split("/"))
                rows[lv]["picks_m"].setdefault(name, {})[row["method"]] = row["pick_m"]
                rows[lv]["regret"].setdefault(name, {})[row["method"]] = row["regret"]
                best[row["method"]] = {"separation_m": row["best_m"], "error": row["best_error"],
                                       "at_grid_edge": row["best_at_edge"]}
            out["truth"][name] = {"best": best, "scanned": res["scanned"], "cached": res["cached"]}
    finally:
        if bar is not None:
            bar.close()
    for r in rows.values():
        regrets = [x for sc in r["regret"].values() for x in sc.values() if x is not None]
        out["levels"].append({
            "variant": r["variant"], "fidelity": r["fidelity"],
            "cpu_seconds_per_plan": float(np.median(r["cpu"])),
            "seconds_per_plan": float(np.median(r["wall"])),
            "model_evaluations": r["evaluations"], "bisection_evaluations": r["bisections"],
            "picks_m": r["picks_m"], "regret": r["regret"],
            "worst_regret": max(regrets) if regrets else None})
    out["cpu_seconds"] = time.process_time() - c_all
    out["load_average_end"] = list(os.getloadavg())
    out["cache"] = None if cache is None else str(cache.path)
    return out


def _f(v, fmt: str) -> str:
    return "-" if v is None else format(v, fmt)


def print_ladder(res: dict) -> None:
    s = res["settings"]
    timed = "" if res["time_scale"] == 1 else \
        f" (timed on {res['separations']}, scaled ×{res['time_scale']:g})"
    print(f"planner ladder: a full plan = {res['full_plan']} separations{timed} and the planner's "
          f"{res['plan_refine']} bisection round(s) × (flood, stripes) × (with, without polarizer), one "
          f"core, process CPU; rendered {s['width']} px wide, exposure {res['exposure']}")
    g = res["grid_m"]
    print(f"regret vs the end-to-end truth: {len(g)} separations {g[0] * 100:.0f}-{g[-1] * 100:.0f} cm "
          f"+ picks + {res['refine']} bisection(s), scans at {s['fidelity']}, {s['orders']} orders, "
          f"{s['n_stripes']} stripes, width {s['width']}; composite error vs T at the pick / least seen")
    for name, t in res["truth"].items():
        best = ", ".join(f"{m} {b['error']:.3f} at {b['separation_m'] * 100:.1f} cm"
                         f"{'>' if b['at_grid_edge'] else ''}" for m, b in t["best"].items())
        print(f"  truth {name}: {t['scanned']} scans made, {t['cached']} from the cache; best {best}")
    head = "".join(f"{m.replace('polarized_', 'pol. '):>13}" for m in METHOD_NAMES)
    print(f"\n{'planner':<8} {'level':<9} {'scene':<14} {'CPU s/plan':>10} {'wall s':>7}{head} {'worst':>7}")
    print(f"{'':<51}regret (pick cm) per method")
    for lv in res["levels"]:
        for name, reg in lv["regret"].items():
            picks = lv["picks_m"][name]
            cells = "".join(f"{_f(reg.get(m), '7.3f')} ({picks[m] * 100:3.0f})" if reg.get(m) is not None
                            else f"{'-':>13}" for m in METHOD_NAMES)
            print(f"{lv['variant']:<8} {lv['fidelity']:<9} {name:<14} {lv['cpu_seconds_per_plan']:10.1f} "
                  f"{lv['seconds_per_plan']:7.1f}{cells} {_f(lv['worst_regret'], '7.3f')}")
    for k in res["skipped"]:
        print(f"{k}: not run (whole frames with A at every pixel: minutes per separation)")
    print(f"\ntargets: ≤ {res['target_cpu_seconds']:g} s CPU per full plan at standard, regret ≤ "
          f"{res['target_regret']}")
    for lv in res["levels"]:
        ok_t = lv["cpu_seconds_per_plan"] <= res["target_cpu_seconds"]
        w = lv["worst_regret"]
        print(f"  {lv['variant']}/{lv['fidelity']}: {'meets' if ok_t else 'misses'} the time "
              f"({lv['cpu_seconds_per_plan'] / res['target_cpu_seconds']:.0f}× the target), "
              f"{'meets' if w is not None and w <= res['target_regret'] else 'misses'} the regret")
    la, lb = res["load_average_start"], res["load_average_end"]
    print(f"{res['cpu_seconds']:.0f} s CPU in all; load average {la[0]:.1f} at the start, {lb[0]:.1f} at "
          "the end")


def main(args: argparse.Namespace) -> int:
    if args.end_to_end:
        return planner_e2e.main(args)
    res = run(args)
    if args.json:
        print(json.dumps(res))
    else:
        print_ladder(res)
    return 0
