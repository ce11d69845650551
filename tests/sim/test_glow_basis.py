"""The glow's per-scene basis (sim/glow.py): each patch's first-flight field at unit exitance carries the
energy a Lambertian patch emits (∫φ dV = M·A/σ̃ in an absorbing medium, closed form), and a frame made with
the basis equals one made without it to rounding."""

import numpy as np
import pytest
from polarstripe.sim import geometry_cache, glow
from polarstripe.sim.kernel_records import PhaseArgs
from polarstripe.sim.multiple import make_grid
from polarstripe.sim.render import render_components
from polarstripe.sim.scene import load_scene


def test_each_patch_field_holds_the_emitted_energy():
    """A patch of area A and unit exitance emits A watts; with σ = 60 /m nearly all of it is absorbed within
    the box (the shortest beams cross ≥ 5 cm, e^{−3} of the grazing few), so ∫φ dV = A/σ to a per cent."""
    scene = load_scene(None)
    m = scene.medium
    grid = make_grid(m.extent.min, m.extent.max, 16)
    sigma = 60.0
    cells = grid.centres().reshape(-1, 3)
    basis = glow.glow_basis(scene, grid, cells, np.zeros(3), sigma, PhaseArgs(0, 0.0, 0.0, 0.0),
                            float(grid.h.min()), 36)
    assert basis.phi is not None and basis.keep.size > 10
    vol = float(np.prod(grid.h))
    energy = basis.phi.sum(0) * vol                     # per kept patch
    expected = basis.patches.area[basis.keep] / sigma
    central = np.argsort(np.abs(energy / expected - 1))[: basis.keep.size // 2]
    np.testing.assert_allclose(energy[central], expected[central], rtol=0.01)
    assert np.all(energy <= expected * (1 + 1e-9))       # never more than emitted


@pytest.mark.parametrize("fidelity", ["standard", "preview"])
def test_a_frame_with_the_basis_equals_one_without(fidelity, monkeypatch):
    scene = load_scene(None)
    geometry_cache.clear()
    calls = []
    rows = glow.weighted_rows
    monkeypatch.setattr(glow, "weighted_rows", lambda *a: calls.append(1) or rows(*a))
    kept = render_components(scene, "stripe:14/30", fidelity)
    used = len(calls)
    assert used                                          # the basis was used
    monkeypatch.setattr(glow, "BASIS_VALUES", 0)
    geometry_cache.clear()
    fresh = render_components(scene, "stripe:14/30", fidelity)
    geometry_cache.clear()
    assert len(calls) == used                            # and not without it
    for k in ("D", "A", "B", "Bq", "Bu"):
        a, b = getattr(kept, k), getattr(fresh, k)
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-13 * np.abs(b).max(), err_msg=k)
