"""The compositor node's params and their checks (the node: nodes/compositor.py)."""

from __future__ import annotations

from typing import Literal

from polarstripe.nodes.compositor_mosaic import MosaicViews
from polarstripe.nodes.compositor_p import MediumModel
from polarstripe.runtime.params import NodeParams


class CompositorParams(NodeParams):
    """The compositor node's params (nodes/compositor.py)."""

    out: str = ""  # output folder; "" = publish only
    dark_offset_dn: float | None = None  # None: the simulator truth's, else 0
    saturation_dn: float | None = None  # None: 2**bit_depth - 1 of the frames
    angle_tolerance_deg: float = 2.0  # a frame's analyzer angle vs the scan's angles
    object_free_roi: list[int] = []  # (row0, row1, col0, col1) for p; empty: from truth, else whole frame
    chart_bright_roi: list[int] = []  # bright bars (row0, row1, col0, col1); empty: from truth
    chart_dark_roi: list[int] = []  # dark bars
    lit_fraction: float = 0.5  # of the checker patterns
    black_level: float = 0.0  # projector "off" relative to "on"
    p_min: float = 0.05
    p_rule: Literal["map", "median", "upper"] = "map"  # eq. 6's p: per pixel, or one p̂ (physics.md §4.2)
    p_scene: str = ""  # the map's medium model: "" the paper's tank, a scene .toml, "none" (the frames')
    p_fidelity: str = "preview"  # … rendered at this fidelity
    light: Literal["scene", "linear", "circular"] = "scene"  # the rig's optics, for the model
    use_truth: bool = True  # score against each scan's simulator/truth message
    truth_wait_s: float = 1.0  # hold a complete scan this long for its truth (until the topic is silent)
    done_grace_s: float = 0.3  # after "done", wait this long since the last frame for frames in flight
    early_frames: int = 16  # frames held ahead of their scan's "start"
    image_format: Literal["tiff", "npy"] = "tiff"
    comparison: bool = True
    geometry: str = ""  # rig for depth: "" the default tank, a scene .toml, a calibration file, or "none"
    depth_k_sigma: float = 4.0  # a stripe is delineated where its margins exceed this many noise sigma
    depth_min_contrast: float = 0.15  # and its edges this fraction of the signal
    depth_noise: list[float] = [1.0, 1.0 / 12.0]  # sensor read noise [DN] and DN per electron
    depth_range_m: list[float] = []  # objects' [near, far] [m]: tells K sheets apart ([]: truth ±10 %)
    mosaic_rule: Literal["local", "global", "pixel"] = "local"  # a polarization camera's E_b/E_w angle
    mosaic_angle_sigma_px: float = 6.0  # the local rule's smoothing of the light's angle [px]
    mosaic_polarized_sigma_px: float = 0.0  # smooth the polarized part of E_b/E_w [px] (0: not)
    mosaic_extinction_ratio: float = 300.0  # the camera's calibration: micro-polarizer ER
    mosaic_crosstalk: list[float] = [0.001, 0.0002]  # … and crosstalk to each edge, diagonal neighbour

    def validate(self):
        super().validate()
        for key in ("object_free_roi", "chart_bright_roi", "chart_dark_roi"):
            if getattr(self, key) and len(getattr(self, key)) != 4:
                raise ValueError(f"{key} must be [row0, row1, col0, col1], got {getattr(self, key)}")
        if bool(self.chart_bright_roi) != bool(self.chart_dark_roi):
            raise ValueError("give both chart_bright_roi and chart_dark_roi, or neither")
        if not (self.truth_wait_s > 0 and self.done_grace_s > 0 and self.early_frames >= 0):
            raise ValueError("truth_wait_s and done_grace_s must be > 0 s, early_frames >= 0")
        if len(self.mosaic_crosstalk) != 2:
            raise ValueError(f"mosaic_crosstalk must be [edge, diagonal], got {self.mosaic_crosstalk}")
        MosaicViews(self)  # ImagingError (a ValueError) names a bad number
        MediumModel(self)  # a bad p_scene or p_fidelity
