"""``polarstripe bench motion``: what speed each mode tolerates — the composite's loss with the rig's speed.

The rig moves at a constant velocity during each scan (sim/motion.py: frame i at its capture time, i/fps plus
the analyzer stage's moves; the rig passes the scene's pose, where the truth is taken, mid-scan), along the
baseline (x) or across it (y). For each speed the scans run as the simulated rig runs them, frame by frame,
with the simulator node's own pieces (its model resolution, auto exposure, sensor with its preview noise,
micro-polarizer mosaic, ground truth: nodes/simulator_frames.py) and the compositor's (the running reductions,
the mosaic views, its medium model for eq. 6's p by ``--p-rule`` (``map``, its default: fitted to the same
rig's polarized flood taken just before each polarized stripe scan, moving alike, as the demo's sequence
takes them; nodes/compositor_p.py), :func:`~polarstripe.imaging.compose.compose`, the score against T over
the frame, gain fitted, and the chart's bars for the contrast, as nodes/compositor_scan.py scores a scan):

* rotating analyzer: polarized flood (2 frames and one stage move) and polarized stripes (2N frames and one
  move), E_b found from four flood frames at rest (the polarizer node's calibration);
* polarization camera: polarized flood (1 frame) and polarized stripes (N frames), the ``local`` rule;
* stripes with K sheets per frame (``stripe:I/N:xK``, ⌈N/K⌉ frames, no analyzer): K = 1, 3 and 5; and the
  polarized stripes with 3 sheets by the rotating analyzer (2⌈N/3⌉ frames and one move) and by the
  polarization camera (⌈N/3⌉ frames).

Frame i of a scan draws its sensor noise from the seed and i alone, the same at every speed, so a row's change
with speed is the motion's, not the noise's. The last column gives, per mode and direction, the speed at
which the error against T grows by 10 % over the rig at rest (linear between the speeds measured); the JSON
also has p̂, the scans' notes (e.g. where the map fell back to the frames' own) and, for the polarized
methods, the error of E_b alone (no eq. 6). docs/planning.md §11 has the table and what it says.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np
from polarstripe.imaging.compose import compose, score
from polarstripe.imaging.composite import RunningComposite
from polarstripe.imaging.p_map import P_RULES
from polarstripe.imaging.polarization import least_backscatter_angle
from polarstripe.imaging.validation import ImagingError
from polarstripe.msgs import Frame, Method
from polarstripe.nodes.compositor import Compositor
from polarstripe.nodes.compositor_mosaic import MosaicViews
from polarstripe.nodes.compositor_p import MediumModel
from polarstripe.nodes.simulator import Simulator
from polarstripe.nodes.simulator_frames import (
    PREVIEW_WIDTH,
    exposure_factor,
    micro_polarizers,
    model_scene,
    to_camera,
    truth_composite,
)
from polarstripe.sim.mosaic import linear_stokes, mosaic_radiance
from polarstripe.sim.motion import RigMotion
from polarstripe.sim.polarization import analyzer
from polarstripe.sim.render import render_components, resolve_fidelity
from polarstripe.sim.scene import load_scene, parse_size
from polarstripe.sim.sensor import dark_offset_dn, electrons_per_radiance, expose, full_scale_dn

DIRECTIONS = {"along": (1.0, 0.0, 0.0), "across": (0.0, 1.0, 0.0), "forward": (0.0, 0.0, 1.0)}
#: (mode, method, sheets per stripe frame): the rows of the table
SCANS = (("rotating analyzer", "polarized_flood", 1), ("rotating analyzer", "polarized_stripes", 1),
         ("polarization camera", "polarized_flood", 1), ("polarization camera", "polarized_stripes", 1),
         ("stripes, K = 1 sheet", "stripes", 1), ("stripes, K = 3 sheets", "stripes", 3),
         ("stripes, K = 5 sheets", "stripes", 5), ("rotating analyzer, K = 3 sheets", "polarized_stripes", 3),
         ("polarization camera, K = 3 sheets", "polarized_stripes", 3))
GROWTH = 0.10  # the error growth the last table reports the speed of
P_MIN = Compositor.Params().p_min
SPEEDS = (0.0, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5)  # [m/s]


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--speeds", nargs="+", type=float, default=SPEEDS, metavar="M_S",
                        help="rig speeds [m/s] (default " + " ".join(f"{s:g}" for s in SPEEDS) + ")")
    parser.add_argument("--directions", nargs="+", choices=tuple(DIRECTIONS), default=("along", "across"),
                        help="rig frame: along the baseline, across it, forward (default along across)")
    parser.add_argument("--scene", default=None, help="scene TOML (default: the paper's tank)")
    parser.add_argument("--resolution", default="160x120", help="camera WxH, even (default 160x120)")
    parser.add_argument("--stripes", type=int, default=30, help="stripes per scan (default 30)")
    parser.add_argument("--fidelity", default="preview", help="model fidelity (default preview)")
    parser.add_argument("--fps", type=float, default=30.0, help="camera frame rate [1/s] (default 30)")
    parser.add_argument("--seed", type=int, default=1, help="sensor noise seed")
    parser.add_argument("--p-rule", choices=P_RULES, default="map",
                        help="eq. 6's p: map (the compositor's default: the medium model's, fitted to the "
                             "polarized flood pair taken just before, moving alike), median or upper (one p̂)")
    parser.add_argument("--only", nargs="+", type=int, default=None, metavar="ROW",
                        help=f"only these rows of the table (0-{len(SCANS) - 1}: " + ", ".join(
                            f"{i} {m} {k}" for i, (m, k, _) in enumerate(SCANS)) + ")")


class Rig:
    """The simulated rig at rest: the simulator node's scene, exposure, sensor and mosaic, the compositor's
    mosaic views, E_b, and the truth at the scene's pose."""

    def __init__(self, args):
        sim = Simulator.Params(resolution=args.resolution, fidelity=args.fidelity, seed=args.seed,
                               fps=args.fps)
        w, h = parse_size(args.resolution, "--resolution")
        if w % 2 or h % 2:
            raise ImagingError(f"--resolution {args.resolution}: the 2x2 mosaic needs an even size")
        base = load_scene(args.scene)
        base = base.replace(camera=base.camera.resized((w, h)))
        self.fidelity = resolve_fidelity(args.fidelity)
        self.scale = max(1, w // PREVIEW_WIDTH) if self.fidelity.name == "preview" else 1
        self.size, self.seed, self.stripes = (w, h), args.seed, args.stripes
        self.stage = (sim.drive_speed_counts_s / sim.counts_per_deg, sim.drive_settle_s)
        flood = self.render(base, "flood")
        e_map = electrons_per_radiance(base.camera)
        factor = exposure_factor(to_camera(flood.D + flood.A + flood.B, (w, h)), e_map, base.camera)
        self.scene = base.replace(camera=base.camera.replace(exposure_s=base.camera.exposure_s * factor))
        self.e_map = e_map * factor
        self.mosaic = micro_polarizers(sim)
        compositor = Compositor.Params(p_rule=args.p_rule, p_scene=args.scene or "")
        self.views, self.medium = MosaicViews(compositor), MediumModel(compositor)
        cam = self.scene.camera
        self.dark, self.saturation = dark_offset_dn(cam), full_scale_dn(cam)
        self.truth = truth_composite(self.scene)
        sweep = [self.expose(to_camera(analyzer(flood, a), (w, h)), 100 + k)
                 for k, a in enumerate((0.0, 45.0, 90.0, 135.0))]
        self.free = self.truth.images["S"] <= 1e-9
        self.e_b = least_backscatter_angle((0.0, 45.0, 90.0, 135.0), sweep, self.free,
                                           dark_offset=self.dark, saturation=self.saturation)

    def render(self, scene, pattern):
        return render_components(model_scene(scene, pattern, self.scale), pattern, self.fidelity)

    def expose(self, radiance, i: int) -> np.ndarray:
        rng = np.random.default_rng([self.seed, i])
        return expose(radiance, self.scene.camera, rng, electrons=self.e_map,
                      gaussian=self.fidelity.name == "preview")

    def scan_after_flood(self, mode: str, method: str, motion: RigMotion, sheets: int = 1) -> dict:
        """:meth:`scan`; a polarized stripe scan after the same rig's polarized flood moving alike, as the
        demo's sequence takes them: the ``map`` rule fits the medium model to that flood pair
        (nodes/compositor_p.py)."""
        if method == "polarized_stripes" and self.medium.rule == "map":
            self.scan(mode, "polarized_flood", motion)
        return self.scan(mode, method, motion, sheets)

    def scan(self, mode: str, method: str, motion: RigMotion, sheets: int = 1) -> dict:
        """One scan of ``method`` by ``mode`` (``sheets`` per stripe frame) with the rig moving as ``motion``
        says: its scores."""
        m = Method(method)
        patterns = [str(p) for p in m.patterns(self.stripes, 1, min(sheets, self.stripes))]
        rotating = mode.startswith("rotating")
        angles = [self.e_b, self.e_b + 90.0] if rotating else []
        times = motion.times(len(patterns), angles)
        rc, cache = None, {}
        for i in range(len(times)):
            pattern, scene = patterns[i % len(patterns)], motion.scene_at(self.scene, times, i)
            key = (pattern, scene.camera.position)
            comp = cache[key] = cache.get(key) or self.render(scene, pattern)
            if mode.startswith("polarization"):
                raw = self.expose(mosaic_radiance(*(to_camera(x, self.size) for x in linear_stokes(comp)),
                                                  self.mosaic), i)
                frame = Frame(image=raw, exposure_s=self.scene.camera.exposure_s,
                              mosaic_deg=list(self.mosaic.layout))
                views = self.views.views(frame, m.polarized, self.saturation)
                sat = self.views.saturation
            else:
                angle = angles[i // len(patterns)] if angles else None
                views = {angle: self.expose(to_camera(analyzer(comp, angle), self.size), i)}
                sat = self.saturation
            for key, view in views.items():
                rc = rc or RunningComposite(view.shape, view.dtype, saturation=sat)
                rc.add(view, key)
        camera = mode.startswith("polarization")
        p_model = self.medium.p_model(method, self.truth, self.free, self.dark, rc.saturation, P_MIN,
                                      crossed=camera) if m.polarized else None
        made = compose(method, {a: rc.result(a) for a in rc.angles}, dark_offset=self.dark,
                       saturation=rc.saturation, object_free=self.free, p_rule=self.medium.rule,
                       p_model=p_model, p_min=P_MIN)
        band, high = self.truth.images["chart_band"], self.truth.images["chart_high"]
        s = score(made.image, bright=(band >= 0) & high, dark=(band >= 0) & ~high,
                  truth=self.truth.images["S"])
        e_b = made.layers.get("e_b")  # the crossed image alone, without eq. 6 (gain fitted like the rest)
        e_b = None if e_b is None else score(e_b, truth=self.truth.images["S"])["error_vs_truth"]
        return {"frames": len(times), "scan_s": float(times[-1]), "error": s["error_vs_truth"],
                "contrast": s["contrast"], "p": made.p, "note": made.note or s.get("metrics_error", ""),
                "error_e_b": e_b}


def tolerated_speed(speeds, errors, growth: float = GROWTH) -> float | None:
    """The speed at which ``errors`` (over ascending ``speeds``, the first 0) first reaches (1 + growth)
    times the error at rest, linear between the speeds measured; None when it never does."""
    limit = (1.0 + growth) * errors[0]
    for k in range(1, len(speeds)):
        if errors[k] >= limit:
            lo, hi = errors[k - 1], errors[k]
            return float(speeds[k - 1] + (speeds[k] - speeds[k - 1]) * (limit - lo) / (hi - lo))
    return None


def run(args) -> dict:
    speeds = sorted(set(float(s) for s in args.speeds) | {0.0})
    if speeds[0] < 0 or not all(np.isfinite(speeds)):
        raise ImagingError(f"--speeds {args.speeds}: speeds are >= 0 m/s (the direction gives the sign)")
    if args.stripes < 2:
        raise ImagingError(f"--stripes {args.stripes}: a stripe scan needs at least 2")
    started = time.process_time()
    rig = Rig(args)
    rows = []
    for index in args.only if args.only is not None else range(len(SCANS)):
        mode, method, sheets = SCANS[index]
        rest = rig.scan_after_flood(mode, method, RigMotion(fps=args.fps, stage_deg_s=rig.stage[0],
                                                            stage_settle_s=rig.stage[1]), sheets)
        row = {"mode": mode, "method": method, "sheets": sheets, "frames": rest["frames"],
               "scan_s": rest["scan_s"], "directions": {}}
        for name in args.directions:
            results = [rest] + [rig.scan_after_flood(mode, method, RigMotion(
                tuple(s * c for c in DIRECTIONS[name]), args.fps, *rig.stage), sheets) for s in speeds[1:]]
            errors = [r["error"] for r in results]
            row["directions"][name] = {
                "error": errors, "contrast": [r["contrast"] for r in results], "p": [r["p"] for r in results],
                "error_e_b": [r["error_e_b"] for r in results],
                "notes": sorted({r["note"] for r in results if r["note"]}),
                "tolerated_m_s": None if None in errors else tolerated_speed(speeds, errors)}
            if not args.json:
                print(_line(row, name, speeds), flush=True)
        rows.append(row)
    return {"speeds_m_s": speeds, "rows": rows, "p_rule": args.p_rule, "growth": GROWTH, "e_b_deg": rig.e_b,
            "fps": args.fps,
            "resolution": list(rig.size), "stripes": args.stripes, "fidelity": args.fidelity,
            "seed": args.seed,
            "exposure_s": rig.scene.camera.exposure_s, "cpu_s": time.process_time() - started,
            "load": os.getloadavg()[0]}


def _f(v, fmt: str) -> str:
    return "—" if v is None else format(v, fmt)


def _line(row: dict, name: str, speeds) -> str:
    d = row["directions"][name]
    cells = [row["mode"], row["method"].replace("_", " "), str(row["frames"]), f"{row['scan_s']:.2f}", name]
    cells += [f"{_f(c, '.3f')} / {_f(e, '.3f')}" for c, e in zip(d["contrast"], d["error"], strict=True)]
    tol = d["tolerated_m_s"]
    cells.append(f"> {speeds[-1]:g}" if tol is None else f"{tol:.2g}")
    return "| " + " | ".join(cells) + " |"


def main(args: argparse.Namespace) -> int:
    speeds = sorted(set(float(s) for s in args.speeds) | {0.0})
    if not args.json:
        cols = ["mode", "method", "frames", "scan [s]", "direction", *(f"{s:g} m/s" for s in speeds),
                f"+{GROWTH:.0%} error at [m/s]"]
        print("| " + " | ".join(cols) + " |\n" + "|---" * len(cols) + "|")
    res = run(args)
    if args.json:
        print(json.dumps(res))
    else:
        print(f"contrast / error vs T per speed; {res['resolution'][0]}x{res['resolution'][1]} "
              f"{res['fidelity']}, {res['stripes']} stripes, {res['fps']:g} fps, "
              f"E_b {res['e_b_deg']:.1f} deg, "
              f"seed {res['seed']}; CPU {res['cpu_s']:.0f} s, load {res['load']:.1f}")
    return 0
