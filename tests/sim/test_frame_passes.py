"""A frame's passes after the model: the analyzer's precomputed form equals Malus's law as written in
docs/physics.md §4.1 (written out here, on random inputs with the edge cases: B = 0, a DOP clipped at 1, no
linear polarization). The sensor's statistics: tests/sim/test_sensor_noise.py."""

import numpy as np
import pytest
from polarstripe.sim.polarization import analyzer, analyzer_basis, through_analyzer
from polarstripe.sim.render import Components
from polarstripe.sim.scene import load_scene


def _components(rng, scene, n=4000):
    d, a, b = (rng.uniform(0, 2, n) * 10.0 ** rng.uniform(-3, 2, n) for _ in range(3))
    q, u, v = (rng.normal(0, 1, n) * b for _ in range(3))        # |(Q, U)| above B in places: p clipped
    b[::17] = 0.0                                                # no backscatter: p = 0
    q[::19], u[::19] = 0.0, 0.0                                  # no linear polarization
    return Components(d.reshape(40, 100), a.reshape(40, 100), b.reshape(40, 100), q.reshape(40, 100),
                      u.reshape(40, 100), None, scene, None, None, Bv=v.reshape(40, 100))


def _malus(c, angle_deg, er):
    """I(φ) = ½(k1 + k2)(D + A + B) + ½(k1 − k2)·B·p·cos 2(φ − χ), k2 = 1/ER (docs/physics.md §4.1)."""
    k1, k2 = 1.0, 1.0 / er                       # k1 = 1
    phi = np.radians(angle_deg)
    return 0.5 * (k1 + k2) * (c.D + c.A + c.B) + 0.5 * (k1 - k2) * c.B * c.p * np.cos(2 * (phi - c.chi_rad))


@pytest.mark.parametrize("plate", [None, 30.0])
def test_precomputed_analyzer_is_malus_law(plate):
    """Equal to rounding: B·p·cos 2(φ − χ) against B·p·(Q cos 2φ + U sin 2φ)/√(Q² + U²), a few ulp of B·p."""
    scene = load_scene(None)
    scene = scene.replace(camera=scene.camera.replace(
        polarizer=scene.camera.polarizer.replace(quarter_wave_deg=plate)))
    c = _components(np.random.default_rng(1), scene)
    assert (c.p == 1.0).mean() > 0.05 and (c.p[c.B > 0] < 1).mean() > 0.3       # both sides of the clip
    basis = analyzer_basis(c)
    for angle in (0.0, 22.5, 90.0, 133.7, -61.0):
        want = _malus(c, angle, scene.camera.polarizer.extinction_ratio)
        got = analyzer(c, angle)
        assert got.shape == want.shape
        assert np.all(np.abs(got - want) <= 1e-12 * (c.D + c.A + c.B))
        assert np.array_equal(through_analyzer(basis, angle), got)
    low = analyzer(c, 10.0, extinction_ratio=50.0)
    assert np.all(np.abs(low - _malus(c, 10.0, 50.0)) <= 1e-12 * (c.D + c.A + c.B))
    assert np.array_equal(analyzer(c, None), c.D + c.A + c.B)
