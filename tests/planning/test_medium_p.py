"""p from an analyzer pair with the medium's model (planning/medium_p.py, docs/physics.md §4.2), against the
backscatter's own DOP from the components (B-weighted over the region), with the analyzer off the mean
backscatter angle by 15° (a calibration that missed): the model's fit takes the angle, the frames alone
read the DOP lowered by the object's light and the angle."""

import numpy as np
import pytest
from polarstripe.planning.medium_p import p_of_pair, p_with_model
from polarstripe.sim.polarization import least_backscatter_angle
from polarstripe.sim.render import render_components, render_frame
from polarstripe.sim.scene import Phase, load_scene, with_separation
from polarstripe.sim.sensor import dark_offset_dn, full_scale_dn
from polarstripe.sim.truth import unscattered_object


@pytest.mark.parametrize("sigma_t,g", [(1.0, 0.7), (8.0, 0.9)])
def test_the_model_reads_the_backscatter_dop_through_object_light_and_a_missed_angle(sigma_t, g):
    s = load_scene(None)
    s = s.replace(camera=s.camera.resized((64, 48)),
                  medium=s.medium.replace(sigma_t=sigma_t, phase=Phase("tthg", g)))
    sd = with_separation(s, 0.25)
    c = render_components(sd, "flood", "preview")
    free = unscattered_object(sd)[0] <= 1e-9
    truth = float(np.sum((c.B * c.p)[free]) / np.sum(c.B[free]))
    chi = least_backscatter_angle(c) + 15.0
    pair = (render_frame(sd, "flood", chi, "preview", seed=1)[0],
            render_frame(sd, "flood", chi + 90.0, "preview", seed=2)[0])
    args = (pair, free, dark_offset_dn(sd.camera), full_scale_dn(sd.camera) - 0.5)
    p, std, why = p_with_model(*args, sd, "preview")
    assert not why and abs(p - truth) < 0.01 and 0 < std < 0.01
    alone, _, _ = p_of_pair(*args)
    assert alone < truth - 0.05
