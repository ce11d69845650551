"""``polarstripe compare``: the paper's comparison of imaging methods (its §2 and Fig. 6), reproduced.

The default tank is rendered at a moderate and a heavy scattering level with every method: flood, polarized
flood (eq. 6), light striping (eq. 7), polarized light striping (eq. 7 per analyzer angle, then eq. 6) and
high-frequency direct/global separation at two checker sizes. Each method's frames go through the analyzer
and the EMVA 1288 sensor (its own exposure: the longest that keeps its brightest frame at 90 % of
saturation, as the paper lengthened the exposure for the dim stripes), then through the pipeline a rig
would run (calibrate the analyzer, then :func:`polarstripe.imaging.compose.compose`, the compositor node's
own pipeline: reduce, estimate p on object-free pixels, recover, separate). The table gives
the Michelson contrast of the chart's bars and the error of each estimate against the ground truth, the
unscattered object radiance T (:func:`polarstripe.sim.truth.unscattered_radiance`, docs/physics.md §10.8:
what the chart would look like if the medium only attenuated the light), gain fitted; and, for comparison,
against the object light S = D + A the water delivers (the truth before all orders: blurred and dimmed under
all orders). One figure shows the images side by side like Fig. 6, each with its contrast and error.
"""

from __future__ import annotations

import argparse
import json
import time

import matplotlib
import matplotlib.pyplot as plt
import numpy as np
from polarstripe.imaging.compose import Composition, compose, score
from polarstripe.imaging.composite import RunningComposite
from polarstripe.imaging.p_map import P_RULES
from polarstripe.imaging.polarization import least_backscatter_angle
from polarstripe.imaging.validation import ImagingError
from polarstripe.msgs.methods import Method
from polarstripe.planning.medium_p import scene_p_model
from polarstripe.sim import sensor
from polarstripe.sim.polarization import analyzer
from polarstripe.sim.render import render_components, render_each
from polarstripe.sim.scene import load_scene, parse_size
from polarstripe.sim.truth import unscattered_radiance

HELP = "reproduce the paper's comparison of imaging methods (contrast and error vs ground truth, Fig. 6)"
TRUTH = "ground truth (unscattered)"
OBJECT_LIGHT = "object light S = D + A"
FILL = 0.9  # brightest frame of a method at this fraction of saturation


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scene", nargs="?", default=None, help="scene TOML (default: the paper's tank)")
    parser.add_argument("--resolution", default="160x120", help="camera resolution WxH (default 160x120)")
    parser.add_argument("--stripes", type=int, default=30, help="stripes per scan (default 30)")
    parser.add_argument("--fidelity", default="preview", help="model fidelity (default preview)")
    parser.add_argument("--orders", choices=("all", "single"), default="all",
                        help="orders of scattering: all (default: those the scene needs, sim/orders.py, as "
                             "the simulator renders) or the paper's single scattering; the truth is the "
                             "unscattered object radiance either way")
    parser.add_argument("--sigma-t", nargs="+", type=float, default=(5.0, 12.0), metavar="SIGMA_T",
                        help="extinction coefficients [1/m] of the scattering levels (default 5 12)")
    parser.add_argument("--checkers", nargs=2, type=int, default=(10, 20), metavar=("SMALL", "LARGE"),
                        help="checker sizes in projector pixels (default 10 20, as the paper)")
    parser.add_argument("--seed", type=int, default=1, help="sensor noise seed")
    parser.add_argument("--p-rule", choices=P_RULES, default="map",
                        help="eq. 6's p (docs/physics.md §4.2): map (default, the compositor's: per pixel "
                        "from the scene's medium model, fitted to the polarized flood pair), median or upper "
                        "(one p-hat from the frames)")
    parser.add_argument("--figure", default="compare.png", help="side-by-side figure (PNG); '' for none")
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of the table")


def _resolution(text: str) -> tuple[int, int]:

    w, h = parse_size(text, "--resolution")
    if w < 16 or h < 12:
        raise ImagingError(f"--resolution: {w}x{h} is too small to resolve the chart (min 16x12)")
    return w, h


class _Camera:
    """Exposes radiance frames for one method at one exposure and converts DN back to radiance."""

    def __init__(self, camera, radiances: list[np.ndarray], rng: np.random.Generator):

        self.sensor = sensor
        e_per_l = sensor.electrons_per_radiance(camera)
        brightest = max(float(np.max(r * e_per_l)) for r in radiances)
        sat_e = min(camera.full_well_e,
                    (sensor.full_scale_dn(camera) - camera.offset_dn) * camera.gain_e_per_dn)
        scale = FILL * sat_e / brightest if brightest > 0 else 1.0
        self.camera = camera.replace(exposure_s=camera.exposure_s * scale)
        self.dn_per_radiance = sensor.electrons_per_radiance(self.camera) / self.camera.gain_e_per_dn
        self.offset = sensor.dark_offset_dn(self.camera)
        self.saturation = sensor.full_scale_dn(self.camera)
        self.rng = rng

    def expose(self, radiance: np.ndarray) -> np.ndarray:
        return self.sensor.expose(radiance, self.camera, self.rng)

    def compose(self, method: str, passes: list[list[np.ndarray]], background, black_level: float = 0.0,
                p_rule: str = "median", p_model=None) -> Composition:
        """Expose each pass (the radiances at one analyzer angle, in order), reduce it (max and min per
        pixel, as the compositor does) and compose ``method`` (eq. 6 by ``p_rule``; ``p_model(dark,
        saturation)`` makes the map's model for this exposure); DN above the dark offset."""
        views = {}
        for k, radiances in enumerate(passes):
            rc = RunningComposite(radiances[0].shape, np.uint16, saturation=self.saturation)
            for r in radiances:
                rc.add(self.expose(r))
            views[float(k)] = rc.result()
        made = compose(method, views, dark_offset=self.offset, saturation=self.saturation,
                       object_free=background, black_level=black_level, p_rule=p_rule,
                       p_model=None if p_model is None else p_model(self.offset, self.saturation))
        self.pair = (views[0.0].maximum, views[1.0].maximum) if len(views) == 2 else None
        if Method(method).polarized and made.p is None:
            raise ImagingError(f"{method}: {made.note}")
        return made

    def to_radiance(self, dn) -> np.ndarray:
        """DN above the dark offset (masked where saturated) in radiance units."""
        return dn / self.dn_per_radiance


def run_level(scene, sigma_t: float, n_stripes: int, checkers, fidelity: str, rng,
              orders: str = "all", p_rule: str = "map") -> dict:
    """All methods at one scattering level; returns images (radiance estimates) and their scores. Eq. 6's p
    by ``p_rule``: ``map`` as the compositor's default makes it, from the scene's own medium model, κ and ψ
    fitted to the polarized flood pair (:func:`~polarstripe.planning.medium_p.scene_p_model`)."""

    scene = scene.replace(medium=scene.medium.replace(sigma_t=sigma_t))
    t0 = time.perf_counter()
    flood = render_components(scene, "flood", fidelity, orders=orders)
    stripes = render_each(scene, [f"stripe:{k}/{n_stripes}" for k in range(n_stripes)], fidelity,
                          orders=orders)
    checker = {c: render_components(scene, f"checker:{c}:0", fidelity, orders=orders) for c in checkers}
    model_s = time.perf_counter() - t0
    surf = flood.surface
    truth = unscattered_radiance(scene)  # docs/physics.md §10.8; S = D + A is what the water delivers
    background = surf.object_id < 0
    if not background.any():
        background = None
    chart = surf.chart_band >= 0
    band0 = surf.chart_band == 0  # the highest-contrast band of bars (true Michelson contrast 0.82)
    bright, dark = band0 & surf.chart_high, band0 & ~surf.chart_high
    est: dict[str, np.ndarray] = {}
    extra: dict[str, dict] = {}

    # calibration: analyzer sweep of the flood-lit tank, least-backscatter angle on object-free pixels
    sweep = [analyzer(flood, a) for a in (0.0, 45.0, 90.0, 135.0)]
    cam = _Camera(scene.camera, sweep, rng)
    frames = [cam.expose(r) for r in sweep]
    ang_b = least_backscatter_angle([0.0, 45.0, 90.0, 135.0], frames, background, dark_offset=cam.offset,
                                    saturation=cam.saturation)
    ang_w = (ang_b + 90.0) % 180.0

    plain = [analyzer(flood, None)]
    cam = _Camera(scene.camera, plain, rng)
    est["flood"] = cam.to_radiance(cam.compose("flood", [plain], background).image)

    renders: dict = {}   # the map's model render, shared by both polarized methods

    def model(flood_pair=None):
        if p_rule != "map":
            return None
        return lambda dark, sat: scene_p_model(scene, background, dark, sat, flood=flood_pair,
                                               renders=renders)

    pair = [analyzer(flood, ang_b), analyzer(flood, ang_w)]
    cam = _Camera(scene.camera, pair, rng)
    made = cam.compose("polarized_flood", [pair[:1], pair[1:]], background, p_rule=p_rule, p_model=model())
    est["polarized flood"], p_flood = cam.to_radiance(made.image), made.p
    flood_pair = (tuple(np.asarray(np.ma.getdata(x), np.float64) for x in cam.pair), cam.offset,
                  cam.saturation)  # E_b first: ang_b is the calibrated crossed angle

    plain = [analyzer(s, None) for s in stripes]
    cam = _Camera(scene.camera, plain, rng)
    est["light striping"] = cam.to_radiance(cam.compose("stripes", [plain], background).image)

    rb, rw = [analyzer(s, ang_b) for s in stripes], [analyzer(s, ang_w) for s in stripes]
    cam = _Camera(scene.camera, rb + rw, rng)
    made = cam.compose("polarized_stripes", [rb, rw], background, p_rule=p_rule, p_model=model(flood_pair))
    est["polarized striping (E_b only)"] = 2.0 * cam.to_radiance(made.layers["e_b"])
    est["polarized striping (eq. 6)"], p_stripes = cam.to_radiance(made.image), made.p

    black = scene.projector.black_level
    for c, comp in checker.items():
        shifted = flood.combine(comp, 1.0, -1.0)  # checker:c:c, the complement, by linearity
        pats = [analyzer(comp, None), analyzer(shifted, None)]
        cam = _Camera(scene.camera, pats, rng)
        made = cam.compose("hf_separation", [pats], background, black)
        est[f"high-frequency {c}px (direct)"] = cam.to_radiance(made.image)
        extra[f"high-frequency {c}px (direct)"] = {"global": cam.to_radiance(made.layers["global"])}

    ests = {TRUTH: truth, OBJECT_LIGHT: flood.S, **est}
    rows = {name: _scores(img, truth, flood.S, bright, dark, chart) for name, img in ests.items()}
    return {"sigma_t": sigma_t, "optical_thickness": sigma_t * (scene.medium.extent.max[2] -
                                                                 scene.medium.extent.min[2]),
            "analyzer_deg": {"crossed": ang_b, "parallel": ang_w},
            "p_estimate": {"flood": p_flood, "stripes": p_stripes}, "model_seconds": model_s,
            "rows": rows, "images": ests, "chart": chart}


def _scores(image, truth, object_light, bright, dark, chart) -> dict:
    """Contrast of the bars; the gain-fitted error over ``chart`` against the unscattered ``truth`` (the
    score) and against the water's ``object_light`` S = D + A (:func:`score`). The gain is fitted because T
    holds only the unscattered light while every estimate holds the light that reached the object by every
    path (docs/physics.md §10.8)."""
    vs_t = score(image, bright=bright, dark=dark, truth=truth, region=chart, fit_gain=True)
    vs_s = score(image, truth=object_light, region=chart, fit_gain=True)
    for s in (vs_t, vs_s):
        if "metrics_error" in s:
            raise ImagingError(s["metrics_error"])
    return {"contrast": vs_t["contrast"], "error": vs_t["error_vs_truth"],
            "error_vs_S": vs_s["error_vs_truth"]}


def _figure(levels: list[dict], path: str) -> None:

    matplotlib.use("Agg")

    names = list(levels[0]["images"])
    fig, axes = plt.subplots(len(levels), len(names), figsize=(2.1 * len(names), 1.9 * len(levels) + 0.4),
                             squeeze=False)
    for row, lev in zip(axes, levels, strict=True):
        for ax, name in zip(row, names, strict=True):
            img = np.ma.asarray(lev["images"][name], dtype=np.float64)
            vals = img[lev["chart"]].compressed() if np.ma.isMaskedArray(img[lev["chart"]]) else \
                np.asarray(img[lev["chart"]]).ravel()
            lo, hi = np.percentile(vals, [1, 99]) if vals.size else (0.0, 1.0)
            ax.imshow(np.clip(img.filled(hi), lo, hi), cmap="gray", vmin=lo, vmax=hi if hi > lo else lo + 1)
            ax.set_xticks([])
            ax.set_yticks([])
            r = lev["rows"][name]
            ax.set_title(f"{name}\nC = {r['contrast']:.2f}   err = {r['error']:.2f}", fontsize=6)
        row[0].set_ylabel(f"σt = {lev['sigma_t']:g} /m", fontsize=7)
    fig.suptitle("polarstripe compare (cf. the paper's Fig. 6): C = Michelson contrast of the chart's bars, "
                 "err = relative RMS error vs the unscattered object (gain fitted);\n"
                 "each image stretched to its chart's 1-99 %", fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def main(args: argparse.Namespace) -> int:

    w, h = _resolution(args.resolution)
    if args.stripes < 1 or min(args.checkers) < 1:
        raise ImagingError(f"--stripes {args.stripes} and --checkers {args.checkers} must be >= 1")
    scene = load_scene(args.scene)
    scene = scene.replace(camera=scene.camera.replace(resolution=(w, h)))
    rng = np.random.default_rng(args.seed)
    levels = [run_level(scene, s, args.stripes, args.checkers, args.fidelity, rng, args.orders, args.p_rule)
              for s in args.sigma_t]
    if args.figure:
        _figure(levels, args.figure)
    if args.json:
        out = [{k: v for k, v in lev.items() if k not in ("images", "chart")} for lev in levels]
        print(json.dumps({"resolution": [w, h], "stripes": args.stripes, "levels": out}))
        return 0
    for lev in levels:
        print(f"σt = {lev['sigma_t']:g} /m (optical thickness "
              f"{lev['optical_thickness']:.2f} to the chart), analyzer crossed at "
              f"{lev['analyzer_deg']['crossed']:.1f}°, p̂ = "
              f"{lev['p_estimate']['flood']:.3f} (flood), {lev['p_estimate']['stripes']:.3f} (stripes); "
              f"model {lev['model_seconds']:.1f} s")
        print(f"  {'method':<32} {'contrast':>9} {'error':>8} {'error vs S = D + A':>19}")
        for name, r in lev["rows"].items():
            print(f"  {name:<32} {r['contrast']:9.3f} {r['error']:8.3f} {r['error_vs_S']:19.3f}")
    print("error: relative RMS over the chart against the unscattered object radiance, gain fitted "
          "(docs/physics.md §10.8)")
    if args.figure:
        print(f"figure written to {args.figure}")
    return 0
