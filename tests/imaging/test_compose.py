"""compose() and score() on small hand-made reductions whose answers are known in closed form: eq. 7 is the
max, eqs. 4-6 with S = 0 in an object-free column give p and S back exactly, complementary checkers give
L+ = D + G/2 and L- = G/2."""

import numpy as np
import pytest
from polarstripe.imaging.compose import compose, score
from polarstripe.imaging.composite import CompositeImage
from polarstripe.imaging.validation import ImagingError


def _view(mx, mn=None, saturation=None):
    mx = np.asarray(mx, np.uint16)
    mn = mx if mn is None else np.asarray(mn, np.uint16)
    mask = (lambda a: a >= saturation) if saturation is not None else (lambda a: np.zeros(a.shape, bool))
    return CompositeImage(np.ma.MaskedArray(mx, mask(mx)), np.ma.MaskedArray(mn, mask(mn)), 1)


def test_flood_and_stripes_are_the_maximum_above_the_dark_offset():
    mx = [[110, 250], [74, 4095]]
    for method in ("flood", "stripes"):
        made = compose(method, {None: _view(mx, saturation=4095)}, dark_offset=64.0)
        assert made.image.dtype == np.float64
        np.testing.assert_array_equal(made.image.data[np.array([[1, 1], [1, 0]], bool)], [46.0, 186.0, 10.0])
        assert made.image.mask.tolist() == [[False, False], [False, True]]
        assert made.saturated_pixels == 1 and made.p is None and made.layers == {} and made.note == ""


def _polarized_views(s, b, p, dark, order=(30.0, 120.0)):
    """E_b = S/2 + B(1-p)/2 at 30 deg, E_w = S/2 + B(1+p)/2 at 120 deg (eqs. 4-5), in DN above ``dark``."""
    e_b = s / 2 + b * (1 - p) / 2 + dark
    e_w = s / 2 + b * (1 + p) / 2 + dark
    views = {30.0: _view(np.round(e_b)), 120.0: _view(np.round(e_w))}
    return {a: views[a] for a in order}


def test_polarized_recovers_p_and_s_by_eq6_with_either_angle_first():
    s = np.zeros((4, 6))
    s[:, 2:] = [[200.0, 400.0, 600.0, 800.0]]  # columns 0-1 object-free
    b, p, dark = 1000.0, 0.6, 64.0
    free = (0, 4, 0, 2)
    for order in ((30.0, 120.0), (120.0, 30.0)):
        made = compose("polarized_stripes", _polarized_views(s, b, p, dark, order), dark_offset=dark,
                       saturation=4095, object_free=free)
        # over the free columns E_w - E_b = pB = 600 and E_w + E_b = B = 1000: p = 0.6 exactly
        assert made.p == pytest.approx(0.6, abs=1e-12)
        # eq. 6: E_b (1 + 1/p) + E_w (1 - 1/p) = S (the DN are whole numbers here, so exact)
        np.testing.assert_allclose(made.image, s, atol=1e-9)
        np.testing.assert_allclose(made.layers["e_b"], s / 2 + 200.0)  # the darker one, whichever came first
        np.testing.assert_allclose(made.layers["e_w"], s / 2 + 800.0)


def test_without_object_free_pixels_the_composite_is_e_b_and_the_note_says_why():
    s, b, dark = np.zeros((2, 2)), 1000.0, 64.0
    views = _polarized_views(s, b, 0.6, dark)
    views = {a: _view(np.full((2, 2), 4095)) if a == 120.0 else v for a, v in views.items()}  # E_w clipped
    made = compose("polarized_flood", views, dark_offset=dark, saturation=4095)
    assert made.p is None and "p not estimated" in made.note and "E_b without eq. 6" in made.note
    np.testing.assert_allclose(made.image, 200.0)  # E_b = B(1 - p)/2 = 200 above the offset


def test_hf_separation_with_a_black_level_solves_nayars_equations():
    d, g, a, bl = 300.0, 500.0, 0.5, 0.1
    # L+ = D + a G + b (1 - a) G, L- = b D + (1 - a) G + a b G (Nayar et al. 2006, §3)
    l_max = d + a * g + bl * (1 - a) * g
    l_min = bl * d + (1 - a) * g + a * bl * g
    made = compose("hf_separation", {None: _view([[l_max]], [[l_min]])}, lit_fraction=a, black_level=bl)
    assert made.image[0, 0] == pytest.approx(d, abs=1e-9)
    assert made.layers["global"][0, 0] == pytest.approx(g, abs=1e-9)


@pytest.mark.parametrize(("method", "views", "match"), [
    ("scatter", {None: None}, "method"),
    ("flood", {}, "no frames"),
    ("polarized_flood", {0.0: None}, r"two analyzer angles, got \[0.0\]"),
])
def test_bad_input_is_an_imaging_error(method, views, match):
    v = {k: _view([[100]]) for k in views}
    with pytest.raises(ImagingError, match=match):
        compose(method, v)


def test_score_gives_michelson_contrast_and_the_gain_fitted_error():
    img = np.array([[300.0, 100.0], [40.0, 60.0]])
    bright, dark = np.array([[1, 0], [0, 0]], bool), np.array([[0, 1], [0, 0]], bool)
    truth = np.array([[3.0, 1.0], [0.5, 0.5]])
    got = score(img, bright=bright, dark=dark, truth=truth)
    assert got["contrast"] == pytest.approx((300 - 100) / (300 + 100))
    e, t = img.ravel(), truth.ravel()
    g = (e @ t) / (e @ e)
    assert got["error_vs_truth"] == pytest.approx(np.linalg.norm(g * e - t) / np.linalg.norm(t), rel=1e-12)
    plain = score(img, truth=truth, region=(0, 1, 0, 2), fit_gain=False)  # top row only, no gain
    assert plain["contrast"] is None
    assert plain["error_vs_truth"] == pytest.approx(np.hypot(297, 99) / np.hypot(3, 1))


def test_score_with_every_bar_saturated_has_no_contrast_but_an_error():
    """The bars (top row) saturated: no contrast, with the reason; the error still counts them as lost:
    the bottom row exact, ‖T_top‖/‖T‖ = √(2/4)."""
    img = np.ma.MaskedArray(np.ones((2, 2)), [[True, True], [False, False]])
    got = score(img, bright=(0, 1, 0, 1), dark=(0, 1, 1, 2), truth=np.ones((2, 2)))
    assert got["contrast"] is None and got["error_vs_truth"] == pytest.approx(np.sqrt(0.5))
    assert got["metrics_error"].startswith("contrast: ") and "masked" in got["metrics_error"]
    assert score(img) == {"contrast": None, "error_vs_truth": None}
