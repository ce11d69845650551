"""The planner's objectives: the paper's quality measures times the SNR weight W (eq. 10) at each observed
point (``measure="paper"``, below), and the default ``error`` measure, 1 − the composite's expected error
against T from whole low-resolution frames (:func:`error_objective`, planning/predicted_error.py,
docs/planning.md §8).

What the planner maximises over the camera–source separation d_LC (docs/planning.md):

* **Flood** — CQM·W (eq. 8 × eq. 10), read three ways:

  - ``E``: no polarizer; the frame E = S + B is the image, CQM = S / (S + B), W from E's signal and noise.
  - ``E_b``: the best-polarized image of eq. 4, E_b = S/2 + B(1 − p)/2, used as it is (optical filtering, no
    post-processing). CQM = S / (S + B(1 − p)) is eq. 8 as the paper defines it; W from E_b's own signal
    S/2 and noise (read, dark, quantization, shot of S/2 + B(1 − p)/2).
  - ``S_hat``: the recovered signal of eq. 6, Ŝ = E_b(1 + 1/p̂) + E_w(1 − 1/p̂) = S + B(1 − p/p̂). With the
    model's p (p̂ = p) the backscatter is removed completely, so its contrast is S / (S + |B(1 − p/p̂)|) = 1
    and all its cost is noise: W from S and the eq. 6 noise, √((1 + 1/p̂)² Var E_b + (1 − 1/p̂)² Var E_w).

* **Stripes** — the delineation margin times W (default, ``edge="margin"``), or eq. 9 as printed
  (``edge="eq9"``). The margin compares O's intensity under its own sheet with the brightest competitor the
  delineation or the per-pixel maximum of eq. 7 meets: O under every other sheet of the scan, and the unlit
  neighbours O′ under the same sheet,

      M = max(0, (E_own − max_c E_c) / E_own),   E = D + A + B(1 − p)   (p = 0 without a polarizer)

  If no competitor carries backscatter or direct light and the neighbour receives the same indirect light
  as O (A(O′) = A(O) ≥ A of O under the other sheets, the assumption of the paper's Fig. 8c), then
  max_c E_c = A and M = (D + B(1 − p)) / (D + A + B(1 − p)), which is eq. 9. Eq. 9 as printed counts the
  sheet's own backscatter B(1 − p) at O as edge signal even when the competitors carry as much or more, so
  its optimum slides to the co-located source (docs/physics.md §9 item 3).

A point whose frame reaches the full well (with its dark electrons) scores 0 (``saturated``): E for ``E``,
E_b for ``E_b``, the brighter E_w for ``S_hat`` (eq. 6 needs both frames).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from polarstripe.imaging.quality import (
    LOGISTIC_PROBIT_SCALE,
    log_cqm,
    log_gqm,
    log_margin,
    log_snr_weight,
    recovered_signal_noise_e,
)
from polarstripe.planning.predicted_error import image_error, reading_image
from polarstripe.sim.scene import SceneError

MODALITIES = ("flood", "stripes")
READINGS = {"flood": ("E", "E_b", "S_hat"), "stripes": ("E", "E_b")}
EDGES = ("margin", "eq9")
#: what the planner maximises: ``error`` (1 − the composite's expected error against T,
#: planning/predicted_error.py) or ``paper`` (CQM·W for flood, the margin or eq. 9 ·W for stripes)
MEASURES = ("error", "paper")
READING_NAMES = {"E": "no polarizer (E = S + B)",
                 "E_b": "best-polarized image E_b (eq. 4, optical filtering)",
                 "S_hat": "recovered signal Ŝ (eq. 6, post-processing)"}


@dataclass(frozen=True)
class Competitors:
    """What a stripe point O competes with, per observed point (rows) and competitor (columns), (n, m):
    radiances [W sr⁻¹ m⁻²] before the analyzer and the backscatter DOP. ``labels`` (m,) names each column's
    kind: ``"neighbour"`` (O′ under O's own sheet) or ``"sheet"`` (O under another sheet of the scan).
    An all-zero entry (a sheet that misses O's ray, O's own sheet) never wins."""

    direct: np.ndarray
    indirect: np.ndarray
    backscatter: np.ndarray
    dop: np.ndarray
    labels: tuple[str, ...] = ()


@dataclass(frozen=True)
class Samples:
    """Model output at n observed points: radiance [W sr⁻¹ m⁻²] before the analyzer, and backscatter DOP.
    Stripes with ``edge="margin"`` also carry the :class:`Competitors`."""

    direct: np.ndarray
    indirect: np.ndarray
    backscatter: np.ndarray
    dop: np.ndarray
    competitors: Competitors | None = None
    # the error measure's whole-image samples (planning/image_model.py): the backscatter's angle [rad],
    # T, and each pixel's location (group); eq. 6's rule (planning/predicted_error.py P_RULES) and the
    # flood frame's (B, p, χ) per pixel that its map and the analyzer's axis are read from
    chi: np.ndarray | None = None
    truth: np.ndarray | None = None
    group: np.ndarray | None = None
    p_rule: str = "map"
    flood_dop: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None


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


@dataclass(frozen=True)
class Objective:
    """Per-point quality at one separation: the measure, W, saturation, and (stripes, margin) the kind of
    the competitor that limits the margin (``"neighbour"``, ``"sheet"``, or ``""`` without competitors)."""

    quality: np.ndarray
    weight: np.ndarray
    saturated: np.ndarray
    limited_by: tuple[str, ...] = ()
    frame_quality: float | None = None  # the error measure: over the whole image, one gain (else None)
    frame_saturated: bool = False
    frame_lost: float = 0.0             # the error measure: the fraction of the image's pixels saturated

    @property
    def value(self) -> np.ndarray:
        return np.where(self.saturated, 0.0, self.quality * self.weight)


def _log(x) -> np.ndarray:
    with np.errstate(divide="ignore"):
        return np.log(np.maximum(np.asarray(x, np.float64), 0.0))


def _dop(dop, p_min: float) -> tuple[np.ndarray, np.ndarray]:
    """(p, p̂): the model's DOP clipped to [0, 1], and the p̂ eq. 6 divides by, clamped to [p_min, 1]."""
    p = np.clip(np.nan_to_num(np.asarray(dop, np.float64)), 0.0, 1.0)
    return p, np.clip(p, p_min, 1.0)


def _log_frame(ld, la, lb, p) -> np.ndarray:
    """log(D + A + B(1 − p)): a frame through the best-polarized analyzer (×2), or E with p = 0."""
    with np.errstate(divide="ignore"):
        return np.logaddexp(np.logaddexp(ld, la), lb + np.log1p(-np.minimum(p, 1.0)))


def _weight(s, b, p, p_hat, noise: SensorNoise, reading: str, k_detect: float):
    """(log W, saturated) for the reading's signal and noise in electrons (docs/planning.md §2)."""
    e = np.asarray(noise.electrons_per_radiance, np.float64)
    if np.all(np.isinf(e)):
        return np.where(s > 0, 0.0, -np.inf), np.zeros(np.shape(s), bool)
    s_e, b_e = s * e, b * e
    kw = dict(read_noise_e=noise.read_noise_e, dark_e=noise.dark_e, quantization_e=noise.quantization_e)
    if reading == "E":
        sig_e, sigma, frame = s_e, recovered_signal_noise_e(s_e, b_e, None, **kw), s_e + b_e
    elif reading == "E_b":
        sig_e = 0.5 * s_e
        frame = sig_e + 0.5 * b_e * (1.0 - p)
        sigma = recovered_signal_noise_e(sig_e, 0.5 * b_e * (1.0 - p), None, **kw)
    else:  # S_hat: eq. 6 from E_b and E_w
        sig_e, sigma = s_e, recovered_signal_noise_e(s_e, b_e, p_hat, **kw)
        frame = 0.5 * s_e + 0.5 * b_e * (1.0 + p)  # E_w, the brighter frame eq. 6 needs
    lw = log_snr_weight(sig_e, k_detect * sigma, sigma / LOGISTIC_PROBIT_SCALE)
    return lw, frame + noise.dark_e >= noise.full_well_e


def _check(modality: str, reading: str, edge: str) -> None:
    if modality not in MODALITIES:
        raise SceneError(f"modality must be one of {MODALITIES}, got {modality!r}")
    if reading not in READINGS[modality]:
        raise SceneError(f"reading for {modality} must be one of {READINGS[modality]}, got {reading!r}")
    if edge not in EDGES:
        raise SceneError(f"edge must be one of {EDGES}, got {edge!r}")


def error_objective(samples: Samples, noise: SensorNoise, reading: str, p_min: float = 0.05,
                    memo: dict | None = None) -> Objective:
    """The ``error`` measure per location: quality = 1 − the reading's expected error against T
    (planning/predicted_error.py), weight 1 (the noise is inside the error), saturated where every pixel of
    the location is. ``samples`` hold electrons at the scene's exposure; ``noise.electrons_per_radiance`` is
    the exposure's multiplier (inf: the noise-free, unsaturating sensor). ``memo``: one dict per
    (``samples``, ``noise``) kept by the caller across the readings: the analyzer's composites are made once
    for E_b and Ŝ (:func:`~polarstripe.planning.predicted_error.reading_image`)."""
    if samples.truth is None:
        raise SceneError("the error measure needs whole-image samples with T (planning/image_model.py)")
    scale = float(np.max(noise.electrons_per_radiance))
    ideal = math.isinf(scale)
    k = 1.0 if ideal else scale
    truth = np.asarray(samples.truth, np.float64)
    group = np.zeros(truth.shape, np.int64) if samples.group is None else samples.group
    n = int(group.max()) + 1 if group.size else 0      # a group of −1: pixels left out
    s_e = (np.asarray(samples.direct) + np.asarray(samples.indirect)) * k
    b_e = np.asarray(samples.backscatter) * k
    dop = np.asarray(samples.dop)
    chi = np.zeros_like(s_e) if samples.chi is None else np.asarray(samples.chi)
    quality, saturated = np.zeros(n), np.zeros(n, bool)
    flood = samples.flood_dop

    # the image as the end-to-end judge scores it: every composed pixel, one gain (a gain per location
    # forgives the fall-off across the image that one gain cannot: the stripe plans' bias, docs/planning.md);
    # the analyzer is calibrated once on the whole flood, as the rig does, so each location's composite is
    # the frame's at its pixels (one pass over the frames serves them all)
    if n == 0:
        return Objective(quality, np.ones(n), saturated, frame_quality=0.0, frame_saturated=True)
    at = group >= 0
    if at.all():
        at = slice(None)                      # every pixel composed: no copies
    mean, var, valid = reading_image(
        reading, s_e[..., at], b_e[..., at], dop[..., at], chi[..., at], truth[at] * k,
        full_well_e=math.inf if ideal else noise.full_well_e, dark_e=noise.dark_e,
        read_noise_e=noise.read_noise_e, quantization_e=noise.quantization_e, p_min=p_min, noise=not ideal,
        p_rule=samples.p_rule, flood_dop=None if flood is None else tuple(np.asarray(x)[at] for x in flood),
        memo=memo)
    t_at, g_at = truth[at] * k, group[at]

    def scored(sub):
        err, lost = image_error(mean[sub], var[sub], t_at[sub], valid[sub])
        return 1.0 - err, lost

    lost = np.zeros(n)
    for g in range(n):
        quality[g], lost[g] = scored(g_at == g) if n > 1 else scored(slice(None))
    saturated = lost >= 1.0
    frame = (quality[0], lost[0]) if n == 1 else scored(slice(None))
    return Objective(quality, np.ones(n), saturated, frame_quality=float(frame[0]),
                     frame_saturated=bool(frame[1] >= 1.0), frame_lost=float(frame[1]))


def objective(samples: Samples, noise: SensorNoise, *, modality: str, reading: str = "E",
              edge: str = "margin", k_detect: float = 3.0, p_min: float = 0.05,
              measure: str = "paper", memo: dict | None = None) -> Objective:
    """The planner's objective per observed point, in log space (module docstring; docs/planning.md).

    Parameters
    ----------
    samples : Samples
        Components at the observed points (stripes: under each point's own sheet, and with
        ``edge="margin"`` the :class:`Competitors`).
    noise : SensorNoise
        The sensor at the sweep's exposure; :data:`IDEAL_SENSOR` for the noise-free curve.
    modality : {"flood", "stripes"}
    reading : {"E", "E_b", "S_hat"}
        Which image is scored: no polarizer, the best-polarized image (eq. 4), or Ŝ (eq. 6, flood only).
    edge : {"margin", "eq9"}
        Stripe measure: the delineation margin (default) or eq. 9 as printed.
    k_detect : float
        Detection threshold of W in noise standard deviations: W ≈ Φ(S_f/σ_f − k) (eq. 10 with μ = kσ,
        z = σ/1.702).
    p_min : float
        Lower clamp of the p that eq. 6 divides by.
    measure : {"paper", "error"}
        ``paper``: the measures above; ``error``: :func:`error_objective` (whole-image samples).
    memo : dict, optional
        The ``error`` measure's store shared by the readings of the same ``samples`` and ``noise``.

    Returns
    -------
    Objective
        ``value`` = quality·W, 0 where the scored frame saturates.
    """
    if measure == "error":
        if reading not in READINGS["flood"]:
            raise SceneError(f"reading must be one of {READINGS['flood']}, got {reading!r}")
        return error_objective(samples, noise, reading, p_min, memo)
    if measure != "paper":
        raise SceneError(f"measure must be one of {MEASURES}, got {measure!r}")
    _check(modality, reading, edge)
    d, a, b = (np.maximum(np.asarray(x, np.float64), 0.0) for x in (samples.direct, samples.indirect,
                                                                       samples.backscatter))
    p, p_hat = _dop(samples.dop, p_min)
    p_frame = np.zeros_like(p) if reading == "E" else p
    ld, la, lb = _log(d), _log(a), _log(b)
    limited: tuple[str, ...] = ()
    if modality == "flood":
        if reading == "S_hat":  # contrast of Ŝ = S + B(1 - p/p̂): 1 when p̂ = p
            lq = log_cqm(np.logaddexp(ld, la), _log(b * np.abs(1.0 - p / p_hat)), 0.0)
        else:
            lq = log_cqm(np.logaddexp(ld, la), lb, p_frame)  # eq. 8
    elif edge == "eq9":
        lq = log_gqm(ld, la, lb, p_frame)
    else:
        c = samples.competitors
        if c is None:
            raise SceneError("edge='margin' needs the competitors of each stripe point (SceneModel(edge="
                             "'margin') computes them)")
        pc = np.zeros_like(c.dop, dtype=np.float64) if reading == "E" else _dop(c.dop, p_min)[0]
        lc = _log_frame(_log(c.direct), _log(c.indirect), _log(c.backscatter), pc)
        if lc.shape[1]:
            win = np.argmax(lc, axis=1)
            lc_max = lc[np.arange(lc.shape[0]), win]
            limited = tuple(c.labels[k] if c.labels and np.isfinite(lc_max[i]) else ""
                            for i, k in enumerate(win))
        else:
            lc_max = np.full(d.shape, -np.inf)
        lq = log_margin(_log_frame(ld, la, lb, p_frame), lc_max)
    lw, sat = _weight(d + a, b, p, p_hat, noise, reading, k_detect)
    return Objective(np.exp(lq), np.exp(lw), sat, limited)


def noise_gain(p_hat) -> np.ndarray:
    """σ_Ŝ / σ for equal noise σ in E_b and E_w: √(2(1 + 1/p̂²)) (docs/physics.md §4.2)."""
    p = np.asarray(p_hat, np.float64)
    return np.sqrt(2.0 * (1.0 + 1.0 / p ** 2))
