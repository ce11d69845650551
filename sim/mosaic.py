"""A division-of-focal-plane polarization sensor: micro-polarizers at 0°, 45°, 90°, 135° over 2×2 pixels
(Sony IMX250MZR/IMX253MZR, in Lucid, FLIR and Basler cameras; docs/physics.md §4.4).

Each pixel sees the scene through its own linear analyzer, so a mosaic frame is the analyzer response of
sim/polarization.py at each pixel's angle φ(x, y):

    I(φ) = ½(k1 + k2)·S0 + ½(k1 − k2)·(S1 cos 2φ + S2 sin 2φ)

with S0 = D + A + B and (S1, S2) = (Bq, Bu) the backscatter's linear Stokes (the object's light is
unpolarized), k1 = 1, k2 = 1/ER the pixel's principal transmittances. Two departures from an ideal mosaic:

* **extinction ratio per pixel**: ER_ij = ER·exp(σ·z_ij), z standard normal, fixed per sensor (a seeded
  map: manufacturing spread, the same in every frame);
* **optical crosstalk**: a fraction ``crosstalk_edge`` of the light through each pixel's micro-polarizer
  lands on each of its 4 edge neighbours and ``crosstalk_diagonal`` on each of its 4 diagonal ones
  (a fixed linear superposition of the neighbours' analyzed intensities, energy kept). For a field that is
  uniform over 3×3 pixels this is an analyzer of the same angle with the polarized term scaled by
  1 − 4c_e − 8c_d in the Sony layout (edge neighbours at φ ± 45° cancel, diagonal ones at φ + 90°
  subtract): :func:`effective_extinction_ratio`.

The sensor's noise is the EMVA 1288 model of sim/sensor.py, applied to the mosaic radiance.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: the IMX250MZR's micro-polarizer angles [deg] over a 2x2 cell, row-major from the top-left pixel
SONY_LAYOUT: tuple[float, float, float, float] = (90.0, 45.0, 135.0, 0.0)
#: Sony's extinction ratio of the IMX250MZR at 525 nm (its flyer: 300:1; 425:1 at 430 nm)
SONY_EXTINCTION_RATIO = 300.0


def check_layout(layout) -> tuple[float, float, float, float]:
    """The 2×2 angles [deg] as a tuple; ValueError unless they are 0, 45, 90, 135 once each (mod 180)."""
    try:
        angles = tuple(float(a) for a in layout)
    except (TypeError, ValueError):
        raise ValueError(f"mosaic layout {layout!r}: need 4 angles in degrees") from None
    if len(angles) != 4 or sorted(round(a % 180.0, 6) for a in angles) != [0.0, 45.0, 90.0, 135.0]:
        raise ValueError(f"mosaic layout {layout!r}: need the angles 0, 45, 90, 135 once each "
                         "(2x2, row-major)")
    return angles  # type: ignore[return-value]


@dataclass(frozen=True)
class MicroPolarizerArray:
    """The mosaic of a polarization sensor.

    Attributes
    ----------
    layout : 4 angles [deg], the 2×2 cell row-major from the top-left pixel (Sony: 90, 45, 135, 0).
    extinction_ratio : nominal ER of a micro-polarizer (k1/k2; Sony: 300 at 525 nm).
    extinction_spread : σ of log ER over the pixels (0: every pixel at the nominal ER).
    crosstalk_edge, crosstalk_diagonal : fraction of a pixel's analyzed light reaching each edge (diagonal)
        neighbour's photodiode.
    seed : the per-pixel ER map's seed (a property of the sensor, not of a frame).
    """

    layout: tuple[float, float, float, float] = SONY_LAYOUT
    extinction_ratio: float = SONY_EXTINCTION_RATIO
    extinction_spread: float = 0.0
    crosstalk_edge: float = 0.0
    crosstalk_diagonal: float = 0.0
    seed: int = 0

    def __post_init__(self):
        object.__setattr__(self, "layout", check_layout(self.layout))
        if not (np.isfinite(self.extinction_ratio) and self.extinction_ratio > 1.0):
            raise ValueError(f"extinction_ratio={self.extinction_ratio} must be > 1")
        if not (np.isfinite(self.extinction_spread) and self.extinction_spread >= 0.0):
            raise ValueError(f"extinction_spread={self.extinction_spread} must be >= 0")
        ce, cd = self.crosstalk_edge, self.crosstalk_diagonal
        if not (0.0 <= ce and 0.0 <= cd and 4.0 * (ce + cd) < 1.0):
            raise ValueError(f"crosstalk_edge={ce}, crosstalk_diagonal={cd}: "
                             "need >= 0 and 4(edge + diagonal) < 1")

    def angles_deg(self, shape: tuple[int, int]) -> np.ndarray:
        """Each pixel's analyzer angle [deg], shape (h, w): the 2×2 layout tiled from the top-left pixel."""
        h, w = shape
        cell = np.asarray(self.layout, float).reshape(2, 2)
        return np.tile(cell, ((h + 1) // 2, (w + 1) // 2))[:h, :w]

    def extinction_map(self, shape: tuple[int, int]) -> np.ndarray:
        """Each pixel's extinction ratio, shape (h, w): ER·exp(σ z), z ~ N(0, 1) seeded by ``seed``."""
        if self.extinction_spread == 0.0:
            return np.full(shape, float(self.extinction_ratio))
        z = np.random.default_rng([self.seed, 25]).standard_normal(shape)
        return np.maximum(self.extinction_ratio * np.exp(self.extinction_spread * z), 1.0 + 1e-9)


def effective_extinction_ratio(extinction_ratio: float, crosstalk_edge: float = 0.0,
                               crosstalk_diagonal: float = 0.0) -> float:
    """The ER a pixel shows to a field uniform over its 3×3 neighbourhood, with crosstalk (Sony layout).

    The polarized term of I(φ) is scaled by d = (ER − 1)/(ER + 1)·(1 − 4c_e − 8c_d) relative to the
    unpolarized one, so ER_eff = (1 + d)/(1 − d).
    """
    d = (extinction_ratio - 1.0) / (extinction_ratio + 1.0) * (1.0 - 4.0 * crosstalk_edge
                                                                - 8.0 * crosstalk_diagonal)
    return (1.0 + d) / (1.0 - d)


def linear_stokes(components) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(S0, S1, S2) of the light reaching the camera [W sr⁻¹ m⁻²]: S0 = D + A + B, (S1, S2) = (Bq + Sq,
    Bu + Su), in the camera frame (angles from image right toward image up; sim/render.py ``Components``:
    Sq, Su the object's light polarized by a camera port)."""
    return (components.D + components.A + components.B, components.Bq + components.Sq,
            components.Bu + components.Su)


def mosaic_radiance(s0, s1, s2, sensor: MicroPolarizerArray) -> np.ndarray:
    """The radiance each pixel of the mosaic records, shape (h, w) of the Stokes maps.

    Parameters
    ----------
    s0, s1, s2 : (h, w) linear Stokes of the light at the sensor [W sr⁻¹ m⁻²] (:func:`linear_stokes`,
        at the camera's resolution).
    sensor : the micro-polarizer array.

    Notes
    -----
    T_ij = ½(k1 + k2)·S0 + ½(k1 − k2)·(S1 cos 2φ_ij + S2 sin 2φ_ij) with k1 = 1, k2 = 1/ER_ij; then the
    recorded value is (1 − 4c_e − 4c_d)·T_ij + c_e·Σ_edge T + c_d·Σ_diagonal T. At the frame's border the
    neighbours are mirrored about the edge pixel, which keeps the 2×2 periodicity of the layout.
    """
    s0, s1, s2 = (np.asarray(a, float) for a in (s0, s1, s2))
    if not (s0.ndim == 2 and s0.shape == s1.shape == s2.shape):
        raise ValueError(f"Stokes maps must be (h, w) of one shape, got {s0.shape}, {s1.shape}, {s2.shape}")
    phi = np.radians(sensor.angles_deg(s0.shape))
    k2 = 1.0 / sensor.extinction_map(s0.shape)
    t = 0.5 * (1.0 + k2) * s0 + 0.5 * (1.0 - k2) * (s1 * np.cos(2.0 * phi) + s2 * np.sin(2.0 * phi))
    ce, cd = sensor.crosstalk_edge, sensor.crosstalk_diagonal
    if ce == 0.0 and cd == 0.0:
        return t
    h, w = t.shape
    pad = np.pad(t, 1, mode="reflect") if min(h, w) > 1 else np.pad(t, 1, mode="edge")
    edge = pad[:-2, 1:-1] + pad[2:, 1:-1] + pad[1:-1, :-2] + pad[1:-1, 2:]
    diag = pad[:-2, :-2] + pad[:-2, 2:] + pad[2:, :-2] + pad[2:, 2:]
    return (1.0 - 4.0 * (ce + cd)) * t + ce * edge + cd * diag
