import numpy as np
import pytest
from polarstripe.imaging.metrics import michelson_contrast, signal_error
from polarstripe.imaging.validation import ImagingError


def test_michelson_on_bars():
    img = np.zeros((10, 10))
    img[:, :5] = 9.0
    img[:, 5:] = 1.0
    assert michelson_contrast(img, (0, 10, 0, 5), (0, 10, 5, 10)) == pytest.approx(0.8)
    # adding a uniform veil (backscatter) lowers it: (9-1)/(9+1+2b)
    assert michelson_contrast(img + 5.0, (0, 10, 0, 5), (0, 10, 5, 10)) == pytest.approx(8 / 20)


def test_michelson_ignores_masked_pixels():
    img = np.ma.MaskedArray(np.full((4, 4), 3.0), np.zeros((4, 4), bool))
    img[0, 0] = 4095.0
    img[0, 0] = np.ma.masked
    bright = np.zeros((4, 4), bool)
    bright[:2] = True
    img[2:] = 1.0
    assert michelson_contrast(img, bright, ~bright) == pytest.approx(0.5)


def test_signal_error():
    truth = np.array([[1.0, 2.0], [3.0, 4.0]])
    assert signal_error(truth, truth) == 0.0
    assert signal_error(2 * truth, truth) == pytest.approx(1.0)
    assert signal_error(0.5 * truth, truth, fit_gain=True) == pytest.approx(0.0, abs=1e-15)


def test_roi_outside_and_shape_mismatch():
    with pytest.raises(ImagingError, match="bright: rectangle"):
        michelson_contrast(np.ones((4, 4)), (0, 5, 0, 2), (0, 2, 0, 2))
    with pytest.raises(ImagingError, match="estimate: shape"):
        signal_error(np.ones((2, 2)), np.ones((3, 2)))
    with pytest.raises(ImagingError, match="image: dtype"):
        michelson_contrast(np.array([["a"]]), (0, 1, 0, 1), (0, 1, 0, 1))


def test_a_masked_pixel_is_lost_not_skipped():
    """Masked (saturated) pixels: ``lost`` counts their truth as error, by hand ‖T_masked‖/‖T‖ when the rest
    is exact; ``skip`` leaves them out (error 0); every pixel masked is error 1."""
    truth = np.array([[1.0, 2.0], [3.0, 4.0]])
    est = np.ma.masked_array(truth.copy(), mask=[[False, False], [False, True]])
    assert signal_error(est, truth, fit_gain=True) == pytest.approx(4.0 / np.sqrt(30.0))
    assert signal_error(est, truth, masked="skip") == 0.0
    every = np.ma.masked_array(truth, mask=np.ones((2, 2), bool))
    assert signal_error(every, truth) == 1.0
    with pytest.raises(ImagingError, match="masked"):
        signal_error(est, truth, masked="ignore")
