"""The simulator's polarization camera: a division-of-focal-plane sensor (Sony IMX250MZR-like:
micro-polarizers at 0°, 45°, 90°, 135° over 2×2 pixels; sim/mosaic.py). Each grab asks the simulator node
for a raw mosaic frame (``simulator/render_mosaic``); the frame's metadata carries the mosaic's angles
(``mosaic_deg``) and the GenICam pixel format a real camera would name (``PolarizeMono12``), so the grabber
publishes it as a mosaic.

Like :class:`~polarstripe.nodes.drivers.sim_camera.SimCamera`, which it extends, it models no free-running
stream. It has no analyzer to put in or out: the micro-polarizers are always in the path, so the analyzer
flag of :meth:`request` is ignored.

::

    # in a node: open_backend("camera", "sim_polarization", {}, context=...)
    cam.request("stripe:3/30", scan_id=7, step=3)
    frame = cam.grab(timeout=6.0)   # frame.metadata["mosaic_deg"] == [90.0, 45.0, 135.0, 0.0]
"""

from __future__ import annotations

from polarstripe.msgs import Frame, RenderRequest
from polarstripe.nodes.drivers.backend import BackendContext, BackendOptions
from polarstripe.nodes.drivers.errors import DeviceLost, DriverError
from polarstripe.nodes.drivers.sim_camera import SimCamera


class SimPolarizationCamera(SimCamera):
    """A polarization camera backed by the simulator node (see the module docstring)."""

    class Options(BackendOptions):
        render_service: str = "simulator/render_mosaic"  # the simulator's service that renders a mosaic frame

    @classmethod
    def from_options(cls, options: Options, context: BackendContext | None = None,
                     **common) -> SimPolarizationCamera:
        """Call the simulator through the node's service ``options.render_service``."""
        if context is None or context.service is None:
            raise DriverError("sim_polarization camera: needs the node's service calls (a BackendContext)")
        return cls(context.service(options.render_service, RenderRequest, Frame),
                   name="sim polarization camera", **common)

    def request(self, pattern: str, *, analyzer: bool = True, scan_id: int = 0, step: int = 0) -> None:
        """What the next :meth:`grab` renders (the micro-polarizers are always in the path)."""
        super().request(pattern, analyzer=True, scan_id=scan_id, step=step)

    def _metadata(self, frame: Frame) -> dict:
        """Also the mosaic's angles and the pixel format; a frame that is no 2×2 mosaic is a fault."""
        if len(frame.mosaic_deg) != 4:
            raise DeviceLost(f"{self.name}: the simulator's frame is no 2x2 mosaic "
                             f"(mosaic_deg={frame.mosaic_deg})")
        return {**super()._metadata(frame), "mosaic_deg": [float(a) for a in frame.mosaic_deg],
                "pixel_format": f"PolarizeMono{frame.bit_depth}"}
