"""The grabber through the node harness: sim and file backends, tags, the analyzer mount, and a camera that
disappears (published fault, no frame, reopened at the next trigger)."""

import cv2
import numpy as np
import pytest
from polarstripe.msgs import AnalyzerMount, Frame, FrameRequest, PolarizerState
from polarstripe.nodes.grabber import Grabber
from polarstripe.runtime.testing import NodeHarness


class FakeSimulator:
    """Answers simulator/render with a frame whose pixels encode the step (and records the requests)."""

    def __init__(self):
        self.requests = []
        self.lost = False

    def __call__(self, req):
        if self.lost:
            raise RuntimeError("simulated camera lost")
        self.requests.append(req)
        image = np.full((4, 5), 100 + req.step, np.uint16)
        return Frame(image=image, exposure_s=0.002, bit_depth=12, pattern=req.pattern,
                     polarizer_deg=33.0 if req.analyzer else None, scan_id=req.scan_id, step=req.step)


@pytest.fixture
def sim():
    fake = FakeSimulator()
    h = NodeHarness(Grabber, name="grabber", namespace="/rig", params={"camera": "sim", "grab_timeout_s": 2})
    h.on_call("simulator/render", fake)
    yield h, fake
    h.stop()


def test_trigger_publishes_the_tagged_frame_with_the_polarizer_angle(sim):
    h, fake = sim
    h.deliver("polarizer/state", PolarizerState(angle_deg=12.5, target_deg=12.5, settled=True))
    ack = h.call("camera/trigger", FrameRequest(scan_id=7, step=3, pattern="stripe:3/8"))
    assert ack.ok
    (frame,) = h.published("camera/frame")
    assert (frame.scan_id, frame.step, frame.pattern) == (7, 3, "stripe:3/8")
    assert frame.polarizer_deg == 12.5  # from polarizer/state, not the backend
    assert frame.exposure_s == 0.002 and frame.bit_depth == 12
    assert int(frame.image[0, 0]) == 103
    assert fake.requests[0].pattern == "stripe:3/8" and fake.requests[0].analyzer


def test_newest_state_is_used_even_if_the_loop_has_not_seen_it(sim):
    h, _ = sim
    h.deliver("polarizer/state", PolarizerState(angle_deg=0.0, target_deg=0.0, settled=True))
    h.queue("polarizer/state", PolarizerState(angle_deg=90.0, target_deg=90.0, settled=True))
    h.call("camera/trigger", FrameRequest(scan_id=1, step=0, pattern="flood"))
    assert h.published("camera/frame")[-1].polarizer_deg == 90.0


def test_the_angle_is_the_grabbers_alone_none_before_any_polarizer_state(sim):
    h, fake = sim
    h.call("camera/trigger", FrameRequest(scan_id=1, step=0, pattern="flood"))
    frame = h.published("camera/frame")[-1]
    assert frame.polarizer_deg is None  # the simulator rendered at 33 deg, but only the stage's state counts
    assert fake.requests[-1].analyzer and int(frame.image[0, 0]) == 100


def test_analyzer_out_gives_untagged_frames_and_tells_the_simulator(sim):
    h, fake = sim
    h.deliver("polarizer/state", PolarizerState(angle_deg=12.5, target_deg=12.5, settled=True))
    assert h.call("camera/analyzer", AnalyzerMount(inserted=False)).ok
    h.call("camera/trigger", FrameRequest(scan_id=2, step=0, pattern="flood"))
    assert h.published("camera/frame")[-1].polarizer_deg is None and not fake.requests[-1].analyzer
    h.call("camera/analyzer", AnalyzerMount(inserted=True))
    h.call("camera/trigger", FrameRequest(scan_id=2, step=1, pattern="flood"))
    assert h.published("camera/frame")[-1].polarizer_deg == 12.5 and fake.requests[-1].analyzer


def test_camera_that_disappears_is_a_published_fault_then_recovers(sim):
    h, fake = sim
    fake.lost = True
    ack = h.call("camera/trigger", FrameRequest(scan_id=4, step=0, pattern="flood"))
    assert not ack.ok and "DeviceLost" in ack.detail and "simulated camera lost" in ack.detail
    assert h.published("camera/frame") == []
    assert h.node.counters["grab_faults"] == 1
    assert any(level == "ERROR" and "scan 4 step 0" in text for level, text in h.logs)
    fake.lost = False
    assert h.call("camera/trigger", FrameRequest(scan_id=4, step=1, pattern="flood")).ok  # reopened
    assert [f.step for f in h.published("camera/frame")] == [1]


def test_simulator_not_answering_is_a_timeout_fault():
    h = NodeHarness(Grabber, name="grabber", namespace="/rig", params={"camera": "sim", "grab_timeout_s": 1})
    ack = h.call("camera/trigger", FrameRequest(scan_id=1, step=0, pattern="flood"))  # no responder set
    # (Camera.grab reports any TimeoutError of the backend as "no frame within …": cf. the report)
    assert not ack.ok and "DriverTimeout" in ack.detail and "sim camera" in ack.detail
    assert h.published("camera/frame") == []
    h.stop()


def test_file_backend_plays_16_bit_images_then_faults_at_the_end(tmp_path):
    rng = np.random.default_rng(0)
    images = [rng.integers(0, 4096, (6, 7), dtype=np.uint16) for _ in range(2)]
    for i, im in enumerate(images):
        cv2.imwrite(str(tmp_path / f"frame_{i:03d}.png"), im)
    h = NodeHarness(Grabber, name="grabber", params={"camera": "file",
                                                          "camera_options": {"source": str(tmp_path)}})
    for step in range(2):
        assert h.call("camera/trigger", FrameRequest(scan_id=1, step=step, pattern="flood")).ok
    got = [f.image for f in h.published("camera/frame")]
    assert all(np.array_equal(a, b) for a, b in zip(got, images, strict=True))
    assert all(f.polarizer_deg is None for f in h.published("camera/frame"))  # no polarizer state yet
    ack = h.call("camera/trigger", FrameRequest(scan_id=1, step=2, pattern="flood"))
    assert not ack.ok and "EndOfFrames" in ack.detail
    h.stop()


def test_missing_device_is_reported_on_every_trigger(tmp_path):
    options = {"source": str(tmp_path / "none")}
    h = NodeHarness(Grabber, name="grabber", params={"camera": "file", "camera_options": options})
    assert any(level == "ERROR" for level, _ in h.logs)
    ack = h.call("camera/trigger", FrameRequest(scan_id=1, step=0, pattern="flood"))
    assert not ack.ok and "unavailable" in ack.detail and "none" in ack.detail
    h.stop()


def test_an_oversize_frame_is_dropped_logged_once_and_the_node_keeps_running(tmp_path, monkeypatch):
    """A real camera delivering more pixels than $POLARSTRIPE_MAX_PIXELS: each such frame is refused (a fault
    reply naming the size and the limit, no frame published), one ERROR line in all, counted; a frame within
    the limit still goes out."""
    big = np.zeros((40, 50), np.uint16)  # 2000 px
    for i in range(3):
        cv2.imwrite(str(tmp_path / f"frame_{i:03d}.png"), big)
    cv2.imwrite(str(tmp_path / "frame_003.png"), np.zeros((10, 10), np.uint16))  # 100 px
    monkeypatch.setenv("POLARSTRIPE_MAX_PIXELS", "1000")
    h = NodeHarness(Grabber, name="grabber", params={"camera": "file",
                                                          "camera_options": {"source": str(tmp_path)}})
    for step in range(3):
        ack = h.call("camera/trigger", FrameRequest(scan_id=1, step=step, pattern="flood"))
        assert not ack.ok and "50x40" in ack.detail and "beyond the limit of 0.001 Mpx" in ack.detail
    assert h.published("camera/frame") == []
    errors = [text for level, text in h.logs if level == "ERROR"]
    assert len(errors) == 1 and "50x40" in errors[0] and "dropped" in errors[0]
    assert h.node.counters["frames_oversize"] == 3
    assert h.call("camera/trigger", FrameRequest(scan_id=1, step=3, pattern="flood")).ok  # still running
    assert h.published("camera/frame")[0].image.shape == (10, 10)
    h.stop()
