"""Quality measures of the paper's §3.1: CQM (eq. 8), GQM (eq. 9), the SNR weight W (eq. 10), and the
delineation margin the stripe planner uses in place of eq. 9 (docs/planning.md).

All are evaluated in log space so they stay finite when the components span hundreds of orders of magnitude
(optical thickness 100): a ratio x/(x + y) is computed as expit(log x - log y), never as a quotient of two
underflowed numbers. W is tied to the sensor model through the noise of the *recovered* signal
(docs/physics.md §7): W ≈ P(detect) = Φ((S - μ)/σ_S), approximated by a logistic with z = σ_S/1.702 and
μ = k·σ_S (the Rose criterion, k = 3 by default) plus any offset.
"""

from __future__ import annotations

import numpy as np
from polarstripe.imaging.validation import ImagingError, finite_param

LOGISTIC_PROBIT_SCALE = 1.702  # expit(1.702 x) approximates the normal CDF Φ(x) within 0.01


def _nonneg(name: str, value) -> np.ndarray:
    arr = np.asarray(value, np.float64)
    if np.any(np.isnan(arr)):
        raise ImagingError(f"{name}: NaN values")
    if np.any(arr < 0):
        raise ImagingError(f"{name}: negative values (min {arr.min():.3g}); radiances are >= 0")
    return arr


def _log(x: np.ndarray) -> np.ndarray:
    with np.errstate(divide="ignore"):
        return np.log(x)


def _log_p(p) -> np.ndarray:
    """log(1 - p) for p in [0, 1] (scalar or array)."""
    arr = np.asarray(p, np.float64)
    if np.any(~np.isfinite(arr)) or np.any(arr < 0) or np.any(arr > 1):
        raise ImagingError(f"p: degree of polarization must lie in [0, 1], got {p!r}")
    with np.errstate(divide="ignore"):
        return np.log1p(-arr)


def _log_ratio(log_num: np.ndarray, log_other: np.ndarray) -> np.ndarray:
    """log(x / (x + y)) from log x and log y, 0 when y = 0, -inf when x = 0 < y; x = y = 0 gives -inf."""
    with np.errstate(invalid="ignore"):
        d = log_other - log_num
    d = np.where(np.isnan(d), np.inf, d)  # both zero: no signal, quality 0
    return -np.logaddexp(0.0, d)


def log_cqm(log_signal, log_backscatter, p=0.0) -> np.ndarray:
    """log CQM from log S and log B (eq. 8): log S - log(S + B(1 - p)). -inf entries mean zero."""
    ls, lb = np.asarray(log_signal, np.float64), np.asarray(log_backscatter, np.float64)
    if np.any(np.isnan(ls)) or np.any(np.isnan(lb)):
        raise ImagingError("log_signal/log_backscatter: NaN values")
    return _log_ratio(ls, lb + _log_p(p))


def cqm(signal, backscatter, p=0.0) -> np.ndarray:
    """Contrast quality measure CQM = S / (S + B(1 - p)) (eq. 8), in [0, 1].

    Parameters
    ----------
    signal, backscatter : array_like
        S = D + A and B, radiance (any common unit), >= 0, broadcastable.
    p : float or array_like
        Backscatter DOP seen through the best-polarized analyzer; 0 without a polarizer.

    Returns
    -------
    float64 array: 1 when B(1 - p) = 0 < S, 0 when S = 0.
    """
    s, b = _nonneg("signal", signal), _nonneg("backscatter", backscatter)
    return np.exp(_log_ratio(_log(s), _log(b) + _log_p(p)))


def log_gqm(log_direct, log_indirect, log_backscatter, p=0.0) -> np.ndarray:
    """log GQM from log D, log A, log B (eq. 9)."""
    ld, la, lb = (np.asarray(x, np.float64) for x in (log_direct, log_indirect, log_backscatter))
    if any(np.any(np.isnan(x)) for x in (ld, la, lb)):
        raise ImagingError("log_direct/log_indirect/log_backscatter: NaN values")
    log_edge = np.logaddexp(ld, lb + _log_p(p))
    return _log_ratio(log_edge, la)


def gqm(direct, indirect, backscatter, p=0.0) -> np.ndarray:
    """Gradient quality measure GQM = (D + B(1 - p)) / (D + A + B(1 - p)) (eq. 9), in [0, 1].

    The normalized brightness step across a stripe edge: the lit point O has D, A and B(1 - p); the unlit
    neighbour O' only A. Radiances D, A, B >= 0, broadcastable. 0 when all are 0.
    """
    d, a, b = _nonneg("direct", direct), _nonneg("indirect", indirect), _nonneg("backscatter", backscatter)
    return np.exp(log_gqm(_log(d), _log(a), _log(b), p))


def log_margin(log_own, log_competitor) -> np.ndarray:
    """log of the delineation margin max(0, (E_own - E_comp)/E_own) from log E_own and log E_comp.

    -inf where E_comp >= E_own (no margin) or E_own = 0; 0 where E_comp = 0 < E_own. Computed as
    log(1 - e^{log E_comp - log E_own}) with ``log1p``, so it stays exact when both underflow.
    """
    lo, lc = np.asarray(log_own, np.float64), np.asarray(log_competitor, np.float64)
    if np.any(np.isnan(lo)) or np.any(np.isnan(lc)):
        raise ImagingError("log_own/log_competitor: NaN values")
    with np.errstate(invalid="ignore"):
        d = lc - lo
    d = np.where(np.isnan(d), np.inf, d)  # both zero: no stripe, no margin
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(d < 0.0, np.log1p(-np.exp(np.minimum(d, 0.0))), -np.inf)


def margin(own, competitor) -> np.ndarray:
    """Delineation margin M = max(0, (E_own - E_comp) / E_own), in [0, 1].

    The relative step by which a lit stripe point O (intensity E_own under its own sheet) exceeds the
    brightest competitor E_comp that a stripe delineation or the per-pixel maximum of eq. 7 meets at or next
    to it. Eq. 9 (GQM) is the special case E_comp = A (the unlit neighbour O' receives only the indirect
    light, Fig. 8c): M = (D + A + B(1 - p) - A) / (D + A + B(1 - p)) = GQM.

    Parameters
    ----------
    own, competitor : array_like
        E_own and E_comp, radiances or electrons (one common unit), >= 0, broadcastable.
    """
    o, c = _nonneg("own", own), _nonneg("competitor", competitor)
    return np.exp(log_margin(_log(o), _log(c)))


def log_snr_weight(signal, mu, z) -> np.ndarray:
    """log W for W = 1 / (1 + exp(-(S - μ)/z)) (eq. 10); z = 0 is the noise-free step (log 1 or -inf)."""
    s = np.asarray(signal, np.float64)
    if np.any(np.isnan(s)):
        raise ImagingError("signal: NaN values")
    mu_a, z_a = np.asarray(mu, np.float64), np.asarray(z, np.float64)
    if np.any(np.isnan(mu_a)):
        raise ImagingError(f"mu: NaN in the sigmoid shift {mu!r}")
    if np.any(np.isnan(z_a)) or np.any(z_a < 0) or np.any(np.isinf(z_a)):
        raise ImagingError(f"z: the sigmoid steepness must be finite and >= 0, got {z!r}")
    x = s - mu_a
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(z_a > 0, x / np.where(z_a > 0, z_a, 1.0), np.sign(x) * np.inf)
    t = np.where(np.isnan(t), 0.0, t)  # S = μ with z = 0: W = 1/2
    return -np.logaddexp(0.0, -t)


def snr_weight(signal, mu, z) -> np.ndarray:
    """SNR-dependent weight W = 1 / (1 + exp(-(S - μ)/z)) (eq. 10), in [0, 1].

    Parameters
    ----------
    signal : array_like
        Recovered signal S (same unit as μ and z: DN or electrons).
    mu : float or array_like
        Shift μ (e.g. the dark offset plus a detection threshold).
    z : float or array_like
        Steepness z > 0, or 0 for the noise-free step function.
    """
    return np.exp(log_snr_weight(signal, mu, z))


def snr_weight_from_noise(signal, noise_std, *, k_detect: float = 3.0, offset: float = 0.0) -> np.ndarray:
    """W with μ and z derived from the recovered signal's noise (docs/physics.md §7).

    μ = offset + k_detect·σ_S and z = σ_S / 1.702, so W ≈ Φ((S - offset)/σ_S - k_detect), the probability
    that the signal clears a k-sigma detection threshold. σ_S = 0 gives the noise-free step (W = 1 for any
    S > offset).
    """
    k = finite_param("k_detect", k_detect, low=0.0)
    off = finite_param("offset", offset)
    sig = np.asarray(noise_std, np.float64)
    if np.any(np.isnan(sig)) or np.any(sig < 0):
        raise ImagingError(f"noise_std: must be >= 0 and not NaN, got {noise_std!r}")
    return snr_weight(signal, off + k * sig, sig / LOGISTIC_PROBIT_SCALE)


def recovered_signal_noise_e(signal_e, backscatter_e, p=None, *, read_noise_e: float, dark_e: float = 0.0,
                             quantization_e: float = 0.0) -> np.ndarray:
    """Noise std (electrons) of the recovered signal, for the SNR weight.

    Parameters
    ----------
    signal_e, backscatter_e : array_like
        Mean electrons the signal S and the backscatter B would give without an analyzer.
    p : float, array_like or None
        None: no polarizer, the frame E = S + B is the estimate. A value in (0, 1]: Ŝ from E_b and E_w by
        eq. 6, each frame receiving S/2 + B(1 ∓ p)/2 through an ideal analyzer.
    read_noise_e, dark_e, quantization_e : float
        Read noise (e⁻ rms), dark electrons per frame (Poisson), quantization noise (e⁻ rms, gain/√12).

    Returns
    -------
    float64 array, σ_S in electrons

    Notes
    -----
    EMVA 1288: Var = σ_read² + μ_e + μ_dark + σ_q². For eq. 6, Var Ŝ = (1 + 1/p)² Var E_b + (1 - 1/p)²
    Var E_w (docs/physics.md §4.2): the backscatter's shot noise stays even where B itself is removed.
    """
    s, b = _nonneg("signal_e", signal_e), _nonneg("backscatter_e", backscatter_e)
    floor = (finite_param("read_noise_e", read_noise_e, low=0.0) ** 2
             + finite_param("dark_e", dark_e, low=0.0)
             + finite_param("quantization_e", quantization_e, low=0.0) ** 2)
    if p is None:
        return np.sqrt(floor + s + b)
    pp = np.asarray(p, np.float64)
    if np.any(~np.isfinite(pp)) or np.any(pp <= 0) or np.any(pp > 1):
        raise ImagingError(f"p: must lie in (0, 1] for eq. 6 (clamp it away from 0), got {p!r}")
    var_b = floor + 0.5 * s + 0.5 * b * (1.0 - pp)
    var_w = floor + 0.5 * s + 0.5 * b * (1.0 + pp)
    return np.sqrt((1.0 + 1.0 / pp) ** 2 * var_b + (1.0 - 1.0 / pp) ** 2 * var_w)
