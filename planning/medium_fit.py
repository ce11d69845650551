"""The medium in situ: σ_t, the phase function's mean cosine g and the backscatter DOP p fitted to the
frames a scan already takes (docs/planning.md §6).

A stripe frame shows the sheet's backscatter in the medium, the visible light plane (the paper's Fig. 7b):
along an image row each pixel's ray crosses the sheet at a different depth, so the profile carries the light's
attenuation source → sheet point → camera (σ_t) and the scattering angle's sweep across the phase function
(g). The flood frame adds the backscatter of the whole lit volume and the object's light. With the rig's
geometry, camera and objects known and the medium's single-scattering albedo taken from the scene, the fit is

    y_i = k · m_i(σ_t, g) + noise,     m_i = mean_dn(D + A + B)_i − dark offset      (docs/physics.md §0, §10)

over the pixels i of a few stripe frames and the flood frame, where y_i is the frame's DN minus the dark
offset (the mean of an analyzer pair at φ and φ + 90°, which is ½(k1 + k2)(D + A + B): the backscatter's
polarization cancels; docs/physics.md §4.1) and m_i is :func:`~polarstripe.sim.render.render_components`
(the simulator's model, ``orders="all"``) of the whole frame at a small resolution (64×48: the path the
simulator's frames take, A's grid and the blurs, for ~20 ms a frame; A exact at requested pixels differs from
it by up to 30 %). The unknown source radiance × exposure × transmittance is the scale k, eliminated in closed
form (k̂ = Σ y m/σ² / Σ m²/σ²). The weights are σ_i² = σ_noise,i² + (ε_B k(B + D)_i)² + (ε_A k A_i)²: the
EMVA 1288 noise of the measured DN (docs/physics.md §7) and the model's error (§10.6; ε_B = 3 %, ε_A = 30 %).
(log σ_t, g) minimise χ² = Σ ((y_i − k̂ m_i)/σ_i)² by scipy's trust-region least squares from the better of
two starting media, the weights taken at the start and again at the first result; the model is rendered at
g nodes 0.02 apart and interpolated linearly (every new g costs the model a forward-cone table, §10.3). The
covariance is (JᵀJ)⁻¹ · max(1, χ²/dof) at the minimum.

p is the ratio of medians of E_w − E_b and E_w + E_b over object-free pixels of an analyzer pair
(docs/physics.md §4.2), its uncertainty the spread of a bootstrap over those pixels.

Never a wild value: saturated pixels and pixels at edges (the stripe on the object, texture) are left out; no
pixel of the stripe frames clearly above the noise (no visible sheet), too few usable pixels, a fit that ends
at a bound, residuals far above the noise or an uncertainty above the limits give a :class:`MediumFit` with
``ok = False`` and the reason.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from polarstripe.msgs.patterns import PatternError, parse
from polarstripe.sim.render import render_components
from polarstripe.sim.scene import Phase, Scene
from polarstripe.sim.sensor import dark_offset_dn, electrons_per_radiance, full_scale_dn
from scipy.optimize import least_squares

SIGMA_BOUNDS = (0.05, 40.0)  # [1/m]
G_BOUNDS = (0.31, 0.97)  # TTHG mean cosine
G_STEP = 0.02  # the model is rendered at g nodes this far apart, linear between
N_NODES = round((G_BOUNDS[1] - G_BOUNDS[0]) / G_STEP) + 1
LOG_STEP = 0.01  # finite difference in log σ_t
STARTS = ((2.0, 0.75), (5.0, 0.85))  # (σ_t, g) tried first; the best χ² starts the fit
MODEL_ERROR = 0.03  # ε_B: the model's relative error of B at requested pixels (docs/physics.md §10.6)
OBJECT_ERROR = 0.3  # ε_A: of A at requested pixels against a whole frame (blur stencils, A's grid)
MAX_REL_SIGMA = 0.15  # cannot estimate beyond: σ_t uncertain by more than 15 %
MAX_G_STD = 0.05  # or g by more than 0.05
MAX_CHI2 = 25.0  # or residuals more than 5× the expected scatter (the model does not describe the frames)
SNR_VISIBLE = 10.0  # a stripe-frame pixel this many σ above the dark level shows the sheet
MIN_PIXELS = 12


@dataclass(frozen=True)
class MediumFit:
    """The estimate: ``ok`` with values and 1σ uncertainties, or ``ok = False`` and ``reason``."""

    ok: bool
    sigma_t_per_m: float = math.nan
    sigma_t_std: float = math.nan
    mean_cosine: float = math.nan
    mean_cosine_std: float = math.nan
    p: float = math.nan
    p_std: float = math.nan
    reason: str = ""
    chi2_per_dof: float = math.nan
    pixels: int = 0
    evaluations: int = 0
    extra: dict = field(default_factory=dict)


def frame_intensity(frames: list[np.ndarray]) -> np.ndarray:
    """Polarization-free DN of one pattern: one frame without analyzer, or the mean of an analyzer pair at φ
    and φ + 90° (½(k1 + k2)(D + A + B), docs/physics.md §4.1)."""
    return np.mean([np.asarray(f, dtype=np.float64) for f in frames], axis=0)


def _usable(img: np.ndarray, sat: np.ndarray, sigma: np.ndarray, rows, cols) -> np.ndarray:
    """(n, 2) pixels of the rows × cols grid that are not saturated (nor a neighbour) and lie on no edge: the
    frame changes by less than 20 % + 3σ to each horizontal and vertical neighbour (the object stripe's edges
    and texture edges move with sub-pixel geometry the fit must not depend on)."""
    h, w = img.shape
    out = []
    for r in rows:
        for c in cols:
            r0, r1, c0, c1 = max(r - 1, 0), min(r + 2, h), max(c - 1, 0), min(c + 2, w)
            if sat[r0:r1, c0:c1].any():
                continue
            nb = np.array([img[r0, c], img[r1 - 1, c], img[r, c0], img[r, c1 - 1]])
            if np.all(np.abs(nb - img[r, c]) <= 0.2 * abs(img[r, c]) + 3.0 * sigma[r, c]):
                out.append((r, c))
    return np.array(out, dtype=np.int64).reshape(-1, 2)


def estimate_p(pair: tuple[np.ndarray, np.ndarray] | None, object_free: np.ndarray | None, dark: float,
               saturation: float, n_boot: int = 200, seed: int = 0) -> tuple[float, float, str]:
    """(p, its bootstrap std, reason) from an (E_b, E_w) pair over object-free pixels (physics.md §4.2)."""
    if pair is None:
        return math.nan, math.nan, "no analyzer pair"
    eb, ew = (np.asarray(f, np.float64) - dark for f in pair)
    ok = (pair[0] < saturation) & (pair[1] < saturation)
    if object_free is not None:
        ok &= object_free
    diff, tot = (ew - eb)[ok], (ew + eb)[ok]
    keep = tot > 0
    diff, tot = diff[keep], tot[keep]
    if tot.size < MIN_PIXELS:
        return math.nan, math.nan, f"only {tot.size} unsaturated object-free pixels for p"
    p = float(np.median(diff) / np.median(tot))
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, tot.size, size=(n_boot, tot.size))
    boot = np.median(diff[idx], axis=1) / np.median(tot[idx], axis=1)
    if not 0.0 < p <= 1.0:
        return math.nan, math.nan, f"p = {p:.3g} from the analyzer pair is outside (0, 1]"
    return p, float(np.std(boot)), ""


def fit_medium(scene: Scene, stripe_frames: dict[str, list[np.ndarray]],
               flood_frames: list[np.ndarray] | None, *,
               polarized_pair: tuple[np.ndarray, np.ndarray] | None = None, fidelity: str = "preview",
               n_stripes_used: int = 4, rows: int | None = None, cols: int | None = None,
               model_error: float = MODEL_ERROR, object_free: np.ndarray | None = None,
               frames_averaged: int = 1) -> MediumFit:
    """Fit σ_t, the TTHG mean cosine g and p to a scan's frames (the module docstring has the method).

    Parameters
    ----------
    scene : the rig as known (camera incl. resolution and exposure, projector at the scan's separation,
        objects, the medium's albedo and DOP model); its σ_t and g are not used.
    stripe_frames : pattern (``"stripe:K/N"``) → the frames of that pattern (one without analyzer, or an
        analyzer pair at φ, φ + 90°), DN (h, w).
    flood_frames : the flood pattern's frames, the same way, or None.
    polarized_pair : (E_b, E_w) frames for p, or None (p not estimated).
    n_stripes_used : stripes of the scan used (evenly spread); rows × cols : the pixel grid per frame
        (None: every row / column but the border). Frames of a few thousand pixels suffice: block-average
        larger ones and pass a scene whose camera has that resolution (:func:`downsample`).
    object_free : bool (h, w) mask for p (default: the whole frame).
    frames_averaged : pixels averaged into each frame pixel (:func:`downsample`), for the noise.
    """
    cam = scene.camera
    w, h = cam.resolution
    dark, full = dark_offset_dn(cam), float(full_scale_dn(cam))
    items: list[tuple[str, np.ndarray]] = []
    keys = []
    for tag in stripe_frames:
        try:
            spec = parse(tag)
        except PatternError:
            spec = None
        if spec is None or spec.kind != "stripe":
            return MediumFit(False, reason=f"{tag!r} is not a stripe pattern")
        keys.append((spec.index, tag))
    keys.sort()
    if keys:
        n_use = min(n_stripes_used, len(keys))
        pick = ((np.arange(n_use) + 0.5) * len(keys) / n_use).astype(int)
        items += [(keys[int(i)][1], frame_intensity(stripe_frames[keys[int(i)][1]])) for i in pick]
    n_stripe_items = len(items)
    if flood_frames:
        items.append(("flood", frame_intensity(flood_frames)))
    if not n_stripe_items:
        return MediumFit(False, reason="no stripe frames (the sheet's backscatter is what the fit reads)")
    for _, img in items:
        if img.shape != (h, w):
            return MediumFit(False, reason=f"frame of {img.shape[1]}x{img.shape[0]} px, the rig's camera is "
                                           f"{w}x{h}")
    grid_r = np.unique(np.linspace(1, h - 2, rows or h - 2).round().astype(int))
    grid_c = np.unique(np.linspace(1, w - 2, cols or w - 2).round().astype(int))
    k_gain = cam.gain_e_per_dn
    e_map = electrons_per_radiance(cam)
    pixels, ys, sig, which, visible, saturated = [], [], [], [], 0, 0
    for j, (tag, img) in enumerate(items):
        n_avg = len(stripe_frames.get(tag, flood_frames or [1]))
        sat = img >= full - 0.5
        y = img - dark
        # noise of the mean of n_avg frames: (σ_read² + e)/K² + 1/12 per frame, e from the measured level
        var = (cam.read_noise_e ** 2 + np.clip(y, 0, None) * k_gain) / k_gain ** 2 + 1.0 / 12.0
        s_noise = np.sqrt(var / (n_avg * frames_averaged))
        pix = _usable(y, sat, s_noise, grid_r, grid_c)
        saturated += int(sat[np.ix_(grid_r, grid_c)].sum())
        if j < n_stripe_items:
            visible += int(np.sum(y[pix[:, 0], pix[:, 1]] > SNR_VISIBLE * s_noise[pix[:, 0], pix[:, 1]])) \
                if len(pix) else 0
        pix = pix[y[pix[:, 0], pix[:, 1]] > 3.0 * s_noise[pix[:, 0], pix[:, 1]]] if len(pix) else pix
        yy = y[pix[:, 0], pix[:, 1]]
        pixels.append(pix)
        ys.append(yy)
        sig.append(s_noise[pix[:, 0], pix[:, 1]])
        which.append(np.full(len(pix), j))
    n_grid = len(items) * grid_r.size * grid_c.size
    if saturated > 0.5 * n_grid:
        return MediumFit(False, reason=f"saturated: {saturated} of {n_grid} sampled pixels at full scale "
                                       "(shorten the exposure)")
    if visible < MIN_PIXELS:
        return MediumFit(False, reason=f"no visible sheet: {visible} stripe-frame pixels are "
                                       f"{SNR_VISIBLE:.0f}σ above the dark level (need {MIN_PIXELS})")
    y_all, s_noise_all = np.concatenate(ys), np.concatenate(sig)
    if y_all.size < MIN_PIXELS + 2:
        return MediumFit(False, reason=f"only {y_all.size} usable pixels (edges, saturation, noise)")
    evals = [0]
    cache: dict[tuple[float, float], np.ndarray] = {}

    def at_node(log_sigma: float, g_node: float) -> np.ndarray:
        key = (round(log_sigma, 12), round(g_node, 6))
        if key not in cache:
            sc = scene.replace(medium=scene.medium.replace(sigma_t=math.exp(log_sigma),
                                                           phase=Phase("tthg", g_node)))
            out = []
            for (tag, _), pix in zip(items, pixels, strict=True):
                if len(pix):
                    # the whole (small) frame: the path the simulator's frames take (A's grid, the blurs);
                    # at 64x48 it costs less than A exact at a few dozen pixels
                    c = render_components(sc, tag, fidelity, need=("D", "A", "B"))
                    r, q = pix[:, 0], pix[:, 1]
                    to_dn = e_map[r, q] / k_gain
                    out.append(np.stack([c.B[r, q] * to_dn, c.D[r, q] * to_dn, c.A[r, q] * to_dn]))
            cache[key] = np.concatenate(out, axis=1)
            evals[0] += 1
        return cache[key]

    def model(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """m at x = (log σ_t, g), linear in g between nodes G_STEP apart (each new g costs the model a
        forward-cone table, docs/physics.md §10.3), and dm/dg of that interpolant."""
        i = min(int((x[1] - G_BOUNDS[0]) / G_STEP), N_NODES - 2)
        ga = G_BOUNDS[0] + i * G_STEP
        t = (x[1] - ga) / G_STEP
        ma, mb = at_node(float(x[0]), ga).sum(axis=0), at_node(float(x[0]), ga + G_STEP).sum(axis=0)
        return (1 - t) * ma + t * mb, (mb - ma) / G_STEP

    def weights(x: np.ndarray) -> np.ndarray:
        """σ_i: the frames' noise and the model's error at x, ε_B of the backscatter B and ε_A of the
        object's light D + A (whose per-pixel values differ most from a whole frame's, docs/physics.md
        §10.3), fixed while a fit runs (D is exact per pixel: ε_B)."""
        i = min(int(round((x[1] - G_BOUNDS[0]) / G_STEP)), N_NODES - 1)
        b, d, a = at_node(float(x[0]), G_BOUNDS[0] + i * G_STEP)
        m = b + d + a
        k = np.sum(y_all * m / s_noise_all ** 2) / max(np.sum(m * m / s_noise_all ** 2), 1e-300)
        return np.sqrt(s_noise_all ** 2 + (model_error * k * (b + d)) ** 2 + (OBJECT_ERROR * k * a) ** 2)

    def scaled(x: np.ndarray):
        m, dm_dg = model(x)
        mp, _ = model(np.array([x[0] + LOG_STEP, x[1]]))
        k = np.sum(y_all * m / s_all ** 2) / max(np.sum(m * m / s_all ** 2), 1e-300)
        return m, np.stack([(mp - m) / LOG_STEP, dm_dg], axis=1), k

    def residuals(x: np.ndarray) -> np.ndarray:
        m, _ = model(x)
        k = np.sum(y_all * m / s_all ** 2) / max(np.sum(m * m / s_all ** 2), 1e-300)
        return (y_all - k * m) / s_all

    def jacobian(x: np.ndarray) -> np.ndarray:
        # r = (y − k̂(x) m(x))/σ with k̂ the weighted projection: dr = −(k̂ dm + m dk̂)/σ
        m, dm, k = scaled(x)
        wm = m / s_all ** 2
        den = max(float(np.sum(m * wm)), 1e-300)
        dk = ((y_all / s_all ** 2) @ dm - 2.0 * k * (wm @ dm)) / den
        return -(k * dm + m[:, None] * dk[None, :]) / s_all[:, None]

    lo = np.array([math.log(SIGMA_BOUNDS[0]), G_BOUNDS[0]])
    hi = np.array([math.log(SIGMA_BOUNDS[1]), G_BOUNDS[1]])
    starts = [np.array([math.log(s), g]) for s, g in STARTS]
    s_all = s_noise_all
    x0 = min(starts, key=lambda x: float(np.sum(residuals(x) ** 2)))
    for _ in range(2):  # weights from the start, then from the first fit (iteratively reweighted)
        s_all = weights(x0)
        res = least_squares(residuals, x0, jac=jacobian, bounds=(lo, hi), x_scale=np.array([0.3, 0.05]),
                            xtol=1e-4, ftol=1e-6, max_nfev=30)
        x0 = res.x
    dof = max(y_all.size - 3, 1)
    chi2 = float(np.sum(res.fun ** 2)) / dof
    sigma_t, g = math.exp(res.x[0]), float(res.x[1])
    try:
        cov = np.linalg.inv(res.jac.T @ res.jac) * max(1.0, chi2)
        std = np.sqrt(np.clip(np.diag(cov), 0, None))
    except np.linalg.LinAlgError:
        std = np.array([math.inf, math.inf])
    s_std, g_std = sigma_t * float(std[0]), float(std[1])
    p, p_std, p_why = estimate_p(polarized_pair, object_free, dark, full - 0.5)
    common = dict(chi2_per_dof=chi2, pixels=int(y_all.size), evaluations=evals[0], p=p, p_std=p_std,
                  extra={"p_reason": p_why, "patterns": [t for t, _ in items]})
    found = dict(sigma_t_per_m=sigma_t, sigma_t_std=s_std, mean_cosine=g, mean_cosine_std=g_std)
    at_bound = np.isclose(res.x, lo, atol=1e-3) | np.isclose(res.x, hi, atol=1e-3)
    if at_bound.any():
        return MediumFit(False, reason=f"fit ends at the bound of {'σ_t' if at_bound[0] else 'g'} "
                                       f"(σ_t {sigma_t:.3g} /m, g {g:.3f})", **common)
    if chi2 > MAX_CHI2:
        return MediumFit(False, reason=f"the model does not describe the frames (χ²/dof = {chi2:.3g})",
                         **common)
    if not (s_std <= MAX_REL_SIGMA * sigma_t and g_std <= MAX_G_STD):
        return MediumFit(False, reason=f"too noisy: σ_t {sigma_t:.3g} ± {s_std:.2g} /m, "
                                       f"g {g:.3f} ± {g_std:.2g}", **common)
    return MediumFit(True, **found, **common)


def downsample(scene: Scene, frames: dict[str, list[np.ndarray]], width: int = 64,
               full_scale: float | None = None):
    """(scene, frames) at about ``width`` pixels across: each frame block-averaged by the integer factor
    f = W // width (the rows and columns that do not fill a block dropped), the scene's camera at that
    resolution with the same exposure (a pixel f² times larger in area changes the model's DN by f², which
    the fit's free scale takes). The noise of a block mean is 1/f of a pixel's: pass the returned f² as
    ``frames_averaged``. A block mean hides a saturated pixel: with ``full_scale`` (DN) a block holding a
    pixel at or above ``full_scale − 0.5`` is set to ``full_scale``, so the fit sees it saturated."""
    w, h = scene.camera.resolution
    f = max(1, w // width)
    if f == 1:
        return scene, frames, 1
    hh, ww = h // f, w // f

    def block(im):
        a = np.asarray(im, np.float64)[:hh * f, :ww * f].reshape(hh, f, ww, f)
        out = a.mean(axis=(1, 3))
        if full_scale is not None:
            out[(a >= full_scale - 0.5).any(axis=(1, 3))] = full_scale
        return out

    out = {tag: [block(im) for im in ims] for tag, ims in frames.items()}
    return scene.replace(camera=scene.camera.replace(resolution=(ww, hh))), out, f * f
