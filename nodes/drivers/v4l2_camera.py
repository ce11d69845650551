"""A V4L2 camera through OpenCV (``cv2.VideoCapture(…, cv2.CAP_V4L2)``): manual exposure and gain, raw 16-bit.

The pixel format is negotiated from ``pixel_formats`` in order (default ``Y16``, ``Y10``, ``GREY``); with
``CAP_PROP_CONVERT_RGB`` off, Y16/Y10 come as 16-bit single-channel frames. Exposure goes through the V4L2
control ``exposure_time_absolute`` (units of 100 µs) after ``CAP_PROP_AUTO_EXPOSURE`` = 1 (manual); every
``set`` is checked, since support depends on the driver. A missing device, a refused control and a camera that
stops delivering frames are :class:`DriverError` / :class:`DeviceLost`, never a blank frame. Cameras with
12-bit packed or Bayer formats need Aravis/GenICam, not this backend (OpenCV does not negotiate them).
"""

from __future__ import annotations

import os

import cv2
import numpy as np
from polarstripe.nodes.drivers.backend import BackendOptions
from polarstripe.nodes.drivers.camera import Camera
from polarstripe.nodes.drivers.errors import DeviceLost, DriverError

#: FOURCC -> significant bits
PIXEL_FORMATS = {"Y16 ": 16, "Y10 ": 10, "GREY": 8}
EXPOSURE_UNIT_S = 100e-6  # V4L2 exposure_time_absolute


def _fourcc_text(code: float) -> str:
    code = int(code)
    return "".join(chr((code >> 8 * i) & 0xFF) for i in range(4))


class V4l2Camera(Camera):
    """A V4L2 device (``0`` or ``"/dev/video0"``).

    :param width, height: requested frame size, or None for the driver's default.
    :param pixel_formats: FOURCCs to try, best first (4 characters; ``"Y16 "`` has a trailing space).
    :param gain: the driver's ``gain`` control value, or None to leave it.
    """

    class Options(BackendOptions):
        device: str = "0"  # index or /dev/videoN
        width: int | None = None  # requested frame size [px]; None: the driver's
        height: int | None = None
        pixel_formats: list[str] = ["Y16 ", "Y10 ", "GREY"]  # FOURCCs to try, best first

    def __init__(self, device: int | str = "0", *, width: int | None = None, height: int | None = None,
                 pixel_formats: tuple[str, ...] = ("Y16 ", "Y10 ", "GREY"), exposure_s: float = 0.01,
                 gain: float | None = None):
        if isinstance(device, str) and device.isdigit():
            device = int(device)
        name = f"V4L2 camera {device}"
        path = f"/dev/video{device}" if isinstance(device, int) else str(device)
        if not os.path.exists(path):
            raise DriverError(f"{name}: no such device {path} (camera plugged in? driver loaded?)")
        self._cap = self._open_capture(device)
        if not self._cap.isOpened():
            raise DriverError(f"{name}: cannot open {path} with V4L2 (busy? no permission: group 'video'?)")
        try:
            if width and height:
                self._set(cv2.CAP_PROP_FRAME_WIDTH, width, name)
                self._set(cv2.CAP_PROP_FRAME_HEIGHT, height, name)
            self._cap.set(cv2.CAP_PROP_CONVERT_RGB, 0)
            depth = 8
            for fourcc in pixel_formats:
                fourcc = fourcc.ljust(4)
                accepted = self._cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter_fourcc(*fourcc))
                if accepted and _fourcc_text(self._cap.get(cv2.CAP_PROP_FOURCC)) == fourcc:
                    depth = PIXEL_FORMATS.get(fourcc, 8)
                    break
            self.pixel_format = _fourcc_text(self._cap.get(cv2.CAP_PROP_FOURCC))
            super().__init__(name, exposure_s=exposure_s, gain=1.0 if gain is None else gain, bit_depth=depth)
            self._set(cv2.CAP_PROP_AUTO_EXPOSURE, 1, name)  # V4L2 menu value 1: manual
            self._apply_exposure(exposure_s)
            if gain is not None:
                self._apply_gain(gain)
        except BaseException:
            self._cap.release()
            raise

    def _open_capture(self, device) -> cv2.VideoCapture:
        return cv2.VideoCapture(device, cv2.CAP_V4L2)

    def _set(self, prop: int, value: float, name: str | None = None) -> None:
        if not self._cap.set(prop, value):
            raise DriverError(f"{name or self.name}: the driver refused property {prop} = {value}")

    def _apply_exposure(self, value: float) -> None:
        self._set(cv2.CAP_PROP_EXPOSURE, max(1, round(value / EXPOSURE_UNIT_S)))

    def _apply_gain(self, value: float) -> None:
        self._set(cv2.CAP_PROP_GAIN, value)

    def _grab(self) -> tuple[np.ndarray, dict]:
        ok, image = self._cap.read()
        if not ok or image is None or image.size == 0:
            raise DeviceLost(f"{self.name}: the device delivered no frame (unplugged or stalled)")
        return image, {"pixel_format": self.pixel_format, "pos_msec": self._cap.get(cv2.CAP_PROP_POS_MSEC)}

    def _close(self) -> None:
        self._cap.release()
