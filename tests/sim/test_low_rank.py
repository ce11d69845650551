"""A scan's grid solves in low rank (sim/multiple.py ``propagate`` with ``rank_tol``): a batch whose sources
span r fields is solved through r transforms and gives each field its own solve; a scan at the planner's
tolerance stays within it of the frames solved one by one, and the tolerance does change them."""

from __future__ import annotations

import numpy as np
from polarstripe.sim import tally
from polarstripe.sim.multiple import _low_rank, make_grid, propagate
from polarstripe.sim.scan_render import render_scan
from polarstripe.sim.scene import load_scene


def _blob(grid, centre, width):
    x = grid.centres() - np.asarray(centre)
    return np.exp(-np.sum(x * x, axis=-1) / (2 * width * width))


def test_a_batch_of_rank_two_takes_two_transforms_and_gives_each_field():
    grid = make_grid((-0.3, -0.3, 0.0), (0.3, 0.3, 0.8), 8)
    a, b = _blob(grid, (0.1, 0.0, 0.3), 0.08), _blob(grid, (-0.1, 0.1, 0.5), 0.12)
    weights = np.array([[1.0, 0.0], [0.0, 1.0], [0.3, 0.7], [2.0, 0.5], [0.1, 1.5], [0.8, 0.8]])
    s0 = np.einsum("mk,k...->m...", weights, np.stack([a, b]))
    s1 = 0.2 * s0[..., None] * np.array([0.0, 0.0, 1.0])
    src = np.concatenate([s0[:, None], np.moveaxis(s1, -1, 1)], axis=1).astype(np.float32)
    basis, coef = _low_rank(src, 1e-4)
    assert basis.shape[0] == 2 and coef.shape == (6, 2)
    with tally.propagations() as counted:
        exact = propagate(grid, 4.0, s0, s1)
        assert counted.transforms == 6
        low = propagate(grid, 4.0, s0, s1, rank_tol=1e-4)
        assert counted.transforms == 6 + 2 and counted.cpu_s > 0      # the batch's rank, not its size
    propagate(grid, 4.0, s0, s1)
    assert counted.transforms == 8                                     # nothing counted outside the block
    for m in range(6):
        peak = exact.phi[m].max()
        assert peak > 0
        np.testing.assert_allclose(low.phi[m], exact.phi[m], atol=1e-5 * peak, rtol=0)
        np.testing.assert_allclose(low.flux[m], exact.flux[m], atol=1e-5 * peak, rtol=0)


def test_full_rank_batches_are_left_alone():
    rng = np.random.default_rng(3)
    src = rng.random((4, 4, 3, 3, 3)).astype(np.float32)
    basis, coef = _low_rank(src, 1e-3)
    assert coef is None and basis is src


def test_a_scan_in_low_rank_is_within_its_tolerance_of_the_frames_own():
    s = load_scene(None)
    scene = s.replace(camera=s.camera.resized((64, 48)), medium=s.medium.replace(sigma_t=5.0))
    patterns = [f"stripe:{k}/12" for k in range(12)]
    exact = render_scan(scene, patterns, "standard")
    low = render_scan(scene, patterns, "standard", rank_tol=1e-3)
    moved = 0.0
    for a, b in zip(exact, low, strict=True):
        peak = a.B.max()
        assert peak > 0
        for k in ("B", "A", "Bq", "Bu"):
            err = np.abs(getattr(b, k) - getattr(a, k)).max() / peak
            assert err < 2e-3, (str(a.pattern), k, err)
            moved = max(moved, err)
        np.testing.assert_array_equal(b.D, a.D)      # the direct light has no grid solve
    assert moved > 1e-7                              # the tolerance took effect
