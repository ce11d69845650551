"""The simulator's camera: each grab asks the simulator node (``simulator/render``) for a rendered frame.

Like python-can's ``virtual.py``, a real backend that says what it does not model: no free-running stream
(a frame is rendered when grabbed, for the pattern and analyzer set with :meth:`SimCamera.request`), no
exposure or gain of its own (``exposure_s`` is sent along only once it has been set; the simulator's scene
decides otherwise; either way the grabbed frame carries the exposure and bit depth the simulator used), no
dropped or torn frames. A simulator that does not answer is a :class:`DriverTimeout`; one that answers with
an error (``camera_lost``) is :class:`DeviceLost`. The image is the received one (a read-only view, not
copied). Like a real camera it does not say at which analyzer angle the frame was taken: the grabber knows
that from ``polarizer/state``.

::

    cam = SimCamera(render=client.call)          # client: the node's simulator/render service client
    # in a node: open_backend("camera", "sim", {"render_service": "simulator/render"}, context=...)
    cam.request("stripe:3/30", analyzer=True, scan_id=7, step=3)
    frame = cam.grab(timeout=6.0)   # CameraFrame; frame.metadata: pattern, scan_id, step
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from polarstripe.msgs import Frame, RenderRequest
from polarstripe.nodes.drivers.backend import BackendContext, BackendOptions
from polarstripe.nodes.drivers.camera import Camera
from polarstripe.nodes.drivers.errors import DeviceLost, DriverError, DriverTimeout


class SimCamera(Camera):
    """A camera backed by the simulator node.

    :param render: ``render(RenderRequest) -> Frame`` — the simulator's ``simulator/render`` service (a bus
        client's ``call``); it must raise ``TimeoutError`` when the simulator does not answer.
    :param exposure_s: exposure [s] sent with each request once set (the constructor value is sent only if
        ``send_exposure``).
    """

    class Options(BackendOptions):
        render_service: str = "simulator/render"  # the simulator's service that renders a frame

    @classmethod
    def from_options(cls, options: Options, context: BackendContext | None = None, **common) -> SimCamera:
        """Call the simulator through the node's service ``options.render_service``."""
        if context is None or context.service is None:
            raise DriverError("sim camera: needs the node's service calls (a BackendContext)")
        return cls(context.service(options.render_service, RenderRequest, Frame), **common)

    def __init__(self, render: Callable, *, exposure_s: float = 0.008, gain: float = 1.0, bit_depth: int = 12,
                 send_exposure: bool = False, name: str = "sim camera"):
        super().__init__(name, exposure_s=exposure_s, gain=gain, bit_depth=bit_depth)
        self._render = render
        self._send_exposure = send_exposure
        self._pattern, self._analyzer, self._scan_id, self._step = "flood", True, 0, 0

    def request(self, pattern: str, *, analyzer: bool = True, scan_id: int = 0, step: int = 0) -> None:
        """What the next :meth:`grab` renders: ``pattern`` tag, analyzer in the path or not, the scan and
        step the frame belongs to."""
        self._pattern, self._analyzer, self._scan_id, self._step = str(pattern), bool(analyzer), scan_id, step

    def _apply_exposure(self, value: float) -> None:
        self._send_exposure = True

    def _grab(self) -> tuple[np.ndarray, dict]:
        req = RenderRequest(pattern=self._pattern, analyzer=self._analyzer, scan_id=self._scan_id,
                            step=self._step, exposure_s=self._exposure_s if self._send_exposure else None)
        try:
            frame = self._render(req)
        except TimeoutError as exc:
            raise DriverTimeout(f"{self.name}: the simulator did not answer: {exc}") from None
        except Exception as exc:  # an error reply: the simulated camera is gone
            raise DeviceLost(f"{self.name}: {exc}") from None
        self._bit_depth, self._exposure_s = frame.bit_depth, frame.exposure_s  # what it was taken with
        return frame.image, self._metadata(frame)

    def _metadata(self, frame: Frame) -> dict:
        """The grabbed frame's metadata: what it shows and which scan step it is."""
        return {"pattern": frame.pattern, "scan_id": frame.scan_id, "step": frame.step}
