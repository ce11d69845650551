"""The camera role: ``grab(timeout)`` gives a :class:`CameraFrame`, the image and what it was taken with.

:class:`Camera` owns the shared behaviour: the grab timeout (a capture call that blocks longer raises
:class:`DriverTimeout` instead of hanging the node), the check that a frame is a real image (a backend that
returns nothing raises :class:`DeviceLost`, never a blank frame), exposure and gain validation, the frame
counter, the count of frames that did not arrive whole (a backend raises :class:`FrameDropped`; nothing
is delivered for them), the context manager and an idempotent :meth:`~Camera.close`. A backend implements
``_grab`` (the image and the device's own metadata) and, where the device can, ``_apply_exposure`` /
``_apply_gain``; a
device that reports the exposure or bit depth it actually used (the simulator) sets ``_exposure_s`` /
``_bit_depth`` in ``_grab``, and the frame carries those. :meth:`Camera.request` says what the next frame is
for; a camera that makes its frame on demand (the simulator's) uses it, a free-running one ignores it.
Exposure and gain are the role's settings, set by the node through the properties; everything else a
backend takes is in its ``Options`` (nodes/drivers/backend.py).
"""

from __future__ import annotations

import concurrent.futures
import math
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass, field

import numpy as np
from polarstripe.nodes.drivers.backend import Backend
from polarstripe.nodes.drivers.errors import (
    DeviceLost,
    DriverError,
    DriverTimeout,
    DriverValueError,
    FrameDropped,
)


@dataclass(frozen=True)
class CameraFrame:
    """One grabbed image and what it was taken with.

    ``image`` is (h, w) or (h, w, c) as the device delivered it (not copied); ``exposure_s`` [s], ``gain``
    and ``bit_depth`` (significant bits) are those the frame was taken with; ``seq`` counts this camera's
    frames from 0; ``stamp_ns`` is wall-clock time (``time.time_ns``) at the end of the grab; ``source``
    names the device or file; ``metadata`` is the backend's own (file name and index, pixel format, the
    simulator's scan and step).
    """

    image: np.ndarray
    exposure_s: float
    gain: float
    bit_depth: int
    seq: int
    stamp_ns: int
    source: str
    metadata: dict = field(default_factory=dict)


class Camera(Backend, ABC):
    """A camera: ``grab(timeout) -> CameraFrame``; ``exposure_s`` and ``gain`` are settable.

    :param name: how the camera is named in error texts (device path, file).
    """

    def __init__(self, name: str, *, exposure_s: float, gain: float, bit_depth: int):
        self.name = name
        self._exposure_s = self._check_exposure(exposure_s)
        self._gain = self._check_gain(gain)
        self._bit_depth = int(bit_depth)
        self._seq = 0
        self.frames_dropped = 0  # frames that did not arrive whole (FrameDropped), never delivered
        self._closed = False
        self._worker = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix=f"grab {name}")
        self._pending: concurrent.futures.Future | None = None

    # -- public --------------------------------------------------------------------------------------------
    def grab(self, timeout: float = 2.0) -> CameraFrame:
        """The next frame: an (h, w) or (h, w, c) image and what it was taken with.

        :raises DriverTimeout: no frame within ``timeout`` seconds (the next grab waits for the late one).
        :raises DeviceLost: the device returned no frame (disconnected).
        :raises FrameDropped: the frame did not arrive whole; counted in :attr:`frames_dropped`.
        :raises DriverError: other failures, the text names the device.
        """
        if self._closed:
            raise DriverError(f"{self.name}: closed")
        if self._pending is None:
            self._pending = self._worker.submit(self._grab)
        # wait first, then take the result: a TimeoutError raised inside the backend (since Python 3.11
        # concurrent.futures.TimeoutError is the builtin) is the backend's error, not this grab's timeout
        done, _ = concurrent.futures.wait([self._pending], timeout)
        if not done:
            raise DriverTimeout(f"{self.name}: no frame within {timeout:g} s")
        pending, self._pending = self._pending, None
        try:
            image, metadata = pending.result()
        except FrameDropped:
            self.frames_dropped += 1
            raise
        if not isinstance(image, np.ndarray) or image.ndim not in (2, 3) or image.size == 0:
            raise DeviceLost(f"{self.name}: returned no image ({type(image).__name__})")
        frame = CameraFrame(image, self._exposure_s, self._gain, self._bit_depth, self._seq, time.time_ns(),
                            self.name, metadata)
        self._seq += 1
        return frame

    def request(self, pattern: str, *, analyzer: bool = True, scan_id: int = 0, step: int = 0) -> None:
        """What the next :meth:`grab` is for: the ``pattern`` tag lit, the analyzer in the path or not, the
        scan and step. A camera that makes its frame on demand renders that; a free-running one ignores it
        (the default)."""

    @property
    def exposure_s(self) -> float:
        """Exposure time [s]."""
        return self._exposure_s

    @exposure_s.setter
    def exposure_s(self, value: float) -> None:
        value = self._check_exposure(value)
        self._apply_exposure(value)
        self._exposure_s = value

    @property
    def gain(self) -> float:
        """Analog gain (the device's unit; 1.0 where it has none)."""
        return self._gain

    @gain.setter
    def gain(self, value: float) -> None:
        value = self._check_gain(value)
        self._apply_gain(value)
        self._gain = value

    @property
    def bit_depth(self) -> int:
        """Significant bits per pixel of the images this camera delivers."""
        return self._bit_depth

    def close(self) -> None:
        """Release the device; idempotent."""
        if self._closed:
            return
        self._closed = True
        self._worker.shutdown(wait=False, cancel_futures=True)
        self._close()

    # -- for backends --------------------------------------------------------------------------------------
    def _check_exposure(self, value: float) -> float:
        value = float(value)
        if not (math.isfinite(value) and value > 0):
            raise DriverValueError(f"{self.name}: exposure_s={value} must be a positive number of seconds")
        return value

    def _check_gain(self, value: float) -> float:
        value = float(value)
        if not (math.isfinite(value) and value >= 0):
            raise DriverValueError(f"{self.name}: gain={value} must be a non-negative number")
        return value

    @abstractmethod
    def _grab(self) -> tuple[np.ndarray, dict]:
        """Block until the next frame; return it and the backend's metadata. Runs in the grab worker
        thread."""

    def _apply_exposure(self, value: float) -> None:  # noqa: B027 - optional hook
        pass

    def _apply_gain(self, value: float) -> None:  # noqa: B027 - optional hook
        pass

    def _close(self) -> None:  # noqa: B027 - optional hook
        pass
