import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from polarstripe.imaging.polarization import (
    aolp,
    dolp,
    estimate_p,
    least_backscatter_angle,
    p_bootstrap_std,
    recover_backscatter,
    recover_signal,
    recovered_signal_variance,
    stokes,
)
from polarstripe.imaging.validation import ImagingError


def _frames_from_model(s, b, p):
    # eqs. 4-5 written out here, independent of the code under test
    return s / 2 + b * (1 - p) / 2, s / 2 + b * (1 + p) / 2


@pytest.mark.parametrize("p", [0.05, 0.3, 0.8, 1.0])
def test_eq6_recovers_signal_exactly(p):
    rng = np.random.default_rng(1)
    s, b = rng.uniform(0, 2, (7, 9)), rng.uniform(0, 50, (7, 9))
    e_b, e_w = _frames_from_model(s, b, p)
    np.testing.assert_allclose(recover_signal(e_b, e_w, p), s, rtol=0, atol=1e-12 * 50 / p)
    np.testing.assert_allclose(recover_backscatter(e_b, e_w, p), b, rtol=1e-12)


def test_p_to_one_gives_twice_the_crossed_frame():
    e_b, e_w = np.array([[1.0, 3.0]]), np.array([[5.0, 7.0]])
    np.testing.assert_allclose(recover_signal(e_b, e_w, 1.0), 2 * e_b)


def test_partially_polarized_object():
    # object light with DOP p_obj along the same axis: E_b = S(1-p_obj)/2 + B(1-p)/2, E_w = S(1+p_obj)/2 + ...
    s, b, p, p_obj = np.array([0.3, 1.0]), np.array([4.0, 9.0]), 0.8, 0.2
    e_b = s * (1 - p_obj) / 2 + b * (1 - p) / 2
    e_w = s * (1 + p_obj) / 2 + b * (1 + p) / 2
    np.testing.assert_allclose(recover_signal(e_b, e_w, p, p_object=p_obj), s, rtol=1e-12)
    np.testing.assert_allclose(recover_backscatter(e_b, e_w, p, p_object=p_obj), b, rtol=1e-12)
    # ignoring the object's polarization gives a wrong answer
    assert not np.allclose(recover_signal(e_b, e_w, p), s, rtol=1e-3)


def test_noise_gain_matches_table():
    # docs/physics.md §4.2 table: sigma_S/sigma for equal frame noise
    for p, gain in [(0.95, 2.05), (0.8, 2.26), (0.5, 3.16), (0.2, 7.2), (0.1, 14.2), (0.05, 28.3)]:
        assert np.sqrt(recovered_signal_variance(1.0, 1.0, p)) == pytest.approx(gain, rel=6e-3)


def test_p_to_zero_is_rejected_not_inf():
    with pytest.raises(ImagingError, match="p: 0.0"):
        recover_signal(np.ones((2, 2)), np.ones((2, 2)), 0.0)


def test_stokes_recovers_known_dolp_and_aolp():
    s0, dop, angle = 10.0, 0.37, np.deg2rad(25.0)
    angles = [0.0, 30.0, 60.0, 90.0, 120.0, 150.0]
    frames = []
    for a in angles:
        # Malus's law for the polarized part plus half the unpolarized part
        th = np.deg2rad(a)
        frames.append(np.full((3, 4), s0 * dop * np.cos(th - angle) ** 2 + s0 * (1 - dop) / 2))
    S0, S1, S2 = stokes(frames, angles)
    np.testing.assert_allclose(S0, s0, rtol=1e-12)
    np.testing.assert_allclose(dolp(S0, S1, S2), dop, rtol=1e-12)
    np.testing.assert_allclose(aolp(S1, S2), angle, rtol=1e-12)


def test_stokes_three_angles_and_real_polarizer():
    k1, k2 = 0.9, 0.05
    s0, s1, s2 = 4.0, 1.0, -2.0
    angles = [10.0, 70.0, 130.0]
    frames = [np.full((2, 2), 0.5 * (k1 + k2) * s0 + 0.5 * (k1 - k2) * (s1 * np.cos(2 * np.deg2rad(a))
                                                                         + s2 * np.sin(2 * np.deg2rad(a))))
              for a in angles]
    S0, S1, S2 = stokes(frames, angles, transmittances=(k1, k2))
    np.testing.assert_allclose([S0[0, 0], S1[0, 0], S2[0, 0]], [s0, s1, s2], rtol=1e-12)


def test_stokes_needs_three_distinct_angles():
    with pytest.raises(ImagingError, match="three distinct angles"):
        stokes([np.ones((2, 2))] * 3, [0.0, 90.0, 180.0])


def test_estimate_p_under_noise_offset_and_saturation():
    rng = np.random.default_rng(7)
    p, offset = 0.8, 64.0
    b = rng.uniform(800, 1600, (60, 80))  # object-free: S = 0, backscatter varies over the region
    e_b = b * (1 - p) / 2
    e_w = b * (1 + p) / 2
    # shot noise (electrons = DN) + read noise + offset, then saturate a corner of E_w at 12 bit
    e_b = rng.poisson(e_b) + rng.normal(0, 5, e_b.shape) + offset
    e_w = rng.poisson(e_w) + rng.normal(0, 5, e_w.shape) + offset
    e_w[:10, :10] = 4095.0
    e_b[:10, :10] = 3000.0  # a hot region that would bias the estimate if not masked
    est = estimate_p(e_b, e_w, dark_offset=offset, saturation=4095)
    assert est == pytest.approx(p, abs=0.01)  # stated tolerance: 0.01 at these SNRs
    # forgetting the offset biases p low (refs §4.2): the test can fail if offset handling is wrong
    assert estimate_p(e_b, e_w, saturation=4095) < p - 0.03


def test_estimate_p_roi_and_clamp():
    e_b = np.full((10, 10), 5.0)
    e_w = np.full((10, 10), 5.0)  # unpolarized: p -> 0, clamped to p_min
    assert estimate_p(e_b, e_w, (0, 5, 0, 5), p_min=0.1) == 0.1
    e_b2 = np.zeros((10, 10))
    assert estimate_p(e_b2, e_w, (0, 5, 0, 5)) == 1.0  # fully polarized


def test_estimate_p_roi_outside_image():
    with pytest.raises(ImagingError, match="outside the 10x10 image"):
        estimate_p(np.ones((10, 10)), np.ones((10, 10)), (0, 11, 0, 5))


def test_least_backscatter_angle():
    true_min = 112.0  # analyzer angle that crosses the backscatter polarization
    angles = [0.0, 45.0, 90.0, 135.0]
    frames = [np.full((8, 8), 100.0 * (0.1 + 0.9 * np.sin(np.deg2rad(a - true_min)) ** 2)) + 20.0
              for a in angles]
    frames[0][0, 0] = 4095.0
    got = least_backscatter_angle(angles, frames, (0, 8, 0, 8), dark_offset=20.0, saturation=4095)
    assert got == pytest.approx(true_min, abs=1e-9)


def test_least_backscatter_angle_unpolarized_is_an_error():
    with pytest.raises(ImagingError, match="unpolarized"):
        least_backscatter_angle([0, 60, 120], [np.ones((3, 3))] * 3)


def test_mismatched_shapes_and_dtypes():
    with pytest.raises(ImagingError, match="e_w: shape"):
        recover_signal(np.ones((2, 2)), np.ones((2, 3)), 0.8)
    with pytest.raises(ImagingError, match=r"frames\[1\]: dtype"):
        stokes([np.ones((2, 2)), np.ones((2, 2), np.float32), np.ones((2, 2))], [0, 60, 120])
    with pytest.raises(ImagingError, match="empty stack"):
        stokes([], [])
    with pytest.raises(ImagingError, match="p: nan is not finite"):
        recover_signal(np.ones(2), np.ones(2), float("nan"))


@settings(max_examples=60, deadline=None)
@given(p=st.floats(0.05, 1.0), s=st.floats(0.0, 1e3), b=st.floats(0.0, 1e4))
def test_eq6_round_trip_any_p(p, s, b):
    e_b, e_w = _frames_from_model(np.array([s]), np.array([b]), p)
    assert abs(recover_signal(e_b, e_w, p)[0] - s) <= 1e-9 * (1 + s + b / p)


def test_estimate_p_unclamped_refuses_instead_and_needs_its_pixels():
    e = np.full((10, 10), 5.0)
    with pytest.raises(ImagingError, match=r"outside \(0, 1\]"):
        estimate_p(e, e, p_min=None)  # unpolarized: p = 0, not published as a number
    with pytest.raises(ImagingError, match="only 25 unsaturated pixels .*need 30"):
        estimate_p(e, 2 * e, (0, 5, 0, 5), min_pixels=30)
    assert estimate_p(e, 3 * e, p_min=None) == pytest.approx(0.5, rel=1e-12)


def test_p_bootstrap_std_matches_the_spread_of_independent_frames():
    """The bootstrap spread over one frame pair against the spread of p̂ over 300 independent noisy pairs
    of the same region (Monte Carlo): within 30 %."""
    rng = np.random.default_rng(3)
    p, b = 0.6, rng.uniform(200, 400, (30, 30))

    def pair():
        return (rng.poisson(b * (1 - p) / 2).astype(float), rng.poisson(b * (1 + p) / 2).astype(float))

    spread = np.std([estimate_p(*pair(), p_min=None) for _ in range(300)])
    boot = p_bootstrap_std(*pair(), n_boot=400)
    assert spread > 0 and boot == pytest.approx(spread, rel=0.3)


def test_upper_rule_reads_the_backscatter_dop_through_object_light():
    """A region with unpolarized object light S varying across it (as the simulated tank's wall, lit by
    forward-scattered light): the measured DOP is p·B/(B + S). The ratio of medians reads it low; the
    ``upper`` rule reads the blocks with the least object light. Independent number: p itself."""
    p, h, w = 0.55, 60, 80
    b = np.full((h, w), 1000.0)
    s = np.tile(np.linspace(0.0, 1500.0, w), (h, 1))   # no object light at the left edge, much at the right
    e_b, e_w = b * (1 - p) / 2 + s / 2, b * (1 + p) / 2 + s / 2
    median = estimate_p(e_b, e_w)
    upper = estimate_p(e_b, e_w, rule="upper")
    assert median < p * 1000 / (1000 + 0.45 * 1500)   # p·B/(B + S) about the median S
    assert p * 1000 / (1000 + 0.21 * 1500) < upper <= p  # the top fifth of blocks: S ≤ 0.21·1500
    assert estimate_p(b * (1 - p) / 2, b * (1 + p) / 2, rule="upper") == pytest.approx(p, rel=1e-12)
    with pytest.raises(ImagingError, match="rule"):
        estimate_p(e_b, e_w, rule="mean")


def test_upper_rule_noise_bias_and_its_spread():
    """Without object light, under shot noise: the ``upper`` rule sits about one block standard deviation
    above p (the price of reading the highest blocks), and its parametric bootstrap matches the spread over
    300 independent pairs within 30 %."""
    rng = np.random.default_rng(5)
    p, b = 0.6, rng.uniform(2000, 4000, (40, 40))

    def pair():
        return (rng.poisson(b * (1 - p) / 2).astype(float), rng.poisson(b * (1 + p) / 2).astype(float))

    runs = [estimate_p(*pair(), p_min=None, rule="upper") for _ in range(300)]
    block_sd = np.sqrt(1 - p * p) / np.sqrt(3000.0 * 25)  # σ of a 25-pixel block's DOP at 3000 e- a pixel
    assert 0 < np.mean(runs) - p < 2.5 * block_sd
    boot = p_bootstrap_std(*pair(), n_boot=400, rule="upper")
    assert boot == pytest.approx(np.std(runs), rel=0.3)
