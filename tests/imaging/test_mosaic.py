"""Demosaicing and Stokes of a polarization camera's frame (imaging/mosaic.py) against closed forms: a uniform
polarized field's Stokes, the extinction ratio and crosstalk calibrated out, the dark offset, the bias of the
per-pixel minimum under noise."""

import numpy as np
import pytest
from polarstripe.imaging.mosaic import (
    SATURATED,
    ImagingError,
    MosaicCalibration,
    crossed_from_stokes,
    crossed_pair,
    demosaic,
    mosaic_intensity,
    mosaic_stokes,
)


def _raw(shape, s0, dop, chi_deg, *, er=300.0, ce=0.0, cd=0.0, layout=(90, 45, 135, 0), offset=0.0):
    """A noise-free uniform field through the mosaic, written from Malus's law (not sim/mosaic.py), in DN."""
    h, w = shape
    cell = np.asarray(layout, float).reshape(2, 2)
    phi = np.radians(np.tile(cell, (h // 2, w // 2)))
    k2 = 1 / er

    def malus(angle):
        return 0.5 * (1 + k2) * s0 + 0.5 * (1 - k2) * s0 * dop * np.cos(2 * (angle - np.radians(chi_deg)))

    own = malus(phi)
    edge = 2 * malus(np.roll(phi, 1, 1)) + 2 * malus(np.roll(phi, 1, 0))
    diag = 4 * malus(np.roll(np.roll(phi, 1, 0), 1, 1))
    return np.round((1 - 4 * ce - 4 * cd) * own + ce * edge + cd * diag + offset).astype(np.uint16)


@pytest.mark.parametrize("chi", [0.0, 25.0, 100.0])
@pytest.mark.parametrize("layout", [(90, 45, 135, 0), (0, 45, 135, 90)])
def test_a_uniform_polarized_field_gives_its_stokes(chi, layout):
    raw = _raw((16, 20), 3000.0, 0.6, chi, layout=layout)
    s = mosaic_stokes(raw, MosaicCalibration(layout=layout))[2:-2, 2:-2]
    c, d = np.cos(2 * np.radians(chi)), np.sin(2 * np.radians(chi))
    np.testing.assert_allclose(s[..., 0], 3000.0, atol=2.0)
    np.testing.assert_allclose(s[..., 1], 3000.0 * 0.6 * c, atol=2.0)
    np.testing.assert_allclose(s[..., 2], 3000.0 * 0.6 * d, atol=2.0)


def test_the_four_images_sit_at_their_angles():
    raw = _raw((8, 8), 2000.0, 1.0, 0.0, er=1e9)
    images, angles = demosaic(raw)
    assert angles == (90.0, 45.0, 135.0, 0.0)
    np.testing.assert_allclose(images[3, 2:-2, 2:-2], 2000.0, atol=1)    # 0 deg: all of it
    np.testing.assert_allclose(images[0, 2:-2, 2:-2], 0.0, atol=1)       # 90 deg: none


def test_extinction_and_crosstalk_are_calibrated_out_and_bias_the_dop_when_they_are_not():
    ce, cd = 0.004, 0.001
    raw = _raw((16, 16), 3000.0, 0.8, 30.0, er=100.0, ce=ce, cd=cd)
    right = mosaic_stokes(raw, MosaicCalibration(extinction_ratio=100.0, crosstalk_edge=ce,
                                                 crosstalk_diagonal=cd))[4:-4, 4:-4]
    naive = mosaic_stokes(raw, MosaicCalibration(extinction_ratio=1e9))[4:-4, 4:-4]
    dop_right = np.hypot(right[..., 1], right[..., 2]) / right[..., 0]
    dop_naive = np.hypot(naive[..., 1], naive[..., 2]) / naive[..., 0]
    np.testing.assert_allclose(dop_right, 0.8, atol=2e-3)
    # an ideal-analyzer reading keeps (ER - 1)/(ER + 1)(1 - 4 ce - 8 cd) of the DOP
    np.testing.assert_allclose(dop_naive, 0.8 * (99 / 101) * (1 - 4 * ce - 8 * cd), atol=2e-3)


def test_e_b_and_e_w_are_eqs_4_and_5_and_carry_the_dark_offset_once():
    """Polarized light B p at chi plus unpolarized S: E_b = a0(S + B(1 - p)), E_w = a0(S + B(1 + p))."""
    s, b, p, chi, o, er = 1200.0, 1800.0, 0.7, 40.0, 64.0, 300.0
    total, dop = s + b, b * p / (s + b)
    raw = _raw((20, 20), total, dop, chi, er=er, offset=o)
    a0 = 0.5 * (1 + 1 / er)
    for rule in ("local", "global", "pixel"):
        e_b, e_w = crossed_pair(raw, MosaicCalibration(extinction_ratio=er), rule=rule)
        np.testing.assert_allclose(e_b[3:-3, 3:-3], a0 * (s + b * (1 - p)) + o, atol=1.5)
        np.testing.assert_allclose(e_w[3:-3, 3:-3], a0 * (s + b * (1 + p)) + o, atol=1.5)
    flat = mosaic_intensity(raw, MosaicCalibration(extinction_ratio=er))
    np.testing.assert_allclose(flat[3:-3, 3:-3], a0 * total + o, atol=1.0)


def test_the_per_pixel_minimum_is_biased_low_by_the_rayleigh_mean_and_the_smoothed_angle_is_not():
    """Unpolarized light with independent noise sigma in S1 and S2: sqrt(S1^2 + S2^2) is Rayleigh, mean
    sigma sqrt(pi/2), so the pixel rule's E_b is low by a0 sigma sqrt(pi/2); the local rule is unbiased."""
    rng = np.random.default_rng(7)
    sigma, a0 = 20.0, 0.5
    stokes = np.stack([np.full((300, 300), 1000.0), rng.normal(0, sigma, (300, 300)),
                       rng.normal(0, sigma, (300, 300))], -1)
    e_b_pixel, _ = crossed_from_stokes(stokes, a0, rule="pixel")
    e_b_local, _ = crossed_from_stokes(stokes, a0, rule="local", angle_sigma_px=8.0)
    assert a0 * 1000.0 - e_b_pixel.mean() == pytest.approx(a0 * sigma * np.sqrt(np.pi / 2), rel=0.02)
    assert abs(e_b_local.mean() - a0 * 1000.0) < 4 * a0 * sigma / 300


def test_saturated_raw_pixels_mark_what_was_made_from_them():
    raw = _raw((12, 12), 2000.0, 0.5, 0.0)
    raw[5, 6] = 4095
    e_b, e_w = crossed_pair(raw, saturation=4095)
    assert e_b[4:7, 5:8].min() == SATURATED and e_w[6, 7] == SATURATED
    assert e_b[1, 1] < SATURATED and e_b[5, 9] < SATURATED


def test_bad_frames_and_rules_are_one_line_errors():
    with pytest.raises(ImagingError, match="even size"):
        demosaic(np.zeros((5, 8), np.uint16))
    with pytest.raises(ImagingError, match="uint8 or uint16"):
        demosaic(np.zeros((8, 8), np.float32))
    with pytest.raises(ImagingError, match="rule"):
        crossed_pair(np.zeros((8, 8), np.uint16), rule="median")
    with pytest.raises(ImagingError, match="mosaic layout"):
        MosaicCalibration(layout=(0, 0, 45, 90))


def test_smoothing_the_polarized_part_keeps_its_mean_and_cuts_white_noise_by_the_gaussians_factor():
    """A Gaussian of sigma px (2-D) scales white noise by 1/(2 sigma sqrt(pi)); E_w - E_b = 2 a0 proj."""
    rng = np.random.default_rng(3)
    sigma, a0, proj = 10.0, 0.5, 300.0
    n = rng.normal(0, sigma, (2, 400, 400))
    stokes = np.stack([np.full((400, 400), 1000.0), proj + n[0], n[1]], -1)   # chi = 0
    raw = crossed_from_stokes(stokes, a0, rule="global")
    smooth = crossed_from_stokes(stokes, a0, rule="global", polarized_sigma_px=2.0)
    diff_raw, diff_smooth = (raw[1] - raw[0])[20:-20, 20:-20], (smooth[1] - smooth[0])[20:-20, 20:-20]
    assert diff_smooth.mean() == pytest.approx(2 * a0 * proj, rel=1e-3)
    assert diff_raw.std() == pytest.approx(2 * a0 * sigma, rel=0.02)
    assert diff_smooth.std() / diff_raw.std() == pytest.approx(1 / (2 * 2.0 * np.sqrt(np.pi)), rel=0.08)
