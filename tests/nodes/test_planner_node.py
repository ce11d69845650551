"""The planner node through the harness: the plan as a service and a topic, re-planned when the medium
estimate moves beyond the tolerance."""

from __future__ import annotations

import numpy as np
import pytest
from polarstripe.msgs import Empty, MediumEstimate
from polarstripe.nodes.planner import Planner
from polarstripe.planning.medium_dop import model_p
from polarstripe.planning.planner import SEARCHES, default_separations, plan_model
from polarstripe.planning.planner import plan as plan_separations
from polarstripe.runtime.params import ParamError
from polarstripe.runtime.testing import NodeHarness

FAST = {"fidelity": "preview", "separations": 6, "d_min_m": 0.05, "d_max_m": 0.45, "resolution": "160x120",
        "refine": 2}     # the default search's rivals, two rounds of its four (a test's seconds)
CHEAP = {**FAST, "width": 96}  # the error measure's renders narrower than the camera: a fifth less CPU
# the tests of when the node re-plans (counters, the medium), not where it goes: 3 separations, no bisection
REPLAN = {**CHEAP, "separations": 3, "refine": 0, "publish_on_start": False}


@pytest.fixture(scope="module")
def harness():
    return NodeHarness(Planner, name="planner", namespace="/rig", params=FAST)


def test_plan_is_served_and_published(harness):
    h = harness
    assert h.published("planner/plan") == []
    h.advance(1.05)  # publish_delay_s: once, after subscribers had time to join
    h.advance(3.0)
    assert len(h.published("planner/plan")) == 1
    plan = h.call("planner/plan", Empty())
    assert plan.modality == "stripes"
    seps = plan.curves["separation_m"]   # the grid and the bisections around the peaks (the default search)
    grid = np.linspace(0.05, 0.45, 6)
    assert h.node.params.search == "coarse"
    search = SEARCHES["coarse"]
    assert np.all(np.diff(seps) > 0) and np.all(np.isin(np.round(grid, 9), np.round(seps, 9)))
    assert 2 <= seps.size - grid.size <= 2 * 3 * 3 * 2   # rounds × readings × peaks × 2
    # the plan is the planner's on the node's scene: in the configured range, and within one grid step of
    # the best separation planning.planner.plan finds for the same scene, modality and polarization
    assert FAST["d_min_m"] <= plan.separation_m <= FAST["d_max_m"]
    assert h.node.params.measure == "error"           # the planner's default measure (docs/planning.md §8)
    # rendered at the camera's width (160 px, its resolution): the pixel grid the stripe composite aliases on
    model = plan_model(h.node.scene, measure="error", fidelity=FAST["fidelity"], width=160,
                       n_stripes=h.node.params.stripes, stripe_step=h.node.params.stripe_step)
    reference = plan_separations(model, default_separations(6, 0.05, 0.45), modalities=("stripes",),
                                 refine=2, rivals=search.rivals)
    step = (FAST["d_max_m"] - FAST["d_min_m"]) / (FAST["separations"] - 1)
    best = reference["stripes_polarized"].curve
    assert abs(plan.separation_m - best.best_separation_m) <= step + 1e-12
    np.testing.assert_allclose(plan.curves["objective"], best.objective)
    # the best objective (its saturated pixels lost): the node plans as `polarstripe plan` does
    assert plan.separation_m == seps[int(np.argmax(plan.curves["objective"]))]
    assert "flood_saturated_fraction" not in plan.curves        # no flood check unless one is asked for
    assert plan.scan_type in ("rotate", "translate", "both")
    assert len(plan.stripe_optima) == 3 and all(0.05 <= d <= 0.45 for d in plan.stripe_optima)
    assert len(h.published("planner/plan")) == 2  # the call publishes it too (the simulator moves the source)


def test_asked_to_the_chosen_separation_does_not_saturate_a_flood_frame():
    """The default tank saturates most of a flood frame with the source next to the camera; with
    ``max_saturated_fraction`` the plan moves to a separation where a full flood frame (rendered here,
    independently) stays below full scale."""
    from polarstripe.sim.render import render_frame
    from polarstripe.sim.scene import with_separation

    harness = NodeHarness(Planner, name="planner", namespace="/rig",
                          params={**FAST, "max_saturated_fraction": 0.02, "publish_on_start": False})
    plan = harness.call("planner/plan", Empty())
    ok = plan.curves["flood_saturated_fraction"] <= 0.02
    assert ok.any() and plan.separation_m == plan.curves["separation_m"][ok][
        int(np.argmax(plan.curves["objective"][ok]))]
    scene = with_separation(harness.node.scene, plan.separation_m)
    dn, _ = render_frame(scene, "flood", polarizer_deg=None, fidelity="preview", seed=3)
    assert np.mean(dn >= 4095) < 0.05
    near, _ = render_frame(with_separation(harness.node.scene, 0.05), "flood", fidelity="preview", seed=3)
    assert np.mean(near >= 4095) > 0.5  # the check had something to avoid
    fractions = plan.curves["flood_saturated_fraction"]
    assert fractions[list(plan.curves["separation_m"]).index(plan.separation_m)] <= 0.02


def test_co_located_placements_score_nothing():
    """Part of what the saturation guard was for (eq. 9's optimum at 1-2 cm, backscatter filling the frame)
    the delineation margin does itself at d -> 0: a source next to the camera scores 0. (The guard still
    matters a few cm out, where the objective is flat and a flood frame at the scene's exposure saturates.)
    The margin as derived, on the paper's single-scattering model (docs/planning.md §1)."""
    h = NodeHarness(Planner, name="planner", params={**FAST, "separations": 3, "d_min_m": 0.001,
                                                        "d_max_m": 0.3, "publish_on_start": False,
                                                        "orders": "single"})
    objective = h.node.plan.curves["objective"]
    assert objective[0] == 0.0 and objective.max() > 0.3 and h.node.plan.separation_m > 0.1


def test_bad_fidelity_and_oversized_resolution_are_param_errors():
    with pytest.raises(ParamError, match="fidelity 'ultra' is not preview, standard, reference"):
        NodeHarness(Planner, name="planner", params={**FAST, "fidelity": "ultra"})
    with pytest.raises(ParamError, match=r"resolution 100000x100000 is .* beyond the limit"):
        NodeHarness(Planner, name="planner", params={**FAST, "resolution": "100000x100000"})
    # the planner's own level is the error measure's: the paper's measure renders with the simulator's
    with pytest.raises(ParamError, match="fidelity 'draft' is not preview, standard, reference"):
        NodeHarness(Planner, name="planner", params={**FAST, "fidelity": "draft", "measure": "paper"})


def test_small_change_of_p_does_not_replan(harness):
    h = harness
    n = len(h.published("planner/plan"))
    h.deliver("medium/estimate", MediumEstimate(p=h.node.p_assumed + 0.03, scan_id=1))
    # the unchanged plan is published as the answer to the estimate (the sequencer's rescan waits for it)
    assert len(h.published("planner/plan")) == n + 1 and h.node.counters["replans"] == 0
    answer = h.published("planner/plan")[-1]
    assert answer.separation_m == h.node.plan.separation_m and list(answer.curves["estimate_scan_id"]) == [1]


def test_changed_p_replans_with_the_measured_medium():
    # the paper's measure and single-scattering model, where the margin's dependence on p below holds
    # (planning.md §1)
    h = NodeHarness(Planner, name="planner", namespace="/rig",
                    params={**FAST, "publish_on_start": False, "orders": "single", "measure": "paper",
                            "refine": 0})     # the curves compared below on the same separations
    before = h.call("planner/plan", Empty())
    n = len(h.published("planner/plan"))
    h.deliver("medium/estimate", MediumEstimate(p=0.2, scan_id=2))
    assert h.node.counters["replans"] == 1 and len(h.published("planner/plan")) == n + 1
    # the Rayleigh DOP model kept (its variation across the image), more depolarizing than the tank's 0.2,
    # giving the measured p where the estimate's scan was (planning/medium_dop.py)
    dop = h.node.scene.medium.dop
    assert dop.model == "rayleigh" and 0.2 < dop.depolarization < 0.499
    assert model_p(h.node.scene, before.separation_m, width=96) == pytest.approx(0.2, abs=2e-3)
    after = h.published("planner/plan")[-1]
    # the stripe margin (docs/planning.md §1), (E_own - max E_comp) / E_own with E = D + A + B(1 - p), falls
    # as p falls wherever a competitor carries backscatter: less of it is filtered. The re-plan used the
    # measured p, not the model's
    assert np.all(after.curves["quality"] < before.curves["quality"])


def test_changed_sigma_replans():
    h = NodeHarness(Planner, params=REPLAN)
    h.deliver("medium/estimate", MediumEstimate(p=h.node.p_assumed, sigma_t_per_m=5.2))  # within 10 %
    assert h.node.counters["replans"] == 0
    h.deliver("medium/estimate", MediumEstimate(p=h.node.p_assumed, sigma_t_per_m=9.0))
    assert h.node.counters["replans"] == 1 and h.node.scene.medium.sigma_t == pytest.approx(9.0)
    h.advance(5.0)
    assert len(h.published("planner/plan")) == 2  # the answer to each estimate: nothing on start-up


def test_fitted_medium_replans_with_sigma_and_mean_cosine():
    h = NodeHarness(Planner, params=REPLAN)
    cannot = MediumEstimate(p=h.node.p_assumed, sigma_t_per_m=None, reason="no visible sheet")
    h.deliver("medium/estimate", cannot)
    assert h.node.counters["replans"] == 0
    h.deliver("medium/estimate", MediumEstimate(p=h.node.p_assumed, sigma_t_per_m=5.0, mean_cosine=0.9,
                                                sigma_t_std=0.2, mean_cosine_std=0.01))
    assert h.node.counters["replans"] == 1
    assert h.node.scene.medium.phase.g == pytest.approx(0.9) and h.node.g_assumed == pytest.approx(0.9)


def test_bad_params_are_rejected_before_start():
    with pytest.raises(ParamError, match="resolution"):
        NodeHarness(Planner, params={"resolution": "640by480"})
    with pytest.raises(ParamError, match="d_min_m"):
        NodeHarness(Planner, params={"d_min_m": 0.5, "d_max_m": 0.1})
    with pytest.raises(ParamError, match="width must be 0 .the camera's. or at least 8 pixels, got 4"):
        NodeHarness(Planner, params={"width": 4})


def test_compositor_p_until_a_fit_gives_p_and_nan_p_is_no_p():
    """The compositor's p (compositor/medium_p) re-plans until the estimator's fit has given p; a fit without
    an analyzer pair (p NaN) changes σ_t and g only."""
    h = NodeHarness(Planner, params=REPLAN)
    h.deliver("compositor/medium_p", MediumEstimate(p=0.3, scan_id=2))
    first = h.node.scene.medium.dop.depolarization          # δ that gives p 0.3 (tank: 0.2 gives ~0.4)
    assert h.node.counters["replans"] == 1 and first > 0.2
    assert not h.node.fitted_p
    nan_p = MediumEstimate(p=float("nan"), sigma_t_per_m=8.0, mean_cosine=0.9, scan_id=3)
    h.deliver("medium/estimate", nan_p)
    assert h.node.counters["replans"] == 2 and h.node.scene.medium.sigma_t == pytest.approx(8.0)
    assert h.node.scene.medium.dop.depolarization == first and not h.node.fitted_p
    h.deliver("medium/estimate", MediumEstimate(p=0.6, sigma_t_per_m=8.0, mean_cosine=0.9, scan_id=4))
    fitted = h.node.scene.medium.dop.depolarization
    assert h.node.counters["replans"] == 3 and h.node.fitted_p and fitted < first
    h.deliver("compositor/medium_p", MediumEstimate(p=0.1, scan_id=5))  # the fit's p outranks it
    assert h.node.counters["replans"] == 3 and h.node.scene.medium.dop.depolarization == fitted


def test_a_frame_budget_plans_the_fewest_sheets_that_fit_it():
    """30 stripes in 20 frames of a polarized scan (two analyzer passes): 10 frames a pass, 3 sheets each;
    the separation is one where three sheets stay apart in the image over the chart's depth range."""
    h = NodeHarness(Planner, name="planner", namespace="/rig", params={**CHEAP, "max_frames": 20})
    plan = h.call("planner/plan", Empty())
    assert plan.sheets == 3
    allowed = plan.curves["sheets_allowed"].astype(bool)
    assert allowed.any() and allowed[list(plan.curves["separation_m"]).index(plan.separation_m)]
    with pytest.raises(ParamError, match="max_frames"):
        NodeHarness(Planner, name="planner", namespace="/rig", params={**FAST, "max_frames": 20,
                                                                       "modality": "flood"})


def test_the_error_measure_plans_at_the_planners_draft_level():
    h = NodeHarness(Planner, name="planner", namespace="/rig",
                    params={**CHEAP, "fidelity": "draft", "publish_on_start": False})
    plan = h.call("planner/plan", Empty())
    assert FAST["d_min_m"] <= plan.separation_m <= FAST["d_max_m"]
    assert h.node.params.fidelity == "draft" and np.all(np.isfinite(plan.curves["objective"]))
