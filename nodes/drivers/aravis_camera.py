"""A GenICam camera (GigE Vision, USB3 Vision) through Aravis, set up by the Standard Features Naming
Convention (SFNC) with the older names where cameras differ.

What the backend sets, in this order (each feature checked against what the camera offers; a value it does
not offer is one :class:`DriverError` listing what it does offer):

* ``PixelFormat``: ``pixel_format``, or the deepest of Mono16, Mono14, Mono12, Mono10, Mono8 the camera
  offers (a camera offering none of them: the deepest polarization mosaic format). Unpacked monochrome only
  (Mono10/12/14 in 16-bit words): the rig measures intensities, so Bayer, colour and packed formats are
  refused. A polarization camera's raw mosaic (PFNC ``PolarizeMono16/12/8``, FLIR's ``Polarized16/8``) is
  read like a monochrome frame, and its metadata carries ``mosaic_deg`` (``mosaic_layout``, Sony's 90, 45 /
  135, 0 by default), so the grabber publishes it as a mosaic and the compositor demosaics it
  (docs/physics.md §4.4). The significant bits are ``PixelDynamicRangeMax`` where the camera
  has it, else the format's.
* ``Width``, ``Height`` when given.
* Triggering on ``TriggerSelector = FrameStart`` (every other selector's ``TriggerMode`` Off first; a camera
  without ``TriggerSelector`` has one trigger): ``trigger = "software"`` sets ``TriggerSource = Software``,
  ``TriggerMode = On``, and each grab executes ``TriggerSoftware`` and waits for that frame; ``"Line0"``,
  ``"Line1"``, …: that source, rising edge, and each grab takes the next frame in the order the pulses came;
  ``"off"``: free running, and each grab takes the first frame that arrives after it asked.
* Exposure: ``ExposureAuto = Off``, then ``ExposureTime`` [µs] (SFNC), else ``ExposureTimeAbs`` [µs] (older
  GigE Vision cameras). The camera rounds to its own steps: a frame carries the exposure read back.
* Gain: ``GainAuto = Off``, ``GainSelector = All`` where offered, then ``Gain`` (SFNC, usually dB), else
  ``GainRaw`` (the camera's integer steps). ``gain`` is in that feature's unit.

Frames: every frame carries the camera's own ``frame_id`` and device timestamp (``device_stamp_ns``: the
camera's clock, ns; ``host_stamp_ns``: when the host received it) in ``CameraFrame.metadata``. A frame that
did not arrive whole (a GigE Vision packet lost and not resent, a USB transfer cut short; Aravis's buffer
status is not SUCCESS, or its data are shorter than the image) is never delivered: the grab raises
:class:`FrameDropped` naming the frame and the status, ``Camera.frames_dropped`` counts it, and the camera
stays open. A camera that stops answering (Aravis's ``control-lost``: heartbeat failed) is
:class:`DeviceLost`.
"""

from __future__ import annotations

import time

import numpy as np
from polarstripe.nodes.drivers.aravis_system import Aravis, GLib, error_text, open_device
from polarstripe.nodes.drivers.backend import BackendOptions
from polarstripe.nodes.drivers.camera import Camera
from polarstripe.nodes.drivers.errors import (
    DeviceLost,
    DriverError,
    DriverTimeout,
    DriverValueError,
    FrameDropped,
)
from polarstripe.sim.mosaic import check_layout

#: PixelFormat name -> (significant bits, numpy dtype): unpacked monochrome, deepest first
MONO_FORMATS = {"Mono16": (16, "<u2"), "Mono14": (14, "<u2"), "Mono12": (12, "<u2"), "Mono10": (10, "<u2"),
                "Mono8": (8, "u1")}
#: … and a polarization camera's raw 2x2 micro-polarizer mosaic (PFNC's names, FLIR's), deepest first
POLARIZED_FORMATS = {"PolarizeMono16": (16, "<u2"), "Polarized16": (16, "<u2"), "PolarizeMono12": (12, "<u2"),
                     "PolarizeMono8": (8, "u1"), "Polarized8": (8, "u1")}
FORMATS = {**MONO_FORMATS, **POLARIZED_FORMATS}
EXPOSURE_FEATURES = ("ExposureTime", "ExposureTimeAbs")  # µs: SFNC, then older GigE Vision
GAIN_FEATURES = ("Gain", "GainRaw")  # SFNC (usually dB), then the camera's integer steps
TRIGGERS = "software | off | Line0, Line1, …"
#: Aravis's buffer status (its nick) -> why the frame is incomplete
_STATUS_TEXT = {
    "missing-packets": "stream packets lost and not resent",
    "timeout": "stream packets lost, the rest did not come in time",
    "cleared": "its first packets were lost (the frame's size is unknown)",
    "wrong-packet-id": "a packet out of place",
    "size-mismatch": "the image is larger than the buffer (the camera's settings changed?)",
    "aborted": "the acquisition was stopped",
    "filling": "still arriving",
}
_POLL_S = 0.1  # how often a waiting grab looks whether the camera was closed or lost


def pick_pixel_format(name: str, offered: list[str], wanted: str | None) -> str:
    """The PixelFormat to set: ``wanted`` if it is one this backend reads (:data:`FORMATS`) and the camera
    offers it, else (None) the deepest unpacked monochrome format offered, else the deepest polarization
    mosaic format (a polarization camera offers only those); one line naming what is offered otherwise."""
    if wanted is None:
        usable = [f for f in MONO_FORMATS if f in offered] or [f for f in POLARIZED_FORMATS if f in offered]
        if not usable:
            raise DriverError(f"{name}: offers no unpacked monochrome format (it offers "
                              f"{', '.join(offered)})")
        return usable[0]
    if wanted not in FORMATS:
        raise DriverValueError(f"{name}: pixel_format={wanted!r} is no unpacked monochrome format nor a "
                               f"polarization mosaic ({', '.join(FORMATS)})")
    if wanted not in offered:
        raise DriverError(f"{name}: pixel_format {wanted} is not offered (the camera offers "
                          f"{', '.join(offered)})")
    return wanted


class AravisCamera(Camera):
    """The GenICam camera ``device`` through Aravis (see the module docstring)."""

    class Options(BackendOptions):
        device: str  # GigE Vision: the camera's address (asked directly, no broadcast); USB3 Vision: its id
        pixel_format: str | None = None  # Mono16 … Mono8, PolarizeMono16/12/8; None: deepest Mono offered
        mosaic_layout: list[float] = [90.0, 45.0, 135.0, 0.0]  # a Polarize format's 2x2 angles [deg]
        trigger: str = "software"  # software | off (free running) | Line0, Line1, … (a hardware line)
        width: int | None = None  # region of interest [px]; None: the camera's
        height: int | None = None
        packet_size: int | None = None  # GigE Vision stream packet [bytes]; None: largest that gets through
        buffers: int = 4  # frames Aravis may hold

    def __init__(self, device: str, *, pixel_format: str | None = None,
                 mosaic_layout: list[float] | tuple[float, ...] = (90.0, 45.0, 135.0, 0.0),
                 trigger: str = "software",
                 width: int | None = None, height: int | None = None, packet_size: int | None = None,
                 buffers: int = 4, exposure_s: float | None = None, gain: float | None = None):
        self.name = name = f"Aravis camera {device}"
        if not (trigger in ("software", "off") or (trigger.startswith("Line") and trigger[4:].isdigit())):
            raise DriverValueError(f"{name}: trigger={trigger!r} is none of {TRIGGERS}")
        if buffers < 2:
            raise DriverValueError(f"{name}: buffers={buffers} must be at least 2")
        self.trigger = trigger
        try:
            self.mosaic_layout = [float(a) for a in check_layout(mosaic_layout)]
        except ValueError as exc:
            raise DriverValueError(f"{name}: {exc}") from None
        self._lost = False
        self._camera = Aravis.Camera.new_with_device(open_device(device))
        self._dev = self._camera.get_device()
        self._stream = None
        try:
            self._dev.set_range_check_policy(Aravis.RangeCheckPolicy.ENABLE)
            self._lost_handler = self._dev.connect("control-lost", self._on_control_lost)
            self.pixel_format, depth = self._set_pixel_format(pixel_format)
            for feature, value in (("Width", width), ("Height", height)):
                if value is not None:
                    self._set(feature, value)
            self._set_trigger()
            self._exposure_feature = self._first_of(EXPOSURE_FEATURES, "exposure")
            self._gain_feature = self._first_of(GAIN_FEATURES, "gain")
            for auto in ("ExposureAuto", "GainAuto"):
                self._set_if_offered(auto, "Off")
            self._set_if_offered("GainSelector", "All")
            self._exposure_used = self._read(self._exposure_feature) / 1e6
            super().__init__(name, exposure_s=exposure_s or self._exposure_used,
                             gain=self._read(self._gain_feature) if gain is None else gain, bit_depth=depth)
            if exposure_s is not None:
                self._apply_exposure(exposure_s)
            if gain is not None:
                self._apply_gain(gain)
            self._start_stream(packet_size, buffers)
        except BaseException:
            self._release()
            raise

    # -- features ---------------------------------------------------------------------------------------
    def _offers(self, feature: str) -> bool:
        return bool(self._dev.is_feature_available(feature))

    def _ask(self, what: str, call, *args):
        """``call(*args)`` on the device; Aravis's GError becomes one DriverError line naming ``what``."""
        try:
            return call(*args)
        except GLib.Error as exc:
            raise DriverError(f"{self.name}: {what}: {error_text(exc)}") from None

    def _is_float(self, feature: str) -> bool:
        return isinstance(self._dev.get_feature(feature), Aravis.GcFloat)

    def _choices(self, feature: str) -> list[str]:
        return list(self._ask(feature, self._dev.dup_available_enumeration_feature_values_as_strings, feature)
                    or [])

    def _read(self, feature: str) -> float:
        dev = self._dev
        call = dev.get_float_feature_value if self._is_float(feature) else dev.get_integer_feature_value
        return float(self._ask(feature, call, feature))

    def _bounds(self, feature: str) -> tuple[float, float]:
        dev = self._dev
        call = dev.get_float_feature_bounds if self._is_float(feature) else dev.get_integer_feature_bounds
        return tuple(self._ask(feature, call, feature))

    def _set(self, feature: str, value) -> None:
        """Write ``feature`` (enumeration, integer or float, by the value's type and the node's)."""
        dev = self._dev
        if isinstance(value, str):
            self._ask(f"{feature} = {value}", dev.set_string_feature_value, feature, value)
        elif self._is_float(feature):
            self._ask(f"{feature} = {value}", dev.set_float_feature_value, feature, float(value))
        else:
            self._ask(f"{feature} = {value}", dev.set_integer_feature_value, feature, int(round(value)))

    def _set_if_offered(self, feature: str, value: str) -> None:
        """Set enumeration ``feature`` to ``value`` where the camera has both and it is not so already."""
        if self._offers(feature) and value in self._choices(feature) and \
                self._ask(feature, self._dev.get_string_feature_value, feature) != value:
            self._set(feature, value)

    def _first_of(self, features: tuple[str, ...], what: str) -> str:
        found = next((f for f in features if self._offers(f)), None)
        if found is None:
            raise DriverError(f"{self.name}: the camera has no {what} feature ({' or '.join(features)})")
        return found

    def _set_pixel_format(self, wanted: str | None) -> tuple[str, int]:
        wanted = pick_pixel_format(self.name, self._choices("PixelFormat"), wanted)
        self._set("PixelFormat", wanted)
        depth = FORMATS[wanted][0]
        if self._offers("PixelDynamicRangeMax"):
            depth = min(depth, max(1, int(self._read("PixelDynamicRangeMax")).bit_length()))
        return wanted, depth

    def _set_trigger(self) -> None:
        name = self.name
        if self._offers("TriggerSelector"):
            selectors = self._choices("TriggerSelector")
            if "FrameStart" not in selectors:
                raise DriverError(f"{name}: TriggerSelector has no FrameStart ({', '.join(selectors)})")
            for selector in selectors:  # only FrameStart triggers
                self._set("TriggerSelector", selector)
                self._set_if_offered("TriggerMode", "Off")
            self._set("TriggerSelector", "FrameStart")
        if self.trigger == "off":
            self._set_if_offered("TriggerMode", "Off")
        else:
            source = "Software" if self.trigger == "software" else self.trigger
            sources = self._choices("TriggerSource") if self._offers("TriggerSource") else []
            if source not in sources:
                raise DriverError(f"{name}: trigger source {source} is not offered (TriggerSource: "
                                  f"{', '.join(sources) or 'none'})")
            self._set("TriggerSource", source)
            if source != "Software":
                self._set_if_offered("TriggerActivation", "RisingEdge")
            self._set("TriggerMode", "On")
        self._set_if_offered("AcquisitionMode", "Continuous")

    def _start_stream(self, packet_size: int | None, buffers: int) -> None:
        try:
            if self._camera.is_gv_device():
                if packet_size:
                    self._camera.gv_set_packet_size(packet_size)
                else:
                    self._camera.gv_auto_packet_size()
            self._stream = self._camera.create_stream(None, None)
            payload = self._camera.get_payload()
            for _ in range(buffers):
                self._stream.push_buffer(Aravis.Buffer.new_allocate(payload))
            self._camera.start_acquisition()
        except GLib.Error as exc:
            raise DriverError(f"{self.name}: cannot start the stream: {error_text(exc)}") from None

    # -- the role ---------------------------------------------------------------------------------------
    def _apply_exposure(self, value: float) -> None:
        feature, us = self._exposure_feature, round(value * 1e6, 3)  # 0.1 s is 100000 µs, not 99999.99…
        lo, hi = self._bounds(feature)
        if not lo <= us <= hi:
            raise DriverValueError(f"{self.name}: exposure {us:g} µs is outside the camera's "
                                   f"{lo:g}-{hi:g} µs ({feature})")
        self._set(feature, us)
        self._exposure_used = self._read(feature) / 1e6  # the camera's own step

    def _apply_gain(self, value: float) -> None:
        feature = self._gain_feature
        lo, hi = self._bounds(feature)
        if not lo <= value <= hi:
            raise DriverValueError(f"{self.name}: gain {value:g} is outside the camera's {lo:g}-{hi:g} "
                                   f"({feature})")
        self._set(feature, value)

    def grab(self, timeout: float = 2.0):
        """The next frame (module docstring); :class:`FrameDropped` for a frame that did not arrive whole.

        The wait is this backend's own (it ends the grab worker's wait, so a frame that comes later is not
        taken for the next grab's); the role's timeout is a little longer."""
        self._wait_s = timeout
        return super().grab(timeout + 1.0)

    def _grab(self) -> tuple[np.ndarray, dict]:
        wait_s, stream = getattr(self, "_wait_s", 2.0), self._stream  # close() may drop self._stream
        if stream is None:
            raise DriverError(f"{self.name}: closed")
        if not self.trigger.startswith("Line"):  # a hardware line's frames are taken in the pulses' order
            self._drain(stream)  # a frame that came after an earlier grab gave up is not this one
        if self.trigger == "software":
            self._fire_software_trigger()
        deadline = time.monotonic() + wait_s
        while True:
            if self._closed:
                raise DriverError(f"{self.name}: closed")
            if self._lost:
                raise DeviceLost(f"{self.name}: the camera stopped answering (GigE Vision heartbeat lost)")
            buffer = stream.timeout_pop_buffer(int(_POLL_S * 1e6))
            if buffer is not None:
                self._exposure_s = self._exposure_used
                return self._take(stream, buffer)
            if time.monotonic() > deadline:
                hint = {"software": "TriggerSoftware was sent", "off": "free running"}.get(
                    self.trigger, f"no pulse on {self.trigger}?")
                raise DriverTimeout(f"{self.name}: no frame within {wait_s:g} s ({hint})")

    def _fire_software_trigger(self) -> None:
        self._ask("TriggerSoftware", self._dev.execute_command, "TriggerSoftware")

    @staticmethod
    def _drain(stream) -> None:
        while (buffer := stream.try_pop_buffer()) is not None:
            stream.push_buffer(buffer)

    def _take(self, stream, buffer) -> tuple[np.ndarray, dict]:
        """The image of ``buffer`` (copied), or FrameDropped; the buffer goes back to the stream."""
        try:
            status = buffer.get_status()
            frame_id = buffer.get_frame_id()
            if status != Aravis.BufferStatus.SUCCESS:
                which = f"frame {frame_id}" if frame_id else "a frame"
                why = _STATUS_TEXT.get(status.value_nick, status.value_nick)
                raise FrameDropped(f"{self.name}: {which} dropped, incomplete: {why}")
            bits, dtype = FORMATS[self.pixel_format]
            width, height = buffer.get_image_width(), buffer.get_image_height()
            pad_x, _ = buffer.get_image_padding()
            data = buffer.get_image_data()
            row = width * np.dtype(dtype).itemsize + pad_x
            if len(data) < row * height:
                raise FrameDropped(f"{self.name}: frame {frame_id} dropped: {len(data)} bytes of "
                                   f"{row * height} ({width}x{height} {self.pixel_format})")
            rows = np.frombuffer(data, np.uint8, row * height).reshape(height, row)
            image = rows[:, : row - pad_x].copy().view(np.dtype(dtype)).reshape(height, width)
            meta = {"pixel_format": self.pixel_format, "frame_id": frame_id,
                    "device_stamp_ns": buffer.get_timestamp(), "host_stamp_ns": buffer.get_system_timestamp()}
            if self.pixel_format in POLARIZED_FORMATS:  # published as a mosaic (Frame.mosaic_deg)
                meta["mosaic_deg"] = list(self.mosaic_layout)
            return image, meta
        finally:
            stream.push_buffer(buffer)

    def _on_control_lost(self, device) -> None:  # Aravis's heartbeat thread
        self._lost = True

    def _release(self) -> None:
        if self._camera is None:
            return
        # stopped and let go explicitly: a reference still held somewhere (a traceback) must not keep the
        # camera streaming or its control channel taken from the next client
        try:
            if self._stream is not None:
                self._camera.stop_acquisition()
            if isinstance(self._dev, Aravis.GvDevice):
                self._dev.leave_control()
        except GLib.Error:
            pass  # a lost camera cannot be stopped
        if getattr(self, "_lost_handler", None) is not None:
            self._dev.disconnect(self._lost_handler)
        self._stream = self._dev = self._camera = None  # the last references: Aravis closes the device

    def _close(self) -> None:
        self._release()
