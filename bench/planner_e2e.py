"""``polarstripe bench planner --end-to-end``: the planner's picks against full scans through the pipeline.

Per scene (default: every ``bench/scenes/*.toml``: the default tank at σ_t = 2, 5, 8, the paper's Fig. 8
geometry with a chart, another phase function, an absorbing medium, a nearer chart, an off-axis object) and
per planner variant (``--plan-orders``: the planner's SceneModel with all orders, single scattering), the
planner picks a separation per method; each method's full scan is rendered on a grid of separations and at
every pick, composed by the compositor's pipeline and scored against the unscattered object T
(:mod:`polarstripe.planning.validate`, :mod:`polarstripe.planning.validate_table`). The table gives per
method and scene the pick, its error, the best separation and its error, the regret (pick error ÷ best)
and whether the best lies at the grid's edge (``>``: it may lie beyond). Target: regret ≤ 1.05.

The scored scans do not depend on the planner, so they are kept (``--cache DIR``, default
``$XDG_CACHE_HOME/polarstripe/planner-e2e``; ``--no-cache``) in a file named by a hash of the model's and the
pipeline's code (``sim/``, ``imaging/``, ``planning/validate.py``): a second run with another objective scans
only its new picks; a change to the model starts a new file.
"""

from __future__ import annotations

import argparse
import glob
import hashlib
import json
import os
import time
from pathlib import Path

from polarstripe.errors import PolarstripeError
from polarstripe.planning.validate import EXPOSURES, ScanSettings
from polarstripe.planning.validate_table import VARIANTS, default_grid, validate
from polarstripe.sim.scene import load_scene

SCENES_DIR = os.path.join(os.path.dirname(os.path.abspath(__file__)), "scenes")
TARGET_REGRET = 1.05
DEFAULT_GRID, DEFAULT_REFINE, DEFAULT_WIDTH = 8, 1, 160
DEFAULT_VARIANTS = "error,all,single"


def configure(parser: argparse.ArgumentParser) -> None:
    g = parser.add_argument_group("end to end (--end-to-end)")
    g.add_argument("--end-to-end", action="store_true",
                   help="judge the planner's picks by full scans through the compositor's pipeline (error vs "
                        "the unscattered object, per method and scene; a few minutes)")
    g.add_argument("--scenes", nargs="+", default=None, metavar="TOML",
                   help="scene files, or names in bench/scenes (default: every bench/scenes/*.toml; the "
                        "positional scene, if given, alone)")
    g.add_argument("--grid", type=int, default=None, help=f"separations of the end-to-end grid (default "
                   f"{DEFAULT_GRID}, log-spaced over --grid-range)")
    g.add_argument("--grid-range", nargs=2, type=float, default=(0.02, 0.6), metavar=("MIN_M", "MAX_M"),
                   help="end-to-end grid range in metres (default 0.02 0.6)")
    g.add_argument("--refine", type=int, default=None, metavar="N",
                   help=f"rounds of bisection around each method's best (default {DEFAULT_REFINE}: its two "
                        "log-midpoints)")
    g.add_argument("--fidelity", default="standard", help="fidelity of the scans' renders (default standard)")
    g.add_argument("--orders", choices=("all", "single"), default="all",
                   help="orders of scattering of the scans' renders (default all: the simulator's)")
    g.add_argument("--plan-orders", default=None,
                   help="planner variants, comma-separated: error (the error measure, all orders), all, "
                        f"single (the paper's measures with that model; default {DEFAULT_VARIANTS} with "
                        "--end-to-end, error for the ladder)")
    g.add_argument("--plan-fidelity", default=None,
                   help="the planner's fidelity (default: preview for the error measure, standard for the "
                        "paper's)")
    g.add_argument("--width", type=int, default=None,
                   help=f"camera width of the scans and of the error measure's renders (default "
                        f"{DEFAULT_WIDTH}; exposure scaled per pixel solid angle)")
    g.add_argument("--scan-exposure", choices=EXPOSURES, default=None,
                   help="exposure of the scans (default rig with --end-to-end, scene for the ladder, the "
                        "exposure the plan assumes): rig (the scene's, shortened for every method if the "
                        "flood would clip, as the simulator node does), scene (as is), method (each method's "
                        "brightest frame at 90 %%, as `polarstripe compare`)")
    g.add_argument("--stripes", type=int, default=30, help="stripes per scan (default 30)")
    g.add_argument("--seed", type=int, default=1, help="sensor noise seed")
    g.add_argument("--p-rule", choices=("map", "median"), default="map",
                   help="eq. 6's p, in the scans' composites and in the error measure's prediction: map "
                        "(default, the compositor's: per pixel from the scene's medium model) or median "
                        "(one p-hat, the ratio of medians over object-free pixels)")
    g.add_argument("--no-progress", action="store_true", help="no progress bar")
    g.add_argument("--cache", default=None, metavar="DIR",
                   help="where scored scans are kept between runs (default $XDG_CACHE_HOME/polarstripe/"
                        "planner-e2e)")
    g.add_argument("--no-cache", action="store_true", help="scan everything, keep nothing")


def code_hash() -> str:
    """sha256 of the code a scored scan depends on: sim/, imaging/, planning/validate.py and medium_p.py
    (the p map)."""
    root = Path(__file__).resolve().parent.parent
    h = hashlib.sha256()
    files = [*root.glob("sim/*.py"), *root.glob("imaging/*.py"),
             *(root / "planning" / f for f in ("validate.py", "medium_p.py"))]
    for path in sorted(files):
        h.update(str(path.relative_to(root)).encode())
        h.update(path.read_bytes())
    return h.hexdigest()[:16]


class ScanCache:
    """Scored scans by :func:`~polarstripe.planning.validate_table.scan_key`, in one JSON file per code hash
    (written whole, atomically, by :meth:`save`)."""

    def __init__(self, folder: str):
        self.path = Path(folder) / f"scans-{code_hash()}.json"
        try:
            self.rows = json.loads(self.path.read_text())
        except (OSError, ValueError):
            self.rows = {}
        self.dirty = False

    @staticmethod
    def _digest(key: str) -> str:
        return hashlib.sha256(key.encode()).hexdigest()

    def get(self, key: str):
        return self.rows.get(self._digest(key))

    def put(self, key: str, row: dict) -> None:
        self.rows[self._digest(key)] = row
        self.dirty = True

    def save(self) -> None:
        if not self.dirty:
            return
        self.path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.path.with_suffix(".tmp")
        tmp.write_text(json.dumps(self.rows))
        os.replace(tmp, self.path)
        self.dirty = False


def default_cache_dir() -> str:
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "polarstripe", "planner-e2e")


def scene_paths(args) -> list[str]:
    if args.scenes:
        out = []
        for s in args.scenes:
            path = s if os.path.exists(s) else os.path.join(SCENES_DIR, s if s.endswith(".toml") else
                                                            s + ".toml")
            if not os.path.exists(path):
                raise PolarstripeError(f"--scenes: no scene file {s!r} (nor in {SCENES_DIR})")
            out.append(path)
        return out
    if args.scene:
        return [args.scene]
    return sorted(glob.glob(os.path.join(SCENES_DIR, "*.toml")))


def run(args) -> dict:
    text = args.plan_orders or DEFAULT_VARIANTS
    variants = tuple(v.strip() for v in text.split(",") if v.strip())
    if not variants or any(v not in VARIANTS for v in variants):
        raise PolarstripeError(f"--plan-orders: comma-separated {', '.join(VARIANTS)}, got {text!r}")
    settings = ScanSettings(fidelity=args.fidelity, orders=args.orders, n_stripes=args.stripes,
                            width=args.width or DEFAULT_WIDTH, exposure=args.scan_exposure or "rig",
                            seed=args.seed, p_rule=args.p_rule)
    settings.check()
    refine = DEFAULT_REFINE if args.refine is None else args.refine
    grid = default_grid(args.grid or DEFAULT_GRID, *args.grid_range)
    paths = scene_paths(args)
    scenes = [(os.path.splitext(os.path.basename(p))[0], load_scene(p)) for p in paths]
    cache = None if args.no_cache else ScanCache(args.cache or default_cache_dir())
    bar = None
    if not args.no_progress:
        from tqdm import tqdm
        bar = tqdm(total=0, unit="sep", desc="end to end", leave=False)
    out = {"grid_m": grid.tolist(), "refine": refine, "settings": vars(settings),
           "plan_orders": list(variants),
           "plan_fidelity": args.plan_fidelity, "target_regret": TARGET_REGRET, "scenes": {}}
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        for name, scene in scenes:
            if bar is not None:
                bar.set_description(name)
            t = time.perf_counter()
            res = validate(scene, grid, settings, plan_orders=variants, plan_fidelity=args.plan_fidelity,
                           progress=(lambda: bar.update(1)) if bar is not None else None,
                           on_total=(lambda n: setattr(bar, "total", bar.total + n)) if bar is not None
                           else None, cache=cache, refine=refine)
            res["seconds"] = time.perf_counter() - t
            out["scenes"][name] = res
            if cache is not None:
                cache.save()
    finally:
        if bar is not None:
            bar.close()
    out["seconds"] = time.perf_counter() - t0
    out["cpu_seconds"] = time.process_time() - c0
    out["cache"] = None if cache is None else str(cache.path)
    return out


def _f(v, fmt):
    return "-" if v is None else format(v, fmt)


def print_table(res: dict) -> None:
    s = res["settings"]
    print(f"planner end to end: {len(res['grid_m'])} separations "
          f"{res['grid_m'][0] * 100:.0f}-{res['grid_m'][-1] * 100:.0f} cm (log) + every pick + "
          f"{res['refine']} bisection(s) around each best; scans at "
          f"{s['fidelity']}, {s['orders']} orders, {s['n_stripes']} stripes, width {s['width']}, exposure "
          f"{s['exposure']}; error vs T (whole frame, gain fitted); regret = error at pick / best error")
    scanned = sum(sc["scanned"] for sc in res["scenes"].values())
    cached = sum(sc["cached"] for sc in res["scenes"].values())
    print(f"{res['seconds']:.0f} s ({res['cpu_seconds']:.0f} s CPU); {scanned} method scans made, {cached} "
          f"from the cache {res['cache'] or '(none)'}")
    head = (f"{'plan':<7} {'method':<18} {'image':<9} {'scene':<15} {'pick cm':>8} {'err':>6} "
            f"{'best cm':>8} {'err':>6} {'regret':>7}")
    print(head)
    worst: dict[str, float] = {}
    for name, sc in res["scenes"].items():
        for r in sc["rows"]:
            edge = ">" if r["best_at_edge"] else " "
            pe = "!" if r["pick_at_edge"] else " "
            print(f"{r['plan']:<7} {r['method']:<18} {r['image']:<9} {name:<15} "
                  f"{r['pick_m'] * 100:7.1f}{pe} {_f(r['pick_error'], '6.3f')} "
                  f"{_f(r['best_m'] and r['best_m'] * 100, '7.1f')}{edge} {_f(r['best_error'], '6.3f')} "
                  f"{_f(r['regret'], '7.3f')}")
            if r["image"] == "composite" and r["regret"] is not None:
                k = f"{r['plan']} {r['method']}"
                worst[k] = max(worst.get(k, 0.0), r["regret"])
    print("'>' the best lies at the grid's edge (it may lie beyond); '!' the pick is at the planner's range "
          "edge")
    print("worst regret per planner variant and method (composite images):")
    for k, v in worst.items():
        print(f"  {k:<28} {v:6.3f}  {'meets' if v <= res['target_regret'] else 'misses'} "
              f"≤ {res['target_regret']}")


def main(args: argparse.Namespace) -> int:
    res = run(args)
    if args.json:
        print(json.dumps(res))
    else:
        print_table(res)
    return 0
