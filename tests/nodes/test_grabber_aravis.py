"""The grabber with the Aravis backend on Aravis's GigE Vision simulator (127.0.0.1): triggered frames are
published as the camera took them; a frame whose packets were lost is a fault reply, one ERROR line and a
count, never a published frame, and the camera stays open for the next trigger."""

from __future__ import annotations

import numpy as np
from gi.repository import GLib
from polarstripe.msgs import FrameRequest
from polarstripe.nodes.grabber import Grabber
from polarstripe.runtime.testing import NodeHarness


def ramp8(frame_id: int) -> np.ndarray:  # Aravis's simulator at 10 ms, gain 0 (src/arvfakecamera.c)
    return ((np.add.outer(np.arange(512), np.arange(512)) + frame_id) % 255).astype(np.uint8)


def test_a_dropped_frame_is_one_fault_and_the_camera_stays_open(gige):
    options = {"device": gige.address, "pixel_format": "Mono8"}
    h = NodeHarness(Grabber, name="grabber", namespace="/rig",
                    params={"camera": "aravis", "camera_options": options, "exposure_s": 0.01, "gain": 0.0,
                            "grab_timeout_s": 2.0})
    try:
        camera = h.node.camera
        assert h.call("camera/trigger", FrameRequest(scan_id=1, step=0, pattern="flood")).ok
        (frame,) = h.published("camera/frame")
        assert frame.exposure_s == 0.01 and frame.bit_depth == 8 and frame.image.dtype == np.uint8
        first_id = int(frame.image[0, 0])  # the ramp's corner is the frame id mod 255
        GLib.random_set_seed(7)
        gige.lost_ratio = 0.5  # about half of 190 packets: no frame arrives whole
        errors_before = sum(level == "ERROR" for level, _ in h.logs)
        ack = h.call("camera/trigger", FrameRequest(scan_id=1, step=1, pattern="flood"))
        assert not ack.ok and "FrameDropped" in ack.detail and "dropped, incomplete" in ack.detail
        assert h.node.counters["frames_dropped"] == 1 and h.node.counters["grab_faults"] == 1
        assert sum(level == "ERROR" for level, _ in h.logs) == errors_before + 1  # one line
        assert len(h.published("camera/frame")) == 1  # nothing published for it
        gige.lost_ratio = 0.0
        assert h.call("camera/trigger", FrameRequest(scan_id=1, step=2, pattern="flood")).ok
        assert h.node.camera is camera  # not reopened
        last = h.published("camera/frame")[-1]
        # the frame after the lost one
        assert last.step == 2 and int(last.image[0, 0]) == (first_id + 2) % 255
        assert np.array_equal(last.image, ramp8(int(last.image[0, 0])))
    finally:
        h.stop()
