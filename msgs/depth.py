"""The depth a stripe scan measures: light-stripe triangulation (docs/depth.md)."""

from __future__ import annotations

from dataclasses import field
from typing import Any

import numpy as np
from polarstripe.msgs.base import Message, message


@message("depth_map")
class DepthMap(Message):
    """Depth from one stripe scan of ``method`` (``stripes`` or ``polarized_stripes``, the latter from
    the crossed frames E_b): ``depth_m`` (h, w) float32, z along the camera's optical axis [m], NaN where the
    stripe could not be delineated; ``points_m`` (n, 3) float32, the valid pixels as camera-frame points [m]
    (x image right, y image down, z forward; row-major; None when no pixel is valid); ``metrics`` (valid
    fraction, stripes, geometry source, the error vs the simulator's truth when known)."""

    depth_m: np.ndarray
    points_m: np.ndarray | None
    method: str
    scan_id: int = 0
    metrics: dict[str, Any] = field(default_factory=dict)


DEPTH_TYPES: tuple[type[Message], ...] = (DepthMap,)
