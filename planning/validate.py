"""The end-to-end truth a plan is judged by: full scans through the real pipeline, scored against T.

For one scene and one camera–source separation d_LC, :func:`score_scans` does what the simulated rig does
(docs/planning.md §7): it renders every frame of each method's scan with the light-transport model
(:func:`polarstripe.sim.render.render_components`, every order of scattering by default, the geometry kept
across the scan's frames by :mod:`polarstripe.sim.geometry_cache`), exposes it through the scene camera's
EMVA 1288 sensor (:func:`polarstripe.sim.sensor.expose`, seeded), folds it into the compositor's running
reductions (:class:`~polarstripe.imaging.composite.RunningComposite`), composes it with the compositor's own
pipeline (:func:`polarstripe.imaging.compose.compose`: eq. 7, eq. 6 with the compositor's default ``map``
rule, p per pixel from the scene's own medium model with κ and ψ fitted to the pose's polarized flood pair as
the compositor fits them, :func:`polarstripe.planning.medium_p.scene_p_model`; ``p_rule`` chooses another,
e.g. ``median``, one p̂ on the object-free pixels) and scores the composite as the compositor's
``metrics.json`` does (:func:`polarstripe.imaging.compose.score`):

* ``error``: ‖g Ŝ − T‖ / ‖T‖ over the whole frame, gain g fitted, T the unscattered object radiance under
  flood light (:func:`polarstripe.sim.truth.unscattered_radiance`, docs/physics.md §10.8) in DN above the
  dark offset as the simulator node sends it (the camera's cos⁴ fall-off included; not clipped at full
  scale, which the ``method`` exposure of a polarized frame, S/2, would otherwise reach); saturated pixels
  are left out as the compositor leaves them out, and counted (``saturated_fraction``);
* ``contrast``: the Michelson contrast of the chart's bright and dark bars;
* for the polarized methods also the best-polarized frame E_b (the composite's ``e_b`` layer) as its own
  image (``error_e_b``, ``contrast_e_b``), and the p̂ eq. 6 used;
* for the stripe methods the depth (:mod:`polarstripe.imaging.delineation`,
  :mod:`polarstripe.imaging.triangulation`) against :func:`polarstripe.sim.depth_truth.depth_truth`:
  ``depth_valid_fraction`` (of the pixels that see an object) and ``depth_rms_mm``; with ``sheets`` > 1 per
  frame (``stripe:I/N:xK``) each pixel's sheet told by the objects' depth range as the compositor tells it
  (:mod:`polarstripe.imaging.sheets`, the range :func:`polarstripe.planning.sheets.object_depth_range`);
* ``frames``: the frames the scan took (patterns × analyzer passes).

The analyzer is calibrated per separation as the polarizer node does it: frames of the flood at 0°, 45°,
90° and 135°, the least-backscatter angle over the object-free pixels
(:func:`polarstripe.imaging.polarization.least_backscatter_angle`).

Exposure (``exposure``): ``scene`` keeps the camera's exposure time (what the planner's default assumes);
``rig`` shortens it, for every method alike, until the flood's 99.5th percentile is at 85 % of full scale (the
simulator node's rule); ``method`` sets each method's own, its brightest frame at 90 % (``polarstripe
compare``'s rule). A camera at a lower ``width`` than the scene's keeps the exposure per unit of pixel solid
angle (exposure × (w / w_scene)²), so each pixel collects the electrons, and has the noise, of the scene's.

The regret of a plan (:mod:`polarstripe.planning.validate_table`) compares these curves at the planner's pick
with their best.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from polarstripe.imaging.compose import compose, score
from polarstripe.imaging.composite import RunningComposite
from polarstripe.imaging.delineation import NoiseModel, RunningArgmax, SheetVotes, delineate
from polarstripe.imaging.p_map import P_RULES
from polarstripe.imaging.polarization import least_backscatter_angle
from polarstripe.imaging.sheets import assign_positions, check_sheets, epipolar_span
from polarstripe.imaging.triangulation import RigGeometry, camera_rays, depth_from_columns, stripe_edges
from polarstripe.imaging.validation import ImagingError
from polarstripe.msgs.patterns import stripes as stripe_frames
from polarstripe.planning.medium_p import scene_p_model
from polarstripe.planning.sheets import object_depth_range
from polarstripe.sim import sensor
from polarstripe.sim.depth_truth import depth_truth, rig_geometry
from polarstripe.sim.polarization import analyzer
from polarstripe.sim.render import render_components, render_each, resolve_fidelity
from polarstripe.sim.scene import Scene, SceneError, with_separation
from polarstripe.sim.truth import unscattered_object

METHODS = ("flood", "polarized_flood", "stripes", "polarized_stripes")
EXPOSURES = ("scene", "rig", "method")
CALIBRATION_DEG = (0.0, 45.0, 90.0, 135.0)
RIG_FILL, RIG_PERCENTILE, METHOD_FILL = 0.85, 99.5, 0.9


@dataclass(frozen=True)
class ScanSettings:
    """How the scans are made: model ``fidelity`` and ``orders`` (``all``, ``single``), stripes per scan,
    camera ``width`` (None: the scene's), the ``exposure`` rule (module docstring), the noise ``seed``, the
    light ``sheets`` per stripe frame, and eq. 6's ``p_rule`` (the compositor's: ``map``, its default,
    ``median`` or ``upper``)."""

    fidelity: str = "standard"
    orders: str = "all"
    n_stripes: int = 30
    width: int | None = 160
    exposure: str = "scene"
    seed: int = 1
    sheets: int = 1
    p_rule: str = "map"

    def check(self) -> None:
        resolve_fidelity(self.fidelity)
        if self.p_rule not in P_RULES:
            raise SceneError(f"p_rule must be one of {', '.join(P_RULES)}, got {self.p_rule!r}")
        if self.orders not in ("all", "single"):
            raise SceneError(f"orders must be 'all' or 'single', got {self.orders!r}")
        if self.exposure not in EXPOSURES:
            raise SceneError(f"exposure must be one of {', '.join(EXPOSURES)}, got {self.exposure!r}")
        if isinstance(self.n_stripes, bool) or int(self.n_stripes) != self.n_stripes or self.n_stripes < 2:
            raise SceneError(f"stripes must be an integer >= 2, got {self.n_stripes!r}")
        if self.width is not None and not 16 <= int(self.width):
            raise SceneError(f"width must be >= 16 pixels, got {self.width!r}")
        if isinstance(self.sheets, bool) or int(self.sheets) != self.sheets or not 1 <= self.sheets <= \
                self.n_stripes:
            raise SceneError(f"sheets must be an integer 1..stripes ({self.n_stripes}), got {self.sheets!r}")


def scan_scene(scene: Scene, width: int | None) -> Scene:
    """``scene`` with its camera ``width`` pixels wide (same aspect, at least 12 high) and the exposure scaled
    by the pixel's solid angle (w / w_scene)², so a pixel collects what the scene's does."""
    if width is None or int(width) == scene.camera.resolution[0]:
        return scene
    w0, h0 = scene.camera.resolution
    w = int(width)
    h = max(12, round(w * h0 / w0))
    cam = scene.camera.replace(resolution=(w, h), exposure_s=scene.camera.exposure_s * (w / w0) ** 2)
    return scene.replace(camera=cam)


class _Sensor:
    """The camera at one exposure: expose radiance frames, with its dark offset and saturation [DN]."""

    def __init__(self, camera, scale: float, rng: np.random.Generator):
        self.camera = camera.replace(exposure_s=camera.exposure_s * scale)
        self.e_map = sensor.electrons_per_radiance(self.camera)
        self.offset = sensor.dark_offset_dn(self.camera)
        self.saturation = sensor.full_scale_dn(self.camera)
        self.rng = rng

    def expose(self, radiance: np.ndarray) -> np.ndarray:
        return sensor.expose(radiance, self.camera, self.rng, electrons=self.e_map)

    def noise(self) -> NoiseModel:
        c = self.camera
        return NoiseModel(dark_dn=self.offset, read_noise_dn=c.read_noise_e / c.gain_e_per_dn,
                          dn_per_electron=1.0 / c.gain_e_per_dn, saturation_dn=self.saturation)


def _span_e(camera) -> float:
    """Electrons above the dark level at which a pixel saturates (ADC or full well, the smaller)."""
    dark_e = camera.dark_current_e_s * camera.exposure_s
    return min(camera.full_well_e,
               (sensor.full_scale_dn(camera) - camera.offset_dn) * camera.gain_e_per_dn - dark_e)


def _scale(rule: str, camera, frames: list[np.ndarray], flood: np.ndarray) -> float:
    """Exposure multiplier of ``rule`` (module docstring) for a method whose radiance ``frames`` these are."""
    if rule == "scene":
        return 1.0
    e_map = sensor.electrons_per_radiance(camera)
    if rule == "rig":
        peak = float(np.percentile(flood * e_map, RIG_PERCENTILE))
        return min(1.0, RIG_FILL * _span_e(camera) / peak) if peak > 0 else 1.0
    brightest = max(float(np.max(f * e_map)) for f in frames)
    return METHOD_FILL * _span_e(camera) / brightest if brightest > 0 else 1.0


def _calibrate(flood, camera, scale, rng, background) -> tuple[tuple[float, float], str]:
    """((crossed, parallel) analyzer angles [deg], note) from four flood frames, as the polarizer node
    calibrates; 0° and 90° when the light shows no polarization (clear water), the note says so."""
    cam = _Sensor(camera, scale, rng)
    frames = [cam.expose(analyzer(flood, a)) for a in CALIBRATION_DEG]
    try:
        crossed = least_backscatter_angle(CALIBRATION_DEG, frames, background, dark_offset=cam.offset,
                                          saturation=cam.saturation)
    except ImagingError as exc:
        return (0.0, 90.0), f"analyzer not calibrated ({exc}): 0° and 90°"
    return (crossed, (crossed + 90.0) % 180.0), ""


def _depth(votes, geom: RigGeometry, noise: NoiseModel, n_stripes: int, truth: np.ndarray, sheets: int = 1,
           near_far=None) -> dict:
    if sheets > 1:      # each pixel's sheet of its brightest frame, as the compositor tells it
        h, w = truth.shape
        lo, hi = epipolar_span(geom, camera_rays(geom, *np.mgrid[0:h, 0:w]), near_far)
        check_sheets(n_stripes, sheets, geom.proj_size[0], lo, hi, near_far)
        index = assign_positions(votes.index, n_stripes, sheets, geom.proj_size[0], lo, hi)
        votes = SheetVotes(votes.best, votes.second, index, votes.n_frames)
    columns = delineate(votes, stripe_edges(n_stripes, geom.proj_size[0]), noise)
    z = depth_from_columns(geom, columns)
    both = np.isfinite(z) & np.isfinite(truth)
    err = (z - truth)[both]
    return {"depth_valid_fraction": float(both.sum() / max(1, np.isfinite(truth).sum())),
            "depth_rms_mm": float(1e3 * np.sqrt(np.mean(err ** 2))) if err.size else None}


def _scored(image, truth, bright, dark) -> tuple[float | None, float | None]:
    s = score(image, bright=bright, dark=dark, truth=truth)
    return s["error_vs_truth"], s["contrast"]


def _ordered(pair, region) -> tuple[np.ndarray, np.ndarray]:
    """(E_b, E_w) raw of an analyzer pair: E_b the frame passing less light over ``region``, as compose
    orders it."""
    a, b = (np.asarray(np.ma.getdata(x), np.float64) for x in pair)
    use = np.ones(a.shape, bool) if region is None else region
    return (b, a) if np.median(a[use]) > np.median(b[use]) else (a, b)


def _flood_pair(flood, angles, settings: ScanSettings, cam0, flood_e, region):
    """The polarized flood's pair at this pose, exposed as its own scan exposes it (its noise stream):
    ((E_b, E_w) raw, dark, saturation)."""
    frames = [analyzer(flood, a) for a in angles]
    scale = _scale(settings.exposure, cam0, frames, flood_e)
    cam = _Sensor(cam0, scale, np.random.default_rng([settings.seed, METHODS.index("polarized_flood")]))
    return _ordered([cam.expose(f) for f in frames], region), cam.offset, cam.saturation


def score_scans(scene: Scene, separation_m: float, settings: ScanSettings | None = None,
                methods=METHODS) -> dict[str, dict]:
    """Each method's scan at camera–source separation ``separation_m`` [m], composed and scored (module
    docstring). ``scene`` is taken as given (its camera already at the scan's width: :func:`scan_scene`).
    Each method's noise comes from its own stream of ``settings.seed``: a row does not depend on which
    other methods were scanned with it.

    Returns
    -------
    {method: {"separation_m", "error", "contrast", "saturated_fraction", "exposure_scale", ...}}; polarized
    methods add ``p``, ``error_e_b``, ``contrast_e_b``, ``analyzer_deg``; stripe methods
    ``depth_valid_fraction``, ``depth_rms_mm``. A measure that cannot be taken is None and ``note`` says why.
    """
    for m in methods:
        if m not in METHODS:
            raise SceneError(f"method must be one of {', '.join(METHODS)}, got {m!r}")
    settings = settings or ScanSettings()
    sd = with_separation(scene, float(separation_m), aim=True)
    fid, orders, n = settings.fidelity, settings.orders, int(settings.n_stripes)
    k_sheets = int(settings.sheets)
    flood = render_components(sd, "flood", fid, orders=orders)
    stripes = []
    if any("stripes" in m for m in methods):
        stripes = render_each(sd, list(stripe_frames(n, k_sheets)), fid, orders=orders)
    truth, surf = unscattered_object(sd)
    background = surf.object_id < 0
    background = background if background.any() else None
    chart = surf.chart_band >= 0
    bright, dark = chart & surf.chart_high, chart & ~surf.chart_high
    if not (bright.any() and dark.any()):
        bright = dark = None
    cam0 = sd.camera
    flood_e = analyzer(flood, None)
    angles, calibration_note = None, ""
    if any(m.startswith("polarized") for m in methods):
        scale = _scale(settings.exposure, cam0, [flood_e], flood_e)
        rng = np.random.default_rng([settings.seed, len(METHODS)])
        angles, calibration_note = _calibrate(flood, cam0, scale, rng, background)
    depth_z = depth_truth(sd) if stripes else None
    geom = RigGeometry.from_dict(rig_geometry(sd)) if stripes and sd.projector.model == "pinhole" else None
    out = {}
    renders: dict = {}   # the p map's model render, shared by the pose's polarized methods
    flood_pair = None    # the polarized flood's ((E_b, E_w) raw, dark, saturation): κ and ψ are fitted to it
    for method in methods:
        comps = [flood] if "flood" in method else stripes
        passes = [[analyzer(c, a) for c in comps] for a in (angles if method.startswith("polarized")
                                                             else (None,))]
        scale = _scale(settings.exposure, cam0, [f for p in passes for f in p], flood_e)
        cam = _Sensor(cam0, scale, np.random.default_rng([settings.seed, METHODS.index(method)]))
        shape = flood_e.shape
        views, votes = {}, RunningArgmax(shape, np.uint16) if "stripes" in method else None
        for k, radiances in enumerate(passes):
            rc = RunningComposite(shape, np.uint16, saturation=cam.saturation)
            for i, r in enumerate(radiances):
                frame = cam.expose(r)
                rc.add(frame)
                if votes is not None:
                    votes.add(frame, i, float(k))
            views[float(k)] = rc.result()
        p_model = None
        if method.startswith("polarized") and settings.p_rule == "map":
            if method == "polarized_stripes" and flood_pair is None:
                flood_pair = _flood_pair(flood, angles, settings, cam0, flood_e, background)
            p_model = scene_p_model(sd, background, cam.offset, cam.saturation, renders=renders,
                                    flood=flood_pair if method == "polarized_stripes" else None)
        made = compose(method, views, dark_offset=cam.offset, saturation=cam.saturation,
                       object_free=background, p_rule=settings.p_rule, p_model=p_model)
        if method == "polarized_flood":
            flood_pair = (_ordered([views[0.0].maximum, views[1.0].maximum], background), cam.offset,
                          cam.saturation)
        truth_dn = truth * cam.e_map / cam.camera.gain_e_per_dn  # DN above the offset, never clipped
        row = {"separation_m": float(separation_m), "exposure_scale": scale,
               "saturated_fraction": made.saturated_pixels / made.image.size,
               "frames": sum(len(p) for p in passes)}
        row["error"], row["contrast"] = _scored(made.image, truth_dn, bright, dark)
        notes = [made.note]
        if method.startswith("polarized"):
            notes.append(calibration_note)
            row["p"], row["analyzer_deg"] = made.p, angles[0]
            row["error_e_b"], row["contrast_e_b"] = _scored(made.layers["e_b"], truth_dn, bright, dark)
        if votes is not None and geom is not None:
            crossed = 0.0
            if len(passes) == 2:  # E_b: the view passing less light over the object-free region, as compose
                region = background if background is not None else np.ones(shape, bool)
                crossed = min((0.0, 1.0), key=lambda a: float(np.median(votes.result(a).best[region])))
            try:
                row.update(_depth(votes.result(crossed), geom, cam.noise(), n, depth_z, k_sheets,
                                  object_depth_range(sd) if k_sheets > 1 else None))
            except ImagingError as exc:
                row.update(depth_valid_fraction=None, depth_rms_mm=None)
                notes.append(f"no depth: {exc}")
        if any(notes):
            row["note"] = "; ".join(n for n in notes if n)
        out[method] = row
    return out


def curves(scene: Scene, separations_m, settings: ScanSettings | None = None, methods=METHODS,
           progress=None) -> dict[str, list[dict]]:
    """:func:`score_scans` at each separation [m] (the camera at ``settings.width``): {method: [row, …]}
    in the order of ``separations_m``; ``progress()`` is called after each separation."""
    settings = settings or ScanSettings()
    settings.check()
    seps = [float(d) for d in separations_m]
    if not seps or any(not (math.isfinite(d) and d > 0) for d in seps):
        raise SceneError("separations: need positive separations [m]")
    sc = scan_scene(scene, settings.width)
    out: dict[str, list[dict]] = {m: [] for m in methods}
    for d in seps:
        for m, row in score_scans(sc, d, settings, methods).items():
            out[m].append(row)
        if progress is not None:
            progress()
    return out
