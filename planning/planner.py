"""The camera–source placement planner (the paper's §3): sweep d_LC and maximise a quality measure times W.

The planner asks a :class:`PlanModel` for the light-transport components at a few observed points O only
(never whole images) and scores them with :func:`polarstripe.planning.objectives.objective`: flood CQM·W
(eq. 8 × eq. 10) without a polarizer, through the best-polarized image E_b and as the recovered signal Ŝ
(eq. 6), recommending the better polarized reading; stripes the delineation margin ·W (or eq. 9 as printed).
:class:`~polarstripe.planning.scene_model.SceneModel` is the model of :mod:`polarstripe.sim` behind that
interface. Scanning a stripe across the scene can rotate the source about one position, translate it with a
fixed sheet angle, or both; :func:`compare_scans` says which wins. docs/planning.md derives the measures.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from polarstripe.planning.image_model import ImageModel
from polarstripe.planning.objectives import (
    EDGES,
    IDEAL_SENSOR,
    MODALITIES,
    READING_NAMES,
    Competitors,
    Objective,
    Samples,
    SensorNoise,
    noise_gain,
    objective,
)
from polarstripe.planning.scene_model import SceneModel
from polarstripe.planning.search import DEFAULT_SEARCH, SEARCHES, Search, midpoints, resolve_search
from polarstripe.sim.scene import SceneError

__all__ = ["DEFAULT_SEARCH", "EDGES", "IDEAL_SENSOR", "MODALITIES", "SCAN_TYPES", "Competitors", "Curve",
           "ImageModel", "ModalityPlan", "Objective", "PlanModel", "SEARCHES", "Samples", "SceneModel",
           "Search", "SensorNoise", "auto_exposure_scale", "compare_scans", "default_separations",
           "objective", "plan", "plan_model", "recommend_reading", "resolve_search", "search_plan"]

SCAN_TYPES = ("rotate", "translate", "both")
POLARIZED_READINGS = {"paper": {"flood": ("E_b", "S_hat"), "stripes": ("E_b",)},
                      "error": {"flood": ("E_b", "S_hat"), "stripes": ("E_b", "S_hat")}}
TIE = 0.02  # relative: E_b wins a tie with Ŝ (one frame, no post-processing)


class PlanModel(Protocol):
    """The interface the planner sweeps. Separations are in metres, pixels (n, 2) int (row, col).
    ``edge`` is the stripe measure its stripe samples serve (``margin`` needs their competitors)."""

    noise: SensorNoise
    edge: str

    def observed_pixels(self) -> np.ndarray: ...

    def lateral_positions_m(self) -> np.ndarray: ...

    def flood(self, d_lc_m: float) -> Samples: ...

    def stripes(self, d_lc_m: float) -> Samples: ...


@dataclass
class Curve:
    """One objective curve over the separations (mean over its observed points). ``limited_by`` (one
    location, margin only): per separation, the kind of competitor that limits the margin."""

    separations_m: np.ndarray
    objective: np.ndarray
    objective_noise_free: np.ndarray
    quality: np.ndarray
    weight: np.ndarray
    saturated: np.ndarray
    limited_by: list[str] | None = None
    lost: np.ndarray | None = None      # the error measure: the fraction of the image saturated (lost)

    @property
    def best_index(self) -> int:
        return int(np.argmax(self.objective))

    @property
    def best_separation_m(self) -> float:
        return float(self.separations_m[self.best_index])


@dataclass
class ModalityPlan:
    """The plan for one modality and polarization: the curve of the chosen ``reading``, every reading's
    curve (polarized flood: ``E_b`` and ``S_hat``) with the recommendation and its reason, per-location
    curves (stripes) and the scan comparison."""

    modality: str
    polarized: bool
    curve: Curve
    reading: str = "E"
    readings: dict[str, Curve] = field(default_factory=dict)
    recommendation: dict | None = None
    locations: list[dict] = field(default_factory=list)
    location_curves: list[Curve] = field(default_factory=list)
    scan: dict | None = None
    exposure_scale: float = 1.0
    edge: str | None = None
    measure: str = "paper"
    evaluations: int = 0                # model evaluations of the modality (its readings share them)


def plan_model(scene, *, measure: str = "error", fidelity: str | None = None, n_stripes: int = 30,
               orders: str = "all", edge: str = "margin", stripe_step: int = 1, sheets: int = 1,
               p_rule: str = "map", width: int | None = None):
    """The model :func:`plan` sweeps for a measure: the ``error`` measure renders low-resolution whole frames
    (:class:`ImageModel`, ``preview`` unless ``fidelity`` says otherwise; every ``stripe_step``-th frame of a
    stripe scan of ``sheets`` sheets per frame), the ``paper``'s measures evaluate a few observed points
    (:class:`SceneModel`, ``standard`` by default, ``edge`` its stripe measure; one sheet per frame).
    ``p_rule``: eq. 6's p the ``error`` measure predicts the composite with (``map``, the compositor's
    default, or ``median``); ``width``: its renders' width [px] (None: the scene camera's, whose pixel grid
    the stripe composite aliases on, docs/planning.md §8; a smaller one is cheaper)."""
    if measure == "error":
        return ImageModel(scene, fidelity=fidelity or "preview", n_stripes=n_stripes, orders=orders,
                          stripe_step=stripe_step, sheets=sheets, p_rule=p_rule, width=width)
    if sheets != 1:
        raise SceneError(f"sheets={sheets}: the paper's measures plan one sheet per frame; several sheets "
                         "need measure 'error' (docs/planning.md §12)")
    if measure == "paper":
        return SceneModel(scene, fidelity=fidelity or "standard", n_stripes=n_stripes, edge=edge,
                          orders=orders)
    raise SceneError(f"measure must be 'error' or 'paper', got {measure!r}")


def default_separations(n: int = 60, d_min_m: float = 0.01, d_max_m: float = 0.6) -> np.ndarray:
    """An even grid of n separations [m] (d_LC = 0 is excluded: the co-located source diverges, refs §8)."""
    if n < 2 or not (0.0 < d_min_m < d_max_m) or not (math.isfinite(d_min_m) and math.isfinite(d_max_m)):
        raise SceneError(f"separations: need n >= 2 and 0 < d_min < d_max, got n={n}, d_min={d_min_m}, "
                         f"d_max={d_max_m}")
    return np.linspace(d_min_m, d_max_m, n)


def _curve(seps: np.ndarray, objs: list[Objective], noise_free: list[Objective], cols=None) -> Curve:
    if cols is None and objs and objs[0].frame_quality is not None:  # the error measure: the whole image
        def whole(o):
            return 0.0 if o.frame_saturated else o.frame_quality
        return Curve(seps, np.array([whole(o) for o in objs]), np.array([whole(o) for o in noise_free]),
                     np.array([o.frame_quality for o in objs]), np.ones(len(objs)),
                     np.array([o.frame_saturated for o in objs]), None,
                     np.array([o.frame_lost for o in objs]))
    pick = (lambda x: x) if cols is None else (lambda x: x[cols])
    limited = None
    if cols is not None and len(cols) == 1 and all(o.limited_by for o in objs):
        limited = [o.limited_by[cols[0]] for o in objs]
    return Curve(
        seps,
        np.array([pick(o.value).mean() for o in objs]),
        np.array([pick(o.value).mean() for o in noise_free]),
        np.array([pick(o.quality).mean() for o in objs]),
        np.array([pick(o.weight).mean() for o in objs]),
        np.array([bool(np.any(pick(o.saturated))) for o in objs]),
        limited,
    )


def compare_scans(seps: np.ndarray, curves: list[Curve], lateral_m: np.ndarray, *,
                  tolerance: float = 0.02) -> dict:
    """Score rotating, translating or both for a stripe scan over the stripe locations.

    * rotate: one source position serves every stripe: max over d of mean_i Q_i(d);
    * translate: the sheet keeps its angle and the source moves with the stripe, d_i = x_i + Δ (x_i the
      lateral position of O_i): max over Δ of mean_i Q_i(x_i + Δ), Q_i interpolated on the grid;
    * both: each stripe gets its own best source position: mean_i max_d Q_i(d) (an upper bound).

    The winner is the best score, except that a simpler scan (rotate, then translate) within ``tolerance``
    (relative) of the best wins, since it needs less motion.
    """
    q = np.array([c.objective for c in curves])
    rotate_curve = q.mean(axis=0)
    i_rot = int(np.argmax(rotate_curve))
    scores = {"rotate": float(rotate_curve[i_rot])}
    per_location = {"rotate": [float(seps[i_rot])] * len(curves)}
    step = float(np.min(np.diff(seps)))
    lo, hi = seps[0] - lateral_m.min(), seps[-1] - lateral_m.max()
    if hi >= lo:
        deltas = np.arange(lo, hi + 0.5 * step, step)
        vals = np.array([np.mean([np.interp(x + dl, seps, qi) for x, qi in zip(lateral_m, q, strict=True)])
                         for dl in deltas])
        j = int(np.argmax(vals))
        scores["translate"] = float(vals[j])
        per_location["translate"] = [float(x + deltas[j]) for x in lateral_m]
    else:
        scores["translate"] = None
        per_location["translate"] = None
    scores["both"] = float(q.max(axis=1).mean())
    per_location["both"] = [float(seps[int(np.argmax(qi))]) for qi in q]
    best = max(v for v in scores.values() if v is not None)
    winner = next(s for s in SCAN_TYPES if scores[s] is not None and scores[s] >= best * (1.0 - tolerance))
    return {"winner": winner, "scores": scores, "separations_m": per_location, "tolerance": tolerance}


def auto_exposure_scale(samples: list[Samples], noise: SensorNoise, fill: float = 0.9) -> float:
    """Exposure multiplier that puts the brightest unpolarized observation of the sweep at ``fill`` × the
    saturation level: one fixed exposure for the whole sweep, as an experimenter sets it once (the paper
    compares separations "with the same exposure time")."""
    e = np.asarray(noise.electrons_per_radiance, np.float64)
    brightest = max(float(np.max((s.direct + s.indirect + s.backscatter) * e)) for s in samples)
    if not math.isfinite(noise.full_well_e) or brightest <= 0.0:
        return 1.0
    return (fill * noise.full_well_e - noise.dark_e) / brightest


def recommend_reading(curves: dict[str, Curve], p: float, *, tie: float = TIE, prefer: str = "E_b") -> dict:
    """Which polarized flood reading to use, E_b (eq. 4) or Ŝ (eq. 6), and why.

    The better best objective wins; within ``tie`` (relative) ``prefer`` wins: E_b for the paper's measures
    (one frame, no post-processing), Ŝ for the error measure (the image the compositor publishes). The
    reason names the trade: Ŝ removes the residual backscatter B(1 − p) that limits
    E_b's contrast (CQM) but multiplies the noise by √(2(1 + 1/p²)) (docs/physics.md §4.2), which W charges;
    ``p`` is the backscatter DOP at Ŝ's optimum (for the reason's text).
    """
    eb, sh = curves["E_b"], curves["S_hat"]
    vb, vs = float(eb.objective.max()), float(sh.objective.max())
    ib, js = eb.best_index, sh.best_index
    gain = float(noise_gain(max(p, 1e-3)))
    if prefer == "S_hat":
        pick = "E_b" if vb > vs * (1.0 + tie) else "S_hat"
    else:
        pick = "S_hat" if vs > vb * (1.0 + tie) else "E_b"
    at = (f"best E_b {vb:.3g} at {eb.separations_m[ib] * 100:.0f} cm (CQM {eb.quality[ib]:.2f}, W "
          f"{eb.weight[ib]:.2f}); best Ŝ {vs:.3g} at {sh.separations_m[js] * 100:.0f} cm (contrast "
          f"{sh.quality[js]:.2f}, W {sh.weight[js]:.2f})")
    if prefer == "S_hat":       # the error measure: quality is 1 − the expected error against T
        at = (f"expected error against T: E_b {1 - vb:.3f} at {eb.separations_m[ib] * 100:.0f} cm, Ŝ "
              f"{1 - vs:.3f} at {sh.separations_m[js] * 100:.0f} cm")
        why = ("the compositor publishes Ŝ, within 2 % of E_b or better" if pick == "S_hat" else
               f"eq. 6's noise (×{gain:.1f}, p = {p:.2f}) and its over- or under-subtraction where p varies "
               "cost more than the backscatter it removes; use the composite's E_b layer")
    elif pick == "S_hat":
        why = (f"removing the residual backscatter raises the contrast from {eb.quality[js]:.2f} to "
               f"{sh.quality[js]:.2f}, worth eq. 6's noise gain ×{gain:.1f} (p = {p:.2f}) at this light "
               "level")
    elif prefer == "E_b" and vs >= vb * (1.0 - tie):
        why = "the two are within 2 %; E_b needs one frame and no post-processing"
    else:
        why = (f"eq. 6 multiplies the noise by ×{gain:.1f} (p = {p:.2f}); the light is too weak to pay for "
               f"the contrast it adds ({eb.quality[ib]:.2f} → {sh.quality[ib]:.2f} at E_b's optimum)")
    return {"reading": pick, "reason": f"{READING_NAMES[pick]}: {why}; {at}"}


def _score(scored: dict, p_mean: list, samples: Samples, noise, modality, edge, measure, p_min, **kw) -> None:
    """Append one separation's objectives and noise-free objectives to ``scored[(polarized, reading)]`` and
    its mean clipped DOP (the recommendation's p̂) to ``p_mean``."""
    p_mean.append(float(np.mean(np.clip(samples.dop, p_min, 1.0))))
    memo, memo_ideal = {}, {}          # the error measure's analyzer composites, shared by E_b and Ŝ
    for (_, reading), (objs, ideal) in scored.items():
        args = dict(modality=modality, reading=reading, edge=edge, measure=measure, p_min=p_min, **kw)
        objs.append(objective(samples, noise, memo=memo, **args))
        ideal.append(objective(samples, IDEAL_SENSOR, memo=memo_ideal, **args))


def _bisections(seps: list[float], scored: dict, *, rivals: float = 0.0, error: bool = True,
                spread: float = 0.0, finest: float = 0.0) -> list[float]:
    """One bisection round over the separations evaluated so far (in the order evaluated) and every
    reading's curve on them (:func:`polarstripe.planning.search.midpoints`)."""
    order = np.argsort(seps)
    ordered = np.asarray(seps)[order]
    curves = []
    for objs, ideal in scored.values():
        c = _curve(ordered, [objs[k] for k in order], [ideal[k] for k in order])
        curves.append((c.objective, c.lost if c.lost is not None else c.saturated.astype(float)))
    return midpoints(ordered, curves, rivals=rivals, error=error, spread=spread, finest=finest)


def plan(model: PlanModel, separations_m: np.ndarray | None = None, *, modalities=MODALITIES,
         k_detect: float = 3.0, p_min: float = 0.05, exposure: str = "scene", refine: int = 0,
         rivals: float = 0.0, progress=None) -> dict[str, ModalityPlan]:
    """Sweep the separations and build the plans keyed ``flood``, ``flood_polarized``, ``stripes``,
    ``stripes_polarized`` (only the requested modalities). One model evaluation per separation and
    modality serves every reading.

    Without a polarizer the reading is ``E``. With one, stripes are delineated on the best-polarized image
    E_b; the polarized flood is scored both as E_b and as Ŝ (eq. 6), its ``curve`` is the recommended one
    (:func:`recommend_reading`) and ``readings`` holds both. ``exposure="auto"`` sets one exposure per
    modality so that no observed point saturates anywhere in the sweep (:func:`auto_exposure_scale`);
    ``"scene"`` keeps the camera's exposure, and saturated points score 0. ``refine`` rounds of bisection
    then evaluate the midpoints between each curve's peaks and their neighbours, down to the grid's step /
    2**refine (the curves hold them too; :mod:`polarstripe.planning.search`): the best, and with ``rivals``
    > 0 the local maxima whose loss is within ``rivals`` of the best's. A stripe composite's error ripples by
    a few per cent between the grid's points, where the stripes' phase on the pixel grid changes
    (docs/planning.md §8). No separation is evaluated twice. ``progress`` is called once per evaluation,
    the grid's first."""
    if exposure not in ("auto", "scene"):
        raise SceneError(f"exposure must be 'auto' or 'scene', got {exposure!r}")
    if isinstance(refine, bool) or int(refine) != refine or refine < 0:
        raise SceneError(f"refine must be a whole number of bisection rounds >= 0, got {refine!r}")
    if not (math.isfinite(rivals) and rivals >= 0.0):
        raise SceneError(f"rivals must be a relative loss >= 0, got {rivals!r}")
    seps = default_separations() if separations_m is None else np.asarray(separations_m, np.float64)
    if seps.ndim != 1 or seps.size < 2 or np.any(~np.isfinite(seps)) or np.any(seps <= 0) or \
            np.any(np.diff(seps) <= 0):
        raise SceneError("separations: need an increasing 1-D grid of at least 2 positive separations [m]")
    for m in modalities:
        if m not in MODALITIES:
            raise SceneError(f"modality must be one of {MODALITIES}, got {m!r}")
    edge = getattr(model, "edge", "margin")
    measure = getattr(model, "measure", "paper")
    lateral = np.asarray(model.lateral_positions_m(), np.float64)
    out: dict[str, ModalityPlan] = {}
    for modality in modalities:
        groups = ((False, ("E",)), (True, POLARIZED_READINGS[measure][modality]))
        scored = {(pol, r): ([], []) for pol, readings in groups for r in readings}
        p_mean = []                                    # per separation: the mean p̂ of the recommendation
        evaluate = model.flood if modality == "flood" else model.stripes
        kw = dict(modality=modality, edge=edge, measure=measure, p_min=p_min, k_detect=k_detect)
        scale = 1.0
        if exposure == "auto":   # one exposure for the sweep: every separation's samples are needed first
            kept = []
            for d in seps:
                kept.append(evaluate(float(d)))
                if progress is not None:
                    progress()
            scale = auto_exposure_scale(kept, model.noise)
        noise = dataclasses.replace(model.noise,
                                    electrons_per_radiance=model.noise.electrons_per_radiance * scale)
        if exposure == "auto":
            for s in kept:
                _score(scored, p_mean, s, noise, **kw)
            del kept
        else:                    # scored as they come: one separation's whole frames in memory at a time
            for d in seps:
                _score(scored, p_mean, evaluate(float(d)), noise, **kw)
                if progress is not None:
                    progress()
        done = [float(d) for d in seps]
        step = float(np.min(np.diff(seps)))
        for _ in range(int(refine)):
            for d in _bisections(done, scored, rivals=rivals, error=measure == "error", spread=step,
                                 finest=step / 2 ** int(refine)):
                _score(scored, p_mean, evaluate(d), noise, **kw)
                done.append(d)
                if progress is not None:
                    progress()
        order = np.argsort(done)
        mseps = np.asarray(done)[order]
        p_mean = [p_mean[k] for k in order]
        for key, (objs, ideal) in scored.items():
            scored[key] = ([objs[k] for k in order], [ideal[k] for k in order])
        for polarized, readings in groups:
            curves = {r: _curve(mseps, *scored[(polarized, r)]) for r in readings}
            rec = None
            if len(readings) > 1:
                rec = recommend_reading(curves, p_mean[curves["S_hat"].best_index],
                                        prefer="S_hat" if measure == "error" else "E_b")
            chosen = rec["reading"] if rec else readings[0]
            mp = ModalityPlan(modality, polarized, curves[chosen], reading=chosen,
                              readings=curves if len(readings) > 1 else {}, recommendation=rec,
                              exposure_scale=scale, edge=edge if modality == "stripes" else None,
                              measure=measure, evaluations=len(done))
            if modality == "stripes":
                objs, ideal = scored[(polarized, chosen)]
                pixels = np.asarray(model.observed_pixels())
                mp.location_curves = [_curve(mseps, objs, ideal, cols=[i]) for i in range(len(pixels))]
                mp.locations = [{"pixel": [int(r), int(c)], "lateral_position_m": float(x)}
                                for (r, c), x in zip(pixels, lateral, strict=True)]
                mp.scan = compare_scans(mseps, mp.location_curves, lateral)
            out[modality + ("_polarized" if polarized else "")] = mp
    return out


def search_plan(model: PlanModel, search: str | Search = DEFAULT_SEARCH, d_min_m: float = 0.01,
                d_max_m: float = 0.6, **kw) -> dict[str, ModalityPlan]:
    """:func:`plan` with one of the tools' searches (:data:`SEARCHES` by name, or a :class:`Search`) over
    [d_min_m, d_max_m]; ``kw`` as :func:`plan`'s."""
    s = resolve_search(search)
    return plan(model, default_separations(s.separations, d_min_m, d_max_m), refine=s.refine, rivals=s.rivals,
                **kw)
