"""Depth from rendered stripe scans vs the simulator's depth truth: a sphere before a tilted plane in the
default tank (bench/depth.py's scene), 160×120, 30 stripes, single scattering (orders='single')."""

from __future__ import annotations

import numpy as np
import pytest
from polarstripe.bench.depth import depth_error, depth_scene, noise_of, scan_votes
from polarstripe.imaging.delineation import delineate
from polarstripe.imaging.triangulation import RigGeometry, depth_from_columns, stripe_edges
from polarstripe.sim.depth_truth import depth_truth, rig_geometry


@pytest.mark.parametrize("sigma_t", [2.0, 10.0])
def test_triangulated_depth_matches_truth(sigma_t):
    scene = depth_scene(sigma_t, 160)
    truth = depth_truth(scene)
    votes, scene = scan_votes(scene, 30, (None, 0.0, 90.0))
    geom = RigGeometry.from_dict(rig_geometry(scene))
    crossed = min((0.0, 90.0), key=lambda a: float(np.median(votes[a].best)))  # E_b, as the compositor picks
    for angle in (None, crossed):
        z = depth_from_columns(geom, delineate(votes[angle], stripe_edges(30, 1024), noise_of(scene)))
        e = depth_error(z, truth)
        assert e["rms_mm"] < 2.5 and e["valid_fraction"] > 0.45 and e["off_object"] == 0, e
