"""``polarstripe bench planner``: time per full plan and how far each optimum lands from the reference's.

A full plan is the paper's: 60 separations × (flood + 3 stripe locations), with and without a polarizer
(every reading shares one model evaluation per separation and modality). With the default stripe margin an
evaluation of the stripes is one own-sheet call per location (O and its neighbours O′) plus one B-only call
per other sheet that crosses an observed ray (docs/planning.md §1.3). Measured in one run at each model
fidelity, beside the alternative that renders whole frames: one full flood frame of the scene timed, times
the number of model evaluations a plan makes (not for ``reference``, which computes A at every pixel).
Target: ≤ 1 s per plan on one core, optimum within one grid step of ``reference``. Each planner variant of
``--plan-orders`` (the planner variants: the error measure, the paper's with all orders or single
scattering) is timed.

``--end-to-end`` judges the picks instead: full scans through the compositor's pipeline, the regret per method
and scene (:mod:`polarstripe.bench.planner_e2e`).
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
from polarstripe.bench import planner_e2e
from polarstripe.errors import PolarstripeError
from polarstripe.planning.planner import default_separations, plan, plan_model
from polarstripe.planning.validate_table import VARIANTS
from polarstripe.sim.render import render_components
from polarstripe.sim.scene import load_scene


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scene", nargs="?", default=None, help="scene TOML (default: the paper's tank)")
    parser.add_argument("--separations", type=int, default=60, help="separations per sweep (default 60)")
    parser.add_argument("--fidelities", default="preview,standard,reference",
                        help="comma-separated fidelity levels (reference must be among them)")
    parser.add_argument("--repeats", type=int, default=3, help="plans timed per fidelity; the median is kept")
    parser.add_argument("--exposure", choices=["scene", "auto"], default="scene",
                        help="exposure rule of the plan (see `polarstripe plan --help`)")
    planner_e2e.configure(parser)


def _optima(plans) -> dict[str, float]:
    out = {}
    for key, mp in plans.items():
        out[key] = mp.curve.best_separation_m
        for i, c in enumerate(mp.location_curves):
            out[f"{key}/O{i + 1}"] = c.best_separation_m
    return out


def run(scene_path, n_sep: int, fidelities: list[str], repeats: int, exposure: str,
        orders: str = "all") -> dict:

    scene = load_scene(scene_path)
    seps = default_separations(n_sep)
    step = float(seps[1] - seps[0])
    rows = {}
    for fid in fidelities:
        measure, model_orders = VARIANTS[orders]
        if measure == "error" and fid == "reference":
            continue                # whole frames with A at every pixel: minutes per separation
        model = plan_model(scene, measure=measure, fidelity=fid, orders=model_orders)
        plan(model, seps[:2])  # warm caches (phase tables, quadrature nodes)
        counter = {"calls": 0}

        def count(counter=counter):
            counter["calls"] += 1

        times, cpu = [], []
        for _ in range(max(1, repeats)):
            t0, c0 = time.perf_counter(), time.process_time()
            plans = plan(model, seps, exposure=exposure, progress=count)
            times.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
        evaluations = counter["calls"] // max(1, repeats)
        row = {"seconds_per_plan": float(np.median(times)), "cpu_seconds_per_plan": float(np.median(cpu)),
               "model_evaluations": evaluations, "optima_m": _optima(plans)}
        if fid != "reference":  # reference computes A at every pixel: a whole frame takes minutes
            render_components(scene, "flood", fid, orders=model_orders)
            t0 = time.perf_counter()
            render_components(scene, "flood", fid, orders=model_orders)
            row["whole_frame_seconds_estimate"] = time.perf_counter() - t0
            row["whole_frame_plan_seconds_estimate"] = row["whole_frame_seconds_estimate"] * evaluations
        rows[fid] = row
    if "reference" in rows and rows:
        ref = rows["reference"]["optima_m"]
        for r in rows.values():
            r["steps_from_reference"] = {k: round(abs(v - ref[k]) / step, 3)
                                         for k, v in r["optima_m"].items()}
            r["max_steps_from_reference"] = max(r["steps_from_reference"].values())
    return {"separations": n_sep, "grid_step_m": step, "exposure": exposure, "orders": orders,
            "target_seconds": 1.0, "fidelities": rows}


def main(args: argparse.Namespace) -> int:

    if args.end_to_end:
        return planner_e2e.main(args)
    fids = [f.strip() for f in args.fidelities.split(",") if f.strip()]
    if not fids:
        raise PolarstripeError("--fidelities: no fidelity given")
    variants = [v.strip() for v in args.plan_orders.split(",") if v.strip()]
    if not variants or any(v not in VARIANTS for v in variants):
        raise PolarstripeError(f"--plan-orders: comma-separated {', '.join(VARIANTS)}, got "
                               f"{args.plan_orders!r}")
    results = {v: run(args.scene, args.separations, fids, args.repeats, args.exposure, v) for v in variants}
    if args.json:
        print(json.dumps(results[variants[0]] if len(variants) == 1 else {"orders": results}))
        return 0
    for res in results.values():
        _print_timing(res)
    return 0


def _print_timing(res: dict) -> None:
    print(f"planner ({res['orders']} orders): {res['separations']} separations × (flood + 3 stripe "
          f"locations) × {{unpolarized, polarized}}, grid step {res['grid_step_m'] * 100:.2f} cm, exposure "
          f"{res['exposure']}, one core")
    print(f"{'fidelity':<10} {'s/plan':>8} {'cpu s':>7} {'evals':>6} {'whole frames (est.)':>20} "
          f"{'× slower':>9} {'max steps from ref':>19}")
    for fid, r in res["fidelities"].items():
        steps = r.get("max_steps_from_reference")
        whole = r.get("whole_frame_plan_seconds_estimate")
        whole_txt = (f"{whole:18.1f} s {whole / r['seconds_per_plan']:9.0f}" if whole
                     else f"{'-':>20} {'-':>9}")
        print(f"{fid:<10} {r['seconds_per_plan']:8.3f} {r['cpu_seconds_per_plan']:7.3f} "
              f"{r['model_evaluations']:6d} {whole_txt} "
              f"{'-' if steps is None else f'{steps:.1f}':>19}")
    keys = list(next(iter(res["fidelities"].values()))["optima_m"])
    print(f"\noptima [cm] {'':<22}" + "".join(f"{fid:>11}" for fid in res["fidelities"]))
    for k in keys:
        print(f"  {k:<32}" + "".join(f"{r['optima_m'][k] * 100:11.1f}" for r in res["fidelities"].values()))
    for fid, r in res["fidelities"].items():
        ok_t = r["cpu_seconds_per_plan"] <= res["target_seconds"]
        steps = r.get("max_steps_from_reference")
        ok_s = steps is not None and steps <= 1.0
        verdict = "within" if ok_s else "NOT within" if steps is not None else "not compared to"
        print(f"{fid}: {'meets' if ok_t else 'misses'} the 1 s target (CPU time); optimum {verdict} one "
              "grid step of reference")
    print()
