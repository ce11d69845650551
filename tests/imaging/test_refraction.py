"""Triangulation through flat ports (imaging/refraction.py): the true projector column of each object point,
found in the world by the model's own port (sim/port.py) and the projector's pinhole, gives back the true
depth; the pinhole-only triangulation of the same columns is off by the port's bias; and (``--long``) a
rendered stripe scan of a sphere before a tilted plane behind the paper's glass wall at σ_t = 2."""

from __future__ import annotations

import numpy as np
import pytest
from polarstripe.bench.depth import depth_error, depth_scene, noise_of, scan_votes
from polarstripe.imaging.delineation import delineate
from polarstripe.imaging.refraction import depth_through_ports, port_of
from polarstripe.imaging.triangulation import RigGeometry, Triangulator, depth_from_columns, stripe_edges
from polarstripe.imaging.validation import ImagingError
from polarstripe.sim.depth_truth import column_truth, depth_truth, rig_geometry
from polarstripe.sim.scene import glass_tank


def test_true_columns_give_back_the_true_depth_and_the_pinhole_pipeline_is_biased():
    scene = glass_tank(depth_scene(2.0, 64))
    truth = depth_truth(scene)
    rig = rig_geometry(scene)
    geom = RigGeometry.from_dict(rig)
    columns = column_truth(scene)
    assert np.isfinite(columns).sum() > 0.5 * columns.size
    z = depth_through_ports(geom, port_of(rig["port_cam"]), port_of(rig["port_proj"]), columns)
    both = np.isfinite(truth)
    assert np.isfinite(z[both]).all()
    np.testing.assert_allclose(z[both], truth[both], atol=1e-6)
    pinhole = depth_from_columns(geom, columns)
    assert np.nanmean(np.abs(pinhole[both] - truth[both])) > 0.05        # the port's bias: tens of mm


def test_no_port_is_the_ray_plane_triangulation():
    scene = depth_scene(2.0, 48)
    geom = RigGeometry.from_dict(rig_geometry(scene))
    assert "port_cam" not in rig_geometry(scene)
    columns = np.tile(np.linspace(300.0, 700.0, 48), (36, 1))
    np.testing.assert_allclose(depth_through_ports(geom, None, None, columns),
                               depth_from_columns(geom, columns), rtol=1e-9)


def test_a_bad_port_is_one_error():
    with pytest.raises(ImagingError, match="a port is 8 numbers"):
        port_of([0, 0, 1, 0.01])
    rig = rig_geometry(glass_tank(depth_scene(2.0, 48)))
    with pytest.raises(ImagingError, match="port_cam must be 8 numbers"):
        RigGeometry.from_dict({**rig, "port_cam": [0, 0, 1]})


def test_the_compositors_triangulator_goes_through_the_ports():
    """A rig with ports (as the simulator's truth carries it, lists) round-trips and its Triangulator gives
    the refractive depth, with points on the water rays at that depth."""
    scene = glass_tank(depth_scene(2.0, 48))
    rig = {k: np.asarray(v, float).tolist() for k, v in rig_geometry(scene).items()}
    geom = RigGeometry.from_dict(rig)
    assert geom.has_ports and RigGeometry.from_dict(geom.to_dict()).has_ports
    columns = column_truth(scene)
    tri = Triangulator(geom, columns.shape)
    z = tri.depth(columns)
    truth = depth_truth(scene)
    both = np.isfinite(truth)
    np.testing.assert_allclose(z[both], truth[both], atol=1e-5)
    pts = tri.points(z)
    assert pts.shape == (int(np.isfinite(z).sum()), 3)
    np.testing.assert_allclose(pts[:, 2], z[np.isfinite(z)], atol=1e-6)
    assert not RigGeometry.from_dict(rig_geometry(depth_scene(2.0, 48))).has_ports


@pytest.mark.long
@pytest.mark.timeout(900)  # ~2.5 minutes of CPU (30 frames through the ports); more on a loaded machine
def test_stripe_scan_through_the_glass_wall():
    """160×120, 30 stripes, σ_t = 2, single scattering: the refractive depth within 2 mm RMS, the pinhole
    pipeline off by the port's bias (docs/depth.md "Through a port")."""
    scene = glass_tank(depth_scene(2.0, 160))
    truth = depth_truth(scene)
    rig = rig_geometry(scene)
    geom = RigGeometry.from_dict(rig)
    votes, scene = scan_votes(scene, 30, (None,))
    columns = delineate(votes[None], stripe_edges(30, 1024), noise_of(scene))
    ports = port_of(rig["port_cam"]), port_of(rig["port_proj"])
    refr = depth_error(depth_through_ports(geom, *ports, columns), truth)
    pin = depth_error(depth_from_columns(geom, columns), truth)
    assert refr["rms_mm"] < 2.0 and refr["valid_fraction"] > 0.45 and refr["off_object"] == 0, refr
    assert pin["rms_mm"] > 20.0, pin
