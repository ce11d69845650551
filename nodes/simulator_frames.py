"""What the simulator node computes, as plain functions: its scene (with a medium override), the model's
resolution per pattern, the radiance resized to the camera, the auto-exposure
factor; its error type and the ``resolution`` param's parser; the calibration board of its ``target`` params
(:class:`Target`); the hosted ELL14. (The sensor is :func:`polarstripe.sim.sensor.expose`, given the node's
precomputed electrons map.)"""

from __future__ import annotations

import math
import os
import shutil
import tempfile

import cv2
import numpy as np
from polarstripe.msgs import Composite
from polarstripe.msgs.rig import FAULT_COMMANDS
from polarstripe.nodes.drivers.simell14 import SimEll14
from polarstripe.sim.depth_truth import depth_truth, rig_geometry
from polarstripe.sim.mosaic import MicroPolarizerArray
from polarstripe.sim.scene import Phase, Scene, SceneError, load_scene, parse_size
from polarstripe.sim.scene_target import (
    board_texture,
    lit_for_target,
    parse_board,
    target_poses,
    with_target,
)
from polarstripe.sim.sensor import dark_offset_dn, full_scale_dn, mean_dn
from polarstripe.sim.truth import unscattered_object

PREVIEW_WIDTH = 160  # model width [px] the preview render scale aims at
WHITE_SUPERSAMPLE = 3  # rays a pixel along each axis in a calibration target's white frame


class SimulatorError(SceneError):
    """A simulator request or parameter that cannot be served; the text names the field and the value."""


def parse_resolution(text: str) -> tuple[int, int] | None:
    """The ``resolution`` param: ``""`` (the scene's) or ``WxH`` with both at least 2."""
    if not text:
        return None
    w, h = parse_size(text)
    if w < 2 or h < 2:
        raise ValueError(f"resolution {text!r}: need at least 2x2")
    return w, h


def check_medium(sigma_t: float | None, g: float | None) -> None:
    """The medium override params: σ_t ≥ 0 [1/m], the mean cosine in [0, 1); ValueError otherwise."""
    if sigma_t is not None and not (math.isfinite(sigma_t) and sigma_t >= 0):
        raise ValueError(f"medium_sigma_t must be >= 0 /m, got {sigma_t}")
    if g is not None and not 0.0 <= g < 1.0:
        raise ValueError(f"medium_g must be in [0, 1), got {g}")


def rig_scene(path: str, resolution: str, exposure_s: float | None, sigma_t: float | None = None,
              g: float | None = None) -> Scene:
    """The simulator's scene: ``path`` ("" the paper's tank) with its camera at ``resolution`` (the exposure
    scaled by (w/w_scene)² to keep the DN level) or at ``exposure_s``; the medium's σ_t and its phase
    function (TTHG of mean cosine ``g``) overridden when given."""
    base = load_scene(path or None)
    res, cam = parse_resolution(resolution), base.camera
    if res is not None and res != cam.resolution:
        cam = cam.resized(res)
    if exposure_s is not None:
        cam = cam.replace(exposure_s=exposure_s)
    medium = base.medium
    if sigma_t is not None:
        medium = medium.replace(sigma_t=float(sigma_t))
    if g is not None:
        medium = medium.replace(phase=Phase("tthg", float(g)))
    return base.replace(camera=cam, medium=medium)


def model_scene(scene: Scene, pattern: str, scale: int, target: bool = False) -> Scene:
    """``scene`` with its camera at the resolution the model runs at for ``pattern``: 1/``scale`` of the
    camera's (at least 2x2), checkers at twice that (their edges are what the high-frequency separation
    measures); with a calibration ``target`` the white (``flood``) frame, where its corners are found, at
    ``WHITE_SUPERSAMPLE`` times the camera's (:func:`to_camera` then averages each pixel's rays, as a sensor
    pixel integrates its area: one ray a pixel aliases the board's edges, docs/depth.md "Calibration")."""
    if target and pattern == "flood":
        w, h = scene.camera.resolution
        k = WHITE_SUPERSAMPLE
        return scene.replace(camera=scene.camera.replace(resolution=(w * k, h * k)))
    scale = max(1, scale // 2) if pattern.startswith("checker") else scale
    if scale <= 1:
        return scene
    w, h = scene.camera.resolution
    small = (max(2, round(w / scale)), max(2, round(h / scale)))
    return scene.replace(camera=scene.camera.replace(resolution=small))


def to_camera(radiance: np.ndarray, resolution: tuple[int, int]) -> np.ndarray:
    """``radiance`` at the camera's ``resolution`` (w, h): as is if it has it, else resized bilinearly (a
    larger one, a supersampled frame, is averaged over each pixel's area)."""
    w, h = resolution
    if radiance.shape == (h, w):
        return radiance
    larger = radiance.shape[0] > h and radiance.shape[1] > w
    return cv2.resize(radiance, (w, h), interpolation=cv2.INTER_AREA if larger else cv2.INTER_LINEAR)


def exposure_factor(radiance: np.ndarray, e_map: np.ndarray, camera, *, fill: float = 0.85,
                    percentile: float = 99.5) -> float:
    """The factor (≤ 1) on ``camera``'s exposure that puts the ``percentile`` of the mean signal of
    ``radiance`` at ``fill`` of the sensor's range above the dark offset (the ADC's or the full well's, the
    smaller); 1 when it is already below.

    ``e_map`` is electrons per unit radiance at ``camera``'s exposure; the signal in DN is
    ``radiance · e_map / K``.
    """
    peak = float(np.percentile(radiance * e_map, percentile)) / camera.gain_e_per_dn
    span = min(full_scale_dn(camera) - dark_offset_dn(camera), camera.full_well_e / camera.gain_e_per_dn)
    limit = fill * span
    return limit / peak if peak > limit else 1.0


class Target:
    """The calibration board of the simulator's ``target`` params: a ``board`` ("COLSxROWS" inner corners)
    checkerboard of ``square_m`` squares (its PNG in a temporary folder) at ``poses`` seeded poses
    (sim/scene_target.py), replacing the scene's objects. The projector's intensity is set at each pose
    (one probe render, the first time it is shown) so that the lit board reaches 60 % of full scale, as
    ``polarstripe calibrate --sim`` sets it: a far or tilted pose in the murk gets the light it needs.
    ``index`` is the pose shown."""

    def __init__(self, board: str, square_m: float, poses: int, seed: int, scene: Scene, fidelity):
        cols, rows = parse_board(board, "param 'target'")
        if not (math.isfinite(square_m) and square_m > 0) or poses < 1:
            raise SceneError(f"target_square_m={square_m} must be > 0 m and target_poses={poses} >= 1")
        self.folder = tempfile.mkdtemp(prefix="polarstripe-target-")
        self.texture = os.path.join(self.folder, "board.png")
        self.size = board_texture(cols, rows, square_m, self.texture)
        self.poses = target_poses(poses, seed, scene, cols, rows, square_m)
        self.scene, self.fidelity = scene, fidelity
        self.intensity: dict[int, float] = {}           # pose -> the projector's intensity [W/sr]
        self.index = 0
        self.calls = 0

    @classmethod
    def of(cls, params, scene: Scene, fidelity) -> Target | None:
        """The target of the simulator's params (None without ``target``)."""
        if not params.target:
            return None
        return cls(params.target, params.target_square_m, params.target_poses, params.target_seed, scene,
                   fidelity)

    def advance(self) -> int:
        """The pose of the next ``simulator/target`` call: k mod N at the k-th call (from 0)."""
        self.calls += 1
        return (self.calls - 1) % len(self.poses)

    def place(self, scene: Scene, index: int) -> Scene:
        """``scene`` with the board at pose ``index`` as its only object and the projector's intensity."""
        self.index = index
        if index not in self.intensity:
            lit = lit_for_target(self.scene, self.poses[index], self.texture, self.size, self.fidelity)
            self.intensity[index] = lit.projector.intensity_w_sr
        return with_target(scene, self.poses[index], self.texture, self.size).replace(
            projector=scene.projector.replace(intensity_w_sr=self.intensity[index]))

    def describe(self) -> str:
        pose = self.poses[self.index]
        point = ", ".join(f"{v:.4f}" for v in pose["point"])
        normal = ", ".join(f"{v:.3f}" for v in pose["normal"])
        return f"target pose {self.index} of {len(self.poses)}: point=({point}) normal=({normal})"

    def close(self) -> None:
        shutil.rmtree(self.folder, ignore_errors=True)


def micro_polarizers(params) -> MicroPolarizerArray:
    """The micro-polarizer array of ``simulator/render_mosaic`` from the ``mosaic_*`` params (its per-pixel
    extinction map seeded by ``seed``); ValueError names a bad param."""
    if len(params.mosaic_crosstalk) != 2:
        raise ValueError(f"mosaic_crosstalk must be [edge, diagonal], got {params.mosaic_crosstalk}")
    return MicroPolarizerArray(tuple(params.mosaic_layout), params.mosaic_extinction_ratio,
                               params.mosaic_extinction_spread, *params.mosaic_crosstalk,
                               seed=0 if params.seed is None else params.seed)


def host_ell14(link: str, node: str, log) -> SimEll14:
    """Start a simulated ELL14 on a pty and symlink it at ``link`` (the ``ell14_link`` param)."""
    dev = SimEll14()
    dev.start()
    try:
        if os.path.islink(link):
            os.unlink(link)
        os.symlink(dev.port, link)
    except OSError as exc:
        dev.stop()
        raise SimulatorError(f"node {node!r}: param 'ell14_link': cannot link {link!r}: {exc}") from None
    log.info("simulated ELL14 on %s (link %s)", dev.port, link)
    return dev


def parse_fault(command: str) -> tuple[str, list[str]]:
    """A ``simulator/fault`` command (msgs/rig.py ``FAULT_COMMANDS``) as (name, args); ValueError names what
    is wrong (an unknown command, a wrong count of numbers, seconds outside [0, 3600])."""
    words = command.split()
    if not words or words[0] not in FAULT_COMMANDS:
        raise ValueError(f"unknown fault command {command!r} (known: {', '.join(FAULT_COMMANDS)})")
    name, args = words[0], words[1:]
    wanted = {"frame_delay": 1, "bus_off": 1, "position_limit": 2}.get(name)
    if wanted is not None and len(args) != wanted:
        raise ValueError(f"{name} takes {wanted} number{'s' * (wanted > 1)}: "
                         f"{name} {FAULT_COMMANDS[name].split(':')[0]}")
    if name in ("frame_delay", "bus_off", "heartbeat_stop") and args and not 0.0 <= float(args[0]) <= 3600.0:
        raise ValueError(f"{name} {args[0]}: seconds must be in [0, 3600]")
    return name, args


def truth_composite(scene: Scene) -> Composite:
    """The ground truth of ``scene`` as ``simulator/truth`` publishes it (the node's docstring): the
    unscattered object radiance in DN above the dark offset (docs/physics.md §10.8), the chart's bands and
    bars, the objects' depth, and the rig's geometry at the current source pose."""
    radiance, surface = unscattered_object(scene)
    cam = scene.camera
    signal = mean_dn(radiance, cam) - dark_offset_dn(cam)
    return Composite(
        images={"S": signal.astype(np.float64),
                "chart_band": surface.chart_band.astype(np.int32),
                "chart_high": surface.chart_high.astype(bool),
                "depth_m": np.nan_to_num(depth_truth(scene), nan=0.0).astype(np.float32)},
        method="truth",
        metrics={"separation_m": scene.separation_m(), "exposure_s": cam.exposure_s,
                 "dark_offset_dn": dark_offset_dn(cam), "rig_geometry": {  # the source moves
                     k: np.asarray(v, float).tolist() for k, v in rig_geometry(scene).items()}},
    )
