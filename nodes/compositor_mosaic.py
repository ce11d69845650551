"""The compositor's view of a polarization camera's frame: the raw 2×2 micro-polarizer mosaic
(``Frame.mosaic_deg``) turned into what the running reductions fold (imaging/mosaic.py; docs/physics.md §4.4).

A polarized method's frame gives two views, E_b and E_w, keyed by the analyzer angle relative to the light's
polarization (90: crossed, 0: along it), so that :func:`polarstripe.imaging.compose.compose` takes them as it
takes a rotating analyzer's two angles; an unpolarized method's frame gives one view, a0·S0 (no analyzer).
Each view is float64 DN with the dark offset once, :data:`~polarstripe.imaging.mosaic.SATURATED` where a raw
pixel it reads was saturated.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from polarstripe.imaging.mosaic import SATURATED, MosaicCalibration, crossed_pair, mosaic_intensity
from polarstripe.msgs import Frame

#: the view keys of a polarized mosaic frame: analyzer angle [deg] relative to the light's polarization
E_B_KEY, E_W_KEY = 90.0, 0.0


class MosaicViews:
    """Views of mosaic frames with the compositor's ``mosaic_*`` params (the camera's calibration and the
    crossed-angle rule)."""

    saturation = SATURATED  # the level the running reductions mask at

    def __init__(self, params):
        self.rule, self.sigma_px = params.mosaic_rule, params.mosaic_angle_sigma_px
        self.polarized_sigma_px = params.mosaic_polarized_sigma_px
        self.calibration = MosaicCalibration(extinction_ratio=params.mosaic_extinction_ratio,
                                             crosstalk_edge=params.mosaic_crosstalk[0],
                                             crosstalk_diagonal=params.mosaic_crosstalk[1])

    def views(self, frame: Frame, polarized: bool,
              saturation: float | None) -> dict[float | None, np.ndarray]:
        """{E_B_KEY: E_b, E_W_KEY: E_w} (``polarized``) or {None: a0·S0}; ImagingError for a frame that is
        no mosaic this can read (odd size, float image, a layout without the four angles)."""
        cal = dataclasses.replace(self.calibration, layout=tuple(frame.mosaic_deg))
        if polarized:
            e_b, e_w = crossed_pair(frame.image, cal, rule=self.rule, angle_sigma_px=self.sigma_px,
                                    polarized_sigma_px=self.polarized_sigma_px, saturation=saturation)
            return {E_B_KEY: e_b, E_W_KEY: e_w}
        return {None: mosaic_intensity(frame.image, cal, saturation=saturation)}
