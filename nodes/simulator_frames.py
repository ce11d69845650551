"""What the simulator node computes, as plain functions: the model's resolution per pattern, a timed component
render, the radiance resized to the camera, the auto-exposure factor; its error type and the ``resolution``
param's parser. (The sensor is :func:`polarstripe.sim.sensor.expose`, given the node's precomputed electrons
map.)"""

from __future__ import annotations

import time

import cv2
import numpy as np
from polarstripe.sim.render import render_components
from polarstripe.sim.scene import Scene, SceneError, parse_size
from polarstripe.sim.sensor import dark_offset_dn, full_scale_dn

PREVIEW_WIDTH = 160  # model width [px] the preview render scale aims at


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


def model_scene(scene: Scene, pattern: str, scale: int) -> Scene:
    """``scene`` with its camera at the resolution the model runs at for ``pattern``: 1/``scale`` of the
    camera's (at least 2x2), checkers at twice that (their edges are what the high-frequency separation
    measures)."""
    scale = max(1, scale // 2) if pattern.startswith("checker") else scale
    if scale <= 1:
        return scene
    w, h = scene.camera.resolution
    small = (max(2, round(w / scale)), max(2, round(h / scale)))
    return scene.replace(camera=scene.camera.replace(resolution=small))


def timed_render(scene: Scene, pattern: str, fidelity):
    """(components of ``pattern``, seconds the render took)."""
    t0 = time.perf_counter()
    comp = render_components(scene, pattern, fidelity)
    return comp, time.perf_counter() - t0


def to_camera(radiance: np.ndarray, resolution: tuple[int, int]) -> np.ndarray:
    """``radiance`` at the camera's ``resolution`` (w, h): as is if it has it, else resized bilinearly."""
    w, h = resolution
    if radiance.shape == (h, w):
        return radiance
    return cv2.resize(radiance, (w, h), interpolation=cv2.INTER_LINEAR)


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
