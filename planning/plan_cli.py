"""``polarstripe plan SCENE.toml``: the best camera–source separation and stripe scan for a scene.

Prints the optimum and the curve per modality (flood: CQM·W, stripes: GQM·W), with and without a polarizer;
``--json`` prints one object keyed ``flood``, ``flood_polarized``, ``stripes``, ``stripes_polarized``;
``--plot`` draws curves like the paper's Figs. 9a and 10d (noise-free beside noisy). :func:`plan_to_json` and
:data:`PLAN_SCHEMA` (JSON Schema 2020-12) define the JSON.
"""

from __future__ import annotations

import argparse
import json

import matplotlib
import matplotlib.pyplot as plt
import numpy as np
from polarstripe.planning.planner import MODALITIES, SCAN_TYPES, Curve, SceneModel, default_separations, plan
from polarstripe.sim.scene import load_scene

HELP = "find the best camera-source separation and stripe scan (CQM*W for flood, GQM*W for stripes)"


def _curve_json(c: Curve) -> dict:
    return {
        "separations": c.separations_m.tolist(),
        "objective": c.objective.tolist(),
        "objective_noise_free": c.objective_noise_free.tolist(),
        "quality": c.quality.tolist(),
        "weight": c.weight.tolist(),
        "saturated": c.saturated.tolist(),
        "best_separation": c.best_separation_m,
    }


def plan_to_json(plans: dict) -> dict:
    """The plan as plain JSON types (validates against :data:`PLAN_SCHEMA`). Separations in metres."""
    out = {}
    for key, mp in plans.items():
        entry = {"modality": mp.modality, "polarized": mp.polarized,
                 "measure": "CQM*W" if mp.modality == "flood" else "GQM*W",
                 "exposure_scale": mp.exposure_scale, **_curve_json(mp.curve)}
        if mp.modality == "stripes":
            entry["locations"] = [{**loc, **_curve_json(c)}
                                  for loc, c in zip(mp.locations, mp.location_curves, strict=True)]
            entry["scan"] = mp.scan
        out[key] = entry
    return out


_NUMS = {"type": "array", "items": {"type": "number"}, "minItems": 2}
_CURVE = {
    "separations": _NUMS, "objective": _NUMS, "objective_noise_free": _NUMS, "quality": _NUMS,
    "weight": _NUMS,
    "saturated": {"type": "array", "items": {"type": "boolean"}}, "best_separation": {"type": "number"},
}
_ENTRY = {
    "type": "object",
    "required": ["modality", "polarized", "separations", "objective", "objective_noise_free",
                 "best_separation"],
    "properties": {"modality": {"enum": list(MODALITIES)}, "polarized": {"type": "boolean"},
                   "measure": {"type": "string"}, "exposure_scale": {"type": "number", "exclusiveMinimum": 0},
                   **_CURVE},
}
_STRIPE_ENTRY = {
    **_ENTRY,
    "required": _ENTRY["required"] + ["locations", "scan"],
    "properties": {
        **_ENTRY["properties"],
        "locations": {"type": "array", "minItems": 1, "items": {
            "type": "object", "required": ["pixel", "lateral_position_m", "separations", "objective",
                                           "objective_noise_free", "best_separation"],
            "properties": {"pixel": {"type": "array", "items": {"type": "integer"}, "minItems": 2,
                                     "maxItems": 2},
                           "lateral_position_m": {"type": "number"}, **_CURVE}}},
        "scan": {"type": "object", "required": ["winner", "scores", "separations_m"],
                 "properties": {"winner": {"enum": list(SCAN_TYPES)},
                                "scores": {"type": "object", "required": list(SCAN_TYPES),
                                           "additionalProperties": {"type": ["number", "null"]}},
                                "separations_m": {"type": "object", "required": list(SCAN_TYPES)}}},
    },
}
PLAN_SCHEMA = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "polarstripe plan",
    "type": "object",
    "minProperties": 1,
    "additionalProperties": False,
    "properties": {"flood": _ENTRY, "flood_polarized": _ENTRY, "stripes": _STRIPE_ENTRY,
                   "stripes_polarized": _STRIPE_ENTRY},
}


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scene", nargs="?", default=None,
                        help="scene TOML file (default: the paper's tank)")
    parser.add_argument("--modality", choices=["flood", "stripes"], default=None,
                        help="plan one modality only (default: both)")
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of tables")
    parser.add_argument("--plot", metavar="PNG", default=None, help="write the curves to this PNG file")
    parser.add_argument("--fidelity", default="standard", help="model fidelity: preview, standard, reference")
    parser.add_argument("--separations", type=int, default=60,
                        help="number of separations swept (default 60)")
    parser.add_argument("--range", nargs=2, type=float, default=(0.01, 0.6), metavar=("MIN_M", "MAX_M"),
                        help="separation range in metres (default 0.01 0.6)")
    parser.add_argument("--stripes", type=int, default=30, help="stripes per scan (default 30)")
    parser.add_argument("--exposure", choices=["scene", "auto"], default="scene",
                        help="scene: the camera's exposure_s, saturated points score 0 (default); auto: one "
                        "exposure per modality, the longest with no saturation over the sweep")
    parser.add_argument("--edge", choices=["eq9", "measured"], default="eq9",
                        help="stripe measure: eq. 9 as printed (default), or the O/O' step rendered with the "
                        "neighbouring sheet lit (3x the stripe cost)")
    parser.add_argument("--k-detect", type=float, default=3.0,
                        help="detection threshold in noise std for the SNR weight W (default 3)")


def _print_tables(doc: dict) -> None:
    for modality in ("flood", "stripes"):
        if modality not in doc:
            continue
        plain, pol = doc[modality], doc[modality + "_polarized"]
        measure = plain["measure"]
        print(f"{modality}: exposure ×{plain['exposure_scale']:.3g} of the scene's")
        print(f"  best d_LC = {plain['best_separation'] * 100:.1f} cm without a polarizer "
              f"({measure} = {max(plain['objective']):.4g}), {pol['best_separation'] * 100:.1f} cm with one "
              f"({measure} = {max(pol['objective']):.4g})")
        if modality == "stripes":
            for tag, entry in (("unpolarized", plain), ("polarized", pol)):
                per = ", ".join(f"O{i + 1} {loc['best_separation'] * 100:.1f} cm"
                                for i, loc in enumerate(entry["locations"]))
                scan = entry["scan"]
                scores = ", ".join(f"{k} {v:.4g}" if v is not None else f"{k} n/a"
                                   for k, v in scan["scores"].items())
                print(f"  {tag}: per-location optima {per}; scan scores {scores}; winner: {scan['winner']}")
        print(f"  {'d_LC [cm]':>9} {measure:>10} {measure + ' pol':>12} {'noise-free':>11} {'n-f pol':>9}"
              f" {'W':>6} {'W pol':>6}")
        for k, d in enumerate(plain["separations"]):
            sat = " saturated" if plain["saturated"][k] or pol["saturated"][k] else ""
            print(f"  {d * 100:9.1f} {plain['objective'][k]:10.4f} {pol['objective'][k]:12.4f} "
                  f"{plain['objective_noise_free'][k]:11.4f} {pol['objective_noise_free'][k]:9.4f} "
                  f"{plain['weight'][k]:6.3f} {pol['weight'][k]:6.3f}{sat}")


def plot_plan(doc: dict, path: str) -> None:
    """Curves like the paper's Fig. 9a (flood CQM·W) and Fig. 10d (GQM·W per stripe location)."""

    matplotlib.use("Agg")

    panels = [m for m in ("flood", "stripes") if m in doc]
    fig, axes = plt.subplots(1, len(panels), figsize=(6.2 * len(panels), 4.4), squeeze=False)
    for ax, modality in zip(axes[0], panels, strict=True):
        for suffix, style in (("", "-"), ("_polarized", "--")):
            entry = doc[modality + suffix]
            tag = "polarized" if suffix else "unpolarized"
            d = np.asarray(entry["separations"]) * 100
            if modality == "flood":
                line, = ax.plot(d, entry["objective"], style, lw=2, label=f"{tag}, with sensor noise")
                ax.plot(d, entry["objective_noise_free"], style, lw=1, color=line.get_color(), alpha=0.5,
                        label=f"{tag}, zero noise")
                ax.axvline(entry["best_separation"] * 100, color=line.get_color(), lw=0.8, ls=":")
            else:
                for i, loc in enumerate(entry["locations"]):
                    ax.plot(d, loc["objective"], style, color=f"C{i}", lw=2 if not suffix else 1.5,
                            label=f"O{i + 1}, {tag}")
                    ax.plot(d, loc["objective_noise_free"], style, color=f"C{i}", lw=0.8, alpha=0.4)
        ax.set_xlabel("sensor–source separation d_LC [cm]")
        ax.set_ylabel("CQM × W" if modality == "flood" else "GQM × W")
        title = "flood lighting (cf. Fig. 9a)" if modality == "flood" else \
            f"light striping (cf. Fig. 10d); scan: {doc['stripes']['scan']['winner']}"
        ax.set_title(title)
        ax.set_ylim(0, 1.02)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(args: argparse.Namespace) -> int:

    scene = load_scene(args.scene)
    seps = default_separations(args.separations, args.range[0], args.range[1])
    model = SceneModel(scene, fidelity=args.fidelity, n_stripes=args.stripes, edge=args.edge)
    modalities = (args.modality,) if args.modality else ("flood", "stripes")
    doc = plan_to_json(plan(model, seps, modalities=modalities, k_detect=args.k_detect,
                            exposure=args.exposure))
    if args.plot:
        plot_plan(doc, args.plot)
    if args.json:
        print(json.dumps(doc))
    else:
        _print_tables(doc)
        if args.plot:
            print(f"plot written to {args.plot}")
    return 0
