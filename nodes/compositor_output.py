"""The compositor's files: ``<method>.png`` (8-bit, for a person: stretched from the 1st to the 99.5th
percentile, saturated pixels white), ``<method>.tiff`` (float32 DN, NaN where masked, for analysis; or
``.npy``), ``metrics.json`` (rewritten atomically) and ``comparison.png`` (the ground truth T, the
unscattered object radiance of docs/physics.md §10.8, and the methods side by side, like the paper's Fig. 6,
the best method marked, a one-line legend of the two numbers; below each stripe method, the depth map it
published on ``compositor/depth``, docs/depth.md)."""

from __future__ import annotations

import json
import os

import cv2
import matplotlib
import matplotlib.pyplot as plt
import numpy as np
from polarstripe.msgs import Method

LEGEND = ("contrast: Michelson (bright − dark)/(bright + dark) of the chart's bars, 0…1, higher is better "
          "(> 1: the dark bars fell below 0, backscatter over-subtracted — not a contrast)   ·   "
          "error: relative RMS against the ground truth T, the unscattered object radiance (gain fitted), "
          "0 = perfect, lower is better")
TRUTH_LABEL = "ground truth T (unscattered)"     # sim/truth.py: flood light attenuated, never scattered
DEPTH_BAR_LABEL = "z [m]"  # along the camera's optical axis (msgs/depth.py)
DEPTH_CMAP, INVALID_GREY = "viridis", (0.6, 0.6, 0.6)  # a neutral grey, not a colour of the depth map


class PublishedDepth:
    """The ``compositor/depth`` publisher that keeps the last :class:`~polarstripe.msgs.DepthMap` of each
    method: the comparison figure shows the depth exactly as it was published."""

    def __init__(self, publisher):
        self.publisher, self.maps = publisher, {}

    def publish(self, depth) -> None:
        self.publisher.publish(depth)
        self.maps[depth.method] = depth


def display_range(image: np.ma.MaskedArray) -> tuple[float, float]:
    """The 1st and 99.5th percentile of the unmasked, finite pixels (0, 1 when there are none)."""
    valid = np.ma.compressed(image)
    valid = valid[np.isfinite(valid)]
    if not valid.size:
        return 0.0, 1.0
    lo, hi = np.percentile(valid, (1, 99.5))
    return float(lo), float(max(hi, lo + 1e-9))


def to_display(image: np.ma.MaskedArray) -> np.ndarray:
    """``image`` [DN] as 8 bits a viewer shows: linear from :func:`display_range`, masked (saturated) 255."""
    lo, hi = display_range(image)
    data = np.ma.filled(np.ma.masked_invalid(np.ma.asarray(image, dtype=np.float64)), hi)
    out = np.clip(np.round((data - lo) * (255.0 / (hi - lo))), 0, 255).astype(np.uint8)
    out[np.ma.getmaskarray(image)] = 255
    return out


def write_method(out: str, method: str, image: np.ma.MaskedArray, metrics: dict, *,
                 image_format: str = "tiff") -> None:
    """Write ``method``'s composite ``image`` [DN] to folder ``out`` and rewrite ``metrics.json``."""

    cv2.imwrite(os.path.join(out, f"{method}.png"), to_display(image))
    raw = np.ma.filled(image.astype(np.float32), np.nan)
    if image_format == "tiff":
        cv2.imwrite(os.path.join(out, f"{method}.tiff"), raw)
    else:
        np.save(os.path.join(out, f"{method}.npy"), raw)
    tmp = os.path.join(out, "metrics.json.tmp")
    with open(tmp, "w") as f:
        json.dump(metrics, f, indent=2, sort_keys=True)
    os.replace(tmp, os.path.join(out, "metrics.json"))


def _number(x) -> float | None:
    return float(x) if isinstance(x, int | float) and not isinstance(x, bool) and np.isfinite(x) else None


def best_method(metrics: dict, methods) -> str | None:
    """The method with the lowest error against the truth; without errors, the highest contrast in [0, 1]
    (a contrast above 1 is not one); None when no method has either."""
    errors = {m: e for m in methods if (e := _number(metrics.get(m, {}).get("error_vs_truth"))) is not None}
    if errors:
        return min(errors, key=errors.get)
    contrasts = {m: c for m in methods
                 if (c := _number(metrics.get(m, {}).get("contrast"))) is not None and 0.0 <= c <= 1.0}
    return max(contrasts, key=contrasts.get) if contrasts else None


def depth_title(method: str, depth) -> str:
    """A depth panel's title: the valid fraction of the drawn map, of the objects and the RMS error against
    the simulator's depth truth when the compositor had it (``depth.metrics``, nodes/compositor_depth.py)."""
    z = np.asarray(depth.depth_m)
    m = depth.metrics or {}
    objects = _number(m.get("valid_fraction_of_objects"))
    rms = _number(m.get("depth_rms_mm"))
    line = f"valid {100 * float(np.isfinite(z).mean()):.0f} % of pixels"
    line += f" ({100 * objects:.0f} % of objects)" if objects is not None else ""
    error = f"RMS {rms:.1f} mm vs depth truth" if rms is not None else "no depth truth: no RMS"
    return f"{method}: depth (grey: none)\n{line}\n{error}"


def _depth_panels(methods, metrics: dict, depth: dict | None) -> dict:
    """Stripe method -> its DepthMap of the scan in ``metrics`` (None: that scan published none)."""
    if depth is None:
        return {}
    return {m: d if (d := depth.get(m)) is not None and d.scan_id == metrics.get(m, {}).get("scan_id")
            else None for m in methods if (known := Method.lookup(m)) is not None and known.striped}


def _depth_range(maps) -> tuple[float, float]:
    """The 1st to 99th percentile [m] of the valid depths of all ``maps`` (one colour scale for all)."""
    z = np.concatenate([np.asarray(d.depth_m, np.float64).ravel() for d in maps] or [np.zeros(0)])
    z = z[np.isfinite(z)]
    if not z.size:
        return 0.0, 1.0
    lo, hi = np.percentile(z, (1, 99))
    return float(lo), float(max(hi, lo + 1e-3))


def _draw_depth(fig, ax, method: str, depth, lo: float, hi: float) -> None:
    ax.set_xticks([])
    ax.set_yticks([])
    if depth is None:
        ax.set_title(f"{method}: depth\nnone for this scan (see the log)", fontsize=8)
        return
    cmap = plt.get_cmap(DEPTH_CMAP).with_extremes(bad=INVALID_GREY)
    shown = ax.imshow(np.ma.masked_invalid(np.asarray(depth.depth_m, np.float64)), cmap=cmap, vmin=lo,
                      vmax=hi, interpolation="nearest")
    bar = fig.colorbar(shown, ax=ax, fraction=0.046, pad=0.02)
    bar.set_label(DEPTH_BAR_LABEL, fontsize=7)
    bar.ax.tick_params(labelsize=6)
    ax.set_title(depth_title(method, depth), fontsize=8)


def write_comparison(path: str, results: dict, metrics: dict, order, truth: np.ndarray | None = None,
                     depth: dict | None = None) -> None:
    """The ground truth ``truth`` (T [DN], when given) and the composites of ``results`` (method -> masked
    image) side by side in ``order``, each stretched from its 1st to 99.5th percentile, titled with contrast
    and error; the best method (:func:`best_method`) framed and marked; :data:`LEGEND` below. With ``depth``
    (method -> published DepthMap), a second row holds each stripe method's depth map of the same scan
    under its composite (one colour scale, invalid grey, titled by :func:`depth_title`). Written to a
    temporary file and renamed: a reader never sees half a figure."""

    matplotlib.use("Agg")

    methods = [m for m in order if m in results]
    panels = ([(TRUTH_LABEL, np.ma.masked_invalid(np.asarray(truth, np.float64)))] if truth is not None
              else []) + [(m, results[m]) for m in methods]
    depths = _depth_panels(methods, metrics, depth)
    rows = 2 if depths else 1
    best = best_method(metrics, methods)
    fig, axes = plt.subplots(rows, len(panels), figsize=(3.2 * len(panels), 3.3 * rows), squeeze=False)
    for ax, (name, img) in zip(axes[0], panels, strict=True):
        lo, hi = display_range(img)
        ax.imshow(np.ma.filled(img, hi), cmap="gray", vmin=lo, vmax=hi)
        ax.set_xticks([])
        ax.set_yticks([])
        if name in metrics:
            m = metrics[name]
            c = _number(m.get("contrast"))
            note = " (>1: n/a)" if c is not None and c > 1.0 else ""
            title = f"{name}{'  ★ best' if name == best else ''}\n" \
                    f"contrast {fmt(m.get('contrast'))}{note}, error {fmt(m.get('error_vs_truth'))}"
        else:
            title = f"{name}\n(reference)"
        ax.set_title(title, fontsize=8, fontweight="bold" if name == best else "normal")
        for spine in ax.spines.values():
            spine.set_visible(name == best)
            spine.set_color("tab:green")
            spine.set_linewidth(3)
    if depths:
        lo, hi = _depth_range([d for d in depths.values() if d is not None])
        for ax, (name, _) in zip(axes[1], panels, strict=True):
            if name in depths:
                _draw_depth(fig, ax, name, depths[name], lo, hi)
            else:
                ax.set_axis_off()
    fig.text(0.5, 0.01, LEGEND, ha="center", va="bottom", fontsize=6, wrap=True)
    fig.tight_layout(rect=(0, 0.07 / rows, 1, 1))  # 0.23 in for the legend
    tmp = path + ".tmp"
    fig.savefig(tmp, dpi=100, format="png")
    plt.close(fig)
    os.replace(tmp, path)


def fmt(x) -> str:
    """A metric for a person: 3 decimals, or n/a when there is none."""
    return "n/a" if x is None else f"{x:.3f}"
