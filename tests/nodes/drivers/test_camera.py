"""Camera backends: one contract for all available here, files written by the test, V4L2 failure paths."""

from __future__ import annotations

import glob
import threading
import time

import cv2
import numpy as np
import pytest
from polarstripe.nodes.drivers.camera import Camera, CameraFrame
from polarstripe.nodes.drivers.errors import (
    DeviceLost,
    DriverError,
    DriverTimeout,
    DriverValueError,
    EndOfFrames,
)
from polarstripe.nodes.drivers.file_camera import FileCamera
from polarstripe.nodes.drivers.registry import load_backend
from polarstripe.nodes.drivers.v4l2_camera import V4l2Camera


def _frames(n=4, h=24, w=32, seed=0):
    rng = np.random.default_rng(seed)
    return [rng.integers(0, 4096, size=(h, w), dtype=np.uint16) for _ in range(n)]


def _write_pngs(folder, frames):
    for i, f in enumerate(frames):
        assert cv2.imwrite(str(folder / f"frame_{i:04d}.png"), f)


def _write_ffv1(path, frames):
    h, w = frames[0].shape
    writer = cv2.VideoWriter(
        str(path),
        cv2.CAP_FFMPEG,
        cv2.VideoWriter_fourcc(*"FFV1"),
        30,
        (w, h),
        [cv2.VIDEOWRITER_PROP_DEPTH, cv2.CV_16U, cv2.VIDEOWRITER_PROP_IS_COLOR, 0],
    )
    if not writer.isOpened():
        pytest.skip("this OpenCV cannot write 16-bit FFV1")
    for f in frames:
        writer.write(f)
    writer.release()


@pytest.fixture(params=["png", "video", "v4l2"])
def camera(request, tmp_path):
    frames = _frames()
    if request.param == "png":
        _write_pngs(tmp_path, frames)
        cam = FileCamera(tmp_path, loop=True)
    elif request.param == "video":
        _write_ffv1(tmp_path / "run.mkv", frames)
        cam = FileCamera(tmp_path / "run.mkv", loop=True)
    else:
        if not glob.glob("/dev/video*"):
            pytest.skip("no V4L2 camera on this machine")
        cam = V4l2Camera(0)
    yield cam
    cam.close()


# -- the contract ------------------------------------------------------------------------------------------
def test_grab_gives_an_image_and_what_it_was_taken_with(camera):
    camera.exposure_s = 0.02
    camera.gain = 2.0
    frame = camera.grab(timeout=5.0)
    assert isinstance(frame, CameraFrame) and frame.image.ndim in (2, 3) and frame.image.size > 0
    assert (frame.seq, frame.exposure_s, frame.gain, frame.bit_depth) == (0, 0.02, 2.0, camera.bit_depth)
    assert abs(frame.stamp_ns - time.time_ns()) < 5e9
    assert camera.grab(timeout=5.0).seq == 1


@pytest.mark.parametrize(
    ("field", "bad"), [("exposure_s", 0.0), ("exposure_s", -1e-3), ("exposure_s", np.nan), ("gain", -1.0)]
)
def test_bad_exposure_or_gain_is_refused(camera, field, bad):
    before = getattr(camera, field)
    with pytest.raises(DriverValueError, match=field):
        setattr(camera, field, bad)
    assert getattr(camera, field) == before


def test_close_is_idempotent_and_final(camera):
    camera.close()
    camera.close()
    with pytest.raises(DriverError, match="closed"):
        camera.grab()


# -- file camera -------------------------------------------------------------------------------------------
def test_png_sequence_is_read_in_order_bit_exact(tmp_path):
    frames = _frames(5)
    _write_pngs(tmp_path, frames)
    with FileCamera(str(tmp_path / "frame_*.png"), bit_depth=12) as cam:
        assert len(cam) == 5 and cam.bit_depth == 12
        for i, expected in enumerate(frames):
            frame = cam.grab()
            assert frame.image.dtype == np.uint16 and np.array_equal(frame.image, expected)
            assert frame.metadata == {"index": i, "file": f"frame_{i:04d}.png"}
        with pytest.raises(EndOfFrames, match="all 5 images"):
            cam.grab()


def test_png_sequence_loops(tmp_path):
    frames = _frames(3)
    _write_pngs(tmp_path, frames)
    with FileCamera(tmp_path, loop=True) as cam:
        got = [cam.grab().image for _ in range(7)]
    for i, image in enumerate(got):
        assert np.array_equal(image, frames[i % 3])


def test_ffv1_video_is_16_bit_exact(tmp_path):
    frames = _frames(4)
    _write_ffv1(tmp_path / "run.mkv", frames)
    with FileCamera(tmp_path / "run.mkv") as cam:
        assert cam.bit_depth == 16
        for expected in frames:
            assert np.array_equal(cam.grab().image, expected)
        with pytest.raises(EndOfFrames):
            cam.grab()


def test_fps_paces_the_frames(tmp_path):
    _write_pngs(tmp_path, _frames(3))
    with FileCamera(tmp_path, fps=20.0) as cam:
        start = time.monotonic()
        for _ in range(3):
            cam.grab()
        assert time.monotonic() - start >= 2 / 20.0 * 0.9


def test_missing_or_empty_sources_are_clear_errors(tmp_path):
    with pytest.raises(DriverError, match="no images"):
        FileCamera(tmp_path)
    with pytest.raises(DriverError, match="no folder, glob, image or video"):
        FileCamera(tmp_path / "nothing-here")


# -- V4L2 and the grab contract's failure paths ------------------------------------------------------------
def test_v4l2_missing_device_is_a_clear_error():
    with pytest.raises(DriverError, match=r"V4L2 camera /dev/video97: no such device"):
        V4l2Camera("/dev/video97")


class _FakeCapture:
    """Stands in for cv2.VideoCapture: frames until ``unplug()``, then read() fails as on a real unplug."""

    def __init__(self):
        self.props, self.plugged = {}, True

    def isOpened(self):  # noqa: N802 - OpenCV's name
        return True

    def set(self, prop, value):
        self.props[prop] = value
        return True

    def get(self, prop):
        return self.props.get(prop, 0.0)

    def read(self):
        if self.plugged:
            return True, np.full((4, 6), 1000, np.uint16)
        return False, None

    def release(self):
        self.plugged = False


def test_a_camera_that_disappears_is_device_lost_not_a_blank_frame(tmp_path, monkeypatch):
    fake = _FakeCapture()
    monkeypatch.setattr(V4l2Camera, "_open_capture", lambda self, device: fake)
    node = tmp_path / "video0"
    node.touch()
    with V4l2Camera(str(node), exposure_s=0.005, gain=3) as cam:
        assert fake.props[cv2.CAP_PROP_AUTO_EXPOSURE] == 1
        assert fake.props[cv2.CAP_PROP_EXPOSURE] == 50  # units of 100 us
        assert fake.props[cv2.CAP_PROP_GAIN] == 3 and fake.props[cv2.CAP_PROP_CONVERT_RGB] == 0
        assert cam.grab().image.shape == (4, 6)
        fake.plugged = False
        with pytest.raises(DeviceLost, match="no frame"):
            cam.grab()


class _StuckCamera(Camera):
    def __init__(self):
        super().__init__("stuck camera", exposure_s=0.01, gain=1.0, bit_depth=12)
        self.release = threading.Event()

    def _grab(self):
        self.release.wait(5)
        return np.zeros((2, 2), np.uint16), {}


def test_a_grab_that_blocks_times_out_instead_of_hanging():
    cam = _StuckCamera()
    start = time.monotonic()
    with pytest.raises(DriverTimeout, match="no frame within 0.2 s"):
        cam.grab(timeout=0.2)
    assert time.monotonic() - start < 0.5
    cam.release.set()
    assert cam.grab(timeout=1.0).image.shape == (2, 2)  # the late frame is delivered next
    cam.close()


class _RaisingCamera(Camera):
    def __init__(self, exc):
        super().__init__("raising camera", exposure_s=0.01, gain=1.0, bit_depth=12)
        self.exc = exc

    def _grab(self):
        raise self.exc


@pytest.mark.parametrize("exc", [DriverTimeout("sim camera: the simulator did not answer"),
                                 TimeoutError("serial read timed out")])
def test_a_timeout_inside_the_backend_keeps_its_own_text(exc):
    cam = _RaisingCamera(exc)
    with pytest.raises(TimeoutError) as info:
        cam.grab(timeout=1.0)
    assert info.value is exc and "no frame within" not in str(info.value)
    cam.close()


def test_camera_backends_are_registered():
    assert load_backend("camera", "file") is FileCamera
    assert load_backend("camera", "v4l2") is V4l2Camera


# -- the simulator's camera --------------------------------------------------------------------------------
class _Simulator:
    """Answers render requests with a frame of its own exposure (0.004 s) and bit depth (10), unless asked."""

    def __init__(self):
        self.requests = []

    def __call__(self, req):
        from polarstripe.msgs import Frame

        self.requests.append(req)
        exposure = 0.004 if req.exposure_s is None else req.exposure_s
        return Frame(image=np.full((3, 4), 7, np.uint16), exposure_s=exposure, bit_depth=10,
                     pattern=req.pattern, polarizer_deg=12.0, scan_id=req.scan_id, step=req.step)


def test_sim_camera_frame_carries_what_the_simulator_used_and_no_angle():
    from polarstripe.nodes.drivers.sim_camera import SimCamera

    sim = _Simulator()
    with SimCamera(sim, exposure_s=0.01) as cam:
        cam.request("stripe:2/8", analyzer=False, scan_id=3, step=2)
        frame = cam.grab(timeout=2.0)
        assert (frame.exposure_s, frame.bit_depth) == (0.004, 10)  # the simulator's, not the constructor's
        assert frame.metadata == {"pattern": "stripe:2/8", "scan_id": 3, "step": 2}  # no analyzer angle
        assert sim.requests[-1].exposure_s is None and not sim.requests[-1].analyzer
        cam.exposure_s = 0.02  # once set, it is sent
        assert cam.grab(timeout=2.0).exposure_s == 0.02 and sim.requests[-1].exposure_s == 0.02


@pytest.mark.parametrize(("exc", "kind"), [(TimeoutError("no reply"), DriverTimeout),
                                           (RuntimeError("camera lost"), DeviceLost)])
def test_sim_camera_faults(exc, kind):
    from polarstripe.nodes.drivers.sim_camera import SimCamera

    def render(req):
        raise exc

    with SimCamera(render) as cam, pytest.raises(kind, match="sim camera"):
        cam.grab(timeout=2.0)


def test_sim_polarization_camera_frame_names_its_mosaic_and_a_frame_without_one_is_a_fault():
    from polarstripe.msgs import Frame
    from polarstripe.nodes.drivers.sim_polarization_camera import SimPolarizationCamera

    requests = []

    def render(req, mosaic=(90.0, 45.0, 135.0, 0.0)):
        requests.append(req)
        return Frame(image=np.full((4, 4), 9, np.uint16), exposure_s=0.004, bit_depth=12, pattern=req.pattern,
                     scan_id=req.scan_id, step=req.step, mosaic_deg=list(mosaic))

    with SimPolarizationCamera(render) as cam:
        cam.request("stripe:1/4", analyzer=False, scan_id=2, step=1)   # no analyzer to take out
        frame = cam.grab(timeout=2.0)
        assert frame.metadata == {"pattern": "stripe:1/4", "scan_id": 2, "step": 1,
                                  "mosaic_deg": [90.0, 45.0, 135.0, 0.0], "pixel_format": "PolarizeMono12"}
        assert requests[-1].analyzer
    with SimPolarizationCamera(lambda req: render(req, mosaic=())) as cam, \
            pytest.raises(DeviceLost, match="no 2x2 mosaic"):
        cam.grab(timeout=2.0)
