"""All orders of scattering (docs/physics.md §10) against the stored Mitsuba 3 references (tests/data/mitsuba,
no Mitsuba needed), closed forms and limits."""

import math
import time
from pathlib import Path

import numpy as np
import pytest
from polarstripe.sim.render import render_components
from polarstripe.sim.scene import SceneError, load_scene

DATA = Path(__file__).resolve().parents[1] / "data" / "mitsuba"
SS = 4                     # the model is rendered 4×4 finer and box-filtered, as Mitsuba's pixels are
SS_PREVIEW = 20            # preview at 640×640: the half-resolution path of frames ≥ 640×480
TANK = [(s, c) for s in (1.0, 2.5, 5.0, 8.0) for c in ("all_plane", "all_medium")]
OWN = sorted(p.stem for p in DATA.glob("own_*.npz"))
BOUND = {"standard": 0.10, "preview": 0.25}


def regions(img: np.ndarray) -> np.ndarray:
    """Means over the left half, the right half and the central 8×8 block (as the references store)."""
    h, w = img.shape
    return np.array([img[:, : w // 2].mean(), img[:, w // 2:].mean(),
                     img[h // 2 - 4: h // 2 + 4, w // 2 - 4: w // 2 + 4].mean()])


def model(scene, pattern: str, level: str, orders: str = "all") -> np.ndarray:
    w, h = scene.camera.resolution
    ss = SS_PREVIEW if level == "preview" else SS
    big = scene.replace(camera=scene.camera.replace(resolution=(w * ss, h * ss)))
    c = render_components(big, pattern, level, orders=orders)
    return (c.D + c.A + c.B).reshape(h, ss, w, ss).mean(axis=(1, 3))


def reference(stem: str):
    z = np.load(DATA / f"{stem}.npz")
    pattern = str(z["pattern"]) if "pattern" in z.files else "flood"
    return load_scene(DATA / f"{stem}.toml"), pattern, regions(z["images"].astype(float).mean(0)), z["spread"]


@pytest.mark.parametrize("level", ["standard", "preview"])
@pytest.mark.parametrize("sigma,case", TANK)
def test_the_papers_tank_against_all_orders(sigma, case, level):
    """The issue's targets: standard within 10 % (20 % at σ_t = 8), preview within 25 %, halves and centre."""
    scene, pattern, truth, spread = reference(f"{case}_sigma{sigma:g}")
    ratio = regions(model(scene, pattern, level)) / truth
    bound = BOUND[level] * (2.0 if sigma >= 8 and level == "standard" else 1.0)
    assert np.all(np.abs(ratio - 1) <= bound + spread), f"{case} σ_t={sigma} {level}: model/truth {ratio}"


@pytest.mark.parametrize("level", ["standard", "preview"])
@pytest.mark.parametrize("stem", OWN)
def test_own_scenes_against_all_orders(stem, level):
    """Stripes, checkers, clear water, albedo 0.5–1, HG and TTHG 0.5–0.95, a sphere: the same bounds."""
    scene, pattern, truth, spread = reference(stem)
    ratio = regions(model(scene, pattern, level)) / truth
    assert np.all(np.abs(ratio - 1) <= BOUND[level] + spread), f"{stem} {level}: model/truth {ratio}"


def test_own_references_are_present_and_sound():
    assert len(OWN) >= 8
    for stem in OWN:
        z = np.load(DATA / f"{stem}.npz")
        assert z["images"].shape == (2, 32, 32) and int(z["max_depth"]) == -1
        assert np.all(np.isfinite(z["images"])) and np.all(z["spread"] < 0.05)


@pytest.mark.parametrize("stem", ["all_plane_sigma5", "own_stripe_tthg08_s5", "own_hg05_albedo05_s8"])
def test_higher_orders_close_most_of_the_gap(stem):
    """Single scattering misses most of the light at these depths; all orders do not."""
    scene, pattern, truth, _ = reference(stem)
    single = regions(model(scene, pattern, "standard", "single")) / truth
    full = regions(model(scene, pattern, "standard")) / truth
    assert np.all(single < 0.5) and np.all(np.abs(full - 1) < np.abs(single - 1) / 5)


# ------------------------------------------------------------------------------------------ limits

def _small(sigma=5.0, albedo=1.0, res=(48, 36)):
    s = load_scene(None)
    return s.replace(medium=s.medium.replace(sigma_t=sigma, albedo=albedo),
                     camera=s.camera.replace(resolution=res))


def test_without_scattering_all_orders_is_single_scattering():
    for scene in (_small(sigma=0.0), _small(albedo=0.0), _small(sigma=1e-4)):
        a = render_components(scene, "stripe:14/30", "standard")
        b = render_components(scene, "stripe:14/30", "standard", orders="single")
        assert not a.orders.modelled
        for k in ("D", "A", "B", "Bq", "Bu"):
            np.testing.assert_array_equal(getattr(a, k), getattr(b, k))


def test_higher_orders_vanish_as_sigma_goes_to_zero():
    """(all − single)/single falls in proportion to σ_t (the second order is O(σ²) against O(σ))."""
    excess = []
    for sigma in (0.8, 0.4, 0.2):
        a = render_components(_small(sigma), "flood", "standard")
        b = render_components(_small(sigma), "flood", "standard", orders="single")
        assert a.orders.modelled
        tot_a, tot_b = (c.D + c.A + c.B for c in (a, b))
        excess.append(float(tot_a.sum() / tot_b.sum() - 1))
    assert all(e > 0 for e in excess)
    assert excess[1] < 0.65 * excess[0] and excess[2] < 0.65 * excess[1]


def test_the_direct_light_is_the_single_scattering_direct_light():
    a = render_components(_small(), "stripe:14/30", "standard")
    b = render_components(_small(), "stripe:14/30", "standard", orders="single")
    np.testing.assert_array_equal(a.D, b.D)
    assert (a.A >= 0).all() and (a.B >= 0).all() and a.A.sum() > 3 * b.A.sum()


def test_stripes_add_up_to_the_flood_frame_with_all_orders():
    """The higher orders are linear in the source (fixed beams, order count and tail ratio): B to the
    single-scattering quadrature's error, A to the blur's."""
    scene = _small(res=(40, 30))
    flood = render_components(scene, "flood", "standard")
    parts = [render_components(scene, f"stripe:{k}/6", "standard") for k in range(6)]
    np.testing.assert_allclose(sum(p.B for p in parts), flood.B, rtol=1e-5, atol=1e-12)
    np.testing.assert_allclose(sum(p.A for p in parts), flood.A, rtol=0.02, atol=1e-6 * flood.A.max())


def test_requested_pixels_agree_with_the_whole_frame():
    """Requested pixels blur with radial stencils of the halo, whole frames in the image: D agrees, B within
    the frame's interpolation between every 3rd pixel, A within the stencils' quadrature (a few per cent on
    the mean, tens of per cent at a stripe's edge)."""
    scene = _small(res=(96, 72))
    full = render_components(scene, "stripe:14/30", "standard")
    rng = np.random.default_rng(3)
    px = np.stack([rng.integers(0, 72, 40), rng.integers(0, 96, 40)], 1)
    part = render_components(scene, "stripe:14/30", "standard", pixels=px)
    np.testing.assert_array_equal(part.D, full.D[px[:, 0], px[:, 1]])
    np.testing.assert_allclose(part.B, full.B[px[:, 0], px[:, 1]], rtol=0.1)   # frames: B on every 3rd pixel
    a, want = part.A, full.A[px[:, 0], px[:, 1]]
    assert abs(a.sum() / want.sum() - 1) < 0.1
    np.testing.assert_allclose(a, want, rtol=0.35, atol=0.05 * want.max())


def test_dop_falls_with_the_order_of_scattering():
    """Single scattering keeps the Mueller DOP (0.8 at the default tank); the higher orders lower it, more
    as the medium thickens, never above single scattering's."""
    medians = []
    for sigma in (1.0, 5.0, 8.0):
        a = render_components(_small(sigma), "flood", "standard")
        b = render_components(_small(sigma), "flood", "standard", orders="single")
        free = ~a.object_mask
        assert np.all(a.p[free] <= b.p[free] + 1e-9)
        medians.append(float(np.median(a.p[free])))
    assert medians[0] > medians[1] > medians[2] > 0.3


def test_thick_white_medium_ends_finite_and_fast():
    """Albedo 1 at τ = 100 each way: no hang (the orders are a fixed count plus a geometric tail) and no
    blow-up."""
    t = time.perf_counter()
    c = render_components(_small(sigma=100 / 0.38), "flood", "standard")
    assert time.perf_counter() - t < 20
    for k in ("D", "A", "B", "Bq", "Bu"):
        assert np.all(np.isfinite(getattr(c, k)))
    assert c.B.min() > 0 and c.B.max() < 1.0


@pytest.mark.parametrize("model,g", [("hg", 0.999999), ("hg", -0.999999), ("tthg", 0.999999),
                                     ("isotropic", 0.0)])
def test_extreme_phase_functions_are_finite(model, g):
    s = _small(res=(32, 24))
    from polarstripe.sim.scene import Phase

    s = s.replace(medium=s.medium.replace(phase=Phase(model, g)))
    c = render_components(s, "stripe:14/30", "standard")
    for k in ("D", "A", "B", "Bq", "Bu"):
        assert np.all(np.isfinite(getattr(c, k)))
    assert (c.A >= 0).all() and (c.B >= 0).all()


def test_a_source_in_view_keeps_its_forward_halo():
    """A camera looking toward the source: all orders never give less backscatter than single scattering
    (the forward cone's once-scattered light is added back for such rays)."""
    s = _small(sigma=2.0, res=(32, 24))
    proj = s.projector.replace(position=(0.05, 0.0, 0.36), look_at=(0.0, 0.0, 0.0))
    s = s.replace(projector=proj, objects=())
    a = render_components(s, "flood", "standard")
    b = render_components(s, "flood", "standard", orders="single")
    assert np.all(a.B >= b.B)


# ------------------------------------------------------------------------------------------ input

def test_bad_orders_and_need_are_one_clear_error():
    s = _small(res=(8, 6))
    with pytest.raises(SceneError, match="orders must be one of all, single"):
        render_components(s, "flood", "preview", orders="double")
    with pytest.raises(SceneError, match="orders must be one of"):
        render_components(s, "flood", "preview", orders=None)
    with pytest.raises(SceneError, match="need must name components"):
        render_components(s, "flood", "preview", need=("D", "X"))
    with pytest.raises(SceneError, match="cells 2..128"):
        render_components(s, "flood", "cells=1")
    from polarstripe.sim.higher import HigherSettings

    for bad in ({"cells": 1}, {"orders": 0}, {"b_div": 2.5}, {"oversample": -1.0}, {"view_steps": True},
                {"a1_exact": "yes"}):
        with pytest.raises(SceneError, match=f"fidelity.higher.{next(iter(bad))}"):
            HigherSettings(**bad)


def test_orders_plan_says_what_is_modelled():
    a = render_components(_small(), "flood", "preview")
    d = a.orders.as_dict()
    assert d["modelled"] == "all orders" and d["expected_error"] == pytest.approx(0.25)   # preview's bound
    thick = render_components(_small(sigma=30.0), "flood", "standard").orders
    assert thick.tau_s > 8 and 0.1 < thick.expected_error <= 1.0                       # beyond validation
    assert d["similarity"]["theta_c_deg"] == pytest.approx(30.0) and 0 < d["similarity"]["f"] < 1
    s = render_components(_small(), "flood", "preview", orders="single").orders
    assert s.as_dict()["modelled"] == "single scattering" and s.single_error > 0.9
    assert math.isclose(a.orders.tau_s, s.tau_s)


def test_preview_at_half_resolution_keeps_d_exact_and_the_rest_close():
    """Preview frames of 640×480 and more compute all but D and the albedo at half resolution."""
    import dataclasses

    from polarstripe.sim.render import resolve_fidelity

    s = _small(res=(640, 480))
    pv = resolve_fidelity("preview")
    full = dataclasses.replace(pv, name="preview-full", higher=dataclasses.replace(pv.higher, half_res=False))
    a = render_components(s, "stripe:14/30", "preview")
    b = render_components(s, "stripe:14/30", full)
    np.testing.assert_array_equal(a.D, b.D)
    ra, rb = regions(a.D + a.A + a.B), regions(b.D + b.A + b.B)
    np.testing.assert_allclose(ra, rb, rtol=0.05)
    np.testing.assert_allclose(a.B.mean(), b.B.mean(), rtol=0.03)
    assert np.isfinite(a.A).all() and (a.A >= 0).all() and np.all(a.A[~a.object_mask] >= 0)
