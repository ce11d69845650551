import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from polarstripe.imaging.separation import separate_direct_global, separate_stack
from polarstripe.imaging.validation import ImagingError


@pytest.mark.parametrize("alpha", [0.25, 0.5, 0.7])
@pytest.mark.parametrize("b", [0.0, 0.1, 0.4])
def test_recovers_known_direct_and_global(alpha, b):
    rng = np.random.default_rng(2)
    direct, glob = rng.uniform(0, 1, (6, 5)), rng.uniform(0, 3, (6, 5))
    # Nayar et al.: a lit pixel sees L_d + alpha L_g + b(1-alpha) L_g; an unlit one b L_d + ...
    l_plus = direct + alpha * glob + b * (1 - alpha) * glob
    l_minus = b * direct + (1 - alpha) * glob + alpha * b * glob
    d, g = separate_direct_global(l_plus, l_minus, lit_fraction=alpha, black_level=b)
    np.testing.assert_allclose(d, direct, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(g, glob, rtol=1e-12, atol=1e-12)


def test_half_lit_black_projector_closed_form():
    d, g = separate_direct_global(np.array([5.0]), np.array([2.0]))
    assert d[0] == 3.0 and g[0] == 4.0


def test_stack_of_shifted_checkers():
    h, w, size = 8, 8, 2
    direct = np.full((h, w), 2.0)
    glob = np.full((h, w), 6.0)
    yy, xx = np.mgrid[:h, :w]
    frames = []
    for shift in range(2 * size):
        lit = (((xx + shift) // size + yy // size) % 2) == 0
        frames.append(np.where(lit, direct + 0.5 * glob, 0.5 * glob))
    d, g = separate_stack(frames)
    np.testing.assert_allclose(d, direct)
    np.testing.assert_allclose(g, glob)


def test_negative_global_falls_back():
    d, g = separate_direct_global(np.array([1.0]), np.array([0.5]), black_level=0.6)
    assert g[0] == 0.0 and d[0] == 1.0


def test_bad_parameters():
    with pytest.raises(ImagingError, match="lit_fraction: 1.0"):
        separate_direct_global(np.ones(2), np.ones(2), lit_fraction=1.0)
    with pytest.raises(ImagingError, match="black_level: nan"):
        separate_direct_global(np.ones(2), np.ones(2), black_level=float("nan"))
    with pytest.raises(ImagingError, match="l_min: shape"):
        separate_direct_global(np.ones(2), np.ones(3))


@settings(max_examples=60, deadline=None)
@given(alpha=st.floats(0.05, 0.95), b=st.floats(0.0, 0.5), direct=st.floats(0.0, 1e3),
       glob=st.floats(0.0, 1e3))
def test_separation_inverts_the_forward_model_for_any_alpha_and_b(alpha, b, direct, glob):
    l_plus = direct + alpha * glob + b * (1 - alpha) * glob
    l_minus = b * direct + (1 - alpha) * glob + alpha * b * glob
    d, g = separate_direct_global(np.array([l_plus]), np.array([l_minus]), lit_fraction=alpha, black_level=b,
                                  clip=False)
    scale = 1e-9 * (1 + direct + glob) / (1 - alpha)
    assert abs(d[0] - direct) <= scale and abs(g[0] - glob) <= scale
