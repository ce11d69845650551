"""The error measure (planning/predicted_error.py) against closed forms, and the planner on it."""

import math

import numpy as np
import pytest
from polarstripe.planning.image_model import ImageModel
from polarstripe.planning.planner import plan, plan_model
from polarstripe.planning.predicted_error import composite, expected_error, reading_error
from polarstripe.sim.scene import SceneError, load_scene


def _chart(n=4000, r=0.4):
    """T of mean 1 and relative standard deviation r (two values, 1 ± r)."""
    return np.where(np.arange(n) % 2 == 0, 1.0 + r, 1.0 - r)


@pytest.mark.parametrize("r,b,nu", [(0.4, 0.0, 0.0), (0.4, 0.5, 0.0), (0.2, 3.0, 0.0), (0.4, 0.5, 0.1),
                                    (0.3, 0.0, 0.2)])
def test_offset_and_noise_match_the_closed_form(r, b, nu):
    """A uniform veil b (relative to the mean signal) and noise of relative variance ν² on T = 1 ± r:
    e² = [r²b² + (1 + r²)ν²] / [(1 + r²)((1 + b)² + r² + ν²)] (the gain-fitted error, derived by hand)."""
    t = _chart(r=r)
    got = expected_error(t + b, np.full(t.size, nu * nu), t, np.ones(t.size, bool))
    r2 = r * r
    want = math.sqrt((r2 * b * b + (1 + r2) * nu * nu) / ((1 + r2) * ((1 + b) ** 2 + r2 + nu * nu)))
    assert got == pytest.approx(want, rel=1e-9)


def test_error_limits():
    t = _chart()
    valid = np.ones(t.size, bool)
    assert expected_error(3.0 * t, np.zeros(t.size), t, valid) == pytest.approx(0.0, abs=1e-7)   # gain only
    assert expected_error(t, np.zeros(t.size), t, np.zeros(t.size, bool)) == 1.0     # all saturated
    big = expected_error(t + 1e9, np.zeros(t.size), t, valid)          # a veil without end: the chart's
    assert big == pytest.approx(0.4 / math.sqrt(1 + 0.16), rel=1e-6)  # angle to a constant, r/√(1 + r²)


def test_eq7_maximum_of_noisy_dark_frames():
    """Two frames of equal mean and unit variance: the maximum's mean is 1/√π above it (E max of two
    standard normals), its variance 1 − 1/π."""
    n = 20000
    m, v = composite(np.full((2, n), 5.0), np.ones((2, n)))
    assert m.mean() == pytest.approx(5.0 + 1 / math.sqrt(math.pi), abs=0.01)
    assert v.mean() == pytest.approx(1 - 1 / math.pi, abs=0.02)
    one_m, one_v = composite(np.array([[1.0, 2.0]]), np.array([[0.5, 0.5]]))
    assert list(one_m) == [1.0, 2.0] and list(one_v) == [0.5, 0.5]


def test_eq6_removes_a_uniformly_polarized_veil_but_not_a_varying_one():
    """Half the pixels see no object (T = S = 0): p̂ is read there, as the compositor reads it."""
    t = np.concatenate([_chart(), np.zeros(4000)])
    s, b = 1000.0 * t, np.full(t.size, 3000.0)
    kw = dict(full_well_e=math.inf, noise=False)
    chi = np.zeros(t.size)
    uniform = reading_error("S_hat", s, b, np.full(t.size, 0.7), chi, t, **kw)[0]
    varying = reading_error("S_hat", s, b, np.linspace(0.5, 0.9, t.size), chi, t, **kw)[0]
    e_b = reading_error("E_b", s, b, np.full(t.size, 0.7), chi, t, **kw)[0]
    assert uniform == pytest.approx(0.0, abs=1e-6)        # Ŝ = S: no longer 1 by construction, but exact
    assert varying > 0.05 and e_b > 0.05                  # p ≠ p̂ somewhere; E_b keeps B(1 − p)/2
    noisy = reading_error("S_hat", s, b, np.full(t.size, 0.7), chi, t, full_well_e=math.inf)[0]
    assert noisy > 0.0                                    # eq. 6's noise is charged


def test_saturated_pixels_are_left_out():
    t = _chart()
    s, b = 1000.0 * t, np.where(np.arange(t.size) < t.size // 2, 1e6, 0.0)
    err, sat = reading_error("E", s, b, np.zeros(t.size), np.zeros(t.size), t, full_well_e=5e4, noise=False)
    assert sat == pytest.approx(0.5) and err == pytest.approx(0.0, abs=1e-7)


def test_planner_with_the_error_measure_on_a_small_scene():
    scene = load_scene(None)
    model = ImageModel(scene, width=16, n_stripes=4)
    assert model.shape == (12, 16)
    plans = plan(model, np.array([0.05, 0.2, 0.4]))
    assert set(plans) == {"flood", "flood_polarized", "stripes", "stripes_polarized"}
    for mp in plans.values():
        assert np.all((mp.curve.objective >= 0) & (mp.curve.objective <= 1))
    assert set(plans["stripes_polarized"].readings) == {"E_b", "S_hat"}
    with pytest.raises(SceneError, match="measure"):
        plan_model(scene, measure="cqm")
