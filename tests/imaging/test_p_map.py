"""Eq. 6's p per region from the frames (imaging/p_map.py) on synthetic pairs whose p is known in closed form:
a p constant per tile comes back at each tile's centre; a p the same everywhere under noise gives a map no
noisier than the tiles' spread beyond their noise allows; eq. 6 with a map has, pixel by pixel, the noise of
docs/physics.md §4.2's formula at that pixel's p."""

import numpy as np
import pytest
from polarstripe.imaging.compose import compose
from polarstripe.imaging.composite import CompositeImage
from polarstripe.imaging.p_map import PEstimate, global_p, regional_p_map
from polarstripe.imaging.polarization import recover_signal
from polarstripe.imaging.validation import ImagingError

ROWS, COLS, SIDE = 3, 4, 21  # tiles of 21 px: cv2's bilinear resize puts a tile's value on its centre pixel
H, W = ROWS * SIDE, COLS * SIDE


def _pair(p, b=2000.0, s=0.0):
    """E_b = S/2 + B(1 - p)/2, E_w = S/2 + B(1 + p)/2 (eqs. 4-5)."""
    return s / 2 + b * (1 - p) / 2, s / 2 + b * (1 + p) / 2


def test_a_p_constant_per_tile_comes_back_at_each_tile_centre():
    tiles = np.array([[0.30, 0.45, 0.60, 0.75], [0.35, 0.50, 0.65, 0.80], [0.40, 0.55, 0.70, 0.85]])
    p = np.kron(tiles, np.ones((SIDE, SIDE)))
    est = regional_p_map(*_pair(p), tiles=(ROWS, COLS))
    centres = est.eq6[SIDE // 2::SIDE, SIDE // 2::SIDE]
    np.testing.assert_allclose(centres, tiles, atol=1e-9)
    # between two centres (10 and 31) the map is the straight line between them, flat beyond the outer ones
    row = est.eq6[SIDE // 2]
    assert row[20] == pytest.approx(tiles[0, 0] + (tiles[0, 1] - tiles[0, 0]) * 10 / 21)
    np.testing.assert_allclose(row[:SIDE // 2], tiles[0, 0])
    # the medium's p is the region's upper p̂: about the mean of the highest fifth of the pixels' p
    top = np.sort(p.ravel())[-p.size // 5:].mean()
    assert est.source == "frames" and est.p == pytest.approx(top, abs=0.01)


def test_noise_alone_is_shrunk_to_the_regions_p():
    rng = np.random.default_rng(4)
    p, b, sigma = 0.5, 400.0, 20.0
    e_b, e_w = (x + rng.normal(0.0, sigma, (H, W)) for x in _pair(np.full((H, W), p), b))
    est = regional_p_map(e_b, e_w, tiles=(ROWS, COLS))
    raw = [regional_p_map(e_b, e_w, (r * SIDE, (r + 1) * SIDE, c * SIDE, (c + 1) * SIDE), tiles=(1, 1)).eq6
           for r in range(ROWS) for c in range(COLS)]
    raw_spread = np.std([float(np.mean(x)) for x in raw])
    assert raw_spread > 0.005  # the tiles' own p̂ scatter from the noise ...
    assert np.ptp(est.eq6) < raw_spread / 3  # ... and the map does not follow it (no spread beyond the noise)


def test_eq6_with_a_map_has_each_pixels_noise_by_the_formula():
    # p = 0.25 on the left half, 0.75 on the right; E_b and E_w with independent noise σ:
    # σ_Ŝ = σ √(2 (1 + 1/p²)) = 5.83 σ and 2.40 σ (docs/physics.md §4.2)
    rng = np.random.default_rng(7)
    p = np.where(np.arange(200)[None, :] < 100, 0.25, 0.75) * np.ones((400, 1))
    s, b, sigma = 300.0, 1000.0, 2.0
    e_b, e_w = (x + rng.normal(0.0, sigma, p.shape) for x in _pair(p, b, s))
    got = recover_signal(e_b, e_w, p)
    for half, pp in ((slice(0, 100), 0.25), (slice(100, 200), 0.75)):
        expect = sigma * np.sqrt(2.0 * (1.0 + 1.0 / pp ** 2))
        assert np.std(got[:, half]) == pytest.approx(expect, rel=0.03)
        assert np.mean(got[:, half]) == pytest.approx(s, abs=4 * expect / np.sqrt(got[:, half].size))


def test_global_p_keeps_the_rule_for_eq6_and_upper_for_the_medium():
    s = np.zeros((40, 40))
    s[:, 20:] = 600.0  # object light on the right half lowers the measured DOP there
    e_b, e_w = _pair(0.6, 1000.0, s)
    med = global_p(e_b, e_w, rule="median")
    up = global_p(e_b, e_w, rule="upper")
    assert up.eq6 == pytest.approx(0.6, abs=1e-9) and med.p == up.p == pytest.approx(0.6, abs=1e-9)
    assert med.eq6 < 0.6 and med.source == "median"
    with pytest.raises(ImagingError, match="rule"):
        global_p(e_b, e_w, rule="map")


def test_compose_divides_by_the_models_map_where_given():
    p = np.linspace(0.3, 0.8, 30)[None, :] * np.ones((20, 1))
    s = np.zeros((20, 30))
    s[5:15, 10:] = 400.0
    dark = 64.0
    e_b, e_w = _pair(p, 1200.0, s)

    def view(x):
        x = np.asarray(x + dark)
        return CompositeImage(np.ma.MaskedArray(x, np.zeros(x.shape, bool)),
                              np.ma.MaskedArray(x, np.zeros(x.shape, bool)), 1)

    def model(a, b):  # what planning/medium_p.py's map would give: here the exact p
        return PEstimate(p, 0.55, 0.001, "model")

    made = compose("polarized_flood", {0.0: view(e_b), 90.0: view(e_w)}, dark_offset=dark, p_rule="map",
                   p_model=model)
    np.testing.assert_allclose(made.image, s, atol=1e-9)  # the backscatter removed where p varies
    assert made.p_backscatter == 0.55 and made.p == pytest.approx(np.median(p))
    one = compose("polarized_flood", {0.0: view(e_b), 90.0: view(e_w)}, dark_offset=dark, p_rule="median")
    assert np.min(one.image) < -100.0  # one p̂ over-subtracts where p is above it
    with pytest.raises(ImagingError, match="p_rule"):
        compose("polarized_flood", {0.0: view(e_b), 90.0: view(e_w)}, p_rule="mean")
