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
from polarstripe.sim.render import render_frame
from polarstripe.sim.scene import PlaneObject, Scene, SceneError


def parse_board(text: str, what: str = "--board") -> tuple[int, int]:
    """``COLSxROWS`` inner corners (at least 3x3)."""
    try:
        cols, rows = (int(v) for v in str(text).lower().split("x"))
    except ValueError:
        raise SceneError(f"{what} {text!r} is not COLSxROWS (inner corners)") from None
    if min(cols, rows) < 3:
        raise SceneError(f"{what} {text!r}: need at least 3x3 inner corners")
    return cols, rows


def board_texture(cols: int, rows: int, square_m: float, path: str, dark: int = 64) -> tuple[float, float]:
    """Write the checkerboard PNG of ``cols``×``rows`` inner corners (one texel per square, dark squares at
    ``dark``/255 of white, a one-square white margin); return its size [m]."""
    nx, ny = cols + 3, rows + 3
    img = np.full((ny, nx), 255, np.uint8)
    for i in range(rows + 1):
        for j in range(cols + 1):
            if (i + j) % 2 == 0:
                img[1 + i, 1 + j] = dark
    if not cv2.imwrite(path, img):
        raise SceneError(f"cannot write the board texture {path!r}")
    return nx * square_m, ny * square_m


def target_poses(n: int, seed: int, scene: Scene) -> list[dict]:
    """Board poses (plane ``point``, ``normal``, ``up``) where camera and projector both see it: around the
    point where the camera's axis and the projector's pass nearest each other, 8–30 % nearer than it, shifted
    ±10 % of its distance, tilted 15–40° either way about two axes and turned up to ±15° in its plane."""
    rng = np.random.default_rng(seed)
    c, p = np.asarray(scene.camera.position, float), np.asarray(scene.projector.position, float)
    fc = np.subtract(scene.camera.look_at, c)
    fc /= np.linalg.norm(fc)
    fp = np.subtract(scene.projector.look_at, p)
    fp /= np.linalg.norm(fp)
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
    poses = []
    for _ in range(n):
        a, bb = np.radians(rng.uniform(15, 40, 2) * rng.choice([-1, 1], 2))
        roll = np.radians(rng.uniform(-15, 15))
        normal = -fc * np.cos(a) * np.cos(bb) + right * np.sin(bb) + up * np.sin(a) * np.cos(bb)
        normal /= np.linalg.norm(normal)
        u = up * np.cos(roll) + right * np.sin(roll)
        u -= normal * (u @ normal)
        shift = rng.uniform(-0.1, 0.1, 2) * dist
        depth = rng.uniform(-0.3, -0.08) * dist
        point = centre + right * shift[0] + up * shift[1] + fc * depth
        poses.append({"point": tuple(point), "normal": tuple(normal), "up": tuple(u / np.linalg.norm(u))})
    return poses


def with_target(scene: Scene, pose: dict, texture: str, size) -> Scene:
    """``scene`` with the board (albedo 0.8 under the texture) at ``pose`` as its only object."""
    board = PlaneObject(point=pose["point"], normal=pose["normal"], up=pose["up"], size=size, albedo=0.8,
                        texture=texture)
    return scene.replace(objects=(board,))


def lit_for_target(scene: Scene, pose: dict, texture: str, size, fidelity, level: float = 0.6,
                   polarizer_deg: float | None = None) -> Scene:
    """``scene`` with the projector's intensity set so that the white board's brightest pixels (99.5th
    percentile), seen through the analyzer at ``polarizer_deg`` (None: none), reach ``level`` of the
    camera's full scale above the dark offset (the radiance is linear in the intensity: one probe render at
    1 mW/sr scales it)."""
    probe = 1e-3
    sc = scene.replace(projector=scene.projector.replace(intensity_w_sr=probe))
    white, _ = render_frame(with_target(sc, pose, texture, size), "flood", polarizer_deg, fidelity, seed=0)
    signal = float(np.percentile(white, 99.5)) - sc.camera.offset_dn
    full = 2 ** sc.camera.bits - 1 - sc.camera.offset_dn
    if signal <= 0:
        raise SceneError("the board is dark even at full exposure: the projector does not light it")
    return scene.replace(projector=scene.projector.replace(intensity_w_sr=probe * level * full / signal))
