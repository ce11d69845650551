"""The compositor's files: ``<method>.png`` (16-bit DN, clipped), ``<method>.tiff`` (float32 DN, NaN where
masked; or ``.npy``), ``metrics.json`` (rewritten atomically) and ``comparison.png`` (the methods side by
side, like the paper's Fig. 6)."""

from __future__ import annotations

import json
import os

import cv2
import matplotlib
import matplotlib.pyplot as plt
import numpy as np


def write_method(out: str, method: str, image: np.ma.MaskedArray, metrics: dict, *,
                 image_format: str = "tiff") -> None:
    """Write ``method``'s composite ``image`` [DN] to folder ``out`` and rewrite ``metrics.json``."""

    png = np.clip(np.round(np.ma.filled(image, 0.0)), 0, 65535).astype(np.uint16)
    cv2.imwrite(os.path.join(out, f"{method}.png"), png)
    raw = np.ma.filled(image.astype(np.float32), np.nan)
    if image_format == "tiff":
        cv2.imwrite(os.path.join(out, f"{method}.tiff"), raw)
    else:
        np.save(os.path.join(out, f"{method}.npy"), raw)
    tmp = os.path.join(out, "metrics.json.tmp")
    with open(tmp, "w") as f:
        json.dump(metrics, f, indent=2, sort_keys=True)
    os.replace(tmp, os.path.join(out, "metrics.json"))


def write_comparison(path: str, results: dict, metrics: dict, order) -> None:
    """The composites of ``results`` (method -> masked image) side by side in ``order``, each stretched from
    its 1st to 99.5th percentile, titled with contrast and error."""

    matplotlib.use("Agg")

    methods = [m for m in order if m in results]
    fig, axes = plt.subplots(1, len(methods), figsize=(3.2 * len(methods), 3.0), squeeze=False)
    for ax, method in zip(axes[0], methods, strict=True):
        img = results[method]
        valid = img.compressed()
        lo, hi = np.percentile(valid, (1, 99.5)) if valid.size else (0.0, 1.0)
        ax.imshow(np.ma.filled(img, hi), cmap="gray", vmin=lo, vmax=max(hi, lo + 1e-9))
        m = metrics[method]
        ax.set_title(f"{method}\ncontrast {fmt(m['contrast'])}, error {fmt(m['error_vs_truth'])}",
                     fontsize=8)
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def fmt(x) -> str:
    """A metric for a person: 3 decimals, or n/a when there is none."""
    return "n/a" if x is None else f"{x:.3f}"
