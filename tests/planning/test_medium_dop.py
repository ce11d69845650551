"""The DOP model from a measured p (planning/medium_dop.py): the Rayleigh model's δ solved for p."""

import pytest
from polarstripe.planning.medium_dop import DELTA_MAX, model_p, with_measured_p
from polarstripe.sim.scene import DopModel, load_scene

W = 32          # renders this narrow keep the test to seconds; the weighted DOP moves by < 1e-3 with width


@pytest.fixture(scope="module")
def scene():
    return load_scene(None)     # the tank: Rayleigh DOP, δ = 0.2


def _delta(scene, delta):
    return scene.replace(medium=scene.medium.replace(dop=scene.medium.dop.replace(depolarization=delta)))


def test_the_weighted_dop_falls_with_the_depolarization(scene):
    p = [model_p(_delta(scene, d), 0.2, width=W) for d in (0.0, 0.1, 0.2, 0.35)]
    assert all(a > b for a, b in zip(p[:-1], p[1:], strict=True))
    # at δ = 0 the backscatter-weighted DOP stays below the DOP at exact backscatter (1 − δ = 1): the image
    # sees angles short of 180° and light scattered more than once
    assert 0.5 < p[0] < 1.0


def test_a_measured_p_gives_back_the_depolarization_that_made_it(scene):
    truth = _delta(scene, 0.3)
    p = model_p(truth, 0.15, width=W)
    got = with_measured_p(scene, p, 0.15, width=W).medium.dop
    assert got.model == "rayleigh" and got.depolarization == pytest.approx(0.3, abs=1e-3)


def test_a_p_beyond_the_model_takes_the_nearest_end_and_a_constant_model_takes_p(scene):
    assert with_measured_p(scene, 1.0, 0.2, width=W).medium.dop.depolarization == 0.0
    assert with_measured_p(scene, 0.0, 0.2, width=W).medium.dop.depolarization == DELTA_MAX
    const = scene.replace(medium=scene.medium.replace(dop=DopModel(model="constant", p=0.8)))
    got = with_measured_p(const, 0.37, 0.2, width=W).medium.dop
    assert got.model == "constant" and got.p == 0.37
