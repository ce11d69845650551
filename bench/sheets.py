"""``polarstripe bench sheets``: K light sheets per frame end to end — error vs T, depth, frames.

For each medium (σ_t, the default tank otherwise) and each number of sheets per stripe frame K
(``stripe:I/N:xK``, msgs/patterns.py), the stripe methods run end to end through the planner's judge
(:func:`polarstripe.planning.validate.score_scans`: the model's components with all orders, the analyzer
calibrated on the flood-lit tank, the EMVA 1288 sensor, the compositor's own pipeline, the depth delineated
and triangulated as the compositor does it, each pixel's sheet told by the objects' depth range): the
gain-fitted error of the composite against T (``stripes`` by eq. 7, ``polarized_stripes`` by eq. 6), the
depth's valid fraction (of the object pixels) and RMS [mm] against the depth truth, and the frames the scan
took (⌈N/K⌉ per analyzer pass). All at one separation (``--separation``, the scene's 0.2 m by default), so
what changes down a column is K alone; the most sheets that separation allows over the objects' depth
range (:func:`polarstripe.planning.sheets.sheet_limits`) is printed with each medium. docs/planning.md §12.
"""

from __future__ import annotations

import argparse
import json
import os
import time

from polarstripe.planning.sheets import sheet_limits
from polarstripe.planning.validate import ScanSettings, scan_scene, score_scans
from polarstripe.sim.scene import load_scene

METHODS = ("stripes", "polarized_stripes")


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--sigma-t", nargs="+", type=float, default=(2.0, 5.0, 8.0), metavar="SIGMA_T",
                        help="extinction coefficients [1/m] (default 2 5 8)")
    parser.add_argument("--sheets", nargs="+", type=int, default=(1, 2, 3, 5), metavar="K",
                        help="sheets per stripe frame (default 1 2 3 5)")
    parser.add_argument("--width", type=int, default=160, help="camera width (default 160: 160x120)")
    parser.add_argument("--stripes", type=int, default=30, help="stripe positions per scan (default 30)")
    parser.add_argument("--separation", type=float, default=0.2, help="camera-source separation [m] "
                        "(default 0.2, the scene's)")
    parser.add_argument("--fidelity", default="preview", help="model fidelity (default preview)")
    parser.add_argument("--exposure", default="rig", choices=("scene", "rig", "method"),
                        help="exposure rule of the scans (default rig, the simulator node's)")
    parser.add_argument("--seed", type=int, default=1, help="sensor noise seed")


def run(args) -> dict:
    base = load_scene(None)
    rows, started = [], time.process_time()
    for sigma in args.sigma_t:
        scene = scan_scene(base.replace(medium=base.medium.replace(sigma_t=float(sigma))), args.width)
        limit = int(sheet_limits(scene, args.stripes, [args.separation])[0])
        for k in args.sheets:
            settings = ScanSettings(fidelity=args.fidelity, n_stripes=args.stripes, width=args.width,
                                    exposure=args.exposure, seed=args.seed, sheets=k)
            settings.check()
            res = score_scans(scene, args.separation, settings, METHODS)
            row = {"sigma_t": float(sigma), "sheets": k, "max_sheets": limit,
                   **{m: {key: res[m].get(key) for key in ("frames", "error", "depth_valid_fraction",
                                                           "depth_rms_mm", "note")} for m in METHODS}}
            rows.append(row)
            if not args.json:
                print(_line(row), flush=True)
    return {"rows": rows, "cpu_s": time.process_time() - started, "load": os.getloadavg()[0],
            "width": args.width, "stripes": args.stripes, "separation_m": args.separation,
            "fidelity": args.fidelity, "exposure": args.exposure, "seed": args.seed}


def _num(x, fmt: str) -> str:
    return "-" if x is None else format(x, fmt)


HEAD = (f"{'σ_t':>4} {'K':>2} {'max K':>5} | {'frames':>6} {'error':>6} {'valid':>6} {'RMS mm':>7} | "
        f"{'frames':>6} {'error':>6} {'valid':>6} {'RMS mm':>7}")


def _line(row: dict) -> str:
    cells = []
    for m in METHODS:
        r = row[m]
        cells.append(f"{_num(r['frames'], '6d')} {_num(r['error'], '6.3f')} "
                     f"{_num(r['depth_valid_fraction'], '6.3f')} {_num(r['depth_rms_mm'], '7.2f')}")
    return f"{row['sigma_t']:4g} {row['sheets']:2d} {row['max_sheets']:5d} | " + " | ".join(cells)


def main(args: argparse.Namespace) -> int:
    if not args.json:
        print(f"K sheets per frame end to end: {args.width} px wide, {args.stripes} stripes, d_LC "
              f"{args.separation:g} m, {args.fidelity}, exposure {args.exposure}; left: stripes (eq. 7), "
              "right: polarized stripes (eq. 6; depth on E_b); error vs T, depth valid fraction of the "
              "object pixels and RMS vs the depth truth")
        print(HEAD)
    out = run(args)
    if args.json:
        print(json.dumps(out))
    else:
        for row in out["rows"]:
            for m in METHODS:
                if row[m].get("note"):
                    print(f"  σ_t {row['sigma_t']:g} K {row['sheets']} {m}: {row[m]['note']}")
        print(f"CPU {out['cpu_s']:.0f} s, load {out['load']:.1f}")
    return 0
