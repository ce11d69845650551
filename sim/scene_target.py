"""A calibration target in a scene: a planar checkerboard (a PNG texture on a plane, docs/scene-format.md) at
seeded poses where both the camera and the projector see it, and the projector's intensity that lights it
well. Used by ``polarstripe calibrate --sim`` (tools/calibrate_cli.py) and by the simulator node's
``target`` params (nodes/simulator.py: the board of a calibration over the rig's nodes,
launch/calibrate.toml).
The method itself is docs/depth.md "Calibration".
"""

from __future__ import annotations

import cv2
import numpy as np
from polarstripe.sim.geometry import pinhole_frame
from polarstripe.sim.polarization import analyzer
from polarstripe.sim.port import light_to, port_geometry
from polarstripe.sim.render import render_components
from polarstripe.sim.scene import PlaneObject, Scene, SceneError
from polarstripe.sim.sensor import dark_offset_dn, mean_dn


def parse_board(text: str, what: str = "--board") -> tuple[int, int]:
    """``COLSxROWS`` inner corners (at least 3x3)."""
    try:
        cols, rows = (int(v) for v in str(text).lower().split("x"))
    except ValueError:
        raise SceneError(f"{what} {text!r} is not COLSxROWS (inner corners)") from None
    if min(cols, rows) < 3:
        raise SceneError(f"{what} {text!r}: need at least 3x3 inner corners")
    return cols, rows


def board_size(cols: int, rows: int, square_m: float) -> tuple[float, float]:
    """The size (w, h) [m] of the board of :func:`board_texture`: its squares and a one-square margin."""
    return (cols + 3) * square_m, (rows + 3) * square_m


def board_texture(cols: int, rows: int, square_m: float, path: str, dark: int = 64) -> tuple[float, float]:
    """Write the checkerboard PNG of ``cols``×``rows`` inner corners (one texel per square, dark squares at
    ``dark``/255 of white, a one-square white margin); return its size [m] (:func:`board_size`)."""
    nx, ny = cols + 3, rows + 3
    img = np.full((ny, nx), 255, np.uint8)
    for i in range(rows + 1):
        for j in range(cols + 1):
            if (i + j) % 2 == 0:
                img[1 + i, 1 + j] = dark
    if not cv2.imwrite(path, img):
        raise SceneError(f"cannot write the board texture {path!r}")
    return board_size(cols, rows, square_m)


MAX_VIEW_DEG = 80.0      # a device sees the board at most this far from its normal (not edge-on)
EDGE = 0.02              # the board's squares stay this fraction of the image inside its edges
TRIES = 400              # draws per pose before giving up


def target_poses(n: int, seed: int, scene: Scene, cols: int, rows: int, square_m: float) -> list[dict]:
    """Board poses (plane ``point``, ``normal``, ``up``) where camera and projector both see the whole
    checkerboard of ``cols``×``rows`` inner corners (its (cols + 1)×(rows + 1) squares of ``square_m``):
    around the point where the camera's axis and the projector's pass nearest each other, 8–30 % nearer than
    it, shifted ±10 % of its distance, tilted 15–40° either way about two axes and turned up to ±15° in its
    plane. A draw is kept when the board faces each device within :data:`MAX_VIEW_DEG` and its squares'
    outer corners reach each device's image (:data:`EDGE` inside) — through the device's port where it has
    one (sim/port.py ``light_to``: a port narrows the view) — and drawn again otherwise (a scene where every
    draw is seen gets the poses it always got).

    :raises SceneError: no draw of a pose is seen whole in :data:`TRIES` (a board too large for the common
        view)."""
    rng = np.random.default_rng(seed)
    c, p = np.asarray(scene.camera.position, float), np.asarray(scene.projector.position, float)
    fc, fp = _forward(scene.camera), _forward(scene.projector)
    # closest points of the two axes: the middle of the common view
    w0, b = c - p, fc @ fp
    den = max(1.0 - b * b, 1e-9)
    s = (b * (fp @ w0) - (fc @ w0)) / den
    t = ((fp @ w0) - b * (fc @ w0)) / den
    centre = 0.5 * ((c + s * fc) + (p + t * fp))
    dist = float(np.linalg.norm(centre - c))
    up0 = np.asarray(scene.camera.up, float)
    right = np.cross(fc, up0)
    right /= np.linalg.norm(right)
    up = np.cross(right, fc)
    views = [_View(scene.camera), _View(scene.projector)]
    half = 0.5 * square_m * np.array([cols + 1, rows + 1])
    poses = []
    for k in range(n):
        for _ in range(TRIES):
            pose = _draw(rng, centre, dist, fc, right, up)
            if _seen(pose, half, views):
                poses.append(pose)
                break
        else:
            raise SceneError(f"the {cols}x{rows} board of {square_m} m squares is not seen whole by camera "
                             f"and projector at pose {k} in {TRIES} draws: a smaller board (fewer or smaller "
                             "squares)")
    return poses


def _forward(device) -> np.ndarray:
    f = np.subtract(device.look_at, device.position)
    return f / np.linalg.norm(f)


def _draw(rng, centre, dist, fc, right, up) -> dict:
    """A board near ``centre`` (:func:`target_poses`) facing the camera (axis ``fc``), tilted and turned."""
    a, bb = np.radians(rng.uniform(15, 40, 2) * rng.choice([-1, 1], 2))
    roll = np.radians(rng.uniform(-15, 15))
    normal = -fc * np.cos(a) * np.cos(bb) + right * np.sin(bb) + up * np.sin(a) * np.cos(bb)
    normal /= np.linalg.norm(normal)
    u = up * np.cos(roll) + right * np.sin(roll)
    u -= normal * (u @ normal)
    shift = rng.uniform(-0.1, 0.1, 2) * dist
    depth = rng.uniform(-0.3, -0.08) * dist
    point = centre + right * shift[0] + up * shift[1] + fc * depth
    return {"point": tuple(point), "normal": tuple(normal), "up": tuple(u / np.linalg.norm(u))}


class _View:
    """A device's image as seen from the water: pixel of a world point through its port."""

    def __init__(self, device):
        self.frame = pinhole_frame(device.position, device.look_at, device.up, device.fov_deg,
                                   device.resolution)
        self.port = None if device.port is None else port_geometry(device.port, self.frame.position,
                                                                    self.frame.f)

    def sees(self, points: np.ndarray, normal: np.ndarray) -> bool:
        fr = self.frame
        to_dev = fr.position - points.mean(axis=0)
        if normal @ to_dev < np.cos(np.radians(MAX_VIEW_DEG)) * np.linalg.norm(to_dev):
            return False
        a = points - fr.position if self.port is None else light_to(self.port, points).air
        z = a @ fr.f
        if not (np.isfinite(a).all() and (z > 0).all()):
            return False
        x, y = fr.w / 2 + (a @ fr.r) / z / fr.s, fr.h / 2 - (a @ fr.u) / z / fr.s
        inside = (np.minimum(x, fr.w - x) > EDGE * fr.w) & (np.minimum(y, fr.h - y) > EDGE * fr.h)
        return bool(inside.all())


def _seen(pose: dict, half, views) -> bool:
    n, u = np.asarray(pose["normal"]), np.asarray(pose["up"])
    r = np.cross(u, n)
    corners = np.array([pose["point"] + i * half[0] * r + j * half[1] * u for i in (-1, 1) for j in (-1, 1)])
    return all(v.sees(corners, n) for v in views)


def with_target(scene: Scene, pose: dict, texture: str, size) -> Scene:
    """``scene`` with the board (albedo 0.8 under the texture) at ``pose`` as its only object."""
    board = PlaneObject(point=pose["point"], normal=pose["normal"], up=pose["up"], size=size, albedo=0.8,
                        texture=texture)
    return scene.replace(objects=(board,))


def lit_for_target(scene: Scene, pose: dict, texture: str, size, fidelity, level: float = 0.6,
                   polarizer_deg: float | None = None) -> Scene:
    """``scene`` with the projector's intensity set so that the white board's brightest pixels (99.5th
    percentile), seen through the analyzer at ``polarizer_deg`` (None: none), reach ``level`` of the
    camera's full scale above the dark offset. The radiance is linear in the intensity: one probe render at
    1 mW/sr scales it, read as the sensor's mean DN (noise-free and unquantized: a probe this dim gives a few
    DN, and its rounded, noisy percentile set every pose alike, 40-50 % of full scale instead of 60 %)."""
    probe = 1e-3
    sc = with_target(scene.replace(projector=scene.projector.replace(intensity_w_sr=probe)), pose, texture,
                     size)
    radiance = analyzer(render_components(sc, "flood", fidelity), polarizer_deg)
    signal = float(np.percentile(mean_dn(radiance, sc.camera), 99.5)) - dark_offset_dn(sc.camera)
    full = 2 ** sc.camera.bits - 1 - sc.camera.offset_dn
    if not signal > 0:
        raise SceneError("the board is dark even at full exposure: the projector does not light it")
    return scene.replace(projector=scene.projector.replace(intensity_w_sr=probe * level * full / signal))
