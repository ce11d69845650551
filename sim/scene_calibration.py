"""A scene's camera and projector from a rig calibration file (``polarstripe calibrate``, docs/depth.md
"Calibration"): the scene key ``calibration = "rig.yaml"`` (docs/scene-format.md) and the planner's
``calibration`` param.

The file is OpenCV FileStorage (``K_cam``, ``K_proj``, ``R``, ``T`` with X_p = R·X_c + T [m], ``cam_size``,
``proj_size`` [w, h]). The model's pinholes (docs/scene-format.md "Geometry") have square pixels, the
principal point at the image centre and no distortion, so a file sets of each device:

* ``resolution`` = its size, ``fov_deg`` = 2·atan(w / (2·f)) with f = (f_x + f_y)/2 (the horizontal fov);
* the projector's pose relative to the camera (which keeps the scene's pose): its centre
  C_p = −Rᵀ·T and its axes (forward Rᵀ·z, image up −Rᵀ·y) in the OpenCV camera frame (x right, y down,
  z forward = the scene's r, −u, f; sim/depth_truth.py), its ``look_at`` as far ahead as the camera's.

The principal point and f_x ≠ f_y cannot be represented: a file whose principal point is more than
``MAX_CENTRE_OFFSET`` of the width (height) from the centre, or whose f_x and f_y differ by more than
``MAX_ASPECT`` (relative), is refused (the model would render another rig). The lens distortion is not taken.
A file written through flat ports (``port_cam``, ``port_proj``) sets each device's ``port`` too, its normal
turned into the world (the scene's ``coated`` kept).
A file of another rig size than the scene states is one error.
"""

from __future__ import annotations

import numpy as np
from polarstripe.sim.filestorage import read_storage
from polarstripe.sim.scene_checks import SceneError
from polarstripe.sim.scene_parts import Scene
from polarstripe.sim.scene_port import Port

MAX_CENTRE_OFFSET = 0.05  # of the image width (height): the principal point's distance from the centre
MAX_ASPECT = 0.01  # relative difference of f_x and f_y
KEYS = ("K_cam", "K_proj", "R", "T", "cam_size", "proj_size")
PORT_KEYS = ("port_cam", "port_proj")  # a rig calibrated through flat ports (imaging/port_calibration.py)


def read_rig(path: str) -> dict:
    """The rig of a calibration file: ``K_cam``, ``K_proj`` (3, 3), ``R`` (3, 3), ``T`` (3,),
    ``cam_size``, ``proj_size`` ((w, h) ints). SceneError naming the file and what is wrong with it (a file
    OpenCV cannot parse, a missing key: sim/filestorage.py)."""
    try:
        out = read_storage(path, KEYS + PORT_KEYS, optional=PORT_KEYS)
    except ValueError as exc:
        hint = " (written by polarstripe calibrate?)" if "missing" in str(exc) else ""
        raise SceneError(f"calibration {path!r}: {exc}{hint}") from None
    shapes = {"K_cam": (3, 3), "K_proj": (3, 3), "R": (3, 3), "T": (3,), "cam_size": (2,), "proj_size": (2,)}
    for key, shape in shapes.items():
        if out[key].size != int(np.prod(shape)) or not np.all(np.isfinite(out[key])):
            raise SceneError(f"calibration {path!r}: {key} must be {shape} finite numbers")
        out[key] = out[key].reshape(shape)
    for key in ("cam_size", "proj_size"):
        out[key] = tuple(int(round(v)) for v in out[key])
    for key in PORT_KEYS:
        if out[key] is not None and (out[key].size != 8 or not np.all(np.isfinite(out[key]))):
            raise SceneError(f"calibration {path!r}: {key} must be 8 finite numbers")
    return out


def _port(numbers, to_world: np.ndarray, old: Port | None, key: str) -> Port:
    """A file's port (normal in the device's OpenCV frame, d, t, n_a, n_g, n_w) in the world; the scene's
    ``coated`` kept (a calibration does not measure the Fresnel loss)."""
    a = np.ravel(numbers)
    return Port(distance_m=float(a[3]), thickness_m=float(a[4]), n_air=float(a[5]), n_glass=float(a[6]),
                n_water=float(a[7]), normal=tuple((to_world @ a[:3]).tolist()),
                coated=False if old is None else old.coated, key=key)


def _fov(K: np.ndarray, size: tuple[int, int], what: str, path: str) -> float:
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    w, h = size
    if not (fx > 0 and fy > 0) or abs(fx / fy - 1) > MAX_ASPECT:
        raise SceneError(f"calibration {path!r}: {what} f_x={fx:.2f}, f_y={fy:.2f} px: the model's pixels "
                         f"are square (within {MAX_ASPECT:.0%})")
    if abs(cx - (w / 2 - 0.5)) > MAX_CENTRE_OFFSET * w or abs(cy - (h / 2 - 0.5)) > MAX_CENTRE_OFFSET * h:
        raise SceneError(f"calibration {path!r}: {what} principal point ({cx:.1f}, {cy:.1f}) px is more than "
                         f"{MAX_CENTRE_OFFSET:.0%} of the {w}x{h} image from its centre: the model's pinhole "
                         "cannot render it")
    return float(np.degrees(2 * np.arctan(w / (fx + fy))))


def with_calibration(scene: Scene, path: str, *, cam_size: tuple[int, int] | None = None,
                     proj_size: tuple[int, int] | None = None, stated_ports: tuple[str, ...] = ()) -> Scene:
    """``scene`` with its camera's resolution and fov and its projector's resolution, fov and pose from the
    calibration file ``path`` (module docstring), and the ports of a file written through them.
    ``cam_size`` / ``proj_size``: the sizes the scene or the launch states (the camera may be binned by an
    integer factor); another size is one SceneError, and so is a port the file has and ``stated_ports``
    (the sections whose ``port`` the scene sets) too."""
    rig = read_rig(path)
    for key, part in zip(PORT_KEYS, ("camera", "projector"), strict=True):
        if rig[key] is not None and part in stated_ports:
            raise SceneError(f"{part}.port is set by the calibration file {path!r}: give one or the other")
    cw, ch = rig["cam_size"]
    if cam_size is not None:
        w, h = cam_size
        if not (cw % w == 0 and ch % h == 0 and cw // w == ch // h):
            raise SceneError(f"calibration {path!r} is of a {cw}x{ch} camera; the rig's is {w}x{h} (not an "
                             "integer binning of it): calibrate this rig")
    if proj_size is not None and tuple(proj_size) != rig["proj_size"]:
        pw, ph = rig["proj_size"]
        raise SceneError(f"calibration {path!r} is of a {pw}x{ph} projector; the rig's is "
                         f"{proj_size[0]}x{proj_size[1]}: calibrate this rig")
    fov_c = _fov(rig["K_cam"], rig["cam_size"], "camera", path)
    fov_p = _fov(rig["K_proj"], rig["proj_size"], "projector", path)
    cam = scene.camera
    c = np.asarray(cam.position, float)
    f = np.subtract(cam.look_at, c)
    reach = float(np.linalg.norm(f))
    f /= reach
    r = np.cross(f, cam.up)
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    to_world = np.column_stack([r, -u, f])  # OpenCV camera frame (x right, y down, z forward) -> world
    R, T = rig["R"], rig["T"]
    centre = c + to_world @ (-R.T @ T)
    forward = to_world @ (R.T @ np.array([0.0, 0.0, 1.0]))
    up = to_world @ (R.T @ np.array([0.0, -1.0, 0.0]))
    new_cam = cam.replace(resolution=tuple(cam_size or rig["cam_size"]), fov_deg=fov_c)
    proj = scene.projector.replace(resolution=rig["proj_size"], fov_deg=fov_p,
                                   position=tuple(centre.tolist()),
                                   look_at=tuple((centre + reach * forward).tolist()), up=tuple(up.tolist()))
    if rig["port_cam"] is not None:
        new_cam = new_cam.replace(port=_port(rig["port_cam"], to_world, cam.port, "camera.port"))
    if rig["port_proj"] is not None:
        proj = proj.replace(port=_port(rig["port_proj"], to_world @ R.T, scene.projector.port,
                                       "projector.port"))
    return scene.replace(camera=new_cam, projector=proj)
