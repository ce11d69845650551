"""``polarstripe bench light``: linear against circular light, end to end, and the planner's recommendation.

For each water (σ_t × the TTHG mean cosine g, the default tank otherwise) and each light
(:func:`polarstripe.sim.scene.with_light`: linear polarizers, or quarter-wave plates making the source
circular and the analyzer circular at two of its angles), the methods of ``polarstripe compare`` run end to
end (:func:`polarstripe.planning.compare.run_level`: the model's components with all orders, the analyzer
calibrated on the flood-lit tank, the EMVA 1288 sensor, the compositor's own pipeline) and the table gives
the chart's band-0 contrast and the gain-fitted error against T for polarized flood (eq. 6) and polarized
striping (eq. 6), with the backscatter's DOP as the analyzer sees it. With ``--plan`` the planner plans the
polarized modalities with each light (:func:`polarstripe.planning.light.compare_lights`) and its
recommendation is set beside the light that scored the lower error end to end at the scene's pose.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np
from polarstripe.planning.compare import run_level
from polarstripe.planning.light import compare_lights
from polarstripe.planning.planner import default_separations
from polarstripe.sim.render import render_components
from polarstripe.sim.scene import LIGHTS, Phase, load_scene, parse_size, with_light

METHODS = {"flood_polarized": "polarized flood", "stripes_polarized": "polarized striping (eq. 6)"}


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--sigma-t", nargs="+", type=float, default=(2.0, 5.0, 8.0), metavar="SIGMA_T",
                        help="extinction coefficients [1/m] (default 2 5 8)")
    parser.add_argument("--g", nargs="+", type=float, default=(0.5, 0.8, 0.95), metavar="G",
                        help="TTHG mean cosines (default 0.5 0.8 0.95)")
    parser.add_argument("--resolution", default="160x120", help="camera WxH (default 160x120)")
    parser.add_argument("--stripes", type=int, default=30, help="stripes per scan (default 30)")
    parser.add_argument("--fidelity", default="preview", help="model fidelity (default preview)")
    parser.add_argument("--seed", type=int, default=1, help="sensor noise seed")
    parser.add_argument("--plan", action="store_true",
                        help="also plan each water with both lights and give the planner's recommendation")
    parser.add_argument("--plan-separations", type=int, default=6, metavar="N",
                        help="separations the planner sweeps with --plan (default 6, 0.05-0.5 m)")


def _dop_seen(scene, fidelity: str) -> float:
    """The backscatter's DOP as the analyzer sees it (p on the plate's circle), B-weighted over the image."""
    c = render_components(scene, "flood", fidelity, need=("B", "p"))
    return float(np.sum(c.p * c.B) / max(float(np.sum(c.B)), 1e-300))


def run(args) -> dict:
    base = load_scene(None)
    w, h = parse_size(args.resolution, "--resolution")
    base = base.replace(camera=base.camera.resized((w, h)))
    rows, started = [], time.process_time()
    for g in args.g:
        for sigma in args.sigma_t:
            medium = base.medium.replace(sigma_t=float(sigma), phase=Phase("tthg", float(g)))
            scene = base.replace(medium=medium)
            row = {"sigma_t": float(sigma), "g": float(g), "lights": {}}
            for light in LIGHTS:
                lit = with_light(scene, light)
                lev = run_level(lit, float(sigma), args.stripes, (), args.fidelity,
                                np.random.default_rng(args.seed))
                row["lights"][light] = {
                    "p_seen": _dop_seen(lit, args.fidelity), "p_estimate": lev["p_estimate"],
                    "analyzer_deg": lev["analyzer_deg"]["crossed"],
                    **{key: lev["rows"][name] for key, name in METHODS.items()}}
            if args.plan:
                rec = compare_lights(scene, default_separations(args.plan_separations, 0.05, 0.5),
                                     fidelity=args.fidelity, n_stripes=args.stripes)
                row["plan"] = rec
            row["e2e_better"] = {key: min(LIGHTS, key=lambda lt: row["lights"][lt][key]["error"])
                                 for key in METHODS}
            rows.append(row)
            if not args.json:
                print(_line(row), flush=True)
    return {"rows": rows, "cpu_s": time.process_time() - started, "load": os.getloadavg()[0],
            "resolution": [w, h], "stripes": args.stripes, "fidelity": args.fidelity, "seed": args.seed}


def _line(row: dict) -> str:
    cells = [f"{row['sigma_t']:g}", f"{row['g']:g}"]
    for light in LIGHTS:
        r = row["lights"][light]
        cells.append(f"{r['p_seen']:.2f}")
        cells += [f"{r[k]['contrast']:.2f} / {r[k]['error']:.3f}" for k in METHODS]
    cells += [row["e2e_better"][k] for k in METHODS]
    if "plan" in row:
        cells += [row["plan"]["recommended"][k] for k in METHODS]
    return "| " + " | ".join(cells) + " |"


def _header(plan: bool) -> str:
    cols = ["σ_t", "g", "linear p", "linear pol. flood", "linear pol. stripes", "circular p",
            "circular pol. flood", "circular pol. stripes", "lower error e2e: flood", "stripes"]
    cols += ["planner: flood", "stripes"] if plan else []
    return "| " + " | ".join(cols) + " |\n" + "|---" * len(cols) + "|"


def main(args: argparse.Namespace) -> int:
    if not args.json:
        print(_header(args.plan))
    res = run(args)
    if args.json:
        print(json.dumps(res))
    else:
        print(f"CPU {res['cpu_s']:.0f} s, load {res['load']:.1f}; contrast / error vs T per method")
    return 0
