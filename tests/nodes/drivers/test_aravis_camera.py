"""The Aravis backend against Aravis's own GigE Vision simulator on 127.0.0.1, opened by address (no
broadcast): software, line and free-running triggers, exposure and gain reaching the sensor, pixel formats,
the camera's frame ids and clock, and lost packets giving a dropped, counted frame, never a corrupt image.

The expected pixels are the simulator's diagonal ramp as its source writes it (Aravis 0.8,
src/arvfakecamera.c, ``arv_fake_camera_diagonal_ramp``): Mono8 ``((x + id + y) % 255) * s``, Mono16
``((256 x + 256 id + 256 y) % 65535) * s``, clamped and truncated, with ``s = 1 + GainRaw + log10(exposure
[µs] / 10000)`` and ``id`` the frame id it sends; its clock is the host's real time (µs) at 1 GHz ticks.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
from gi.repository import GLib
from polarstripe.nodes.drivers.aravis_camera import AravisCamera
from polarstripe.nodes.drivers.errors import DriverError, DriverTimeout, DriverValueError, FrameDropped
from polarstripe.nodes.drivers.registry import open_backend


def ramp(frame_id: int, fmt: str, exposure_us: float, gain: int, shape=(512, 512)) -> np.ndarray:
    y, x = np.indices(shape, dtype=np.int64)
    scale = 1.0 + gain + np.log10(exposure_us / 10000.0)
    if fmt == "Mono8":
        return np.clip(((x + frame_id + y) % 255) * scale, 0, 255).astype(np.uint8)
    return np.clip(((256 * x + 256 * frame_id + 256 * y) % 65535) * scale, 0, 65535).astype(np.uint16)


def after(frame_id: int, n: int = 1) -> int:
    """The simulator's frame id ``n`` frames later (16 bits, 0 skipped)."""
    return (frame_id - 1 + n) % 65535 + 1


def grab_whole(cam, tries: int = 3):
    """A frame and the frames dropped before it: on a loaded host even loopback UDP loses packets, and these
    tests are not about that (the last one is)."""
    for dropped in range(tries):
        try:
            return cam.grab(2.0), dropped
        except FrameDropped:
            continue
    raise AssertionError(f"{tries} frames in a row dropped without any packet loss asked for")


@pytest.fixture
def camera(gige):
    cams = []

    def make(**options):
        cams.append(open_backend("camera", "aravis", {"device": gige.address, **options}))
        return cams[-1]

    yield make
    for cam in cams:
        cam.close()


def test_the_fallback_features_are_found_and_the_deepest_mono_format_chosen(camera):
    cam = camera()
    assert cam.pixel_format == "Mono16" and cam.bit_depth == 16  # it offers Mono8 and Mono16
    assert (cam._exposure_feature, cam._gain_feature) == ("ExposureTimeAbs", "GainRaw")  # no SFNC names


@pytest.mark.parametrize("fmt", ["Mono8", "Mono16"])
def test_software_triggered_frames_are_the_simulators_ramp_bit_exact(camera, fmt):
    cam = camera(pixel_format=fmt)
    cam.exposure_s, cam.gain = 0.01, 0
    frames = [grab_whole(cam)[0] for _ in range(3)]
    for f in frames:
        assert f.image.dtype == (np.uint8 if fmt == "Mono8" else np.uint16)
        assert f.metadata["pixel_format"] == fmt and f.bit_depth == (8 if fmt == "Mono8" else 16)
        assert np.array_equal(f.image, ramp(f.metadata["frame_id"], fmt, 10000, 0))


def test_each_software_trigger_is_one_frame(camera):
    cam = camera(pixel_format="Mono8")
    first = grab_whole(cam)[0].metadata["frame_id"]
    time.sleep(0.3)  # a free-running camera would send about 7 frames meanwhile (25 fps)
    frame, dropped = grab_whole(cam)
    assert frame.metadata["frame_id"] == after(first, 1 + dropped)


def test_free_running_takes_a_frame_that_came_after_the_grab_asked(camera):
    cam = camera(pixel_format="Mono8", trigger="off")
    first = grab_whole(cam)[0].metadata["frame_id"]
    time.sleep(0.3)
    second = grab_whole(cam)[0].metadata["frame_id"]
    assert (second - first) % 65535 >= 5  # the frames sent meanwhile were not taken


def test_a_line_trigger_without_a_pulse_gives_no_frame(camera):
    cam = camera(pixel_format="Mono8", trigger="Line0")
    with pytest.raises(DriverTimeout, match="no frame within 0.5 s .no pulse on Line0"):
        cam.grab(0.5)


@pytest.mark.parametrize(("exposure_s", "gain", "scale"), [(0.1, 0, 2.0), (0.01, 1, 2.0), (0.01, 0, 1.0)])
def test_exposure_and_gain_reach_the_sensor(camera, exposure_s, gain, scale):
    cam = camera(pixel_format="Mono8")
    cam.exposure_s, cam.gain = exposure_s, gain
    f = grab_whole(cam)[0]
    assert f.exposure_s == pytest.approx(exposure_s) and f.gain == gain
    assert np.array_equal(f.image, ramp(f.metadata["frame_id"], "Mono8", exposure_s * 1e6, gain))
    base = ramp(f.metadata["frame_id"], "Mono8", 10000, 0).astype(float)
    assert np.array_equal(f.image, np.clip(base * scale, 0, 255).astype(np.uint8))  # the same, by hand


def test_the_frame_carries_the_exposure_the_camera_took(camera):
    cam = camera(pixel_format="Mono8")
    cam.exposure_s = 0.0123456  # the simulator keeps whole microseconds
    f = grab_whole(cam)[0]
    assert f.exposure_s * 1e6 == pytest.approx(round(f.exposure_s * 1e6), abs=1e-6)
    assert abs(f.exposure_s - 0.0123456) <= 1e-6 and f.exposure_s != 0.0123456


def test_device_timestamps_are_the_cameras_clock(camera):
    cam = camera(pixel_format="Mono8")
    stamps = []
    for _ in range(3):
        before = time.time_ns()
        f = grab_whole(cam)[0]
        stamps.append(f.metadata["device_stamp_ns"])
        assert before <= stamps[-1] <= time.time_ns()  # the simulator's clock is this host's real time
        assert stamps[-1] <= f.metadata["host_stamp_ns"]  # taken before it arrived
    assert stamps == sorted(stamps) and len(set(stamps)) == 3


@pytest.mark.parametrize(("options", "error", "text"), [
    ({"pixel_format": "Mono12"}, DriverError, "pixel_format Mono12 is not offered .the camera offers "
                                              "BayerBG8, BayerGB8, BayerGR8, BayerRG8, Mono8, RGB8, Mono16"),
    ({"pixel_format": "RGB8"}, DriverValueError, "no unpacked monochrome format"),
    ({"trigger": "Line3"}, DriverError, "source Line3 is not offered .TriggerSource: Line0, Software"),
    ({"trigger": "hardware"}, DriverValueError, "trigger='hardware' is none of software"),
])
def test_what_the_camera_does_not_offer_is_one_line(camera, options, error, text):
    with pytest.raises(error, match=text) as err:
        camera(**options)
    assert "\n" not in str(err.value)


def test_an_exposure_beyond_the_cameras_range_is_refused(camera):
    cam = camera()
    cam.exposure_s = 0.01
    with pytest.raises(DriverValueError, match="exposure 2e.07 µs is outside the camera's 10-1e.07 µs"):
        cam.exposure_s = 20.0
    assert cam.exposure_s == 0.01 and grab_whole(cam)[0].exposure_s == 0.01  # kept


def test_nothing_at_the_address_is_one_line(gige):
    with pytest.raises(DriverError, match="Aravis camera 127.0.0.9: .*127.0.0.9"):
        AravisCamera("127.0.0.9")


def test_lost_packets_give_dropped_counted_frames_never_a_corrupt_image(camera, gige):
    cam = camera(pixel_format="Mono8")
    cam.exposure_s, cam.gain = 0.01, 0
    GLib.random_set_seed(2026)  # the simulator draws its losses from GLib's random numbers
    gige.lost_ratio = 0.005  # about 190 packets a frame: some frames whole, most not
    dropped = delivered = 0
    for _ in range(8):
        try:
            f = cam.grab(2.0)
        except FrameDropped as exc:
            assert "dropped" in str(exc) and "\n" not in str(exc)
            dropped += 1
        else:
            delivered += 1
            assert np.array_equal(f.image, ramp(f.metadata["frame_id"], "Mono8", 10000, 0))
    assert dropped >= 1 and cam.frames_dropped == dropped
    gige.lost_ratio = 0.0
    f, more = grab_whole(cam)  # the camera stayed open
    assert np.array_equal(f.image, ramp(f.metadata["frame_id"], "Mono8", 10000, 0))
    assert f.seq == delivered and cam.frames_dropped == dropped + more  # dropped ones are not delivered


def test_a_polarization_cameras_mosaic_formats_are_read_and_chosen_when_it_offers_no_mono():
    from polarstripe.nodes.drivers.aravis_camera import FORMATS, pick_pixel_format

    lucid = ["PolarizeMono8", "PolarizeMono12", "PolarizeMono12p", "PolarizeMono16"]   # PFNC names
    assert pick_pixel_format("cam", lucid, None) == "PolarizeMono16"
    assert pick_pixel_format("cam", ["Polarized8", "BayerRGPolarized8"], None) == "Polarized8"   # FLIR's
    assert pick_pixel_format("cam", ["Mono8", *lucid], None) == "Mono8"   # a plain format first
    assert pick_pixel_format("cam", lucid, "PolarizeMono12") == "PolarizeMono12"
    assert FORMATS["PolarizeMono12"] == (12, "<u2") and FORMATS["PolarizeMono8"] == (8, "u1")
    with pytest.raises(DriverValueError, match="no unpacked monochrome format nor a polarization mosaic"):
        pick_pixel_format("cam", lucid, "PolarizeMono12p")   # packed
    with pytest.raises(DriverError, match="offers no unpacked monochrome format"):
        pick_pixel_format("cam", ["BayerRG8"], None)


def test_a_bad_mosaic_layout_is_one_line(gige):
    with pytest.raises(DriverValueError, match="mosaic layout"):
        open_backend("camera", "aravis", {"device": gige.address, "mosaic_layout": [0, 0, 45, 90]})
