"""``polarstripe sweep SPEC.toml``: the planner over a designer's grid of scenes; one table and two plots.

Writes ``OUT/sweep.csv`` (one row per scene and separation: the scene's axis values, each objective curve's
value and its best separation, the recommended polarized flood reading, the stripe scan winners; a failed or
missing scene is one row whose ``status`` says why), ``OUT/optimum_vs_sigma_t.png`` (the best separation
against σ_t per modality and reading) and ``OUT/objective_map.png`` (each objective over separation × σ_t).
CSV rather than Parquet: the table is small (a 10 000-scene grid of 30 separations is ~60 MB of text), any
tool reads it, and it needs no pyarrow. The spec's format: :mod:`polarstripe.planning.sweep_spec`.
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
from pathlib import Path

import matplotlib
import matplotlib.pyplot as plt
import numpy as np
from polarstripe.planning.sweep import SweepResult, curve_columns, run_sweep, write_table
from polarstripe.planning.sweep_spec import load_spec

HELP = "run the planner over a grid of scenes (SPEC.toml): one CSV table and plots of the optima"

LABELS = {"flood": "flood, no polarizer", "flood_E_b": "flood, E_b (eq. 4)",
          "flood_S_hat": "flood, Ŝ (eq. 6)", "stripes": "stripes, no polarizer",
          "stripes_E_b": "stripes, E_b"}
MAX_LINES = 6


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("spec", help="sweep spec TOML (see docs/planning.md, 'Design studies')")
    parser.add_argument("-o", "--out", default=None, help="output folder (default: SPEC's name + '-sweep')")
    parser.add_argument("--jobs", type=int, default=None,
                        help="local worker processes (default: all cores; 0 = in this process)")
    parser.add_argument("--scheduler", metavar="ADDRESS", default=None,
                        help="run on this Dask distributed scheduler instead (needs the 'dask' extra)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--json", action="store_true", help="print a JSON summary instead of text")


def _x_axis(result: SweepResult) -> str | None:
    axes = result.spec.axes
    if "sigma_t" in axes:
        return "sigma_t"
    return next((k for k, v in axes.items() if len(v) > 1), None)


def _groups(result: SweepResult, x: str | None) -> tuple[list[dict], str]:
    """The combinations of the other axes to draw (at most MAX_LINES) and a note if some were left out."""
    others = {k: v for k, v in result.spec.axes.items() if k != x and len(v) > 1}
    combos = [dict(zip(others, c, strict=True)) for c in itertools.product(*others.values())]
    if len(combos) <= MAX_LINES:
        return combos or [{}], ""
    return [combos[0]], " (first of " + " × ".join(f"{len(v)} {k}" for k, v in others.items()) + ")"


def _select(result: SweepResult, x: str | None, fixed: dict) -> list:
    """[(x value, result)] of the finished scenes matching ``fixed``, sorted by x."""
    out = []
    for job in result.jobs:
        res = result.results.get(job.index)
        if res is not None and all(job.params[k] == v for k, v in fixed.items()):
            out.append((job.params[x] if x else job.index, res))
    return sorted(out, key=lambda t: t[0])


def plot_optima(result: SweepResult, path: Path) -> None:
    """Best separation against σ_t (or the first varying axis), one line per objective and combination."""
    matplotlib.use("Agg")
    x = _x_axis(result)
    groups, note = _groups(result, x)
    fig, ax = plt.subplots(figsize=(7.5, 4.8))
    for ci, col in enumerate(curve_columns(result.spec)):
        for gi, fixed in enumerate(groups):
            pts = _select(result, x, fixed)
            if not pts:
                continue
            tag = ", ".join(f"{k}={v}" for k, v in fixed.items())
            ax.plot([p[0] for p in pts], [p[1]["best"][col] * 100 for p in pts], marker="o", ms=3,
                    color=f"C{ci}", ls=["-", "--", ":", "-.", (0, (5, 1)), (0, (1, 3))][gi % 6],
                    label=LABELS[col] + (f" ({tag})" if tag else ""))
    ax.set_xlabel({"sigma_t": "extinction σ_t [1/m]"}.get(x, x or "scene"))
    ax.set_ylabel("best separation d_LC [cm]")
    ax.set_title("optimal camera–source separation" + note, fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_maps(result: SweepResult, path: Path) -> None:
    """Each objective over separation × σ_t (the first combination of the other axes), optimum marked."""
    matplotlib.use("Agg")
    x = _x_axis(result)
    groups, _ = _groups(result, x)
    pts = _select(result, x, groups[0])
    cols = curve_columns(result.spec)
    fig, axes = plt.subplots(1, len(cols), figsize=(3.6 * len(cols), 3.8), squeeze=False)
    seps = result.spec.separations * 100
    for ax, col in zip(axes[0], cols, strict=True):
        if pts:
            xs = np.array([p[0] for p in pts], float) if x else np.arange(len(pts), dtype=float)
            z = np.array([p[1]["objective"][col] for p in pts])
            ax.pcolormesh(seps, xs, z, shading="nearest", vmin=0, vmax=1, cmap="viridis")
            ax.plot([p[1]["best"][col] * 100 for p in pts], xs, "w.", ms=4)
        ax.set_title(LABELS[col], fontsize=9)
        ax.set_xlabel("d_LC [cm]")
        ax.set_ylabel({"sigma_t": "σ_t [1/m]"}.get(x, x or "scene"))
    fixed = ", ".join(f"{k}={v}" for k, v in groups[0].items())
    fig.suptitle("objective (quality × W), white: optimum" + (f"; {fixed}" if fixed else ""), fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def summary(result: SweepResult, out: Path) -> dict:
    n = len(result.jobs)
    return {"scenes": n, "separations": int(result.spec.separations.size), "finished": len(result.results),
            "failed": {str(k): v for k, v in sorted(result.failed.items())}, "missing": result.missing,
            "interrupted": result.interrupted, "seconds": result.seconds, "workers": result.workers,
            "scenes_per_second": len(result.results) / result.seconds if result.seconds > 0 else None,
            "table": str(out / "sweep.csv")}


def main(args: argparse.Namespace) -> int:
    spec = load_spec(args.spec)
    out = Path(args.out) if args.out else Path(args.spec).with_name(Path(args.spec).stem + "-sweep")
    show = not args.no_progress and sys.stderr.isatty()
    result = run_sweep(spec, jobs=args.jobs, scheduler=args.scheduler, progress=show)
    out.mkdir(parents=True, exist_ok=True)
    write_table(result, out / "sweep.csv")
    if result.results:
        plot_optima(result, out / "optimum_vs_sigma_t.png")
        plot_maps(result, out / "objective_map.png")
    doc = summary(result, out)
    if args.json:
        print(json.dumps(doc))
    else:
        rate = f"{doc['scenes_per_second']:.2f} scenes/s" if doc["scenes_per_second"] else "-"
        where = f"Dask at {args.scheduler}" if args.scheduler else \
            f"{result.workers or 'no'} worker processes"
        print(f"sweep: {doc['finished']} of {doc['scenes']} scenes × {doc['separations']} separations in "
              f"{result.seconds:.1f} s ({rate}, {where})")
        for k, why in doc["failed"].items():
            print(f"  scene {k} failed: {why}")
        if doc["missing"]:
            print(f"  {len(doc['missing'])} scenes missing{' (interrupted)' if result.interrupted else ''}: "
                  f"{doc['missing'][:20]}{' ...' if len(doc['missing']) > 20 else ''}")
        print(f"table: {out / 'sweep.csv'}" + (f"; plots: {out / 'optimum_vs_sigma_t.png'}, "
                                              f"{out / 'objective_map.png'}" if result.results else ""))
    if result.interrupted:
        return 130
    return 1 if result.failed or doc["missing"] else 0
