"""Circular light against the stored polarized Mitsuba 3 references (tests/data/mitsuba_polarized, the
``circ_`` scenes: the default source polarizer at 90° and a quarter-wave plate at 45°, V_L = +1; see its
README.md). The truth's S0..S3 are in the camera frame (r, u) as the model's (checked through physical
analyzer sheets in front of the camera, docs/physics.md §5.1); the circular analyzers are the plate at 45°
with the polarizer at 90° (passes V > 0: E_b, the backscatter's V < 0) and at 0° (E_w)."""

from pathlib import Path

import numpy as np
import pytest
from polarstripe.bench.mitsuba_polarized_references import SCENES, circular, dop, file_stem, polarized_scene
from polarstripe.bench.mitsuba_references import regions
from polarstripe.sim.polarization import analyzer
from polarstripe.sim.render import render_components

DATA = Path(__file__).resolve().parents[1] / "data" / "mitsuba_polarized"
SS = 4                     # the model at 4× the references' resolution, box-filtered as Mitsuba's pixels
DOP_TOL = 0.03             # all orders, absolute (as the linear light's DOP)
LEVEL_TOL = {"standard": 0.10, "preview": 0.25}    # E_b, E_w per region (relative), as the intensity's
CIRCULAR = [n for n in SCENES if n.startswith("circ_")]


def _truth(name: str, depth: int) -> tuple[np.ndarray, np.ndarray]:
    """Stokes region means (4, 3) of the seed mean, and the seed spread (rows S0 %, DOP, V)."""
    path = DATA / f"{file_stem(name, depth)}.npz"
    assert path.exists(), f"missing {path} (python -m polarstripe.bench.mitsuba_polarized_references)"
    z = np.load(path)
    return z["regions"].mean(0), z["spread"]


def _model(name: str, level: str, orders: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Stokes region means (4, 3), and E_b, E_w through the circular analyzers (3,) each."""
    scene = polarized_scene(name)
    w, h = scene.camera.resolution
    cam = scene.camera.replace(resolution=(w * SS, h * SS),
                               polarizer=scene.camera.polarizer.replace(quarter_wave_deg=45.0))
    c = render_components(scene.replace(camera=cam), "flood", level, need=("B", "p"), orders=orders)

    def reg(a):
        return regions(a.reshape(h, SS, w, SS).mean(axis=(1, 3)))

    e_b, e_w = (reg(analyzer(c, a, extinction_ratio=np.inf)) for a in (90.0, 0.0))
    return np.stack([reg(c.B), reg(c.Bq), reg(c.Bu), reg(c.Bv)]), e_b, e_w


@pytest.mark.parametrize("name", CIRCULAR)
def test_stored_circular_reference(name):
    """Complete files, and the physics the truth must show: V < 0 everywhere (the helicity flips), |V| at
    most 1 − 2δ = 0.6 (m44/m11 straight back) in single scattering."""
    for depth in SCENES[name][4]:
        z = np.load(DATA / f"{file_stem(name, depth)}.npz")
        assert polarized_scene(name).projector.polarization.quarter_wave_deg == 45.0
        assert z["stokes"].shape == (len(z["seeds"]), 4, 32, 32) and len(z["seeds"]) >= 2
        v = circular(z["regions"].mean(0))
        assert np.all(v < 0), v
        if depth == 2:
            assert np.all(-v <= 0.6 + 1e-3)


@pytest.mark.parametrize("name", CIRCULAR)
def test_single_scattering_v_and_circular_frames_match_max_depth_2(name):
    """The gate: Mitsuba's max_depth = 2 is the model's single scattering for circular light: V/S0 and the
    linear DOP within 0.01 per region, the frames through both circular analyzers within 1 % (plus the seed
    spread)."""
    t, spread = _truth(name, 2)
    m, e_b, e_w = _model(name, "reference", "single")
    np.testing.assert_allclose(circular(m), circular(t), atol=0.01)
    np.testing.assert_allclose(dop(m), dop(t), atol=0.01)
    tol = 0.01 + float(spread[0].max())
    np.testing.assert_allclose(e_b / (0.5 * (t[0] + t[3])), 1.0, atol=tol)
    np.testing.assert_allclose(e_w / (0.5 * (t[0] - t[3])), 1.0, atol=tol)


@pytest.mark.parametrize("level", list(LEVEL_TOL))
@pytest.mark.parametrize("name", CIRCULAR)
def test_all_orders_circular_light_matches_the_truth(name, level):
    """All orders: V/S0 (the DOP a circular analyzer sees) and the linear DOP (what orders ≥ 2 make of the
    light, KAPPA_MADE) within 0.03 per region, the frames through the circular analyzers within the level's
    intensity tolerance plus the seed spread."""
    t, spread = _truth(name, -1)
    m, e_b, e_w = _model(name, level, "all")
    np.testing.assert_allclose(circular(m), circular(t), atol=DOP_TOL, err_msg=f"{name} at {level}: V")
    np.testing.assert_allclose(dop(m), dop(t), atol=DOP_TOL, err_msg=f"{name} at {level}: linear DOP")
    tol = LEVEL_TOL[level] + float(spread[0].max())
    np.testing.assert_allclose(e_b / (0.5 * (t[0] + t[3])), 1.0, atol=tol, err_msg=f"{name} at {level}: E_b")
    np.testing.assert_allclose(e_w / (0.5 * (t[0] - t[3])), 1.0, atol=tol, err_msg=f"{name} at {level}: E_w")


def test_circular_dictionary(monkeypatch):
    """The plate follows the polarizer sheet on the light's way (1 mm further), as a retarder whose fast axis
    is at quarter_wave_deg, both sheets proper rotations."""
    import sys

    from polarstripe.sim.mitsuba_polarized import POLARIZER, SHEET_DISTANCE_M, to_mitsuba_polarized

    monkeypatch.setitem(sys.modules, "mitsuba", None)
    scene = polarized_scene("circ_tthg08_s5")
    d = to_mitsuba_polarized(scene, native=False)
    pol, ret = d["polarizer"], d["retarder"]
    assert pol["bsdf"] == {"type": POLARIZER, "angle_deg": 90.0}
    assert ret["bsdf"] == {"type": POLARIZER, "angle_deg": 45.0, "retarder": True}
    f = np.subtract(scene.projector.look_at, scene.projector.position)
    f /= np.linalg.norm(f)
    for sheet, dist in ((pol, SHEET_DISTANCE_M), (ret, 2 * SHEET_DISTANCE_M)):
        np.testing.assert_allclose(sheet["to_world"][:3, 3], np.add(scene.projector.position, dist * f))
        assert np.linalg.det(sheet["to_world"][:3, :3]) > 0


@pytest.mark.long
def test_the_analyzer_formula_is_what_sheets_before_the_camera_pass():
    """Convention check of docs/physics.md §5.1 through physical optics: Mitsuba renders single scattering of
    circular light through an ideal quarter-wave plate and polarizer sheet in front of a narrow camera (proper
    transforms, local x = image right); the model's analyzer with the same plate and angle within 3 %."""
    pytest.importorskip("mitsuba")
    import mitsuba as mi
    from polarstripe.sim.mitsuba_polarized import POLARIZER, VARIANT, register, to_mitsuba_polarized
    from polarstripe.sim.mitsuba_scene import _native, select_variant

    s = polarized_scene("circ_tthg08_s5")
    s = s.replace(camera=s.camera.replace(resolution=(4, 4), fov_deg=20.0))
    select_variant(VARIANT)
    register()

    def sheet(z, angle, retarder):
        m = np.eye(4)
        m[0, 0], m[1, 1], m[2, 2], m[2, 3] = -0.05, 0.05, -1.0, z      # x = r = −x_world, y = u, z = r × u
        bsdf = {"type": POLARIZER, "angle_deg": angle, **({"retarder": True} if retarder else {})}
        return {"type": "rectangle", "to_world": m, "bsdf": bsdf}

    for alpha, phi in ((45.0, 0.0), (45.0, 90.0), (30.0, 100.0)):
        d = to_mitsuba_polarized(s, max_depth=2, spp=2048, native=False)
        d["an_pol"], d["an_qwp"] = sheet(-0.04, phi, False), sheet(-0.03, alpha, True)
        img = np.array(mi.render(mi.load_dict(_native(d)), spp=2048, seed=1), dtype=np.float64)
        truth = img[..., 1].mean()
        big = s.replace(camera=s.camera.replace(resolution=(16, 16), polarizer=s.camera.polarizer.replace(
            quarter_wave_deg=alpha)))
        c = render_components(big, "flood", "reference", need=("B", "p"), orders="single")
        assert analyzer(c, phi, extinction_ratio=np.inf).mean() == pytest.approx(truth, rel=0.03)
