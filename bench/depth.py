"""``polarstripe bench depth``: triangulation time per stripe scan, and (``--accuracy``) depth error vs truth.

Timing (1280×1024 uint16, N stripes, the default): per scan, the delineation + ray–plane triangulation the
compositor runs once a scan is complete (:func:`~polarstripe.imaging.delineation.delineate`,
:func:`~polarstripe.imaging.triangulation.depth_from_columns`, the point cloud), its target ≤ 20 ms, as a
ratio to the compositor's own running reductions of the same scan (``RunningComposite.add`` of every frame;
the running argmax the depth needs is timed too, as the per-frame cost it adds). Wall and CPU time are both
reported, with the load average: on a shared machine the wall time holds the waits for a core.

Accuracy (``--accuracy``): a sphere in front of a tilted plane in the default tank, rendered by the model
(:func:`polarstripe.sim.render.render_each`: a scan's frames together, each as it renders alone) at a small
resolution for each ``--sigmas`` (2, 5, 8),
scanned with stripes (E, no analyzer) and polarized stripes read as E_b (the analyzer crossed to the
backscatter) and as Ŝ (eq. 6 from E_b and E_w, p̂ measured on the frames), with all orders of scattering as
the simulator renders them (``--orders single``: the paper's single-scattering model), delineated with each
``--k-sigma`` and ``--min-contrast``; RMS depth error [mm] against the simulator's depth truth
(:func:`polarstripe.sim.depth_truth.depth_truth`) and the fraction of object pixels with a valid depth.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from dataclasses import replace

import numpy as np
from polarstripe.errors import PolarstripeError
from polarstripe.imaging.composite import RunningComposite
from polarstripe.imaging.delineation import NoiseModel, RunningArgmax, delineate
from polarstripe.imaging.triangulation import (
    RigGeometry,
    Triangulator,
    camera_rays,
    depth_from_columns,
    stripe_edges,
)
from polarstripe.sim.depth_truth import depth_truth, rig_geometry
from polarstripe.sim.polarization import analyzer, least_backscatter_angle
from polarstripe.sim.render import render_each
from polarstripe.sim.scene import PlaneObject, Scene, SphereObject, load_scene
from polarstripe.sim.sensor import dark_offset_dn, electrons_per_radiance, expose, full_scale_dn
from scipy.ndimage import uniform_filter1d


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--width", type=int, default=1280, help="frame width in pixels (default 1280)")
    parser.add_argument("--height", type=int, default=1024, help="frame height in pixels (default 1024)")
    parser.add_argument("--stripes", type=int, default=30, help="stripes per scan (default 30)")
    parser.add_argument("--repeats", type=int, default=5, help="scans timed; the median is reported")
    parser.add_argument("--accuracy", action="store_true",
                        help="also the depth error table (renders the model: about a minute)")
    parser.add_argument("--accuracy-width", type=int, default=160, help="camera width of the accuracy "
                        "renders (default 160)")
    parser.add_argument("--orders", choices=("all", "single"), default="all",
                        help="orders of scattering of the accuracy renders (default all, as the simulator)")
    parser.add_argument("--sigmas", default="2,5,8", metavar="S,S,…",
                        help="media sigma_t [1/m] of the accuracy table (default 2,5,8)")
    parser.add_argument("--min-contrast", default="0.15,0.05,0", metavar="C,C,…",
                        help="edge contrast tests of the accuracy table (default 0.15,0.05,0; 0: the noise "
                             "test alone)")
    parser.add_argument("--rows", default="1", metavar="N,N,…",
                        help="frames averaged over N camera rows along the stripes before delineation "
                             "(default 1: none)")
    parser.add_argument("--k-sigma", default="4", metavar="K,K,…",
                        help="noise tests of the accuracy table: K sigma of the reading's noise model "
                             "(default 4)")


# ---- the accuracy scene -----------------------------------------------------------------------------------
def depth_scene(sigma_t: float, width: int = 160) -> Scene:
    """The default tank with a sphere (r 5 cm at z 0.26 m) before a plane tilted 19° about the vertical axis,
    the camera at ``width`` × ¾ ``width`` (exposure scaled by the pixel area)."""
    s = load_scene(None)
    n = np.array([0.35, 0.0, -1.0])
    n /= np.linalg.norm(n)
    objects = (SphereObject(center=(0.02, 0.0, 0.26), radius=0.05, albedo=0.6),
               PlaneObject(point=(0.0, 0.0, 0.34), normal=tuple(n), size=(0.4, 0.3), albedo=0.6))
    cam = s.camera.resized((width, width * 3 // 4))
    return s.replace(objects=objects, camera=cam, medium=s.medium.replace(sigma_t=float(sigma_t)))


def scan_votes(scene: Scene, stripes: int, angles=(None,), *, orders: str = "single", seed: int = 1,
               fidelity: str = "preview") -> tuple[dict, Scene]:
    """Render a stripe scan of ``scene`` at each analyzer angle and fold it into a RunningArgmax; the exposure
    is set so the brightest stripe frame (no analyzer) peaks at 80 % of full scale. Returns
    ({angle: SheetVotes}, the scene as exposed)."""
    comps = render_each(scene, [f"stripe:{k}/{stripes}" for k in range(stripes)], fidelity, orders=orders)
    scene = _exposed(scene, comps, None)
    w, h = scene.camera.resolution
    ra = RunningArgmax((h, w), np.uint16)
    rng = np.random.default_rng(seed)
    for k, comp in enumerate(comps):
        for a in angles:
            ra.add(expose(analyzer(comp, a), scene.camera, rng), k, a)
    return {a: ra.result(a) for a in angles}, scene


def _exposed(scene: Scene, comps, angle: float | None, fill: float = 0.8) -> Scene:
    """``scene`` with the exposure that brings the brightest of the frames through the analyzer at ``angle``
    (None: none) to ``fill`` of full scale."""
    cam = scene.camera
    e_map = electrons_per_radiance(cam)
    peak = max(float(np.max(analyzer(c, angle) * e_map)) for c in comps) / cam.gain_e_per_dn
    limit = fill * min(full_scale_dn(cam) - dark_offset_dn(cam), cam.full_well_e / cam.gain_e_per_dn)
    return scene.replace(camera=cam.replace(exposure_s=cam.exposure_s * limit / peak))


def noise_of(scene: Scene) -> NoiseModel:
    c = scene.camera
    return NoiseModel(dark_dn=dark_offset_dn(c), read_noise_dn=c.read_noise_e / c.gain_e_per_dn,
                      dn_per_electron=1.0 / c.gain_e_per_dn, saturation_dn=full_scale_dn(c))


def depth_error(depth: np.ndarray, truth: np.ndarray) -> dict:
    """RMS error [mm] where both are finite, the valid fraction of object pixels, depths where truth has
    no object."""
    both = np.isfinite(depth) & np.isfinite(truth)
    err = (depth - truth)[both]
    return {"rms_mm": float(1e3 * np.sqrt(np.mean(err ** 2))) if err.size else None,
            "median_abs_mm": float(1e3 * np.median(np.abs(err))) if err.size else None,
            "valid_fraction": float(both.sum() / max(1, np.isfinite(truth).sum())),
            "off_object": int((np.isfinite(depth) & ~np.isfinite(truth)).sum())}


def readings(scene: Scene, comps, truth: np.ndarray, seed: int = 1):
    """The frames of a stripe scan as each reading sees them, each exposed for its own brightest frame:
    E (no analyzer), E_b (the analyzer crossed to the backscatter,
    :func:`~polarstripe.sim.polarization.least_backscatter_angle`) and Ŝ = E_b(1 + 1/p̂) + E_w(1 − 1/p̂)
    (eq. 6; p̂ measured on the frames' object-free pixels, E_w at 90° to E_b, both at E_w's exposure).
    Returns {reading: (frames (float DN), NoiseModel)} and p̂; Ŝ's noise model is the sensor's through
    eq. 6: Var Ŝ = c·read² + (c/2)·Ŝ/gain with c = 2(1 + 1/p̂²), where E_b ≈ E_w ≈ Ŝ/2."""
    crossed = least_backscatter_angle(comps[len(comps) // 2])
    parallel = (crossed + 90.0) % 180.0
    rng = np.random.default_rng(seed)
    out = {}
    for name, angle in (("E", None), ("E_b", crossed)):
        sc = _exposed(scene, comps, angle)
        out[name] = ([expose(analyzer(c, angle), sc.camera, rng).astype(float) for c in comps], noise_of(sc))
    sw = _exposed(scene, comps, parallel)
    dark = dark_offset_dn(sw.camera)
    pairs = [tuple(expose(analyzer(c, a), sw.camera, rng) - dark for a in (crossed, parallel)) for c in comps]
    water = ~np.isfinite(truth)
    eb, ew = sum(p[0] for p in pairs), sum(p[1] for p in pairs)
    seen = water & (ew + eb > 0)
    p_hat = float(np.clip(np.median((ew - eb)[seen] / (ew + eb)[seen]), 0.05, 1.0)) if seen.any() else 1.0
    n = noise_of(sw)
    c = 2.0 * (1.0 + 1.0 / p_hat ** 2)
    out["S_hat"] = ([b * (1 + 1 / p_hat) + e * (1 - 1 / p_hat) for b, e in pairs],
                    NoiseModel(dark_dn=0.0, read_noise_dn=n.read_noise_dn * np.sqrt(c),
                               dn_per_electron=n.dn_per_electron * c / 2, saturation_dn=None))
    return out, p_hat


def along_stripes(frames, noise: NoiseModel, rows: int):
    """SheetVotes of ``frames`` each averaged over ``rows`` camera rows (a box along the vertical stripes:
    the edges, which cross the rows, stay sharp; vertical resolution is given for noise), and the noise
    model of the average (variance / ``rows``)."""
    ra = RunningArgmax(frames[0].shape, np.float64)
    for k, f in enumerate(frames):
        ra.add(uniform_filter1d(f, rows, axis=0, mode="nearest") if rows > 1 else f, k)
    return ra.result(), replace(noise, read_noise_dn=noise.read_noise_dn / np.sqrt(rows),
                                dn_per_electron=noise.dn_per_electron / rows)


def accuracy(sigmas=(2.0, 5.0, 8.0), stripes: int = 30, width: int = 160, orders: str = "all",
             min_contrasts=(0.15,), k_sigmas=(4.0,), rows=(1,)) -> list[dict]:
    """Depth error per σ_t, reading (E: no analyzer; E_b; Ŝ), frames averaged over ``rows`` camera rows
    along the stripes, and thresholds: the edge contrast test ``min_contrast`` (0: the noise test alone)
    and the noise test ``k_sigma`` (σ of the reading's noise model)."""
    out = []
    for sigma in sigmas:
        scene = depth_scene(sigma, width)
        truth = depth_truth(scene)
        comps = render_each(scene, [f"stripe:{k}/{stripes}" for k in range(stripes)], "preview",
                            orders=orders)
        geom = RigGeometry.from_dict(rig_geometry(scene))
        edges = stripe_edges(stripes, geom.proj_size[0])
        frames, p_hat = readings(scene, comps, truth)
        for name, (fr, noise0) in frames.items():
            for n_rows in rows:
                votes, noise = along_stripes(fr, noise0, int(n_rows))
                for k in k_sigmas:
                    for mc in min_contrasts:
                        columns = delineate(votes, edges, noise, k_sigma=k, min_contrast=mc)
                        z = depth_from_columns(geom, columns)
                        out.append({"sigma_t": sigma, "reading": name, "method": METHOD_OF[name],
                                    "rows": int(n_rows), "k_sigma": k, "min_contrast": mc, "p_hat": p_hat,
                                    **depth_error(z, truth)})
    return out


METHOD_OF = {"E": "stripes", "E_b": "polarized_stripes", "S_hat": "polarized_stripes"}


# ---- timing ----------------------------------------------------------------------------------------------
def _synthetic(width: int, height: int, stripes: int):
    """A stripe scan of a plane seen by a 1280-wide rig like the default tank's: frames, geometry."""
    scene = load_scene(None)
    geom = RigGeometry.from_dict(rig_geometry(scene)).for_camera(width, height)
    rr, cc = np.mgrid[0:height, 0:width]
    rays = camera_rays(geom, rr, cc)
    x_p = rays * 0.38 @ geom.R.T + geom.T  # points of the plane z = 0.38 in the projector frame
    col = x_p[..., 0] / x_p[..., 2] * geom.K_proj[0, 0] + geom.K_proj[0, 2] + 0.5
    edges = stripe_edges(stripes, geom.proj_size[0])
    sheet = np.searchsorted(edges, col, side="right") - 1
    rng = np.random.default_rng(0)
    frames = [np.where(sheet == k, 3000, 200).astype(np.uint16) + rng.integers(0, 8, (height, width),
                                                                                dtype=np.uint16)
              for k in range(stripes)]
    return frames, geom, edges


def _median_time(fn, repeats: int) -> tuple[float, float]:
    """Median wall time and median CPU time of this process [s] (on a shared machine the CPU time is what
    the work costs; the wall time also holds the waits for a core)."""
    wall, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return float(np.median(wall)), float(np.median(cpu))


def run(width: int, height: int, stripes: int, repeats: int) -> dict:
    frames, geom, edges = _synthetic(width, height, stripes)
    shape = (height, width)
    rc = RunningComposite(shape, np.uint16, saturation=4095)
    ra = RunningArgmax(shape, np.uint16)

    def reductions():
        rc.reset()
        for f in frames:
            rc.add(f)

    def argmax():
        ra.reset()
        for k, f in enumerate(frames):
            ra.add(f, k)

    argmax()
    votes = ra.result()
    tri = Triangulator(geom, shape)
    noise = NoiseModel(dark_dn=0.0, saturation_dn=4095)

    def triangulate():
        tri.points(tri.depth(delineate(votes, edges, noise)))

    triangulate()  # compile

    out = {"width": width, "height": height, "stripes": stripes, "target_ms": 20.0,
           "load_average": os.getloadavg()[0], "cpus": os.cpu_count()}
    for key, fn in (("compositor_scan", reductions), ("argmax_scan", argmax), ("triangulation", triangulate),
                    ("delineate", lambda: delineate(votes, edges, noise))):
        wall, cpu = _median_time(fn, repeats)
        out[f"{key}_ms"], out[f"{key}_cpu_ms"] = 1e3 * wall, 1e3 * cpu
    out["triangulation_vs_compositor"] = out["triangulation_ms"] / out["compositor_scan_ms"]
    return out


def _floats(text: str, what: str) -> tuple[float, ...]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise PolarstripeError(f"{what} {text!r}: comma-separated numbers expected") from None
    if not values or not all(np.isfinite(v) and v >= 0 for v in values):
        raise PolarstripeError(f"{what} {text!r}: numbers >= 0 expected")
    return values


def _rows(text: str) -> tuple[int, ...]:
    values = _floats(text, "--rows")
    if not all(v >= 1 and v == int(v) for v in values):
        raise PolarstripeError(f"--rows {text!r}: whole numbers >= 1 expected")
    return tuple(int(v) for v in values)


def main(args: argparse.Namespace) -> int:
    out = run(args.width, args.height, args.stripes, args.repeats)
    if args.accuracy:
        out["accuracy"] = accuracy(_floats(args.sigmas, "--sigmas"), args.stripes, args.accuracy_width,
                                   args.orders, _floats(args.min_contrast, "--min-contrast"),
                                   _floats(args.k_sigma, "--k-sigma"), _rows(args.rows))
        what = "all orders of scattering" if args.orders == "all" else "single scattering"
        out["accuracy_model"] = (f"{what} (render_each orders={args.orders!r}), preview fidelity, "
                                 f"{args.accuracy_width} px wide")
    if args.json:
        print(json.dumps(out))
        return 0
    print(f"depth from a stripe scan, {out['width']}x{out['height']} uint16, {out['stripes']} stripes "
          f"(median of {args.repeats}; load average {out['load_average']:.1f} on {out['cpus']} CPUs)")
    print(f"  {'step':<44}{'ms/scan':>9}{'CPU ms':>8}{'vs compositor':>15}")
    for key, label in (("compositor_scan", "compositor running max/min (all frames)"),
                       ("argmax_scan", "running argmax + second (all frames)"),
                       ("delineate", "delineation (edges, columns)"),
                       ("triangulation", "delineation + triangulation + points")):
        print(f"  {label:<44}{out[key + '_ms']:>9.2f}{out[key + '_cpu_ms']:>8.2f}"
              f"{out[key + '_ms'] / out['compositor_scan_ms']:>15.2f}")
    for what in ("", "_cpu"):
        t = out[f"triangulation{what}_ms"]
        ok = "meets" if t <= out["target_ms"] else "misses"
        kind = "CPU" if what else "wall"
        print(f"  triangulation ({kind} time {t:.1f} ms) {ok} the {out['target_ms']:.0f} ms target")
    if args.accuracy:
        print(f"\ndepth error vs the simulator's truth ({out['accuracy_model']})")
        print(f"  {'sigma_t':>7}  {'method':<18}{'reading':<8}{'rows':>5}{'k_sigma':>8}{'min contr.':>11}"
              f"{'RMS mm':>8}{'median mm':>10}{'valid':>7}{'off-obj':>8}")
        for r in out["accuracy"]:
            rms = "n/a" if r["rms_mm"] is None else f"{r['rms_mm']:.2f}"
            med = "n/a" if r["median_abs_mm"] is None else f"{r['median_abs_mm']:.2f}"
            print(f"  {r['sigma_t']:>7g}  {r['method']:<18}{r['reading']:<8}{r['rows']:>5d}{r['k_sigma']:>8g}"
                  f"{r['min_contrast']:>11g}{rms:>8}{med:>10}{r['valid_fraction']:>7.2f}"
                  f"{r['off_object']:>8d}")
    return 0
