"""The rig moving during a scan (docs/planning.md §11): when each frame is taken, and the scene at that time.

A scan's frames are taken 1/fps apart, and a rotating analyzer's stage turns between its passes (E_b, then
E_w), which takes |Δφ|/ω + t_settle: the simulated CiA 402 drive's model (constant speed ω, no acceleration,
``settle_s`` at the target; nodes/drivers/sim402_axis.py). Frame i of a scan of n frames per pass at the
analyzer angles φ_0, φ_1, … is taken at

    t_i = i / fps + Σ_{k < ⌊i/n⌋} (|φ_{k+1} − φ_k| / ω + t_settle)                    (:func:`capture_times`)

and the rig is translated by v·(t_i − t_mid), t_mid = (t_0 + t_last)/2: it passes the scene's own pose at the
middle of the scan, where the ground truth is taken (the composite mixes every frame of the scan, so the
middle is the one pose it is centred on; against the start pose the error would also count half the scan's
travel, a shift a navigation log removes, and +v and −v would score differently).

The velocity is given in the rig's frame (:func:`rig_axes`): x along the baseline from the camera toward the
projector (perpendicular to the view axis), z the camera's view axis, y = z × x (for the default tank: x, y, z
of the scene). :func:`moved` translates the camera, the projector and the medium's extent together: the water
around a vehicle travels with it (the tank's walls would otherwise come into view after 0.3 m), so only the
objects move relative to the rig. The pose is held for the exposure (a few ms: v·t_exp is under a pixel at
the speeds of docs/planning.md §11, against the scan's travel of tens of pixels), so there is no blur within
one frame.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from polarstripe.sim.scene import Scene, baseline_direction
from polarstripe.sim.scene_checks import SceneError, Vec3, vec3


@dataclass(frozen=True)
class RigMotion:
    """A constant velocity of the rig during scans and the timing of its frames.

    ``velocity_m_s`` [m/s] in the rig frame (x along the baseline, y across it, z forward; module
    docstring); ``fps`` the camera's frame rate [1/s]; ``stage_deg_s`` [deg/s] and ``stage_settle_s`` [s]
    the analyzer stage's speed and settle time (a move of Δφ takes |Δφ|/speed + settle)."""

    velocity_m_s: Vec3 = (0.0, 0.0, 0.0)
    fps: float = 30.0
    stage_deg_s: float = 200.0
    stage_settle_s: float = 0.02

    def __post_init__(self):
        object.__setattr__(self, "velocity_m_s", vec3("velocity_m_s", self.velocity_m_s))
        for key in ("fps", "stage_deg_s"):
            value = getattr(self, key)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise SceneError(f"{key} must be a positive number, got {value!r}")
        if not (math.isfinite(self.stage_settle_s) and self.stage_settle_s >= 0):
            raise SceneError(f"stage_settle_s must be >= 0 s, got {self.stage_settle_s!r}")

    @property
    def moving(self) -> bool:
        """False for a rig at rest (every frame at the scene's pose, bit-identical to a static render)."""
        return any(v != 0.0 for v in self.velocity_m_s)

    def times(self, frames_per_pass: int, angles_deg: Sequence[float] = ()) -> np.ndarray:
        """The capture times of a scan's frames (:func:`capture_times` with this rig's timing)."""
        return capture_times(frames_per_pass, angles_deg, self.fps, self.stage_deg_s, self.stage_settle_s)

    def scene_at(self, scene: Scene, times: np.ndarray, i: int) -> Scene:
        """``scene`` as frame ``i`` of a scan with capture ``times`` sees it: the rig translated by
        v·(t_i − t_mid) (``scene`` itself at rest, or for a frame outside ``times``)."""
        if not self.moving or not 0 <= i < len(times):
            return scene
        t_mid = 0.5 * (float(times[0]) + float(times[-1]))
        return moved(scene, rig_axes(scene).T @ np.asarray(self.velocity_m_s) * (float(times[i]) - t_mid))


def stage_move_s(from_deg: float, to_deg: float, deg_s: float, settle_s: float) -> float:
    """The time [s] the analyzer stage takes from ``from_deg`` to ``to_deg``: |Δφ|/``deg_s`` + ``settle_s``
    (the simulated drive's constant speed, nodes/drivers/sim402_axis.py; no move, no time)."""
    delta = abs(float(to_deg) - float(from_deg))
    return delta / deg_s + settle_s if delta > 0 else 0.0


def capture_times(frames_per_pass: int, angles_deg: Sequence[float], fps: float, deg_s: float,
                  settle_s: float) -> np.ndarray:
    """Capture times [s] of a scan's frames, the first at 0 (module docstring): ``frames_per_pass`` frames
    at each analyzer angle of ``angles_deg`` in order (one pass when there is none), 1/``fps`` apart, the
    stage's move between passes (:func:`stage_move_s`) added before each later pass."""
    if frames_per_pass < 1:
        raise SceneError(f"frames_per_pass must be >= 1, got {frames_per_pass}")
    angles = [float(a) for a in angles_deg] or [0.0]
    moves = np.concatenate([[0.0], np.cumsum([stage_move_s(a, b, deg_s, settle_s)
                                              for a, b in zip(angles, angles[1:], strict=False)])])
    i = np.arange(frames_per_pass * len(angles))
    return i / fps + moves[i // frames_per_pass]


def rig_axes(scene: Scene) -> np.ndarray:
    """(3, 3): the rig frame's x, y, z axes (rows, unit, world coordinates): x along the baseline
    (:func:`~polarstripe.sim.scene.baseline_direction`), z the camera's view axis, y = z × x."""
    z = np.subtract(scene.camera.look_at, scene.camera.position)
    z /= np.linalg.norm(z)
    x = baseline_direction(scene)
    return np.stack([x, np.cross(z, x), z])


def moved(scene: Scene, offset_m) -> Scene:
    """``scene`` with the rig translated by ``offset_m`` (3,) [m, world]: camera, projector (positions and
    aim points) and the medium's extent; the objects stay (module docstring)."""
    d = np.asarray(offset_m, float)
    if d.shape != (3,) or not np.all(np.isfinite(d)):
        raise SceneError(f"offset_m must be 3 finite numbers [m], got {offset_m!r}")

    def shift(v):
        return tuple((np.asarray(v, float) + d).tolist())

    cam, proj, ext = scene.camera, scene.projector, scene.medium.extent
    return scene.replace(
        camera=cam.replace(position=shift(cam.position), look_at=shift(cam.look_at)),
        projector=proj.replace(position=shift(proj.position), look_at=shift(proj.look_at)),
        medium=scene.medium.replace(extent=ext.replace(min=shift(ext.min), max=shift(ext.max))))
