"""A camera that plays frames from files: a folder or glob of images (16-bit PNG/TIFF kept at 16 bits) or a
video file (lossless 16-bit FFV1 is read back bit-exact).

Exposure and gain are recorded in the frame info but do not change the pixels (the files are what they are);
``bit_depth`` is the dtype's unless given (12 for 12-bit data stored in 16-bit PNGs). With ``loop=False`` the
end of the files raises :class:`EndOfFrames`; with ``loop=True`` it starts again. ``fps`` paces the frames
(None: as fast as asked).
"""

from __future__ import annotations

import glob
import os
import time
from pathlib import Path

import cv2
import numpy as np
from polarstripe.nodes.drivers.backend import BackendOptions
from polarstripe.nodes.drivers.camera import Camera
from polarstripe.nodes.drivers.errors import DriverError, EndOfFrames

IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".pgm")


class FileCamera(Camera):
    """Frames from ``source``: a folder of images, a glob (``"run/frame_*.png"``), or a video file."""

    class Options(BackendOptions):
        source: str  # a folder of images, a glob ("run/frame_*.png") or a video file
        loop: bool = False  # start again at the end
        fps: float | None = None  # pace the frames; None: as fast as grabbed
        bit_depth: int | None = None  # significant bits; None: the file's sample size

    def __init__(self, source: str | os.PathLike, *, loop: bool = False, fps: float | None = None,
                 exposure_s: float = 0.01, gain: float = 1.0, bit_depth: int | None = None):
        source = str(source)
        self._files: list[str] = []
        self._video: cv2.VideoCapture | None = None
        if os.path.isdir(source):
            self._files = sorted(str(p) for p in Path(source).iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        elif glob.has_magic(source):
            self._files = sorted(glob.glob(source))
        elif os.path.isfile(source) and Path(source).suffix.lower() in IMAGE_SUFFIXES:
            self._files = [source]
        elif os.path.isfile(source):
            self._video = cv2.VideoCapture(source, cv2.CAP_FFMPEG, [cv2.CAP_PROP_CONVERT_RGB, 0])
            if not self._video.isOpened():
                raise DriverError(f"file camera: cannot open video {source!r}")
        else:
            raise DriverError(f"file camera: {source!r} is no folder, glob, image or video file")
        if self._video is None and not self._files:
            raise DriverError(f"file camera: no images ({', '.join(IMAGE_SUFFIXES)}) in {source!r}")
        self.loop, self.fps = loop, fps
        self._index = 0
        self._last = -1e18
        first, _ = self._read()
        self._first = first
        depth = bit_depth if bit_depth is not None else 8 * first.dtype.itemsize
        super().__init__(f"file camera {source}", exposure_s=exposure_s, gain=gain, bit_depth=depth)

    def __len__(self) -> int:
        """Number of frames in one pass (a video's frame count as its container reports it)."""
        if self._video is not None:
            return int(self._video.get(cv2.CAP_PROP_FRAME_COUNT))
        return len(self._files)

    def _read(self) -> tuple[np.ndarray, dict]:
        if self._video is not None:
            ok, image = self._video.read()
            if not ok and self.loop and self._index > 0:
                self._video.set(cv2.CAP_PROP_POS_FRAMES, 0)
                self._index = 0
                ok, image = self._video.read()
            if not ok or image is None:
                raise EndOfFrames(f"file camera: video ended after {self._index} frames")
            extra = {"index": self._index}
        else:
            if self._index >= len(self._files):
                if not self.loop:
                    raise EndOfFrames(f"file camera: all {len(self._files)} images were played")
                self._index = 0
            path = self._files[self._index]
            image = cv2.imread(path, cv2.IMREAD_UNCHANGED)
            if image is None:
                raise DriverError(f"file camera: cannot read image {path!r}")
            extra = {"index": self._index, "file": os.path.basename(path)}
        self._index += 1
        return image, extra

    def _grab(self) -> tuple[np.ndarray, dict]:
        if self._first is not None:  # the frame read to learn the dtype is the first one delivered
            image, self._first = self._first, None
            extra = {"index": 0} if self._video is not None else {"index": 0,
                                                                   "file": os.path.basename(self._files[0])}
        else:
            image, extra = self._read()
        if self.fps:
            wait = self._last + 1.0 / self.fps - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            self._last = time.monotonic()
        return image, extra

    def _close(self) -> None:
        if self._video is not None:
            self._video.release()
