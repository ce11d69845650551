"""The micro-polarizer mosaic (sim/mosaic.py) against Malus's law written out per pixel, the extinction
ratio and the crosstalk's closed forms."""

import numpy as np
import pytest
from polarstripe.sim.mosaic import (
    SONY_LAYOUT,
    MicroPolarizerArray,
    check_layout,
    effective_extinction_ratio,
    mosaic_radiance,
)


def _field(shape, s0, dop, chi_deg):
    chi = np.radians(chi_deg)
    return (np.full(shape, s0), np.full(shape, s0 * dop * np.cos(2 * chi)),
            np.full(shape, s0 * dop * np.sin(2 * chi)))


def _malus(s0, dop, chi_deg, phi_deg, er):
    """A real polarizer at phi on light of DOP dop at chi:
    (1 + 1/er)/2 S0 + (1 - 1/er)/2 S0 dop cos 2(phi - chi)."""
    return 0.5 * (1 + 1 / er) * s0 + 0.5 * (1 - 1 / er) * s0 * dop * np.cos(2 * np.radians(phi_deg - chi_deg))


def test_the_sony_layout_tiles_90_45_135_0_from_the_top_left():
    angles = MicroPolarizerArray().angles_deg((4, 6))
    assert angles[0, :4].tolist() == [90, 45, 90, 45] and angles[1, :4].tolist() == [135, 0, 135, 0]
    assert angles[3, 5] == 0 and SONY_LAYOUT == (90.0, 45.0, 135.0, 0.0)


@pytest.mark.parametrize("chi", [0.0, 30.0, 112.0])
def test_a_uniform_polarized_field_gives_malus_at_each_pixels_angle(chi):
    sensor = MicroPolarizerArray(extinction_ratio=300.0)
    raw = mosaic_radiance(*_field((6, 8), 2.0, 0.7, chi), sensor)
    for (r, c), phi in zip([(0, 0), (0, 1), (1, 0), (1, 1)], (90, 45, 135, 0), strict=True):
        assert raw[r, c] == pytest.approx(_malus(2.0, 0.7, chi, phi, 300.0), rel=1e-12)
        assert raw[r + 4, c + 2] == pytest.approx(raw[r, c], rel=1e-12)


def test_the_extinction_ratio_is_the_ratio_of_the_parallel_and_crossed_pixels():
    raw = mosaic_radiance(*_field((4, 4), 1.0, 1.0, 0.0), MicroPolarizerArray(extinction_ratio=300.0))
    assert raw[1, 1] / raw[0, 0] == pytest.approx(300.0, rel=1e-9)     # 0 deg over 90 deg
    assert raw[0, 1] == pytest.approx(0.5 * (1 + 1 / 300), rel=1e-12)   # 45 deg: the unpolarized level


def test_crosstalk_keeps_the_light_and_lowers_the_extinction_as_its_closed_form_says():
    ce, cd = 0.004, 0.001
    sensor = MicroPolarizerArray(extinction_ratio=300.0, crosstalk_edge=ce, crosstalk_diagonal=cd)
    raw = mosaic_radiance(*_field((8, 8), 1.0, 1.0, 0.0), sensor)
    clean = mosaic_radiance(*_field((8, 8), 1.0, 1.0, 0.0), MicroPolarizerArray(extinction_ratio=300.0))
    assert raw.sum() == pytest.approx(clean.sum(), rel=1e-12)          # energy kept
    t = {phi: _malus(1.0, 1.0, 0.0, phi, 300.0) for phi in (0, 45, 90, 135)}
    # the 0 deg pixel: its own light, 2 edge neighbours at 45 and 2 at 135, 4 diagonal ones at 90
    by_hand = (1 - 4 * ce - 4 * cd) * t[0] + ce * (2 * t[45] + 2 * t[135]) + cd * 4 * t[90]
    assert raw[3, 3] == pytest.approx(by_hand, rel=1e-12)
    assert raw[3, 3] / raw[2, 2] == pytest.approx(effective_extinction_ratio(300.0, ce, cd), rel=1e-9)
    d = (299 / 301) * (1 - 4 * ce - 8 * cd)
    assert effective_extinction_ratio(300.0, ce, cd) == pytest.approx((1 + d) / (1 - d))
    assert effective_extinction_ratio(300.0, ce, cd) < 300.0 / 2


def test_the_extinction_map_is_fixed_per_sensor_and_spread_as_asked():
    sensor = MicroPolarizerArray(extinction_ratio=300.0, extinction_spread=0.2, seed=3)
    a, b = sensor.extinction_map((200, 200)), sensor.extinction_map((200, 200))
    assert np.array_equal(a, b)
    assert np.std(np.log(a)) == pytest.approx(0.2, rel=0.03)
    assert np.exp(np.mean(np.log(a))) == pytest.approx(300.0, rel=0.01)


@pytest.mark.parametrize("bad", [(0, 45, 90, 90), (0, 45, 90), ("a", 1, 2, 3)])
def test_a_layout_that_is_not_the_four_angles_is_refused(bad):
    with pytest.raises(ValueError, match="mosaic layout"):
        check_layout(bad)


def test_bad_sensor_numbers_are_refused_in_one_line():
    with pytest.raises(ValueError, match="extinction_ratio"):
        MicroPolarizerArray(extinction_ratio=1.0)
    with pytest.raises(ValueError, match="crosstalk"):
        MicroPolarizerArray(crosstalk_edge=0.2, crosstalk_diagonal=0.1)
