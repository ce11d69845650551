"""``polarstripe bench sweep``: scenes per second of a design-study sweep with 1 and 2 local workers.

A fixed grid (σ_t evenly spaced, the default tank, ``--fidelity`` plans of ``--separations`` separations,
flood and stripes) runs on joblib's process pool with 1 worker, then 2. Each pool is started and its
workers warmed (the numba kernels loaded from their cache, :func:`~polarstripe.planning.sweep.warm_worker`)
before the clock starts, so the rates compare steady-state throughput; the scaling ratio is rate(2)/rate(1)
(2.0 is perfect on two free cores; the machine's other load lowers it).
"""

from __future__ import annotations

import argparse
import json
import os

from joblib.externals.loky import get_reusable_executor
from polarstripe.errors import PolarstripeError
from polarstripe.planning.sweep import run_sweep, warm_worker
from polarstripe.planning.sweep_spec import parse_spec


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scenes", type=int, default=24, help="scenes in the grid (default 24)")
    parser.add_argument("--separations", type=int, default=20, help="separations per plan (default 20)")
    parser.add_argument("--fidelity", default="preview", help="model fidelity (default preview)")
    parser.add_argument("--workers", default="1,2", help="worker counts to time (default 1,2)")
    parser.add_argument("--repeats", type=int, default=2,
                        help="sweeps timed per worker count; the fastest is kept (default 2)")


def run(scenes: int, separations: int, fidelity: str, workers: list[int], repeats: int = 2) -> dict:
    spec = parse_spec({"fidelity": fidelity, "grid": {
        "separation": {"min": 0.01, "max": 0.3, "n": separations},
        "sigma_t": {"min": 2.0, "max": 10.0, "n": scenes}, "stripes": [30]}})
    rows = {}
    for n in workers:
        ex = get_reusable_executor(max_workers=n, initializer=warm_worker)
        for f in [ex.submit(warm_worker) for _ in range(2 * n)]:
            f.result()
        best = None
        for _ in range(max(1, repeats)):
            res = run_sweep(spec, jobs=n)
            if res.failed or res.missing:
                raise PolarstripeError(f"bench sweep: scenes failed with {n} workers: {res.failed}")
            best = res.seconds if best is None else min(best, res.seconds)
        rows[n] = {"seconds": best, "scenes_per_second": len(res.results) / best}
    base = rows[workers[0]]["scenes_per_second"]
    for r in rows.values():
        r["scaling"] = r["scenes_per_second"] / base
    return {"scenes": scenes, "separations": separations, "fidelity": fidelity, "repeats": repeats,
            "cpus": os.cpu_count(), "load_average_1min": os.getloadavg()[0],
            "workers": {str(k): v for k, v in rows.items()}}


def main(args: argparse.Namespace) -> int:
    try:
        workers = sorted({int(w) for w in args.workers.split(",") if w.strip()})
    except ValueError:
        raise PolarstripeError(f"--workers: integers, comma-separated, got {args.workers!r}") from None
    if not workers or workers[0] < 1 or args.scenes < 1 or args.separations < 2:
        raise PolarstripeError("need --workers >= 1, --scenes >= 1 and --separations >= 2")
    res = run(args.scenes, args.separations, args.fidelity, workers, args.repeats)
    if args.json:
        print(json.dumps(res))
        return 0
    print(f"sweep: {res['scenes']} scenes × {res['separations']} separations, {res['fidelity']}, flood + "
          f"stripes; pools warmed before timing; best of {res['repeats']}; {res['cpus']} cores, load "
          f"{res['load_average_1min']:.1f} (other processes share the cores)")
    print(f"{'workers':>8} {'seconds':>9} {'scenes/s':>9} {'scaling':>8}")
    for n, r in res["workers"].items():
        print(f"{n:>8} {r['seconds']:9.2f} {r['scenes_per_second']:9.2f} {r['scaling']:8.2f}")
    return 0
