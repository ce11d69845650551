"""The rig's geometry for exports and live views: where the camera, projector and analyzer are (tf poses)
and their pinhole intrinsics (``CameraInfo`` / ``foxglove.CameraCalibration``), from the recording's scene.

Frames (ROS REP 103/105 style; the scene's coordinates are the tank's, metres)::

    tank ─┬─ camera ── polarizer      camera: optical frame (x image right, y image down, z forward)
          └─ projector                projector: the same convention for the projector's image

The ``polarizer`` (analyzer) frame sits on the camera's optical axis with the camera's orientation; the
analyzer's angle [deg, from image right toward image up] travels apart (``JointState`` / the polarizer
state's ``angle_deg``).

Intrinsics follow the model's pinhole (:mod:`polarstripe.sim.geometry`: horizontal ``fov_deg``, square
pixels, the ray through pixel (i, j) passing its centre): for an image ``w`` × ``h`` pixels,
``fx = fy = w / (2 tan(fov/2))``, ``cx = w/2 − 0.5``, ``cy = h/2 − 0.5``, no distortion. They are computed
for each image's own size (the simulator renders any resolution with the scene's field of view).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from polarstripe.sim.scene import Scene, SceneError, load_scene, with_separation

WORLD, CAMERA, PROJECTOR, POLARIZER = "tank", "camera", "projector", "polarizer"
SIMULATOR_MODULE = "polarstripe.nodes.simulator"


@dataclass(frozen=True)
class Pose:
    """``child`` in ``parent``: translation [m] and rotation quaternion (x, y, z, w)."""

    parent: str
    child: str
    translation: tuple[float, float, float]
    rotation: tuple[float, float, float, float]


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics of an image ``width`` × ``height`` [px]: focal lengths and principal point [px]."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    @property
    def k(self) -> list[float]:
        """The 3×3 camera matrix, row-major."""
        return [self.fx, 0.0, self.cx, 0.0, self.fy, self.cy, 0.0, 0.0, 1.0]

    @property
    def p(self) -> list[float]:
        """The 3×4 projection matrix of a monocular camera, row-major."""
        return [self.fx, 0.0, self.cx, 0.0, 0.0, self.fy, self.cy, 0.0, 0.0, 0.0, 1.0, 0.0]


def pinhole(fov_deg: float, width: int, height: int) -> Intrinsics:
    """Intrinsics of the model's pinhole (horizontal field of view ``fov_deg``) at ``width`` × ``height``."""
    f = width / (2.0 * math.tan(math.radians(fov_deg) / 2.0))
    return Intrinsics(int(width), int(height), f, f, width / 2.0 - 0.5, height / 2.0 - 0.5)


def quaternion(m: np.ndarray) -> tuple[float, float, float, float]:
    """The unit quaternion (x, y, z, w) of a 3×3 rotation matrix (Shepperd's method)."""
    t = np.trace(m)
    if t > 0:
        s = 2.0 * math.sqrt(t + 1.0)
        q = ((m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s)
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k])
        q = [0.0, 0.0, 0.0, (m[k, j] - m[j, k]) / s]
        q[i], q[j], q[k] = 0.25 * s, (m[j, i] + m[i, j]) / s, (m[k, i] + m[i, k]) / s
    n = math.sqrt(sum(c * c for c in q))
    return tuple(float(c) / n for c in q)  # type: ignore[return-value]


def optical_pose(parent: str, child: str, position, look_at, up) -> Pose:
    """The optical frame (x right, y down, z forward) of a pinhole at ``position`` looking at ``look_at``."""
    p = np.asarray(position, float)
    f = np.asarray(look_at, float) - p
    f /= np.linalg.norm(f)
    r = np.cross(f, np.asarray(up, float))
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    rot = np.column_stack([r, -u, f])
    return Pose(parent, child, tuple(float(c) for c in p), quaternion(rot))  # type: ignore[arg-type]


@dataclass(frozen=True)
class RigGeometry:
    """The scene of a recording, where it came from, and the projector's image size [px]."""

    scene: Scene
    source: str
    projector_size: tuple[int, int]

    def poses(self) -> list[Pose]:
        """tank → camera, camera → polarizer, tank → projector."""
        c, pr = self.scene.camera, self.scene.projector
        return [
            optical_pose(WORLD, CAMERA, c.position, c.look_at, c.up),
            Pose(CAMERA, POLARIZER, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)),
            optical_pose(WORLD, PROJECTOR, pr.position, pr.look_at, pr.up),
        ]

    def camera(self, width: int, height: int) -> Intrinsics:
        """The camera's intrinsics for an image ``width`` × ``height``."""
        return pinhole(self.scene.camera.fov_deg, width, height)

    def projector(self) -> Intrinsics:
        """The projector's intrinsics at its image size."""
        return pinhole(self.scene.projector.fov_deg, *self.projector_size)

    def separated(self, separation_m: float) -> RigGeometry:
        """The same rig with the source moved to camera–source distance ``separation_m`` [m]."""
        if not (math.isfinite(separation_m) and separation_m > 0):
            return self
        return RigGeometry(with_separation(self.scene, separation_m), self.source, self.projector_size)


def _nodes(metadata: dict) -> dict:
    try:
        return json.loads(metadata.get("launch", {}).get("graph", "") or "{}").get("nodes", {}) or {}
    except (ValueError, AttributeError):
        return {}


def _projector_size(nodes: dict, scene: Scene) -> tuple[int, int]:
    for node in nodes.values():
        display = (node.get("params", {}) or {}).get("display_options", {}) or {}
        if isinstance(display, dict) and ("width" in display or "height" in display):
            try:
                w = int(display.get("width") or scene.projector.resolution[0])
                h = int(display.get("height") or scene.projector.resolution[1])
            except (TypeError, ValueError):
                continue
            if w > 0 and h > 0:
                return w, h
    return scene.projector.resolution


def geometry_from_metadata(metadata: dict, scene_path=None) -> tuple[RigGeometry | None, str]:
    """The rig's geometry of a recording and a note saying where it came from (or why there is none).

    ``scene_path`` (a scene TOML) wins; else a node's ``scene`` param in the recorded launch graph (relative
    paths from the working directory, then from the launch file's folder); else the paper's tank when the
    launch ran the simulator; else None (a rig without a scene file: no tf, no camera info).
    Raises :class:`~polarstripe.sim.scene.SceneError` or ``OSError`` for a ``scene_path`` that cannot be read.
    """
    nodes = _nodes(metadata)
    if scene_path:
        scene = load_scene(scene_path)
        return RigGeometry(scene, f"scene {scene_path}", _projector_size(nodes, scene)), f"scene {scene_path}"
    launch_dir = Path(metadata.get("launch", {}).get("file", "") or ".").parent
    for name, node in sorted(nodes.items()):
        text = str((node.get("params", {}) or {}).get("scene", "") or "")
        if not text:
            continue
        for candidate in (Path(text), launch_dir / text):
            try:
                scene = load_scene(candidate)
            except (OSError, SceneError):
                continue
            note = f"scene {candidate} (node {name})"
            return RigGeometry(scene, note, _projector_size(nodes, scene)), note
        return None, f"scene {text!r} of node {name!r} not found: no tf, no camera info"
    if any(node.get("module", "").split(":")[0] == SIMULATOR_MODULE for node in nodes.values()):
        scene = Scene()
        return RigGeometry(scene, "the default tank (simulator)", _projector_size(nodes, scene)), (
            "the default tank (simulator)"
        )
    return None, "no scene in the recording (give --scene FILE): no tf, no camera info"
