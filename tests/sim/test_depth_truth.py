"""The simulator's depth truth and rig geometry, against closed-form geometry of the default tank."""

from __future__ import annotations

import numpy as np
from polarstripe.sim.depth_truth import depth_truth, rig_geometry
from polarstripe.sim.scene import BoxObject, PlaneObject, SphereObject, load_scene


def _small(scene, w=64):
    return scene.replace(camera=scene.camera.replace(resolution=(w, w * 3 // 4)))


def test_depth_truth_of_plane_sphere_and_box():
    s = _small(load_scene(None))
    z = depth_truth(s)
    assert np.nanmax(np.abs(z - 0.38)) < 1e-12  # the chart on the back wall, z = 0.38
    assert np.isnan(z[0, 0])  # the 0.3 × 0.2 m chart does not fill the 60° view
    sph = s.replace(objects=(SphereObject(center=(0.0, 0.0, 0.25), radius=0.05),))
    zs = depth_truth(sph)
    h, w = zs.shape
    # the central pixels' rays are near the axis: z ≈ 0.25 − 0.05 (pixel centres ½ px off the axis)
    f = w / 2 / np.tan(np.radians(30.0))
    x = 0.5 / f
    v = np.array([x, x, 1.0]) / np.linalg.norm([x, x, 1.0])
    t = v @ np.array([0, 0, 0.25]) - np.sqrt((v @ np.array([0, 0, 0.25])) ** 2 - 0.25 ** 2 + 0.05 ** 2)
    assert abs(zs[h // 2, w // 2] - t * v[2]) < 1e-12
    box = s.replace(objects=(BoxObject(min=(-0.05, -0.05, 0.2), max=(0.05, 0.05, 0.3)),))
    assert np.nanmax(np.abs(depth_truth(box)[h // 2 - 2:h // 2 + 2, w // 2 - 2:w // 2 + 2] - 0.2)) < 1e-12
    n = np.array([0.35, 0.0, -1.0]) / np.linalg.norm([0.35, 0.0, -1.0])
    tilt = s.replace(objects=(PlaneObject(point=(0.0, 0.0, 0.34), normal=tuple(n), size=None),))
    zt = depth_truth(tilt)
    # closed form: world x = −(camera x) (image right is −x); on the plane n·(X − P) = 0
    cols = np.arange(w) + 0.5 - w / 2
    xw = -cols / f  # world x per unit z, row through the centre (y ≈ 0)
    z_row = (n @ [0, 0, 0.34]) / (n[0] * xw + n[2])
    np.testing.assert_allclose(zt[h // 2], z_row, rtol=1e-9)


def test_rig_geometry_maps_the_projector_centre_and_axis():
    s = load_scene(None)
    g = rig_geometry(s)
    R, T = g["R"], g["T"]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    # camera frame: x = world −x (image right), y = world −y, z = world z; the projector at world (0.2, 0, 0)
    c_proj_cam = np.array([-0.2, 0.0, 0.0])
    np.testing.assert_allclose(R @ c_proj_cam + T, 0.0, atol=1e-12)  # its centre is its origin
    aim = np.array([0.0, 0.0, 0.38])  # the chart centre lies on the projector's axis
    p = R @ aim + T
    assert abs(p[0]) < 1e-12 and abs(p[1]) < 1e-12 and abs(p[2] - np.hypot(0.2, 0.38)) < 1e-12
    assert g["K_cam"][0, 0] == 320 / np.tan(np.radians(30)) and g["K_cam"][0, 2] == 319.5
