"""``polarstripe calibrate``: projector–camera calibration with coded light on a checkerboard (docs/depth.md).

``polarstripe calibrate -o rig.yaml --sim [--poses N] [--sigma-t S] [scene.toml]`` runs it on the simulated
rig: the scene's camera and projector, its medium (σ_t from ``--sigma-t``), and instead of its objects a
checkerboard plane (a PNG texture on a plane, docs/scene-format.md) at N random, seeded poses, each rendered
under the white (``flood``) pattern, in the dark, and under every pattern of the projector's XOR code
(imaging/structured_light.py ``calibration_code``), through the analyzer at the angle of least backscatter
(E_b, found as the polarizer node finds it: four flood frames of the empty tank; none in clear water); then
:mod:`polarstripe.imaging.calibration` decodes and calibrates.

A scene whose camera and projector look through flat ports (``port`` keys, ``preset = "glass_tank"``) gets
the refractive model as well (:mod:`polarstripe.imaging.port_calibration`: each port's distance and normal
fitted, its thickness and indices taken from the scene as from the housing's data sheet); the file then
holds that model, the ports included, and the printout both fits (``--pinhole``: the pinhole fit only).

Writes ``rig.yaml`` (OpenCV FileStorage, atomically: a failed run leaves the previous file untouched) and
``rig_coverage.png`` beside it (the projector plane with every pose's corners, rewritten after every pose:
a live view to watch). With ``--sim`` it prints the simulator's truth beside the estimate.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time

import numpy as np
from polarstripe.errors import PolarstripeError
from polarstripe.imaging.calibration import (
    MIN_POSES,
    Board,
    CalibrationError,
    PoseError,
    calibrate,
    decode_pose,
    failed_poses,
    load,
    save,
)
from polarstripe.imaging.polarization import least_backscatter_angle
from polarstripe.imaging.port_calibration import PortSpec, fit_ports
from polarstripe.imaging.structured_light import calibration_code
from polarstripe.imaging.triangulation import RigGeometry
from polarstripe.imaging.validation import ImagingError
from polarstripe.nodes.rig_calibrator import coverage_path, write_coverage
from polarstripe.sim import scene_target as target
from polarstripe.sim.depth_truth import rig_geometry
from polarstripe.sim.polarization import analyzer
from polarstripe.sim.port import port_geometry
from polarstripe.sim.render import render_components, render_frame
from polarstripe.sim.scene import Scene, SceneError, load_scene, parse_size
from polarstripe.sim.sensor import expose
from tqdm import tqdm

SUPERSAMPLE = 3
ANALYZER_PROBE_DEG = (0.0, 45.0, 90.0, 135.0)  # the polarizer node's calibration angles
HELP = "projector-camera calibration with Gray code on a checkerboard (--sim: on the simulated rig)"


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scene", nargs="?", default=None,
                        help="scene TOML of the simulated rig (--sim; omitted: the default tank)")
    parser.add_argument("-o", "--out", metavar="FILE",
                        help="calibration file to write (.yaml; .xml or .json also work)")
    parser.add_argument("--check", metavar="FILE",
                        help="instead: compare calibration FILE with the scene's rig (an error if it is "
                             "another rig size)")
    parser.add_argument("--sim", action="store_true", help="calibrate the simulated rig")
    parser.add_argument("--poses", type=int, default=8, help=f"board poses (>= {MIN_POSES}; default 8)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the poses and the sensor noise")
    parser.add_argument("--sigma-t", type=float, default=None, metavar="PER_M",
                        help="medium extinction [1/m] (default: the scene's)")
    parser.add_argument("--resolution", default=None, metavar="WxH",
                        help="camera resolution (default: scene)")
    parser.add_argument("--projector", default=None, metavar="WxH",
                        help="projector resolution (default: scene)")
    parser.add_argument("--board", default="8x6", metavar="COLSxROWS", help="inner corners (default 8x6)")
    parser.add_argument("--square", type=float, default=0.015, metavar="M", help="square size [m]")
    parser.add_argument("--distortion", default="radial", choices=("none", "radial", "full"),
                        help="camera lens distortion to fit: none, radial (k1, k2; default), full (5)")
    parser.add_argument("--pinhole", action="store_true",
                        help="behind ports too, write the pinhole fit (default: the refractive model)")
    parser.add_argument("--fidelity", default="preview",
                        help="model fidelity of the renders (default preview)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def board_texture(board: Board, path: str, dark: int = 64) -> tuple[float, float]:
    """Write the checkerboard PNG (sim/scene_target.py); its size [m]."""
    return target.board_texture(board.cols, board.rows, board.square_m, path, dark)


random_poses = target.target_poses


def rig_scene(args: argparse.Namespace) -> Scene:
    """The simulated rig: the scene with the options applied, no objects yet."""
    scene = load_scene(args.scene)
    if args.sigma_t is not None:
        if not np.isfinite(args.sigma_t) or args.sigma_t < 0:
            raise PolarstripeError(f"--sigma-t must be >= 0, got {args.sigma_t}")
        scene = scene.replace(medium=scene.medium.replace(sigma_t=float(args.sigma_t)))
    if args.resolution:
        scene = scene.replace(camera=scene.camera.replace(resolution=parse_size(args.resolution,
                                                                                   "--resolution")))
    if args.projector:
        scene = scene.replace(projector=scene.projector.replace(resolution=parse_size(args.projector,
                                                                                      "--projector")))
    if scene.projector.model != "pinhole":
        raise PolarstripeError("the projector is a point source: it shows no patterns (projector.model)")
    return scene


def exposed(scene: Scene, pose: dict, texture: str, size, fidelity: str, level: float = 0.6,
            polarizer_deg: float | None = None) -> Scene:
    """The scene with the projector lighting the white board at ``level`` of full scale through the analyzer
    at ``polarizer_deg`` (sim/scene_target.py ``lit_for_target``)."""
    try:
        return target.lit_for_target(scene, pose, texture, size, fidelity, level, polarizer_deg)
    except SceneError as exc:
        raise CalibrationError(str(exc)) from None


def crossed_angle(scene: Scene, fidelity: str, rng) -> float | None:
    """E_b: the analyzer angle [deg] of least backscatter, from flood frames of the empty tank at
    :data:`ANALYZER_PROBE_DEG` (imaging/polarization.py ``least_backscatter_angle``, as the polarizer node
    calibrates); None where the water sends back no light above the read noise (clear water) or light that
    shows no polarization: no analyzer then."""
    empty = scene.replace(objects=())
    comp = render_components(empty, "flood", fidelity)
    cam = scene.camera
    frames = [expose(analyzer(comp, a), cam, rng) for a in ANALYZER_PROBE_DEG]
    if np.mean(frames) - cam.offset_dn < 10 * cam.read_noise_e / cam.gain_e_per_dn:
        return None
    try:
        return least_backscatter_angle(ANALYZER_PROBE_DEG, frames, dark_offset=cam.offset_dn,
                                       saturation=2 ** cam.bits - 1)
    except ImagingError:
        return None


_with_board = target.with_target


def render_pose(scene: Scene, pose: dict, texture: str, size, rng, fidelity: str, tick=None,
                polarizer_deg: float | None = None):
    """White, black and code frames (uint16 DN; :func:`calibration_code`) of the board at one pose, through
    the analyzer at ``polarizer_deg`` (None: none). The white frame, where the corners are found, integrates
    each pixel's area (SUPERSAMPLE² rays, as a sensor pixel does; one ray per pixel aliases the board's edges
    by ~0.2 px); the code frames, decoded per pixel, take one ray."""
    sc = _with_board(scene, pose, texture, size)
    w, h = sc.camera.resolution
    fine = render_components(sc.replace(camera=sc.camera.replace(resolution=(w * SUPERSAMPLE,
                                                                             h * SUPERSAMPLE))),
                             "flood", fidelity, need=("D", "A", "B") if polarizer_deg is None else
                             ("D", "A", "B", "p"))
    radiance = analyzer(fine, polarizer_deg).reshape(h, SUPERSAMPLE, w, SUPERSAMPLE).mean(axis=(1, 3))
    white = expose(radiance, sc.camera, rng)
    black = expose(np.zeros(white.shape), sc.camera, rng)
    frames = []
    for p in calibration_code(*sc.projector.resolution):
        frames.append(render_frame(sc, p, polarizer_deg, fidelity, seed=rng)[0])
        if tick is not None:
            tick(1)
    return white, black, frames


def _board(text: str) -> tuple[int, int]:
    return target.parse_board(text)


def port_specs(scene: Scene) -> tuple[PortSpec, PortSpec] | None:
    """What the housings' data sheets give of the scene's ports (thickness, indices); None without ports.

    :raises CalibrationError: only one of the devices is behind a port."""
    ports = scene.camera.port, scene.projector.port
    if ports == (None, None):
        return None
    if None in ports:
        raise CalibrationError("the refractive fit needs both camera and projector behind a port; this "
                               f"scene has one only on the {'camera' if ports[0] else 'projector'} "
                               "(--pinhole: the pinhole fit)")
    return tuple(PortSpec(*_sheet(p)) for p in ports)


def one_wall(scene: Scene) -> bool:
    """Whether camera and projector look through one flat wall (a tank's, ``preset = "glass_tank"``): the
    same data sheet and both ports' inner faces in one plane of the world (the refractive fit then ties
    them together, imaging/port_calibration.py)."""
    ports = scene.camera.port, scene.projector.port
    if None in ports or PortSpec(*_sheet(ports[0])) != PortSpec(*_sheet(ports[1])):
        return False
    faces = []
    for dev in (scene.camera, scene.projector):
        g = port_geometry(dev.port, dev.position, np.subtract(dev.look_at, dev.position))
        faces.append((g.normal, g.normal @ g.apex + g.d))
    (n0, c0), (n1, c1) = faces
    return bool(n0 @ n1 > 1 - 1e-9 and abs(c0 - c1) < 1e-9)


def _sheet(port) -> tuple[float, float, float, float]:
    return port.thickness_m, port.n_air, port.n_glass, port.n_water


def calibrate_sim(args: argparse.Namespace, progress: bool):
    """Render and calibrate (module docstring); returns (Calibration, truth geometry, scene, analyzer
    angle, PortCalibration or None)."""
    scene = rig_scene(args)
    specs = None if getattr(args, "pinhole", False) else port_specs(scene)
    cols, rows = _board(args.board)
    board = Board(cols, rows, float(args.square))
    proj = tuple(scene.projector.resolution)
    poses = random_poses(args.poses, args.seed, scene, cols, rows, board.square_m)
    rng = np.random.default_rng(args.seed)
    n_frames = len(calibration_code(*proj)) + 2
    results, failures = [], []
    angle = crossed_angle(scene, args.fidelity, rng)
    with tempfile.TemporaryDirectory(prefix="polarstripe-calib-") as tmp:
        tex = os.path.join(tmp, "board.png")
        size = board_texture(board, tex)
        bar = tqdm(total=args.poses * n_frames, desc="calibrate", unit="frame", disable=not progress,
                   file=sys.stderr)
        for k, pose in enumerate(poses):
            lit = exposed(scene, pose, tex, size, args.fidelity, polarizer_deg=angle)   # each pose its own
            white, black, frames = render_pose(lit, pose, tex, size, rng, args.fidelity, bar.update, angle)
            bar.update(2)
            try:
                results.append(decode_pose(white, black, frames, board, proj, pose=k))
            except PoseError as exc:
                failures.append(exc)
                bar.write(f"skipped {exc}")
                continue
            write_coverage(coverage_path(args.out), results, proj)   # the live view: poses so far
        bar.close()
    if len(results) < MIN_POSES:
        raise CalibrationError(f"{len(results)} usable poses of {args.poses}: a calibration needs at least "
                               f"{MIN_POSES}" + (f"; {failed_poses(failures)}" if failures else ""))
    cal = calibrate(results, board, tuple(scene.camera.resolution), proj, distortion=args.distortion)
    fit = None if specs is None else fit_ports(cal, board, *specs, one_wall=one_wall(scene))
    return cal, rig_geometry(scene), scene, angle, fit


def comparison_rows(cal, truth: dict) -> list[tuple[str, float, float, str]]:
    """(quantity, truth, estimate, unit) rows of a calibration (a Calibration, or a RigGeometry: no RMS
    rows) against the simulator's geometry."""
    Kc, Kp, Tc, Tp = cal.K_cam, cal.K_proj, truth["K_cam"], truth["K_proj"]
    dR = cal.R @ np.asarray(truth["R"]).T
    angle = float(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))))
    base_t, base_e = float(np.linalg.norm(truth["T"])), float(np.linalg.norm(cal.T))
    rows = [("camera f_x", Tc[0, 0], Kc[0, 0], "px"), ("camera f_y", Tc[1, 1], Kc[1, 1], "px"),
            ("camera c_x", Tc[0, 2], Kc[0, 2], "px"), ("camera c_y", Tc[1, 2], Kc[1, 2], "px"),
            ("projector f_x", Tp[0, 0], Kp[0, 0], "px"),
            ("projector f_y", Tp[1, 1], Kp[1, 1], "px"),
            ("projector c_x", Tp[0, 2], Kp[0, 2], "px"), ("projector c_y", Tp[1, 2], Kp[1, 2], "px"),
            ("baseline", 1e3 * base_t, 1e3 * base_e, "mm"), ("rotation error", 0.0, angle, "deg")] + (
        [("RMS camera", 0.0, cal.rms_cam, "px"), ("RMS projector", 0.0, cal.rms_proj, "px"),
         ("RMS stereo", 0.0, cal.rms_stereo, "px")] if hasattr(cal, "rms_cam") else [])
    for key, name in (("port_cam", "camera"), ("port_proj", "projector")):
        est, true = getattr(cal, key, None), truth.get(key)
        if est is not None and true is not None:
            cos = np.dot(est[:3], true[:3]) / (np.linalg.norm(est[:3]) * np.linalg.norm(true[:3]))
            rows += [(f"{name} port d", 1e3 * true[3], 1e3 * est[3], "mm"),
                     (f"{name} port tilt", 0.0, float(np.degrees(np.arccos(np.clip(cos, -1, 1)))), "deg")]
            sigma = getattr(cal, "sigma", {})
            if sigma:      # the fit's own standard errors: no truth to compare
                rows += [(f"{name} port d σ", np.nan, 1e3 * sigma[f"{key}_d_sigma_m"], "mm"),
                         (f"{name} port tilt σ", np.nan, sigma[f"{key}_tilt_sigma_deg"], "deg")]
    return rows


def check(args: argparse.Namespace) -> int:
    """``--check FILE``: the file's rig beside the scene's pinholes (the camera rescaled if binned)."""
    scene = rig_scene(args)
    w, h = scene.camera.resolution
    g = load(args.check, cam_size=(w, h), proj_size=scene.projector.resolution)
    rig = RigGeometry.from_dict(g).for_camera(w, h)
    print(f"{args.check}: {g['cam_size'].ravel().astype(int).tolist()} camera, "
          f"{g['proj_size'].ravel().astype(int).tolist()} projector: the scene's rig size")
    print(f"{'':16}{'scene':>12}{'file':>12}")
    for name, t, e, unit in comparison_rows(rig, rig_geometry(scene)):
        print(f"{name:16}{t:12.4f}{e:12.4f} {unit}")
    return 0


def main(args: argparse.Namespace) -> int:
    if args.check:
        return check(args)
    if not args.out:
        raise PolarstripeError("-o FILE is required (or --check FILE)")
    if args.poses < MIN_POSES:
        raise CalibrationError(f"--poses {args.poses}: a calibration needs at least {MIN_POSES} poses")
    if not args.sim:
        raise PolarstripeError("calibrate on a rig runs over its nodes: polarstripe launch "
                               "launch/calibrate.toml --once out=FILE (docs/depth.md \"Calibration\"); "
                               "this command needs --sim")
    out_dir = os.path.dirname(os.path.abspath(args.out))
    if not os.path.isdir(out_dir):
        raise PolarstripeError(f"-o {args.out!r}: folder {out_dir!r} does not exist")
    t0 = time.perf_counter()
    pinhole, truth, scene, angle, fit = calibrate_sim(args, not args.no_progress and sys.stderr.isatty())
    cal = pinhole if fit is None else fit
    extra = {"rms_cam": cal.rms_cam, "rms_proj": cal.rms_proj, "rms_stereo": cal.rms_stereo,
             "poses": len(pinhole.poses), "board": f"{args.board} inner corners, {args.square} m squares",
             "analyzer_deg": "none" if angle is None else f"{round(angle, 1) % 180:.1f}",
             "source": "polarstripe calibrate --sim" if args.sim else "polarstripe calibrate"}
    if fit is not None:
        extra.update(model="refractive (flat ports)", corners_dropped=fit.dropped,
                     pinhole_rms_cam=pinhole.rms_cam, pinhole_rms_proj=pinhole.rms_proj, **fit.sigma)
    save(args.out, {**cal.geometry(), "dist_proj": getattr(cal, "dist_proj", np.zeros(5))}, extra)
    coverage = coverage_path(args.out)
    write_coverage(coverage, pinhole.poses, cal.proj_size)
    model = "pinhole" if fit is None else f"refractive model ({fit.dropped} corners left out)"
    print(f"{args.out}: {len(pinhole.poses)} poses, {model}, RMS camera {cal.rms_cam:.3f} px, projector "
          f"{cal.rms_proj:.3f} px, stereo {cal.rms_stereo:.3f} px ({time.perf_counter() - t0:.1f} s; "
          + ("no analyzer" if angle is None else f"analyzer at E_b, {round(angle, 1) % 180:.1f} deg") + ")")
    print(f"coverage: {coverage}")
    if args.sim:
        fits = [("pinhole", pinhole)] + ([] if fit is None else [("refractive", fit)])
        print(f"{'':22}{'truth':>12}" + "".join(f"{name:>12}" for name, _ in fits))
        rows = [comparison_rows(c, truth) for _, c in fits]
        for name, t, _, unit in rows[-1]:
            values = [dict((r[0], r[2]) for r in rs).get(name) for rs in rows]
            cells = [t if np.isfinite(t) else None, *values]
            print(f"{name:22}" + "".join(f"{'-':>12}" if v is None else f"{v:12.4f}" for v in cells)
                  + f" {unit}")
    return 0
