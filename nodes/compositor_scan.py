"""The compositor's bookkeeping of one scan (:mod:`polarstripe.nodes.compositor`): what a scan expects, which
of its analyzer angles a frame belongs to, and the numbers its composite is published with."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from polarstripe.imaging.compose import score
from polarstripe.msgs import Composite, Method


def roi(values: list[int]):
    """A ``[row0, row1, col0, col1]`` param as a tuple, None when empty."""
    return tuple(values) if values else None


@dataclass
class Scan:
    scan_id: int
    method: str
    stripes: int
    analyzer_deg: list[float]
    steps: set[int] = field(default_factory=set)
    frames: int = 0  # folded in
    dropped: int = 0  # of this scan, dropped
    bit_depth: int = 12
    done: bool = False  # its "done" event came
    waiting_truth: bool = False  # complete, held for its simulator/truth message
    fault: str = ""
    mosaic: list[float] = field(default_factory=list)  # a polarization camera's layout (its frames')
    sheets: int = 1  # a stripe scan's sheets per frame

    @property
    def expected(self) -> int | None:
        """Frames the scan takes: its method's patterns at each analyzer angle; None when unknown (a
        stripe scan announced without its stripe count)."""
        n = len(Method(self.method).patterns(self.stripes, 1, self.sheets)) * max(1, len(self.analyzer_deg))
        return n or None

    @property
    def complete(self) -> bool:
        return self.expected is not None and self.frames + self.dropped >= self.expected

    def angle_key(self, angle: float | None, tolerance_deg: float):
        """The scan's nominal analyzer angle nearest ``angle`` (modulo 180), None without one, or False."""
        if not self.analyzer_deg:
            return None
        if angle is None or not math.isfinite(angle):
            return False
        dist = [abs((angle - a + 90.0) % 180.0 - 90.0) for a in self.analyzer_deg]
        i = int(np.argmin(dist))
        return self.analyzer_deg[i] if dist[i] <= tolerance_deg else False


def scan_metrics(scan: Scan, made, truth: Composite | None, dark: float, bright, dim) -> dict:
    """The scan's numbers: its frames and settings, p, and the scores of the composite ``made`` (the chart's
    bars ``bright``/``dim`` from the params, else from the truth; the error against the truth)."""
    if bright is None and truth is not None:
        band, high = truth.images["chart_band"], truth.images["chart_high"]
        if np.any((band >= 0) & high) and np.any((band >= 0) & ~high):
            bright, dim = (band >= 0) & high, (band >= 0) & ~high
    m = {"scan_id": scan.scan_id, "frames": scan.frames, "frames_dropped": scan.dropped,
         "stripes": scan.stripes, "sheets": scan.sheets, "analyzer_deg": scan.analyzer_deg,
         "dark_offset_dn": dark,
         "saturated_pixels": made.saturated_pixels}
    if made.p_estimate is not None:  # eq. 6's p (one p̂ or a map's percentiles) and the medium's
        m.update(made.p_estimate.summary())
    if scan.fault:
        m["fault"] = scan.fault
    m.update(score(made.image, bright=bright, dark=dim, truth=None if truth is None else truth.images["S"]))
    return m
