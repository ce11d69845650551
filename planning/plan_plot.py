"""The paper's Figs. 9a and 10d anew (``polarstripe plan --plot``), and Fig. 10's scan question as a table.

:func:`figure_data` turns a plan's JSON (:func:`polarstripe.planning.plan_cli.plan_to_json`, with the
``reference`` plan and ``validation`` that ``plan`` adds) into the data of each panel, plain lists, so what is
drawn can be checked against plans computed independently; :func:`draw_figure` only draws it.

* Panels: flood lighting (Fig. 9a: E and the polarized reading), light striping (Fig. 10d: the stripe
  locations O1–O3 and their mean, the rotate scan's curve), and polarized light striping.
* Curves: the plan's own measure and orders (default: 1 − the expected error, all orders; docs/planning.md §8)
  solid, the paper's measure with single scattering (``--measure paper --orders single``, §1–§2) dashed. A
  model's curves of one modality share one normaliser, their maximum, so E against the polarized reading and
  O1–O3 against each other keep their relative heights; each curve's pick (its argmax) is marked.
* End to end (``--validate``, §7): the composite's error against the unscattered object at every separation
  scanned (grid, picks, bisections) on a second, right-hand axis (lower is better), its best marked.
* Fig. 10's question (rotate the source, translate it, or both; :func:`~polarstripe.planning.planner.
  compare_scans`): :func:`scan_rows`, per stripe plan and model, printed by ``plan`` and written on each
  stripe panel.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from polarstripe.sim.scene import SceneError

#: the paper's model and measure: the reference curves of every plot
REFERENCE = {"measure": "paper", "orders": "single"}
#: panel key → (title, plan keys whose curves it draws, end-to-end (method, image, label) it shows)
PANELS = {
    "flood": ("flood lighting (cf. Fig. 9a)", ("flood", "flood_polarized"),
              (("flood", "error", "flood"), ("polarized_flood", "error", "polarized flood, Ŝ"),
               ("polarized_flood", "error_e_b", "polarized flood, E_b"))),
    "stripes": ("light striping (cf. Fig. 10d)", ("stripes",), (("stripes", "error", "stripes"),)),
    "stripes_polarized": ("polarized light striping (cf. Fig. 10d)", ("stripes_polarized",),
                          (("polarized_stripes", "error", "polarized stripes, Ŝ"),
                           ("polarized_stripes", "error_e_b", "polarized stripes, E_b"))),
}
PLOT_SUFFIXES = (".png", ".pdf", ".svg")
_ORDERS = {"all": "all orders", "single": "single scattering"}


def model_label(measure: str, orders: str) -> str:
    """'1-error, all orders' from an entry's measure name and the model's orders."""
    return f"{measure}, {_ORDERS.get(orders, orders)}"


def _models(doc: dict) -> list[tuple[str, dict, str]]:
    """(role, plans keyed like ``doc``, orders) of the plan itself and, when there, of its reference."""
    out = [("plan", doc, doc.get("model", {}).get("orders", "all"))]
    if "reference" in doc:
        out.append(("reference", doc["reference"]["plans"], doc["reference"]["orders"]))
    return out


def scan_rows(doc: dict) -> list[dict]:
    """Fig. 10's answer per stripe plan and model: {"plan", "model", "label", "winner", "scores",
    "separations_m"} (the winner: the best score, a simpler scan within its tolerance winning)."""
    rows = []
    for key in ("stripes", "stripes_polarized"):
        for role, plans, orders in _models(doc):
            if key in plans:
                scan = plans[key]["scan"]
                rows.append({"plan": key, "model": role, "label": model_label(plans[key]["measure"], orders),
                             "winner": scan["winner"], "scores": dict(scan["scores"]),
                             "separations_m": scan["separations_m"]})
    return rows


def print_scan_rows(rows: list[dict]) -> None:
    if not rows:
        return
    print("Fig. 10's question, rotate the source, translate it or both (mean objective over the stripe "
          "locations; a simpler scan within 2 % wins):")
    print(f"  {'plan':<18} {'model':<30} {'rotate':>7} {'translate':>9} {'both':>7}  winner")
    for r in rows:
        s = {k: "n/a" if v is None else f"{v:.4f}" for k, v in r["scores"].items()}
        print(f"  {r['plan']:<18} {r['label']:<30} {s['rotate']:>7} {s['translate']:>9} {s['both']:>7}  "
              f"{r['winner']}")


def _curve(label: str, role: str, key: str, entry: dict, values, scale: float,
           location: int | None = None) -> dict:
    v = np.asarray(values, np.float64)
    norm = v / scale if scale > 0 else v
    return {"label": label, "model": role, "plan": key, "location": location,
            "separations_cm": (np.asarray(entry["separations"]) * 100).tolist(), "values": norm.tolist(),
            "pick_cm": float(entry["separations"][int(np.argmax(v))]) * 100,
            "pick_at_edge": int(np.argmax(v)) in (0, v.size - 1)}


def _panel_curves(keys: tuple[str, ...], role: str, plans: dict, orders: str) -> list[dict]:
    """One model's curves of a panel, normalised by the maximum over that model's curves of the modality."""
    modality = keys[0].split("_")[0]
    family = [plans[k] for k in (modality, modality + "_polarized") if k in plans]
    if modality == "flood":
        scale = max(max(e["objective"]) for e in family)
    else:
        scale = max(max(loc["objective"]) for e in family for loc in e["locations"])
    out = []
    for key in keys:
        if key not in plans:
            continue
        entry = plans[key]
        tag = model_label(entry["measure"], orders)
        if modality == "flood":
            out.append(_curve(f"{entry['reading']}, {tag}", role, key, entry, entry["objective"], scale))
            continue
        for i, loc in enumerate(entry["locations"]):
            out.append(_curve(f"O{i + 1}, {tag}", role, key, {**entry, **loc}, loc["objective"], scale, i))
        out.append(_curve(f"mean of O1-O{len(entry['locations'])} (rotate), {entry['reading']}, {tag}", role,
                          key, entry, entry["objective"], scale))
    return out


def _e2e_points(validation: dict, method: str, image: str, label: str) -> dict | None:
    rows = validation.get("curves", {}).get(method, []) + validation.get("extra", {}).get(method, [])
    pts = sorted((r["separation_m"] * 100, r[image]) for r in rows if r.get(image) is not None)
    if not pts:
        return None
    d, e = (list(x) for x in zip(*pts, strict=True))
    best = int(np.argmin(e))
    return {"label": label, "method": method, "image": image, "separations_cm": d, "error": e,
            "best_cm": d[best], "best_at_edge": best in (0, len(d) - 1)}


def figure_data(doc: dict) -> dict:
    """The panels to draw (module docstring) from a plan's JSON: {"panels": [{"key", "title", "curves",
    "e2e", "scans"}]} with

    * curves: [{"label", "model", "plan", "location", "separations_cm", "values" (normalised), "pick_cm",
      "pick_at_edge"}];
    * e2e (only with a ``validation``): [{"label", "method", "image", "separations_cm", "error", "best_cm",
      "best_at_edge"}];
    * scans: the :func:`scan_rows` of the panel's plan.
    """
    scans = scan_rows(doc)
    panels = []
    for key, (title, keys, e2e) in PANELS.items():
        if keys[0] not in doc:
            continue
        curves = [c for role, plans, orders in _models(doc) for c in _panel_curves(keys, role, plans, orders)]
        points = []
        if "validation" in doc:
            points = [p for m, image, label in e2e if (p := _e2e_points(doc["validation"], m, image, label))]
        panels.append({"key": key, "title": title, "curves": curves, "e2e": points,
                       "scans": [r for r in scans if r["plan"] == key]})
    return {"panels": panels}


def check_plot_path(path: str) -> None:
    """Refuse, before any work, a plot file that cannot be written: a folder that is not there or not
    writable, or a format matplotlib does not write here."""
    p = Path(path)
    if p.suffix.lower() not in PLOT_SUFFIXES:
        raise SceneError(f"--plot: {path!r} must end in {', '.join(PLOT_SUFFIXES)}")
    folder = p.parent if str(p.parent) else Path(".")
    if not folder.is_dir():
        raise SceneError(f"--plot: folder {str(folder)!r} does not exist")
    if p.is_dir():
        raise SceneError(f"--plot: {path!r} is a folder")
    if not os.access(folder, os.W_OK) or (p.exists() and not os.access(p, os.W_OK)):
        raise SceneError(f"--plot: {path!r} is not writable")


_STYLE = {"plan": "-", "reference": "--"}
_MARKERS = {"error": "o", "error_e_b": "s"}
_COLOURS = {"flood": "C0", "flood_polarized": "C1"}  # a stripe panel's mean curve: black


def draw_figure(data: dict, path: str) -> None:
    """Draw :func:`figure_data`'s panels side by side into ``path`` (PNG, PDF or SVG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = data["panels"]
    if not panels:
        raise SceneError("--plot: nothing to draw")
    fig, axes = plt.subplots(1, len(panels), figsize=(6.4 * len(panels), 8.0), squeeze=False)
    for ax, panel in zip(axes[0], panels, strict=True):
        for c in panel["curves"]:
            wide = c["location"] is None
            colour = _COLOURS.get(c["plan"], "k") if wide else f"C{c['location']}"
            ax.plot(c["separations_cm"], c["values"], _STYLE[c["model"]], color=colour, lw=2 if wide else 1.2,
                    label=f"{c['label']}: pick {c['pick_cm']:.1f} cm" + (" (range end)" * c["pick_at_edge"]))
            ax.plot([c["pick_cm"]], [np.interp(c["pick_cm"], c["separations_cm"], c["values"])], "v",
                    color=colour, ms=7 if wide else 5)
        ax.set_xlabel("sensor–source separation d_LC [cm]")
        ax.set_ylabel("objective / its maximum (per model and modality)")
        ax.set_ylim(0, 1.08)
        ax.grid(alpha=0.3)
        handles, labels = ax.get_legend_handles_labels()
        if panel["e2e"]:
            tw = ax.twinx()
            for j, p in enumerate(panel["e2e"]):
                colour = f"C{6 + j}"
                tw.plot(p["separations_cm"], p["error"], _MARKERS[p["image"]], color=colour, ms=5,
                        mfc=colour if p["image"] == "error" else "none", ls=":", lw=0.8,
                        label=f"end to end, {p['label']} (right axis): best {p['best_cm']:.1f} cm"
                        + (" (grid end)" * p["best_at_edge"]))
                tw.plot([p["best_cm"]], [min(p["error"])], "*", color=colour, ms=12)
            tw.set_ylabel("end-to-end error vs T (lower is better)")
            h2, l2 = tw.get_legend_handles_labels()
            handles, labels = handles + h2, labels + l2
        scans = "\n".join(f"{r['label']}: {r['winner']} (" + ", ".join(
            f"{k} {'n/a' if v is None else f'{v:.3f}'}" for k, v in r["scores"].items()) + ")"
            for r in panel["scans"])
        leg = ax.legend(handles, labels, fontsize=6.5, loc="upper center", bbox_to_anchor=(0.5, -0.12),
                        title="rotate the source, translate it or both?\n" + scans if scans else None,
                        title_fontsize=7)
        leg.get_title().set_multialignment("left")
        ax.set_title(panel["title"], fontsize=10)
    if any(c["model"] == "reference" for p in panels for c in p["curves"]):
        fig.suptitle("solid: the plan's measure and orders; dashed: the paper's measure with single "
                     "scattering; ▼ each curve's pick, ★ the end-to-end best", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
