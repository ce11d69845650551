"""The ``polarstripe figure`` command writes the two PNG plots; the D/S curve falls with thickness."""

import argparse

import numpy as np
from polarstripe.planning import figures
from polarstripe.sim.scene import load_scene


def test_figure_command_writes_pngs(tmp_path):
    args = argparse.Namespace(scene=None, which="all", fidelity="preview", max_thickness=4.0,
                              out=str(tmp_path))
    assert figures.main(args) == 0
    for name in ("fig5_ds_vs_thickness.png", "fig11_dop_vs_angle.png"):
        data = (tmp_path / name).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000


def test_ds_is_one_in_clear_medium_and_falls_with_thickness():
    tau = np.array([0.0, 1.0, 3.0, 8.0])
    t, mean, lo, hi = figures.ds_curve(load_scene(None), tau, "preview", n_pixels=4)
    assert mean[0] == 1.0 and np.all(np.diff(mean) < 0) and np.all(lo <= mean) and np.all(mean <= hi)
