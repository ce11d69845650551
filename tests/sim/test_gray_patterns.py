"""The simulator's projector shows OpenCV's Gray code images: surface light (D) and the lit ray intervals of
the backscatter (lit_intervals) both, checked against cv2.structured_light.GrayCodePattern.generate()."""

import cv2
import numpy as np
from polarstripe.msgs.patterns import gray_code, xor_code
from polarstripe.sim.depth_truth import projector_frame
from polarstripe.sim.geometry import pixel_rays
from polarstripe.sim.patterns import lit_intervals
from polarstripe.sim.render import render_components
from polarstripe.sim.scene import scene_from_dict

W, H = 40, 24


def _scene():
    # the camera sits in the projector with its size and field of view: camera pixel = pattern pixel
    pose = {"position": [0.0, 0.0, 0.0], "look_at": [0.0, 0.0, 0.3], "resolution": [W, H], "fov_deg": 40.0}
    return scene_from_dict({"medium": {"sigma_t": 0.0}, "camera": dict(pose), "projector": dict(pose),
                            "object": [{"type": "plane", "point": [0, 0, 0.3], "normal": [0, 0, -1]}]})


def test_surface_light_is_opencvs_gray_code():
    scene = _scene()
    ok, images = cv2.structured_light.GrayCodePattern.create(W, H).generate()
    for spec, image in zip(gray_code(W, H), images, strict=True):
        d = render_components(scene, spec, "preview", need=("D",)).D
        np.testing.assert_array_equal(d > 0, image > 0, err_msg=str(spec))


def test_lit_intervals_are_opencvs_gray_code():
    scene = _scene()
    frame = projector_frame(scene)
    dirs = pixel_rays(frame)
    x0, x1 = np.full(len(dirs), 0.05), np.full(len(dirs), 0.25)
    ok, images = cv2.structured_light.GrayCodePattern.create(W, H).generate()
    for spec, image in zip(gray_code(W, H), images, strict=True):
        ray, lo, hi = lit_intervals(spec, frame, frame.position, dirs, x0, x1)
        lit = np.zeros(len(dirs), bool)
        lit[ray] = True
        np.testing.assert_array_equal(lit.reshape(H, W), image > 0, err_msg=str(spec))
        np.testing.assert_allclose(hi - lo, 0.2)        # a ray from the apex is lit whole or not at all


def test_lit_intervals_of_rays_across_the_sheets():
    """Camera rays beside the projector cross many Gray code stripes: the lit intervals are where dense
    points along each ray project to a lit pattern pixel (OpenCV's image looked up at the point)."""
    from polarstripe.sim.geometry import pinhole_frame, projector_coords

    scene = _scene()
    frame = projector_frame(scene)
    cam = pinhole_frame((0.08, 0.03, 0.0), (0.0, 0.0, 0.3), (0.0, 1.0, 0.0), 40.0, (16, 12))
    dirs = pixel_rays(cam)
    x0, x1 = np.full(len(dirs), 0.1), np.full(len(dirs), 0.4)
    ok, images = cv2.structured_light.GrayCodePattern.create(W, H).generate()
    t = np.linspace(0.1, 0.4, 4001)[1:-1]
    for spec, image in list(zip(gray_code(W, H), images, strict=True))[::3]:
        ray, lo, hi = lit_intervals(spec, frame, cam.position, dirs, x0, x1)
        for i in range(0, len(dirs), 7):
            col, row, depth = projector_coords(frame, cam.position + t[:, None] * dirs[i])
            inside = (depth > 0) & (col >= 0) & (col < W) & (row >= 0) & (row < H)
            c, r = np.clip(col.astype(int), 0, W - 1), np.clip(row.astype(int), 0, H - 1)
            want = inside & (image[r, c] > 0)
            mine = ray == i
            got = np.zeros(t.size, bool)
            for a, b in zip(lo[mine], hi[mine], strict=True):
                got |= (t > a) & (t < b)
            # equal except within one sample of an interval end (the sampling's own resolution)
            near = np.zeros(t.size, bool)
            for e in np.concatenate([lo[mine], hi[mine]]):
                near |= np.abs(t - e) < 2 * (t[1] - t[0])
            assert np.array_equal(got[~near], want[~near]), (str(spec), i)


def _xor_images(base: int):
    """The XOR code's images from OpenCV's Gray code images: each XOR the column base bit's image."""
    ok, images = cv2.structured_light.GrayCodePattern.create(W, H).generate()
    by = {(p.axis, p.index, p.inverse): img > 0 for p, img in zip(gray_code(W, H), images, strict=True)}
    return [(p, by[(p.axis, p.index, p.inverse)] ^ (by[("col", base, False)] if p.xor >= 0 else False))
            for p in xor_code(W, H, base)]


def test_surface_light_and_lit_intervals_are_the_xor_codes_images():
    scene = _scene()
    frame = projector_frame(scene)
    dirs = pixel_rays(frame)
    x0, x1 = np.full(len(dirs), 0.05), np.full(len(dirs), 0.25)
    for spec, image in _xor_images(1):
        d = render_components(scene, spec, "preview", need=("D",)).D
        np.testing.assert_array_equal(d > 0, image, err_msg=str(spec))
        ray, lo, hi = lit_intervals(spec, frame, frame.position, dirs, x0, x1)
        lit = np.zeros(len(dirs), bool)
        lit[ray] = True
        np.testing.assert_array_equal(lit.reshape(H, W), image, err_msg=str(spec))


def test_lit_intervals_of_rays_across_an_xor_codes_sheets():
    """A row pattern XOR a column bit changes along a camera ray where either changes: the lit intervals
    are where dense points along the ray project to a lit pixel of the image."""
    from polarstripe.sim.geometry import pinhole_frame, projector_coords

    frame = projector_frame(_scene())
    cam = pinhole_frame((0.08, 0.03, 0.0), (0.0, 0.0, 0.3), (0.0, 1.0, 0.0), 40.0, (16, 12))
    dirs = pixel_rays(cam)
    x0, x1 = np.full(len(dirs), 0.1), np.full(len(dirs), 0.4)
    t = np.linspace(0.1, 0.4, 4001)[1:-1]
    for spec, image in [s for s in _xor_images(2) if s[0].xor >= 0][::4]:
        ray, lo, hi = lit_intervals(spec, frame, cam.position, dirs, x0, x1)
        for i in range(0, len(dirs), 11):
            col, row, depth = projector_coords(frame, cam.position + t[:, None] * dirs[i])
            inside = (depth > 0) & (col >= 0) & (col < W) & (row >= 0) & (row < H)
            c, r = np.clip(col.astype(int), 0, W - 1), np.clip(row.astype(int), 0, H - 1)
            want = inside & image[r, c]
            mine = ray == i
            got = np.zeros(t.size, bool)
            for a, b in zip(lo[mine], hi[mine], strict=True):
                got |= (t > a) & (t < b)
            near = np.zeros(t.size, bool)
            for e in np.concatenate([lo[mine], hi[mine]]):
                near |= np.abs(t - e) < 2 * (t[1] - t[0])
            assert np.array_equal(got[~near], want[~near]), (str(spec), i)
