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
* :func:`p_map_with_model`: the same fit, and the DOP the pair sees at each pixel, κ·p_m·cos 2(χ − ψ): the
  map eq. 6 divides by (docs/physics.md §4.2), so that it removes the backscatter where p and χ vary.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from polarstripe.imaging.p_map import PEstimate, regional_p_map
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


@dataclasses.dataclass(frozen=True)
class PairFit:
    """The least-squares fit (E_w − E_b)/(E_w + E_b) = q·(u cos 2χ + v sin 2χ) of an analyzer pair to the
    model's q = p_m B/(S + B) and χ (module docstring): u = κ cos 2ψ, v = κ sin 2ψ, and κ's std."""

    u: float
    v: float
    kappa_std: float
    rss: float = 0.0  # the fit's sum of squared residuals [DOP²] over the pixels it kept
    rss_constant: float = math.inf  # … and one constant DOP's over the same pixels
    crossed: bool = False  # the pair crossed at each pixel's own angle (a polarization camera): v = 0

    def seen(self, components) -> np.ndarray:
        """The DOP the pair sees at each pixel: κ p_m cos 2(χ − ψ) = p_m (u cos 2χ + v sin 2χ), or κ p_m for
        a pair crossed per pixel."""
        if self.crossed:
            return self.u * components.p
        two_chi = 2.0 * components.chi_rad
        return components.p * (self.u * np.cos(two_chi) + self.v * np.sin(two_chi))

    @property
    def explains(self) -> bool:
        """True when the model fits the pair's DOP better than one constant does (a pair the model does not
        describe, e.g. frames of another rig, is better told by the frames alone)."""
        return self.rss < self.rss_constant

    @property
    def kappa(self) -> float:
        return math.hypot(self.u, self.v)


def fit_pair(components, pair, region, dark: float, saturation: float, *,
             crossed: bool = False) -> PairFit | str:
    """:class:`PairFit` of ``pair`` (E_b, E_w raw) to the model's flood ``components`` at the pair's
    resolution over the bool mask ``region``, or why it cannot be fitted (str). ``crossed``: the pair was
    crossed at each pixel's own angle (a polarization camera's ``local`` or ``pixel`` rule, docs/physics.md
    §4.4), so it sees κ p_m B/(S + B) without the cos 2(χ − ψ): κ alone is fitted."""
    c = components
    eb, ew = (np.asarray(x, np.float64) for x in pair)
    # E_w − E_b = κ p_m cos 2(χ − ψ) B/(S + B) · (E_w + E_b), ψ the pair's co-polarized angle in the
    # model's camera frame: linear in (κ cos 2ψ, κ sin 2ψ), so the analyzer's angle need not be known
    with np.errstate(invalid="ignore", divide="ignore"):
        q = np.where(c.B > 0, c.p * c.B / (c.S + c.B), 0.0)
    diff, total = ew - eb, ew + eb - 2.0 * dark
    use = region & (eb < saturation) & (ew < saturation) & (total > 0) & (q > 0)
    if use.sum() < MIN_PIXELS or not np.any(c.B[region] > 0):
        return f"{int(use.sum())} pixels with backscatter in the model (need {MIN_PIXELS})"
    # in DOP units, each pixel alike, then once more without the pixels beyond 4 median absolute deviations
    # (a few bright pixels, an object's edge blurred into the region, would rule a fit in intensity)
    two_chi = 2.0 * c.chi_rad[use]
    x = q[use][:, None] * (np.ones((two_chi.size, 1)) if crossed else
                           np.column_stack([np.cos(two_chi), np.sin(two_chi)]))
    y = diff[use] / total[use]
    coef, *_ = np.linalg.lstsq(x, y, rcond=None)
    resid = y - x @ coef
    mad = float(np.median(np.abs(resid - np.median(resid))))
    keep = np.abs(resid) <= 4.0 * 1.4826 * mad if mad > 0 else np.ones(y.size, bool)
    if keep.sum() < MIN_PIXELS:
        return "too few pixels left after the outliers"
    x, y = x[keep], y[keep]
    coef, *_ = np.linalg.lstsq(x, y, rcond=None)
    u, v = float(coef[0]), 0.0 if crossed else float(coef[1])
    kappa = math.hypot(u, v)
    if not kappa > 0 or (crossed and u <= 0):
        return "the model's DOP does not fit the pair (κ = 0)"
    resid = y - x @ coef
    try:
        cov = np.linalg.inv(x.T @ x) * float(resid @ resid) / max(y.size - x.shape[1], 1)
    except np.linalg.LinAlgError:
        return "singular fit"
    grad = np.array([1.0]) if crossed else np.array([u, v]) / kappa
    return PairFit(u, v, math.sqrt(max(float(grad @ cov @ grad), 0.0)), float(resid @ resid),
                   float(np.sum((y - y.mean()) ** 2)), crossed)


def _components(pair, scene: Scene, fidelity: str):
    h, w = np.shape(pair[0])
    return render_components(scene.replace(camera=scene.camera.replace(resolution=(w, h))), "flood", fidelity)


def _region(object_free, shape) -> np.ndarray:
    return np.ones(shape, bool) if object_free is None else np.asarray(object_free, bool)


def p_with_model(pair: tuple[np.ndarray, np.ndarray], object_free: np.ndarray | None, dark: float,
                 saturation: float, scene: Scene, fidelity: str, components=None) -> tuple[float, float, str]:
    """(p, its standard error, "") from an (E_b, E_w) pair and ``scene`` with the fitted medium (module
    docstring), or what :func:`p_of_pair` gives where the model cannot serve (no backscatter in the
    region, too few pixels, κ not positive). ``components``: the model's flood components at the pair's
    resolution, when already rendered."""
    c = _components(pair, scene, fidelity) if components is None else components
    region = _region(object_free, np.shape(pair[0]))
    fit = fit_pair(c, pair, region, dark, saturation)
    if isinstance(fit, str):
        return p_of_pair(pair, object_free, dark, saturation)
    p_b = float(np.sum((c.B * c.p)[region]) / np.sum(c.B[region]))
    p = fit.kappa * p_b
    if not 0.0 < p <= 1.0:
        return math.nan, math.nan, f"p = {p:.3g} from the analyzer pair and the model is outside (0, 1]"
    return p, fit.kappa_std * p_b, ""


def p_map_with_model(pair: tuple[np.ndarray, np.ndarray], object_free: np.ndarray | None, dark: float,
                     saturation: float, scene: Scene, fidelity: str, *, p_min: float = 0.05,
                     components=None, fit: PairFit | None = None, crossed: bool = False) -> PEstimate:
    """Eq. 6's p per pixel from the medium's model (docs/physics.md §4.2).

    With κ and ψ fitted as for :func:`p_with_model` (u = κ cos 2ψ, v = κ sin 2ψ), the DOP the pair sees
    at each pixel is p_e(x) = κ p_m(x) cos 2(χ(x) − ψ) = p_m(x)(u cos 2χ(x) + v sin 2χ(x)), clamped to
    [p_min, 1]; ``p`` is κ Σ p_m B / Σ B over the region (the medium's DOP). Where the model cannot serve
    (no backscatter in the region, too few pixels, κ not positive, p outside (0, 1], a fit no better than
    one constant DOP over the region) the map comes from the frames alone
    (:func:`~polarstripe.imaging.p_map.regional_p_map`) and ``note`` says why.
    ``components``: the model's flood components at the pair's resolution, when already rendered;
    ``fit``: κ and ψ already fitted (:func:`fit_pair`; e.g. to the flood pair of this pose, for a stripe
    scan's composites, whose object light the flood model does not predict), else fitted to ``pair``;
    ``crossed``: as :func:`fit_pair`'s (the map is then κ p_m).
    """
    c = _components(pair, scene, fidelity) if components is None else components
    region = _region(object_free, np.shape(pair[0]))
    fit = fit_pair(c, pair, region, dark, saturation, crossed=crossed) if fit is None else fit
    if not isinstance(fit, str) and not fit.explains:
        fit = "it explains the pair's DOP no better than one constant DOP"
    if not isinstance(fit, str):
        p_b = float(np.sum((c.B * c.p)[region]) / np.sum(c.B[region]))
        p = fit.kappa * p_b
        if 0.0 < p <= 1.0:
            eq6 = np.clip(fit.seen(c), p_min, 1.0)
            return PEstimate(eq6, p, fit.kappa_std * p_b, "model")
        fit = f"p = {p:.3g} from the pair and the model is outside (0, 1]"
    sat = saturation if math.isfinite(saturation) else None
    est = regional_p_map(*pair, object_free, dark_offset=dark, saturation=sat, p_min=p_min)
    return dataclasses.replace(est, note=f"the model's p map not used: {fit}")



def scene_p_model(scene: Scene, object_free: np.ndarray | None, dark: float, saturation: float | None, *,
                  fidelity: str = "preview", p_min: float = 0.05, flood=None, renders: dict | None = None):
    """The ``p_model`` :func:`~polarstripe.imaging.compose.compose` takes under the ``map`` rule where the
    scene is known (the end-to-end judge, ``compare``) for a pair of dark offset ``dark`` and ``saturation``
    [DN]: :func:`p_map_with_model` with ``scene``'s own medium at the scan's pose, as the compositor's
    ``p_scene`` gives it (nodes/compositor_p.py; ``preview``, its ``p_fidelity``), κ and ψ fitted to
    ``flood`` = ((E_b, E_w) raw, its dark, its saturation), the polarized flood pair of this pose, as the
    compositor fits them (None: to the pair composed). ``renders``: a dict the model's flood render is kept
    in per frame size, to share it between the pairs of one pose."""
    renders = {} if renders is None else renders

    def p_map(e_b: np.ndarray, e_w: np.ndarray) -> PEstimate:
        h, w = np.shape(e_b)
        sc = scene.replace(camera=scene.camera.replace(resolution=(w, h)))
        if (w, h) not in renders:
            renders[(w, h)] = render_components(sc, "flood", fidelity)
        comps, region = renders[(w, h)], _region(object_free, (h, w))
        fit = None
        if flood is not None:
            pair, f_dark, f_sat = flood
            fit = fit_pair(comps, pair, region, f_dark, math.inf if f_sat is None else float(f_sat))
        sat = math.inf if saturation is None else float(saturation)
        return p_map_with_model((e_b, e_w), region, dark, sat, sc, fidelity, p_min=p_min, components=comps,
                                fit=None if isinstance(fit, str) else fit)

    return p_map
