"""The compositor's ``map`` rule through the harness on frames of the model itself (noise-free, the default
tank at a pose the compositor learns from the truth message): eq. 6 with the model's map gives the object's
light (k1 + k2)·S where one p̂ does not, the published p is the backscatter's B-weighted DOP over the pixels
without object, and a stripe scan at the same pose takes κ and ψ from the polarized flood before it."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from polarstripe.msgs import Frame, MediumEstimate, ScanEvent
from polarstripe.nodes.compositor import Compositor
from polarstripe.nodes.simulator_frames import truth_composite
from polarstripe.runtime.testing import NodeHarness
from polarstripe.sim.polarization import analyzer, least_backscatter_angle, polarizer_transmittances
from polarstripe.sim.render import render_components
from polarstripe.sim.scene import load_scene, with_separation

GAIN, DARK, SEP = 4e3, 64.0, 0.2


def _scene():
    s = load_scene(None)
    return with_separation(s.replace(camera=s.camera.resized((64, 48))), SEP)


def _scan(h, scan_id, method, scene, patterns, eb_deg, stripes=0):
    angles = [eb_deg, eb_deg + 90.0]
    h.deliver("emitter/scan", ScanEvent(scan_id=scan_id, event="start", method=method, stripes=stripes,
                                        analyzer_deg=angles))
    truth = truth_composite(scene)
    h.deliver("simulator/truth", dataclasses.replace(truth, scan_id=scan_id,
                                                     metrics={**truth.metrics, "dark_offset_dn": DARK}))
    step = 0
    for pattern in patterns:
        c = render_components(scene, pattern, "preview")
        for a in angles:
            image = analyzer(c, a) * GAIN + DARK
            h.deliver("camera/frame", Frame(image=image, exposure_s=0.01, pattern=pattern, polarizer_deg=a,
                                            scan_id=scan_id, step=step))
            step += 1
    h.deliver("emitter/scan", ScanEvent(scan_id=scan_id, event="done", method=method, stripes=stripes,
                                        analyzer_deg=angles))
    return h.published("compositor/composite")[-1]


@pytest.mark.parametrize("rule", ["map", "median"])
def test_the_map_removes_the_backscatter_where_one_p_does_not(rule):
    scene = _scene()
    c = render_components(scene, "flood", "preview")
    eb_deg = least_backscatter_angle(c)
    h = NodeHarness(Compositor, name="compositor", namespace="/rig",
                    params={"done_grace_s": 0.05, "p_rule": rule, "dark_offset_dn": DARK})
    comp = _scan(h, 1, "polarized_flood", scene, ["flood"], eb_deg)
    k1, k2 = polarizer_transmittances(scene.camera.polarizer.extinction_ratio)
    want = GAIN * (k1 + k2) * c.S
    free = truth_composite(scene).images["S"] <= 1e-9
    truth_p = float(np.sum((c.B * c.p)[free]) / np.sum(c.B[free]))
    est = h.published("compositor/medium_p")[-1]
    worst = float(np.max(np.abs(comp.images["composite"] - want)) / np.max(want))
    if rule == "map":
        assert comp.metrics["p_source"] == "model" and worst < 0.01
        assert est.p == pytest.approx(truth_p, abs=0.01)
        # a stripe scan at the same pose: κ and ψ from the flood pair, so the same medium's p
        stripes = _scan(h, 2, "polarized_stripes", scene, [f"stripe:{k}/4" for k in range(4)], eb_deg, 4)
        assert stripes.metrics["p_backscatter"] == pytest.approx(est.p, abs=1e-9)
        assert "p_note" not in stripes.metrics
    else:  # one p̂ from the wall, whose object light lowers it: over-subtracted
        assert comp.metrics["p_source"] == "median" and worst > 0.05
        assert comp.metrics["p"] < truth_p - 0.05


def test_a_fitted_medium_replaces_the_scenes():
    scene = _scene()
    h = NodeHarness(Compositor, name="compositor", namespace="/rig", params={"done_grace_s": 0.05})
    model = h.node.medium
    assert model.scene(None).medium.sigma_t == pytest.approx(scene.medium.sigma_t)
    h.deliver("medium/estimate", MediumEstimate(p=0.5, sigma_t_per_m=2.5, mean_cosine=0.9, scan_id=3))
    assert model.scene(None).medium.sigma_t == pytest.approx(2.5)
    h.deliver("medium/estimate", MediumEstimate(p=0.5, scan_id=4, reason="fit at a bound"))
    assert model.scene(None).medium.sigma_t == pytest.approx(2.5)  # a refusal keeps the last fit
