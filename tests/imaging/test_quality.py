import math

import numpy as np
import pytest
from polarstripe.imaging.quality import (
    cqm,
    gqm,
    log_cqm,
    log_gqm,
    recovered_signal_noise_e,
    snr_weight,
    snr_weight_from_noise,
)
from polarstripe.imaging.validation import ImagingError
from scipy.stats import norm


def test_cqm_gqm_plain_values():
    assert cqm(2.0, 3.0, 0.0) == pytest.approx(2 / 5)
    assert cqm(2.0, 3.0, 0.8) == pytest.approx(2 / (2 + 3 * 0.2))
    assert gqm(1.0, 2.0, 3.0, 0.5) == pytest.approx((1 + 1.5) / (1 + 2 + 1.5))


def test_sanity_table_refs_section_2_4():
    # docs/physics.md §2.4: CQM (p = 0.8) from the D and B columns (A ignored)
    for d, b, want in [(2.84e-2, 0.911, 0.135), (1.60e-2, 3.93e-2, 0.67), (8.70e-4, 7.00e-4, 0.861)]:
        assert cqm(d, b, 0.8) == pytest.approx(want, abs=0.002)


def test_finite_at_optical_thickness_100():
    # S ~ e^-200, B ~ e^-100: linear values underflow to 0 in float64 products, logs do not
    lc = log_cqm(-200.0, -100.0, 0.8)
    assert math.isfinite(float(lc)) and float(lc) == pytest.approx(-200 + 100 - math.log(0.2), rel=1e-12)
    lg = log_gqm(-200.0, -150.0, -300.0, 0.0)
    assert float(lg) == pytest.approx(-(-150 + 200), rel=1e-9)
    assert 0.0 <= float(cqm(1e-300, 1e-200)) < 1e-90


def test_limits():
    assert cqm(0.0, 0.0) == 0.0 and cqm(1.0, 0.0) == 1.0 and cqm(1.0, 5.0, 1.0) == 1.0
    assert gqm(0.0, 0.0, 0.0) == 0.0 and gqm(1.0, 0.0, 1.0) == 1.0


def test_weight_sigmoid_and_extremes():
    assert snr_weight(3.0, 1.0, 2.0) == pytest.approx(1 / (1 + math.exp(-1.0)))
    assert snr_weight(-1e6, 0.0, 1e-3) == 0.0
    assert snr_weight(1e6, 0.0, 1e-3) == 1.0
    assert snr_weight(1.0, 0.0, 0.0) == 1.0 and snr_weight(0.0, 0.0, 0.0) == 0.5


def test_weight_from_noise_approximates_detection_probability():
    for snr in [1.0, 3.0, 4.0, 6.0]:
        assert snr_weight_from_noise(snr * 10.0, 10.0, k_detect=3.0) == pytest.approx(norm.cdf(snr - 3.0),
                                                                                        abs=0.01)


def test_recovered_noise_model():
    # no polarizer: Poisson on S + B plus read noise
    assert recovered_signal_noise_e(100.0, 300.0, read_noise_e=3.0) == pytest.approx(math.sqrt(409.0))
    # polarized, p = 1: S_hat = 2 E_b, Var = 4 (9 + 50)
    assert recovered_signal_noise_e(100.0, 300.0, 1.0, read_noise_e=3.0) == pytest.approx(math.sqrt(4 * 59.0))


def test_bad_parameters():
    with pytest.raises(ImagingError, match="p: degree"):
        cqm(1.0, 1.0, 1.5)
    with pytest.raises(ImagingError, match="z: "):
        snr_weight(1.0, 0.0, float("nan"))
    with pytest.raises(ImagingError, match="signal: negative"):
        cqm(-1.0, 1.0)
    with pytest.raises(ImagingError, match="backscatter: NaN"):
        cqm(np.ones(2), np.array([1.0, np.nan]))


def test_recovered_noise_grows_like_sqrt2_over_p_as_p_goes_to_zero():
    # refs §4.2/§8: sigma_S/sigma -> sqrt(2)/p for equal frame noise; read noise only (no light) isolates it
    for p in (0.05, 0.01, 1e-3):
        sigma = recovered_signal_noise_e(0.0, 0.0, p, read_noise_e=1.0)
        assert math.isfinite(float(sigma))
        assert float(sigma) == pytest.approx(math.sqrt(2 * (1 + 1 / p**2)), rel=1e-12)
    with pytest.raises(ImagingError, match="clamp it away from 0"):
        recovered_signal_noise_e(1.0, 1.0, 0.0, read_noise_e=1.0)
