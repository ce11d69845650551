"""EMVA 1288 linear camera model: radiance → electrons → digital numbers (docs/physics.md §7).

Radiance to photo-electrons per pixel (pinhole camera with a circular aperture of diameter a):

    μ_e = η · L · (π a²/4) · Ω_px · cos⁴α · t_exp / (h c / λ)

with Ω_px = s² the solid angle of a pixel on the optical axis (s from the camera geometry), α the pixel's
off-axis angle (cos⁴ falloff: cos α projected aperture, cos³ α pixel solid angle), η the QE.
Then μ_y = (μ_e + μ_dark)/K + offset, σ_y² = (σ_read² + μ_e + μ_dark)/K² + 1/12 (K = gain in e⁻/DN),
shot noise Poisson, read noise Gaussian, electrons capped at the full well, y = clip(round(·), 0, 2^bits − 1).
The draws: sim/counter_rng.py, the pass: sim/sensor_kernels.py.
"""

from __future__ import annotations

import numpy as np
from polarstripe.sim.geometry import pinhole_frame, pixel_rays
from polarstripe.sim.scene import Camera
from polarstripe.sim.sensor_kernels import expose_gaussian, expose_poisson
from polarstripe.sim.threads import in_bands

_H = 6.62607015e-34
_C = 299792458.0


def electrons_per_radiance(camera: Camera, pixels: np.ndarray | None = None) -> np.ndarray:
    """Mean photo-electrons per unit radiance [e⁻ per (W sr⁻¹ m⁻²)] per pixel, shape (h, w) or (n,)."""
    fr = pinhole_frame(camera.position, camera.look_at, camera.up, camera.fov_deg, camera.resolution)
    cos_a = pixel_rays(fr, pixels) @ fr.f
    photon_j = _H * _C / (camera.wavelength_nm * 1e-9)
    k = camera.qe * np.pi * camera.aperture_m ** 2 / 4.0 * fr.s ** 2 * camera.exposure_s / photon_j
    out = k * cos_a ** 4
    return out.reshape(fr.h, fr.w) if pixels is None else out


def dark_offset_dn(camera: Camera) -> float:
    """Mean DN of a dark frame: offset + dark-current electrons / gain."""
    return camera.offset_dn + camera.dark_current_e_s * camera.exposure_s / camera.gain_e_per_dn


def full_scale_dn(camera: Camera) -> int:
    return (1 << camera.bits) - 1


def mean_dn(radiance, camera: Camera, pixels: np.ndarray | None = None) -> np.ndarray:
    """Expected DN for a radiance field (before clipping). ``radiance`` broadcasts against the pixel grid."""
    e = np.minimum(np.asarray(radiance, float) * electrons_per_radiance(camera, pixels), camera.full_well_e)
    return e / camera.gain_e_per_dn + dark_offset_dn(camera)


def noise_std_dn(radiance, camera: Camera, pixels: np.ndarray | None = None) -> np.ndarray:
    """Temporal noise std [DN]: √((σ_read² + μ_e + μ_dark)/K² + 1/12) (EMVA 1288 linear model)."""
    e = np.minimum(np.asarray(radiance, float) * electrons_per_radiance(camera, pixels), camera.full_well_e)
    dark = camera.dark_current_e_s * camera.exposure_s
    return np.sqrt((camera.read_noise_e ** 2 + e + dark) / camera.gain_e_per_dn ** 2 + 1.0 / 12.0)


def expose(radiance: np.ndarray, camera: Camera, rng: int | np.random.Generator | None = None,
           pixels: np.ndarray | None = None, *, electrons: np.ndarray | None = None,
           gaussian: bool = False) -> np.ndarray:
    """Simulate one exposure: shot noise, Gaussian read noise, full well, gain, ADC, clipping.

    Parameters
    ----------
    radiance : (h, w) or (n,) radiance [W sr⁻¹ m⁻²] reaching the sensor (after the analyzer), ≥ 0
        (NaN and +inf count as 0).
    camera : Camera (exposure, QE, full well, read noise, dark current, gain, bits, offset).
    rng : Generator or seed (reproducible; two 64-bit keys are drawn from it); None uses ``camera.seed``.
    pixels : (n, 2) pixel coordinates for an (n,) ``radiance``; None: the whole (h, w) grid.
    electrons : mean photo-electrons per unit radiance, broadcastable to ``radiance``, precomputed
        (:func:`electrons_per_radiance` of ``camera``, scaled to its exposure); None computes it. A node that
        exposes many frames of one camera computes it once.
    gaussian : draw shot + read noise as one normal variate of the EMVA 1288 variance σ_r² + μ_e (mean and
        variance exact, shape approximate below ~20 e⁻, no whole electrons) instead of Poisson shot noise
        plus normal read noise.

    Returns
    -------
    uint16 DN, same shape, in [0, 2^bits − 1].

    Notes
    -----
    μ_e = L·e_L + μ_dark (capped at 1e12), e = min(Poisson(μ_e), full well) + N(0, σ_r²),
    y = clip(round(e/K + offset), 0, 2^bits − 1): one compiled kernel (sim/sensor_kernels.py), in bands of
    pixels on the model's threads (sim/threads.py). Each pixel draws from its own window of a counter-based
    stream keyed by the generator (sim/counter_rng.py), so a seed gives the same frame on any number of
    threads. Poisson counts are exact below μ_e = 30 and a Cornish–Fisher expansion above
    (docs/physics.md §7: within 10⁻⁴ of Poisson in total variation).
    """
    rng = np.random.default_rng(camera.seed if rng is None else rng)
    keys = rng.integers(0, 2 ** 64, size=2, dtype=np.uint64)
    e_map = electrons_per_radiance(camera, pixels) if electrons is None else electrons
    shape = np.broadcast_shapes(np.shape(radiance), np.shape(e_map))
    rad, e_map = (np.ascontiguousarray(np.broadcast_to(np.asarray(a, float), shape)).reshape(-1)
                  for a in (radiance, e_map))
    out = np.empty(rad.size, np.uint16)
    args = (float(camera.dark_current_e_s * camera.exposure_s), keys)
    adc = (float(camera.read_noise_e), float(camera.full_well_e), 1.0 / camera.gain_e_per_dn,
           float(camera.offset_dn), float(full_scale_dn(camera)))
    kernel = expose_gaussian if gaussian else expose_poisson

    def band(first: int, end: int) -> None:
        kernel(rad[first:end], e_map[first:end], *args, first, *adc, out[first:end])

    in_bands(rad.size, band, min_size=1 << 16)
    return out.reshape(shape)
