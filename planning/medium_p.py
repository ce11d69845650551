"""The backscatter's DOP p from an analyzer pair (E_b, E_w) of flood frames (docs/planning.md §6,
docs/physics.md §4.2): from the frames alone, or with the fitted medium's model.

Through an ideal analyzer crossed and parallel to the backscatter (eqs. 4–5), E_w − E_b = p·B and
E_w + E_b = S + B, S the object's unpolarized light. Where S = 0 the ratio is p; the simulated tank and a rig
looking at a wall have object light everywhere (forward-scattered light lights the whole wall: S/B ≥ 0.07 in
the demo), and every ratio reads p·B/(S + B), low.

* :func:`p_of_pair`: the frames alone (:func:`~polarstripe.imaging.polarization.estimate_p`: the mean of the
  highest block DOPs, the blocks with the least object light).
* :func:`p_with_model`: the fitted medium's model predicts each pixel's measured DOP up to the medium's own
  depolarization and the analyzer's angle ψ, p_m·cos 2(χ − ψ)·B/(S + B) from
  :func:`~polarstripe.sim.render.render_components` (p_m, χ the model's DOP and angle per pixel); the scale
  κ of (E_w − E_b)/(E_w + E_b) = κ·p_m·cos 2(χ − ψ)·B/(S + B), linear in (κ cos 2ψ, κ sin 2ψ), is fitted
  by least squares over the region's unsaturated pixels (each pixel alike; a second pass without outliers),
  and p is κ times the model's backscatter-weighted DOP over the region, Σ p_m B / Σ B: what the planner's
  constant DOP stands for.
"""

from __future__ import annotations

import math

import numpy as np
from polarstripe.imaging.polarization import estimate_p, p_bootstrap_std
from polarstripe.imaging.validation import ImagingError
from polarstripe.sim.render import render_components
from polarstripe.sim.scene import Scene

MIN_PIXELS = 12


def p_of_pair(pair: tuple[np.ndarray, np.ndarray] | None, object_free: np.ndarray | None, dark: float,
              saturation: float) -> tuple[float, float, str]:
    """(p, its bootstrap std, "") from an (E_b, E_w) pair over the region (docs/physics.md §4.2, by
    :func:`~polarstripe.imaging.polarization.estimate_p`'s ``upper`` rule, unclamped), or (nan, nan, the
    reason)."""
    if pair is None:
        return math.nan, math.nan, "no analyzer pair"
    kw = dict(roi=object_free, dark_offset=dark, saturation=saturation, rule="upper")
    try:
        p = estimate_p(*pair, p_min=None, min_pixels=MIN_PIXELS, **kw)
        return p, p_bootstrap_std(*pair, **kw), ""
    except ImagingError as exc:
        return math.nan, math.nan, f"p: {exc}"


def p_with_model(pair: tuple[np.ndarray, np.ndarray], object_free: np.ndarray | None, dark: float,
                 saturation: float, scene: Scene, fidelity: str) -> tuple[float, float, str]:
    """(p, its standard error, "") from an (E_b, E_w) pair and ``scene`` with the fitted medium (module
    docstring), or what :func:`p_of_pair` gives where the model cannot serve (no backscatter in the
    region, too few pixels, κ not positive)."""
    eb, ew = (np.asarray(x, np.float64) for x in pair)
    h, w = eb.shape
    sc = scene.replace(camera=scene.camera.replace(resolution=(w, h)))
    c = render_components(sc, "flood", fidelity)
    region = np.ones((h, w), bool) if object_free is None else np.asarray(object_free, bool)
    # E_w − E_b = κ p_m cos 2(χ − ψ) B/(S + B) · (E_w + E_b), ψ the pair's co-polarized angle in the
    # model's camera frame: linear in (κ cos 2ψ, κ sin 2ψ), so the analyzer's angle need not be known
    with np.errstate(invalid="ignore", divide="ignore"):
        q = np.where(c.B > 0, c.p * c.B / (c.S + c.B), 0.0)
    diff, total = ew - eb, ew + eb - 2.0 * dark
    use = region & (eb < saturation) & (ew < saturation) & (total > 0) & (q > 0)
    if use.sum() < MIN_PIXELS or not np.any(c.B[region] > 0):
        return p_of_pair(pair, object_free, dark, saturation)
    # in DOP units, each pixel alike, then once more without the pixels beyond 4 median absolute deviations
    # (a few bright pixels, an object's edge blurred into the region, would rule a fit in intensity)
    two_chi = 2.0 * c.chi_rad[use]
    x = q[use][:, None] * np.column_stack([np.cos(two_chi), np.sin(two_chi)])
    y = diff[use] / total[use]
    (u, v), *_ = np.linalg.lstsq(x, y, rcond=None)
    resid = y - x @ np.array([u, v])
    mad = float(np.median(np.abs(resid - np.median(resid))))
    keep = np.abs(resid) <= 4.0 * 1.4826 * mad if mad > 0 else np.ones(y.size, bool)
    if keep.sum() < MIN_PIXELS:
        return p_of_pair(pair, object_free, dark, saturation)
    x, y = x[keep], y[keep]
    (u, v), *_ = np.linalg.lstsq(x, y, rcond=None)
    kappa = math.hypot(u, v)
    if not kappa > 0:
        return p_of_pair(pair, object_free, dark, saturation)
    resid = y - x @ np.array([u, v])
    try:
        cov = np.linalg.inv(x.T @ x) * float(resid @ resid) / max(y.size - 2, 1)
    except np.linalg.LinAlgError:
        return p_of_pair(pair, object_free, dark, saturation)
    grad = np.array([u, v]) / kappa
    kappa_std = math.sqrt(max(float(grad @ cov @ grad), 0.0))
    p_b = float(np.sum((c.B * c.p)[region]) / np.sum(c.B[region]))
    p = kappa * p_b
    if not 0.0 < p <= 1.0:
        return math.nan, math.nan, f"p = {p:.3g} from the analyzer pair and the model is outside (0, 1]"
    return p, kappa_std * p_b, ""
