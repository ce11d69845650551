"""The simulator's depth truth and the rig's geometry as plain numbers (OpenCV conventions).

* :func:`depth_truth` — per camera pixel, the depth z [m] along the camera's optical axis of the nearest
  object the pixel's centre ray hits (planes, spheres, boxes; :func:`polarstripe.sim.geometry.intersect`),
  NaN where the ray hits nothing. It is what a stripe scan's triangulation should measure, and
  :func:`column_truth` the projector column that lights that point (what the scan should decode).
* :func:`rig_geometry` — the scene's camera and projector pinholes as a calibration would give them: 3×3
  intrinsics ``K_cam``, ``K_proj`` (pixel centres at integer coordinates, so c_x = w/2 − ½), image sizes,
  and the pose ``R``, ``T`` taking camera-frame points to the projector frame (X_p = R·X_c + T, the
  ``cv2.stereoCalibrate`` convention). The OpenCV camera frame is x = image right, y = image down, z =
  forward, i.e. the scene's (r, −u, f) (docs/physics.md §0.2). No lens distortion. A device behind a port
  adds ``port_cam`` / ``port_proj``: its normal in the device's own OpenCV frame, d, t, n_a, n_g, n_w (8
  numbers; :mod:`polarstripe.imaging.refraction` triangulates through them).

Plain arrays only, so :mod:`polarstripe.imaging` (which must not import the model) can take them.
"""

from __future__ import annotations

import numpy as np
from polarstripe.sim.geometry import PinholeFrame, intersect, pinhole_frame, pixel_rays
from polarstripe.sim.port import light_to, port_geometry, water_rays
from polarstripe.sim.scene import Scene


def camera_frame(scene: Scene) -> PinholeFrame:
    c = scene.camera
    return pinhole_frame(c.position, c.look_at, c.up, c.fov_deg, c.resolution)


def projector_frame(scene: Scene) -> PinholeFrame:
    p = scene.projector
    return pinhole_frame(p.position, p.look_at, p.up, p.fov_deg, p.resolution)


def depth_truth(scene: Scene) -> np.ndarray:
    """Depth z [m] (along the camera axis, from its pinhole) of the first object each pixel's centre ray
    hits, (h, w) float64, NaN where it hits none; behind a port along the pixel's water ray (docs/physics.md
    §11)."""
    cam = camera_frame(scene)
    dirs = pixel_rays(cam)
    origins = np.asarray(cam.position, float)
    if scene.camera.port is not None:
        origins, dirs, _, _ = water_rays(port_geometry(scene.camera.port, cam.position, cam.f), dirs)
    hits = intersect(scene.objects, origins, dirs)
    z = (origins - np.asarray(cam.position, float)) @ cam.f + hits.t * (dirs @ cam.f)
    z[~np.isfinite(hits.t) | (hits.index < 0)] = np.nan
    return z.reshape(cam.h, cam.w)


def column_truth(scene: Scene) -> np.ndarray:
    """Per camera pixel, the continuous projector column (msgs/patterns.py) of the light that reaches the
    object point its centre ray hits, through the ports where the scene has them; (h, w), NaN where the ray
    hits nothing: what a perfect stripe scan decodes."""
    cam, proj = camera_frame(scene), projector_frame(scene)
    dirs, origins = pixel_rays(cam), np.asarray(cam.position, float)
    if scene.camera.port is not None:
        origins, dirs, _, _ = water_rays(port_geometry(scene.camera.port, cam.position, cam.f), dirs)
    hits = intersect(scene.objects, origins, dirs)
    air = hits.point - np.asarray(proj.position, float)
    if scene.projector.port is not None:
        air = light_to(port_geometry(scene.projector.port, proj.position, proj.f), hits.point).air
    col = proj.w / 2.0 + (air @ proj.r) / (air @ proj.f) / proj.s
    return np.where(hits.index >= 0, col, np.nan).reshape(cam.h, cam.w)


def _intrinsics(frame: PinholeFrame) -> np.ndarray:
    f = 1.0 / frame.s
    return np.array([[f, 0.0, frame.w / 2.0 - 0.5], [0.0, f, frame.h / 2.0 - 0.5], [0.0, 0.0, 1.0]])


def _axes(frame: PinholeFrame) -> np.ndarray:
    """Rows: the OpenCV frame's x, y, z axes in world coordinates."""
    return np.stack([frame.r, -frame.u, frame.f])


def rig_geometry(scene: Scene) -> dict:
    """The rig as a calibration file holds it: ``K_cam``, ``K_proj`` (3, 3), ``cam_size``, ``proj_size``
    ([w, h]), ``R`` (3, 3), ``T`` (3,) [m] with X_p = R·X_c + T, ``dist_cam`` (5,) zeros."""
    if scene.projector.model != "pinhole":
        raise ValueError("the projector is a point source: no light sheets (projector.model = 'pinhole')")
    cam, proj = camera_frame(scene), projector_frame(scene)
    a_c, a_p = _axes(cam), _axes(proj)
    R = a_p @ a_c.T  # camera coords -> world directions (a_c.T) -> projector coords (a_p)
    T = a_p @ (np.asarray(cam.position, float) - np.asarray(proj.position, float))
    out = {"K_cam": _intrinsics(cam), "K_proj": _intrinsics(proj), "cam_size": [cam.w, cam.h],
           "proj_size": [proj.w, proj.h], "R": R, "T": T, "dist_cam": np.zeros(5)}
    for key, part, frame, axes in (("port_cam", scene.camera, cam, a_c),
                                   ("port_proj", scene.projector, proj, a_p)):
        if part.port is not None:
            g = port_geometry(part.port, frame.position, frame.f)
            out[key] = np.array([*(axes @ g.normal), g.d, g.t, g.n_a, g.n_g, g.n_w])
    return out
