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

p comes from an analyzer pair of flood frames with the fitted medium's model (:mod:`.medium_p`: the
model's measured DOP p_m·B/(S + B) scaled to the pair by least squares; the frames alone give a DOP lowered
by the object's light wherever the wall is lit).

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
from polarstripe.planning.medium_p import MIN_PIXELS, p_of_pair, p_with_model
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


@dataclass(frozen=True)
class ScanFrames:
    """What the fit reads of one scan: DN frames (h, w) at the resolution of the scene's camera.

    Attributes
    ----------
    stripes : pattern (``"stripe:K/N"``) → the frames of that pattern (one without analyzer, or an analyzer
        pair at φ, φ + 90°).
    flood : the flood pattern's frames, the same way, or None.
    polarized_pair : (E_b, E_w) frames for p, or None (p not estimated).
    object_free : bool (h, w) mask where p is read (None: the whole frame).
    frames_averaged : pixels averaged into each frame pixel (:func:`downsample`), for the noise.
    """

    stripes: dict[str, list[np.ndarray]]
    flood: list[np.ndarray] | None = None
    polarized_pair: tuple[np.ndarray, np.ndarray] | None = None
    object_free: np.ndarray | None = None
    frames_averaged: int = 1


@dataclass(frozen=True)
class FitSettings:
    """How the fit samples and models the frames.

    Attributes
    ----------
    fidelity : the model rendered (``sim/render.py``), the simulator's.
    n_stripes_used : stripes of the scan used (evenly spread).
    rows, cols : the pixel grid per frame (None: every row / column but the border). Frames of a few thousand
        pixels suffice: block-average larger ones and pass a scene whose camera has that resolution
        (:func:`downsample`).
    model_error : ε_B, the model's relative error of the backscatter B.
    """

    fidelity: str = "preview"
    n_stripes_used: int = 4
    rows: int | None = None
    cols: int | None = None
    model_error: float = MODEL_ERROR


class _Refused(Exception):
    """A step found the frames unusable; the text is the :class:`MediumFit` reason."""


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


def _pick_frames(frames: ScanFrames, n_stripes_used: int, size: tuple[int, int]):
    """[(tag, polarization-free image, frames averaged)] of ``n_stripes_used`` evenly spread stripes, then
    the flood's if any; and how many of them are stripes."""
    keys = []
    for tag in frames.stripes:
        try:
            spec = parse(tag)
        except PatternError:
            spec = None
        if spec is None or spec.kind != "stripe":
            raise _Refused(f"{tag!r} is not a stripe pattern")
        keys.append((spec.index, tag))
    keys.sort()
    items = []
    if keys:
        n_use = min(n_stripes_used, len(keys))
        pick = ((np.arange(n_use) + 0.5) * len(keys) / n_use).astype(int)
        for i in pick:
            tag = keys[int(i)][1]
            items.append((tag, frame_intensity(frames.stripes[tag]), len(frames.stripes[tag])))
    n_stripes = len(items)
    if frames.flood:
        items.append(("flood", frame_intensity(frames.flood), len(frames.flood)))
    if not n_stripes:
        raise _Refused("no stripe frames (the sheet's backscatter is what the fit reads)")
    w, h = size
    for _, img, _ in items:
        if img.shape != (h, w):
            raise _Refused(f"frame of {img.shape[1]}x{img.shape[0]} px, the rig's camera is {w}x{h}")
    return items, n_stripes


@dataclass
class _Samples:
    """The fit's data: per frame the pixels used; over all of them y (DN above dark) and its noise σ."""

    pixels: list[np.ndarray]
    y: np.ndarray
    noise: np.ndarray


def _sample(items, n_stripes: int, cam, frames_averaged: int, grid) -> _Samples:
    """The usable pixels of each frame (not saturated, on no edge, 3σ above the dark level), refusing frames
    mostly saturated, a sheet not visible, or too few pixels."""
    dark, full = dark_offset_dn(cam), float(full_scale_dn(cam))
    grid_r, grid_c = grid
    k_gain = cam.gain_e_per_dn
    pixels, ys, sig, visible, saturated = [], [], [], 0, 0
    for j, (_, img, n_avg) in enumerate(items):
        sat = img >= full - 0.5
        y = img - dark
        # noise of the mean of n_avg frames: (σ_read² + e)/K² + 1/12 per frame, e from the measured level
        var = (cam.read_noise_e ** 2 + np.clip(y, 0, None) * k_gain) / k_gain ** 2 + 1.0 / 12.0
        s_noise = np.sqrt(var / (n_avg * frames_averaged))
        pix = _usable(y, sat, s_noise, grid_r, grid_c)
        saturated += int(sat[np.ix_(grid_r, grid_c)].sum())
        if j < n_stripes:
            visible += int(np.sum(y[pix[:, 0], pix[:, 1]] > SNR_VISIBLE * s_noise[pix[:, 0], pix[:, 1]])) \
                if len(pix) else 0
        pix = pix[y[pix[:, 0], pix[:, 1]] > 3.0 * s_noise[pix[:, 0], pix[:, 1]]] if len(pix) else pix
        pixels.append(pix)
        ys.append(y[pix[:, 0], pix[:, 1]])
        sig.append(s_noise[pix[:, 0], pix[:, 1]])
    n_grid = len(items) * grid_r.size * grid_c.size
    if saturated > 0.5 * n_grid:
        raise _Refused(f"saturated: {saturated} of {n_grid} sampled pixels at full scale "
                       "(shorten the exposure)")
    if visible < MIN_PIXELS:
        raise _Refused(f"no visible sheet: {visible} stripe-frame pixels are {SNR_VISIBLE:.0f}σ above the "
                       f"dark level (need {MIN_PIXELS})")
    out = _Samples(pixels, np.concatenate(ys), np.concatenate(sig))
    if out.y.size < MIN_PIXELS + 2:
        raise _Refused(f"only {out.y.size} usable pixels (edges, saturation, noise)")
    return out


def _scale(y: np.ndarray, m: np.ndarray, sigma: np.ndarray) -> float:
    """k̂ = Σ y m/σ² / Σ m²/σ²: the free scale (source radiance × exposure × transmittance) in closed form."""
    return np.sum(y * m / sigma ** 2) / max(np.sum(m * m / sigma ** 2), 1e-300)


class _FrameModel:
    """m_i at the sampled pixels: the simulator's model (:func:`render_components`, whole frames) of the
    scene's medium at (log σ_t, g), rendered at g nodes G_STEP apart and cached, B, D and A in DN."""

    def __init__(self, scene: Scene, tags: list[str], pixels: list[np.ndarray], fidelity: str):
        self.scene, self.tags, self.pixels, self.fidelity = scene, tags, pixels, fidelity
        self.to_dn = electrons_per_radiance(scene.camera) / scene.camera.gain_e_per_dn
        self.cache: dict[tuple[float, float], np.ndarray] = {}
        self.evaluations = 0

    def at_node(self, log_sigma: float, g_node: float) -> np.ndarray:
        """(3, n): B, D and A at the sampled pixels for σ_t = exp(log_sigma), g = ``g_node``."""
        key = (round(log_sigma, 12), round(g_node, 6))
        if key not in self.cache:
            sc = self.scene.replace(medium=self.scene.medium.replace(sigma_t=math.exp(log_sigma),
                                                                     phase=Phase("tthg", g_node)))
            out = []
            for tag, pix in zip(self.tags, self.pixels, strict=True):
                if len(pix):
                    # the whole (small) frame: the path the simulator's frames take (A's grid, the blurs);
                    # at 64x48 it costs less than A exact at a few dozen pixels
                    c = render_components(sc, tag, self.fidelity, need=("D", "A", "B"))
                    r, q = pix[:, 0], pix[:, 1]
                    to_dn = self.to_dn[r, q]
                    out.append(np.stack([c.B[r, q] * to_dn, c.D[r, q] * to_dn, c.A[r, q] * to_dn]))
            self.cache[key] = np.concatenate(out, axis=1)
            self.evaluations += 1
        return self.cache[key]

    def __call__(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """m at x = (log σ_t, g), linear in g between nodes G_STEP apart (each new g costs the model a
        forward-cone table, docs/physics.md §10.3), and dm/dg of that interpolant."""
        i = min(int((x[1] - G_BOUNDS[0]) / G_STEP), N_NODES - 2)
        ga = G_BOUNDS[0] + i * G_STEP
        t = (x[1] - ga) / G_STEP
        ma, mb = self.at_node(float(x[0]), ga).sum(axis=0), self.at_node(float(x[0]), ga + G_STEP).sum(axis=0)
        return (1 - t) * ma + t * mb, (mb - ma) / G_STEP

    def weights(self, x: np.ndarray, y: np.ndarray, noise: np.ndarray, model_error: float) -> np.ndarray:
        """σ_i: the frames' noise and the model's error at x, ε_B of the backscatter B and ε_A of the
        object's light D + A (whose per-pixel values differ most from a whole frame's, docs/physics.md
        §10.3), fixed while a fit runs (D is exact per pixel: ε_B)."""
        i = min(int(round((x[1] - G_BOUNDS[0]) / G_STEP)), N_NODES - 1)
        b, d, a = self.at_node(float(x[0]), G_BOUNDS[0] + i * G_STEP)
        k = _scale(y, b + d + a, noise)
        return np.sqrt(noise ** 2 + (model_error * k * (b + d)) ** 2 + (OBJECT_ERROR * k * a) ** 2)


class _Residuals:
    """r(x) = (y − k̂(x) m(x))/σ with the weights σ fixed, and its Jacobian, for scipy's least squares."""

    def __init__(self, model: _FrameModel, y: np.ndarray, sigma: np.ndarray):
        self.model, self.y, self.sigma = model, y, sigma

    def __call__(self, x: np.ndarray) -> np.ndarray:
        m, _ = self.model(x)
        return (self.y - _scale(self.y, m, self.sigma) * m) / self.sigma

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        # r = (y − k̂(x) m(x))/σ with k̂ the weighted projection: dr = −(k̂ dm + m dk̂)/σ
        y, s = self.y, self.sigma
        m, dm_dg = self.model(x)
        mp, _ = self.model(np.array([x[0] + LOG_STEP, x[1]]))
        dm = np.stack([(mp - m) / LOG_STEP, dm_dg], axis=1)
        k = _scale(y, m, s)
        wm = m / s ** 2
        den = max(float(np.sum(m * wm)), 1e-300)
        dk = ((y / s ** 2) @ dm - 2.0 * k * (wm @ dm)) / den
        return -(k * dm + m[:, None] * dk[None, :]) / s[:, None]


def _least_squares(model: _FrameModel, data: _Samples, model_error: float):
    """scipy's trust-region fit of (log σ_t, g) from the better of STARTS (noise weights), the weights taken
    at the start and again at the first result (iteratively reweighted); returns the last result."""
    lo = np.array([math.log(SIGMA_BOUNDS[0]), G_BOUNDS[0]])
    hi = np.array([math.log(SIGMA_BOUNDS[1]), G_BOUNDS[1]])
    starts = [np.array([math.log(s), g]) for s, g in STARTS]
    first = _Residuals(model, data.y, data.noise)
    x0 = min(starts, key=lambda x: float(np.sum(first(x) ** 2)))
    for _ in range(2):
        r = _Residuals(model, data.y, model.weights(x0, data.y, data.noise, model_error))
        res = least_squares(r, x0, jac=r.jacobian, bounds=(lo, hi), x_scale=np.array([0.3, 0.05]),
                            xtol=1e-4, ftol=1e-6, max_nfev=30)
        x0 = res.x
    return res, lo, hi


def fit_medium(scene: Scene, frames: ScanFrames, settings: FitSettings = FitSettings()) -> MediumFit:
    """Fit σ_t, the TTHG mean cosine g and p to a scan's ``frames`` (the module docstring has the method).

    ``scene`` is the rig as known (camera incl. resolution and exposure, projector at the scan's separation,
    objects, the medium's albedo and DOP model); its σ_t and g are not used. Unusable frames give
    ``ok = False`` and the reason, never an exception.
    """
    cam = scene.camera
    w, h = cam.resolution
    try:
        items, n_stripes = _pick_frames(frames, settings.n_stripes_used, (w, h))
        grid = (np.unique(np.linspace(1, h - 2, settings.rows or h - 2).round().astype(int)),
                np.unique(np.linspace(1, w - 2, settings.cols or w - 2).round().astype(int)))
        data = _sample(items, n_stripes, cam, frames.frames_averaged, grid)
    except _Refused as exc:
        return MediumFit(False, reason=str(exc))
    model = _FrameModel(scene, [tag for tag, _, _ in items], data.pixels, settings.fidelity)
    res, lo, hi = _least_squares(model, data, settings.model_error)
    dof = max(data.y.size - 3, 1)
    chi2 = float(np.sum(res.fun ** 2)) / dof
    sigma_t, g = math.exp(res.x[0]), float(res.x[1])
    try:
        cov = np.linalg.inv(res.jac.T @ res.jac) * max(1.0, chi2)
        std = np.sqrt(np.clip(np.diag(cov), 0, None))
    except np.linalg.LinAlgError:
        std = np.array([math.inf, math.inf])
    s_std, g_std = sigma_t * float(std[0]), float(std[1])
    at_bound = np.isclose(res.x, lo, atol=1e-3) | np.isclose(res.x, hi, atol=1e-3)
    why = (f"fit ends at the bound of {'σ_t' if at_bound[0] else 'g'} (σ_t {sigma_t:.3g} /m, g {g:.3f})"
           if at_bound.any() else
           f"the model does not describe the frames (χ²/dof = {chi2:.3g})" if chi2 > MAX_CHI2 else
           f"too noisy: σ_t {sigma_t:.3g} ± {s_std:.2g} /m, g {g:.3f} ± {g_std:.2g}"
           if not (s_std <= MAX_REL_SIGMA * sigma_t and g_std <= MAX_G_STD) else "")
    # p with the fitted medium's model where the fit holds (planning/medium_p.py), else from the frames
    pair = (frames.polarized_pair, frames.object_free, dark_offset_dn(cam), float(full_scale_dn(cam)) - 0.5)
    fitted = scene.replace(medium=scene.medium.replace(sigma_t=sigma_t, phase=Phase("tthg", g)))
    p, p_std, p_why = (p_of_pair(*pair) if why or frames.polarized_pair is None else
                       p_with_model(*pair, fitted, settings.fidelity))
    common = dict(chi2_per_dof=chi2, pixels=int(data.y.size), evaluations=model.evaluations, p=p, p_std=p_std,
                  extra={"p_reason": p_why, "patterns": [t for t, _, _ in items]})
    if why:
        return MediumFit(False, reason=why, **common)
    return MediumFit(True, sigma_t_per_m=sigma_t, sigma_t_std=s_std, mean_cosine=g, mean_cosine_std=g_std,
                     **common)


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
