"""Phase functions: normalisation, mean cosine, Haltrin's table and stability at |g| → 1."""

import numpy as np
import pytest
from polarstripe.sim.phase import hg, tthg, tthg_parameters
from scipy.integrate import quad


@pytest.mark.parametrize("g, gf, gb, alpha", [(0.5, 0.76037, 0.46015, 0.78667),
                                              (0.8, 0.91271, 0.61961, 0.92645),
                                              (0.924, 0.96783, 0.67820, 0.97337)])
def test_haltrin_closure_matches_table(g, gf, gb, alpha):
    assert tthg_parameters(g) == pytest.approx((gf, gb, alpha), abs=1e-5)


@pytest.mark.parametrize("g", [0.5, 0.8, 0.9, 0.924, 0.95])
def test_tthg_normalised_mean_cosine_and_backscatter_fraction(g):
    def p(mu):
        return float(tthg(np.array(1 - mu), np.array(1 + mu), g))

    pts = [1 - 1e-3, 1 - 1e-2, 0.9]
    norm = 2 * np.pi * quad(p, -1, 1, points=pts, limit=500, epsabs=0, epsrel=1e-12)[0]
    mean = 2 * np.pi * quad(lambda m: m * p(m), -1, 1, points=pts, limit=500, epsabs=0, epsrel=1e-12)[0]
    back = 2 * np.pi * quad(p, -1, 0, epsabs=0, epsrel=1e-12)[0]
    assert norm == pytest.approx(1.0, abs=1e-9)
    assert mean == pytest.approx(g, abs=1e-9)
    assert back == pytest.approx(2 * (1 - g) / (4 + g), rel=1e-4)          # Haltrin's B_p identity


def test_tthg_backscatter_value_at_0_8():
    assert 4 * np.pi * float(tthg(np.array(2.0), np.array(0.0), 0.8)) == pytest.approx(0.845, abs=1e-3)


@pytest.mark.parametrize("g", [0.999, -0.999, 0.3, -0.3])
def test_hg_extreme_g_peak_and_normalisation_against_cdf(g):
    # peak value (1+|g|)/(1-|g|)^2 / 4π at the exact pole, without cancellation
    peak = hg(np.array(0.0), np.array(2.0), g) if g > 0 else hg(np.array(2.0), np.array(0.0), g)
    assert 4 * np.pi * float(peak) == pytest.approx((1 + abs(g)) / (1 - abs(g)) ** 2, rel=1e-12)

    def cdf(mu):   # closed form F(μ) = (1−g²)/(2g)[1/√(1+g²−2gμ) − 1/(1+g)]
        return (1 - g * g) / (2 * g) * (1 / np.sqrt(1 + g * g - 2 * g * mu) - 1 / (1 + g))

    def dens(m):
        return 2 * np.pi * float(hg(np.array(1 - m), np.array(1 + m), g))

    pieces = ((-1, -0.99), (-0.99, 0.99), (0.99, 1))
    for a, b in pieces:
        got = quad(dens, a, b, epsabs=0, epsrel=1e-11, limit=200)[0]
        assert got == pytest.approx(cdf(b) - cdf(a), rel=1e-8)
    # the code's phase function itself, by brute-force quadrature: normalised to 1, mean cosine g
    norm = sum(quad(dens, a, b, epsabs=0, epsrel=1e-11, limit=200)[0] for a, b in pieces)
    mean = sum(quad(lambda m: m * dens(m), a, b, epsabs=0, epsrel=1e-11, limit=200)[0] for a, b in pieces)
    assert norm == pytest.approx(1.0, rel=1e-9)
    assert mean == pytest.approx(g, rel=1e-8)
