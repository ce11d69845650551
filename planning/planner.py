"""The camera–source placement planner (the paper's §3): sweep d_LC, maximise CQM·W and GQM·W.

The planner asks a :class:`PlanModel` for the light-transport components at a few observed points O only
(never whole images) and turns them into the paper's objectives with the quality measures of
:mod:`polarstripe.imaging.quality`. :class:`SceneModel` is the model of :mod:`polarstripe.sim` behind that
interface. Scanning a stripe across the scene can rotate the source about one position, translate it with a
fixed sheet angle, or both; :func:`compare_scans` says which wins.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from polarstripe.imaging.quality import (
    LOGISTIC_PROBIT_SCALE,
    log_cqm,
    log_gqm,
    log_snr_weight,
    recovered_signal_noise_e,
)
from polarstripe.sim.geometry import intersect, pinhole_frame, pixel_rays
from polarstripe.sim.render import render_components
from polarstripe.sim.scene import SceneError, with_separation
from polarstripe.sim.sensor import electrons_per_radiance

MODALITIES = ("flood", "stripes")
SCAN_TYPES = ("rotate", "translate", "both")


@dataclass(frozen=True)
class Samples:
    """Model output at n observed points: radiance [W sr⁻¹ m⁻²] before the analyzer, and backscatter DOP."""

    direct: np.ndarray
    indirect: np.ndarray
    backscatter: np.ndarray
    dop: np.ndarray
    neighbour: Samples | None = None  # stripes, edge="measured": O under the brighter adjacent sheet


@dataclass(frozen=True)
class SensorNoise:
    """What the SNR weight needs from the sensor (EMVA 1288), per frame.

    ``electrons_per_radiance`` (scalar or per observed point) converts radiance [W sr⁻¹ m⁻²] to mean
    photo-electrons; ``full_well_e`` is where the pixel saturates (full well or ADC full scale);
    :data:`IDEAL_SENSOR` (infinitely many electrons) makes W a step, the paper's ideal zero-noise case.
    """

    electrons_per_radiance: float | np.ndarray
    read_noise_e: float = 0.0
    dark_e: float = 0.0
    quantization_e: float = 0.0
    full_well_e: float = math.inf



IDEAL_SENSOR = SensorNoise(math.inf)  # unlimited light: W = 1 wherever S > 0 (the paper's zero-noise case)


class PlanModel(Protocol):
    """The interface the planner sweeps. Separations are in metres, pixels (n, 2) int (row, col)."""

    noise: SensorNoise

    def observed_pixels(self) -> np.ndarray: ...

    def lateral_positions_m(self) -> np.ndarray: ...

    def flood(self, d_lc_m: float) -> Samples: ...

    def stripes(self, d_lc_m: float) -> Samples: ...


@dataclass(frozen=True)
class Objective:
    """Per-point quality at one separation: the measure (CQM or GQM), W, their product, saturation."""

    quality: np.ndarray
    weight: np.ndarray
    saturated: np.ndarray

    @property
    def value(self) -> np.ndarray:
        return np.where(self.saturated, 0.0, self.quality * self.weight)


def objective(samples: Samples, noise: SensorNoise, *, modality: str, polarized: bool,
              k_detect: float = 3.0, p_min: float = 0.05) -> Objective:
    """CQM·W (flood, eq. 8 × eq. 10) or GQM·W (stripes, eq. 9 × eq. 10) per observed point, in log space.

    Without a polarizer p = 0 in eqs. 8-9 and the frame E = S + B is the estimate of S; with one, the best-
    polarized frame sets the measure and Ŝ comes from eq. 6, whose noise sets W (refs/physics.md §7):
    μ = k_detect·σ_S, z = σ_S/1.702. A point whose co-polarized (or unpolarized) frame exceeds the full
    well carries no information and scores 0 (``saturated``).
    """
    if modality not in MODALITIES:
        raise SceneError(f"modality must be one of {MODALITIES}, got {modality!r}")
    d, a, b = (np.maximum(np.asarray(x, np.float64), 0.0) for x in (samples.direct, samples.indirect,
                                                                       samples.backscatter))
    p = np.clip(np.asarray(samples.dop, np.float64), p_min, 1.0) if polarized else np.zeros_like(d)
    with np.errstate(divide="ignore"):
        ld, la, lb = np.log(d), np.log(a), np.log(b)
    ls = np.logaddexp(ld, la)
    if modality == "flood":
        lq = log_cqm(ls, lb, p)  # eq. 8
    elif samples.neighbour is None:
        lq = log_gqm(ld, la, lb, p)  # eq. 9
    else:  # the step the paper describes in words: (E_O - E_O')/E_O through the best-polarized analyzer
        nb = samples.neighbour
        pn = np.clip(np.asarray(nb.dop, np.float64), p_min, 1.0) if polarized else 0.0
        e_o = d + a + b * (1.0 - p)
        e_n = np.maximum(nb.direct, 0.0) + np.maximum(nb.indirect, 0.0) + np.maximum(nb.backscatter, 0.0) * (
            1.0 - pn)
        with np.errstate(divide="ignore", invalid="ignore"):
            lq = np.where(e_o > e_n, np.log(np.maximum(e_o - e_n, 1e-320)) - np.log(e_o), -np.inf)
    e = np.asarray(noise.electrons_per_radiance, np.float64)
    if np.all(np.isinf(e)):
        lw = np.where(np.exp(ls) > 0, 0.0, -np.inf)
        sat = np.zeros(d.shape, bool)
    else:
        s_e, b_e = (d + a) * e, b * e
        sigma = recovered_signal_noise_e(s_e, b_e, p if polarized else None, read_noise_e=noise.read_noise_e,
                                         dark_e=noise.dark_e, quantization_e=noise.quantization_e)
        lw = log_snr_weight(s_e, k_detect * sigma, sigma / LOGISTIC_PROBIT_SCALE)
        brightest = 0.5 * s_e + 0.5 * b_e * (1.0 + p) if polarized else s_e + b_e
        sat = brightest + noise.dark_e >= noise.full_well_e
    return Objective(np.exp(lq), np.exp(lw), sat)


@dataclass
class Curve:
    """One objective curve over the separations (mean over its observed points)."""

    separations_m: np.ndarray
    objective: np.ndarray
    objective_noise_free: np.ndarray
    quality: np.ndarray
    weight: np.ndarray
    saturated: np.ndarray

    @property
    def best_index(self) -> int:
        return int(np.argmax(self.objective))

    @property
    def best_separation_m(self) -> float:
        return float(self.separations_m[self.best_index])


@dataclass
class ModalityPlan:
    """The plan for one modality and polarization: the mean curve, per-location curves (stripes) and scans."""

    modality: str
    polarized: bool
    curve: Curve
    locations: list[dict] = field(default_factory=list)
    location_curves: list[Curve] = field(default_factory=list)
    scan: dict | None = None
    exposure_scale: float = 1.0


class SceneModel:
    """:class:`PlanModel` on the light-transport model of :mod:`polarstripe.sim` (render_components at the
    observed pixels only).

    Parameters
    ----------
    scene : Scene
        The rig; the projector is moved along the front face by :func:`~polarstripe.sim.scene.with_separation`
        and kept aimed at its look-at point (its stripes are vertical sheets through the source either way).
    fidelity : str
        Model fidelity (``preview``, ``standard``, ``reference`` or explicit counts).
    n_stripes : int
        Stripes per scan; sets the angular width of the light sheet (see :meth:`stripes`).
    pixels : (n, 2) int array, optional
        Observed points O_i (row, col). Default: three points on the centre row at 1/4, 1/2 and 3/4 of the
        width (the stripe locations O1, O2, O3 of the paper's Fig. 10); each must see an object.
    edge : {"eq9", "measured"}
        The stripe measure: eq. 9 as printed (O' is assumed to receive only A), or the step the paper
        describes in words, (E_O - E_O')/E_O, with E_O' rendered at O under the brighter adjacent sheet
        (three times the stripe cost; it differs from eq. 9 where O' also sees the sheet's backscatter, as
        when source and camera nearly coincide).
    """

    def __init__(self, scene, fidelity: str = "standard", n_stripes: int = 30, pixels=None,
                 edge: str = "eq9"):
        if edge not in ("eq9", "measured"):
            raise SceneError(f"edge must be 'eq9' or 'measured', got {edge!r}")
        self.edge = edge

        cam = scene.camera
        w, h = cam.resolution
        if pixels is None:
            pixels = [[h // 2, int(w * f)] for f in (0.25, 0.5, 0.75)]
        self.pixels = np.asarray(pixels, dtype=np.int64).reshape(-1, 2)
        if isinstance(n_stripes, bool) or int(n_stripes) != n_stripes or n_stripes < 1:
            raise SceneError(f"n_stripes must be a positive integer, got {n_stripes!r}")
        self.scene, self.fidelity, self.n_stripes = scene, fidelity, int(n_stripes)
        frame = pinhole_frame(cam.position, cam.look_at, cam.up, cam.fov_deg, cam.resolution)
        hits = intersect(scene.objects, frame.position, pixel_rays(frame, self.pixels))
        if not np.all(np.isfinite(hits.t)):
            bad = self.pixels[~np.isfinite(hits.t)].tolist()
            raise SceneError(f"planner pixels {bad} see no object: observed points must lie on an object")
        self.points = hits.point
        axis = np.subtract(with_separation(scene, 1.0).projector.position, cam.position)
        self._lateral = (self.points - np.asarray(cam.position)) @ (axis / np.linalg.norm(axis))
        gain = cam.gain_e_per_dn
        self.noise = SensorNoise(electrons_per_radiance(cam, self.pixels), cam.read_noise_e,
                                 cam.dark_current_e_s * cam.exposure_s, gain / math.sqrt(12.0),
                                 min(cam.full_well_e, ((1 << cam.bits) - 1 - cam.offset_dn) * gain))

    def observed_pixels(self) -> np.ndarray:
        return self.pixels

    def lateral_positions_m(self) -> np.ndarray:
        """Position of each O_i along the direction the source moves [m], from the camera."""
        return self._lateral

    def _at(self, d_lc_m: float):

        return with_separation(self.scene, d_lc_m, aim=True)

    def flood(self, d_lc_m: float) -> Samples:

        c = render_components(self._at(d_lc_m), "flood", self.fidelity, self.pixels)
        return Samples(c.D, c.A, c.B, c.p)

    def stripes(self, d_lc_m: float) -> Samples:
        """Components at each O_i lit by a light sheet centred on it (zeros where the sheet misses O_i).

        The sheet has the angular width of one of ``n_stripes`` stripes of the scene's projector and passes
        through the source and O_i (the paper's Fig. 8c): the projector is aimed at O_i and narrowed to three
        columns of that width, of which the middle one is lit. This keeps O_i at the centre of its stripe at
        every separation, so the curves do not jitter with where a fixed projector's stripe edges happen to
        fall.
        """

        base = self._at(d_lc_m).projector
        tan_half = math.tan(math.radians(base.fov_deg) / 2.0)
        pitch = 2.0 * tan_half / self.n_stripes  # one stripe's width, tan units
        rows = max(3, round(base.resolution[1] * 2.0 * tan_half / base.resolution[0] / pitch))
        fov = math.degrees(2.0 * math.atan(1.5 * pitch))
        out = [np.zeros(len(self.pixels)) for _ in range(4)]
        nb = [np.zeros(len(self.pixels)) for _ in range(4)]
        for i, point in enumerate(self.points):
            scene = self.scene.replace(projector=base.replace(look_at=tuple(float(v) for v in point),
                                                              resolution=(3, rows), fov_deg=fov))
            c = render_components(scene, "stripe:1/3", self.fidelity, self.pixels[i:i + 1])
            for arr, val in zip(out, (c.D, c.A, c.B, c.p), strict=True):
                arr[i] = val[0]
            if self.edge == "measured":  # O' = O with the neighbouring sheet lit instead (same albedo)
                sides = [render_components(scene, f"stripe:{k}/3", self.fidelity, self.pixels[i:i + 1])
                         for k in (0, 2)]
                side = max(sides, key=lambda x: float(x.D[0] + x.A[0] + x.B[0]))
                for arr, val in zip(nb, (side.D, side.A, side.B, side.p), strict=True):
                    arr[i] = val[0]
        return Samples(*out, neighbour=Samples(*nb) if self.edge == "measured" else None)


def default_separations(n: int = 60, d_min_m: float = 0.01, d_max_m: float = 0.6) -> np.ndarray:
    """An even grid of n separations [m] (d_LC = 0 is excluded: the co-located source diverges, refs §8)."""
    if n < 2 or not (0.0 < d_min_m < d_max_m) or not (math.isfinite(d_min_m) and math.isfinite(d_max_m)):
        raise SceneError(f"separations: need n >= 2 and 0 < d_min < d_max, got n={n}, d_min={d_min_m}, "
                         f"d_max={d_max_m}")
    return np.linspace(d_min_m, d_max_m, n)


def _curve(seps: np.ndarray, objs: list[Objective], noise_free: list[Objective], cols=None) -> Curve:
    pick = (lambda x: x) if cols is None else (lambda x: x[cols])
    return Curve(
        seps,
        np.array([pick(o.value).mean() for o in objs]),
        np.array([pick(o.value).mean() for o in noise_free]),
        np.array([pick(o.quality).mean() for o in objs]),
        np.array([pick(o.weight).mean() for o in objs]),
        np.array([bool(np.any(pick(o.saturated))) for o in objs]),
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
    step = float(seps[1] - seps[0])
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


def plan(model: PlanModel, separations_m: np.ndarray | None = None, *, modalities=MODALITIES,
         k_detect: float = 3.0, p_min: float = 0.05, exposure: str = "scene",
         progress=None) -> dict[str, ModalityPlan]:
    """Sweep the separations and build the plans keyed ``flood``, ``flood_polarized``, ``stripes``,
    ``stripes_polarized`` (only the requested modalities). One model evaluation per separation and
    modality serves both polarizations.

    ``exposure="auto"`` sets one exposure per modality so that no observed point saturates anywhere in the
    sweep (:func:`auto_exposure_scale`); ``"scene"`` keeps the camera's exposure, and saturated points
    score 0."""
    if exposure not in ("auto", "scene"):
        raise SceneError(f"exposure must be 'auto' or 'scene', got {exposure!r}")
    seps = default_separations() if separations_m is None else np.asarray(separations_m, np.float64)
    if seps.ndim != 1 or seps.size < 2 or np.any(~np.isfinite(seps)) or np.any(seps <= 0) or \
            np.any(np.diff(seps) <= 0):
        raise SceneError("separations: need an increasing 1-D grid of at least 2 positive separations [m]")
    for m in modalities:
        if m not in MODALITIES:
            raise SceneError(f"modality must be one of {MODALITIES}, got {m!r}")
    ideal = IDEAL_SENSOR
    lateral = np.asarray(model.lateral_positions_m(), np.float64)
    out: dict[str, ModalityPlan] = {}
    for modality in modalities:
        samples = []
        for d in seps:
            samples.append(model.flood(float(d)) if modality == "flood" else model.stripes(float(d)))
            if progress is not None:
                progress()
        scale = auto_exposure_scale(samples, model.noise) if exposure == "auto" else 1.0
        noise = dataclasses.replace(model.noise,
                                    electrons_per_radiance=model.noise.electrons_per_radiance * scale)
        for polarized in (False, True):
            kw = dict(modality=modality, polarized=polarized, k_detect=k_detect, p_min=p_min)
            objs = [objective(s, noise, **kw) for s in samples]
            ideal_objs = [objective(s, ideal, **kw) for s in samples]
            mp = ModalityPlan(modality, polarized, _curve(seps, objs, ideal_objs), exposure_scale=scale)
            if modality == "stripes":
                pixels = np.asarray(model.observed_pixels())
                mp.location_curves = [_curve(seps, objs, ideal_objs, cols=[i]) for i in range(len(pixels))]
                mp.locations = [{"pixel": [int(r), int(c)], "lateral_position_m": float(x)}
                                for (r, c), x in zip(pixels, lateral, strict=True)]
                mp.scan = compare_scans(seps, mp.location_curves, lateral)
            out[modality + ("_polarized" if polarized else "")] = mp
    return out
