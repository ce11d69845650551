"""The planner's objectives against closed forms and hand-computed numbers (docs/planning.md)."""

import math

import numpy as np
import pytest
from polarstripe.imaging.quality import gqm, margin
from polarstripe.planning.objectives import (
    IDEAL_SENSOR,
    Competitors,
    Samples,
    SensorNoise,
    noise_gain,
    objective,
)
from scipy.stats import norm

D, A, B, P = 0.2, 0.1, 0.5, 0.8


def _samples(comp_d, comp_a, comp_b, comp_p, labels=("neighbour", "sheet")):
    c = Competitors(*(np.atleast_2d(np.asarray(x, float)) for x in (comp_d, comp_a, comp_b, comp_p)),
                    labels=labels)
    return Samples(np.array([D]), np.array([A]), np.array([B]), np.array([P]), competitors=c)


@pytest.mark.parametrize("reading,p", [("E", 0.0), ("E_b", P)])
def test_margin_reduces_to_eq9_when_competitors_carry_no_backscatter(reading, p):
    # Fig. 8c: O' receives only A (the same A as O); the other sheet reaches O with less A and no B
    s = _samples([0.0, 0.0], [A, 0.3 * A], [0.0, 0.0], [0.0, 0.0])
    q = objective(s, IDEAL_SENSOR, modality="stripes", reading=reading).quality[0]
    assert q == pytest.approx((D + B * (1 - p)) / (D + A + B * (1 - p)), rel=1e-12)
    assert q == pytest.approx(gqm(D, A, B, p), rel=1e-12)


def test_margin_with_backscattering_competitors_by_hand():
    # O' sees A plus some of the sheet's backscatter; another sheet crosses O's ray near the camera
    s = _samples([0.0, 0.0], [0.08, 0.001], [0.05, 0.2], [0.6, 0.9])
    e_own = D + A + B
    plain = objective(s, IDEAL_SENSOR, modality="stripes", reading="E")
    assert plain.quality[0] == pytest.approx((e_own - 0.201) / e_own)
    assert plain.limited_by == ("sheet",)
    e_own_b = D + A + B * 0.2
    pol = objective(s, IDEAL_SENSOR, modality="stripes", reading="E_b")
    # through the analyzer: O' 0.08 + 0.05*0.4 = 0.1, the sheet 0.001 + 0.2*0.1 = 0.021
    assert pol.quality[0] == pytest.approx((e_own_b - 0.1) / e_own_b)
    assert pol.limited_by == ("neighbour",)
    brighter = _samples([0.0, 0.0], [0.0, 0.0], [0.0, 5.0], [0.0, 0.0])
    assert objective(brighter, IDEAL_SENSOR, modality="stripes", reading="E").value[0] == 0.0


def test_margin_survives_underflow():
    # components near 1e-300: the ratio is still exact (log space)
    k = 1e-300
    s = Samples(np.array([D * k]), np.array([A * k]), np.array([B * k]), np.array([P]),
                competitors=Competitors(np.zeros((1, 1)), np.array([[A * k]]), np.zeros((1, 1)),
                                        np.zeros((1, 1)), ("neighbour",)))
    q = objective(s, IDEAL_SENSOR, modality="stripes", reading="E").quality[0]
    assert q == pytest.approx((D + B) / (D + A + B), rel=1e-9)
    assert margin(3.0, 1.0) == pytest.approx(2.0 / 3.0) and margin(1.0, 2.0) == 0.0


def _phi_weight(signal_e, var_e, k=3.0):
    sigma = math.sqrt(var_e)
    return norm.cdf(signal_e / sigma - k)


def test_flood_readings_weights_from_their_own_noise():
    """E: S on S + B; E_b: S/2 on S/2 + B(1 - p)/2; Ŝ: S on the eq. 6 combination. 1 radiance unit = 1000
    electrons, read noise 10 e-, dark 4 e-."""
    s = Samples(np.array([0.3]), np.array([0.1]), np.array([2.0]), np.array([P]))
    noise = SensorNoise(1000.0, read_noise_e=10.0, dark_e=4.0)
    floor = 100.0 + 4.0
    S, Bn = 400.0, 2000.0
    e = objective(s, noise, modality="flood", reading="E")
    assert e.weight[0] == pytest.approx(_phi_weight(S, floor + S + Bn), abs=0.01)
    assert e.quality[0] == pytest.approx(S / (S + Bn))
    eb = objective(s, noise, modality="flood", reading="E_b")
    assert eb.weight[0] == pytest.approx(_phi_weight(S / 2, floor + S / 2 + Bn * (1 - P) / 2), abs=0.01)
    assert eb.quality[0] == pytest.approx(S / (S + Bn * (1 - P)))
    sh = objective(s, noise, modality="flood", reading="S_hat")
    var_b, var_w = floor + S / 2 + Bn * (1 - P) / 2, floor + S / 2 + Bn * (1 + P) / 2
    var_s = (1 + 1 / P) ** 2 * var_b + (1 - 1 / P) ** 2 * var_w
    assert sh.weight[0] == pytest.approx(_phi_weight(S, var_s), abs=0.01)
    assert sh.quality[0] == pytest.approx(1.0)  # p̂ = p: eq. 6 removes all backscatter
    assert noise_gain(0.8) == pytest.approx(math.sqrt(2 * (1 + 1 / 0.64)))


def test_s_hat_contrast_keeps_the_residual_when_p_is_below_p_min():
    # p = 0.02 < p_min = 0.05: eq. 6 divides by 0.05 and over-subtracts B(1 - 0.02/0.05) = 0.6 B
    s = Samples(np.array([0.3]), np.array([0.1]), np.array([2.0]), np.array([0.02]))
    q = objective(s, IDEAL_SENSOR, modality="flood", reading="S_hat", p_min=0.05).quality[0]
    assert q == pytest.approx(0.4 / (0.4 + 0.6 * 2.0))


def test_saturation_is_judged_on_the_frame_each_reading_uses():
    # S = 400 e-, B = 2000 e-, p = 0.8: E = 2400, E_b = 200 + 200 = 400, E_w = 200 + 1800 = 2000
    s = Samples(np.array([0.3]), np.array([0.1]), np.array([2.0]), np.array([P]))
    noise = SensorNoise(1000.0, full_well_e=1500.0)
    sat = {r: bool(objective(s, noise, modality="flood", reading=r).saturated[0])
           for r in ("E", "E_b", "S_hat")}
    assert sat == {"E": True, "E_b": False, "S_hat": True}
    assert not objective(s, IDEAL_SENSOR, modality="flood", reading="E").saturated[0]
