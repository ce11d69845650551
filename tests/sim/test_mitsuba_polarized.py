"""The stored polarized Mitsuba 3 references (tests/data/mitsuba_polarized, see its README.md) against the
model's backscatter polarization, and the polarized scene's dictionary. Only the tests marked ``mitsuba``
at the end render (they are skipped without Mitsuba)."""

import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest
from polarstripe.bench.mitsuba_polarized_references import SCENES, dop, file_stem, polarized_scene
from polarstripe.bench.mitsuba_references import regions
from polarstripe.sim.mitsuba_polarized import PHASE, POLARIZER, lobes, mueller_elements, to_mitsuba_polarized
from polarstripe.sim.phase import evaluate
from polarstripe.sim.polarization import analyzer, pair_retention, rayleigh_mueller
from polarstripe.sim.render import render_components
from polarstripe.sim.scene import SceneError, scene_from_dict

DATA = Path(__file__).resolve().parents[1] / "data" / "mitsuba_polarized"
SS = 4                     # the model at 4× the references' resolution, box-filtered as Mitsuba's pixels
DOP_TOL = 0.03             # all orders: the model's DOP per region vs the truth's (absolute)
LEVEL_TOL = {"standard": 0.10, "preview": 0.25}    # E_b, E_w per region (relative), as the intensity's


def _load(name: str, depth: int) -> dict:
    path = DATA / f"{file_stem(name, depth)}.npz"
    assert path.exists(), f"missing {path} (python -m polarstripe.bench.mitsuba_polarized_references)"
    z = np.load(path)
    return {k: z[k] for k in z.files}


def _truth(name: str, depth: int) -> np.ndarray:
    """Stokes region means (4, 3) of the seed mean."""
    return _load(name, depth)["regions"].mean(0)


def _model(name: str, level: str, orders: str) -> np.ndarray:
    """(B, E_b, E_w, DOP) region means (4, 3) of the model: E_b through an ideal analyzer at 0° (crossed with
    the vertical backscatter polarization), E_w at 90°; DOP from the region means of the Stokes images."""
    scene = polarized_scene(name)
    w, h = scene.camera.resolution
    big = scene.replace(camera=scene.camera.replace(resolution=(w * SS, h * SS)))
    c = render_components(big, "flood", level, need=("B", "p"), orders=orders)

    def reg(a):
        return regions(a.reshape(h, SS, w, SS).mean(axis=(1, 3)))

    stokes = np.stack([reg(c.B), reg(c.Bq), reg(c.Bu), np.zeros(3)])
    e_b, e_w = (reg(analyzer(c, a, extinction_ratio=np.inf)) for a in (0.0, 90.0))
    return np.stack([stokes[0], e_b, e_w, dop(stokes)])


def _truth_frames(s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(E_b, E_w, DOP) of truth Stokes region means (4, 3)."""
    return 0.5 * (s[0] + s[1]), 0.5 * (s[0] - s[1]), dop(s)


LINEAR = [n for n in SCENES if not n.startswith("circ_")]        # circular light: test_mitsuba_circular.py
STORED = [(n, d) for n in LINEAR for d in SCENES[n][4]]


@pytest.mark.parametrize("name,depth", STORED)
def test_stored_reference_is_complete(name, depth):
    z = _load(name, depth)
    scene = polarized_scene(name)
    assert scene_from_dict(tomllib.loads(str(z["scene_toml"]))) == scene
    assert int(z["max_depth"]) == depth and bool(z["m12"])
    st = z["stokes"]
    assert st.shape == (len(z["seeds"]), 4, 32, 32) and len(z["seeds"]) >= 2
    assert np.all(np.isfinite(st)) and np.all(st[:, 0] > 0)
    np.testing.assert_allclose(z["regions"], [[regions(c) for c in im] for im in st], rtol=1e-4, atol=1e-7)
    assert np.all(z["spread"][0] < 0.05) and np.all(z["spread"][1] < 0.02), f"spread {z['spread']}"
    assert np.all(np.abs(z["regions"][:, 3]) < 1e-6)            # linear light only: S3 = 0
    # vertical source polarization, horizontal baseline: the backscatter is polarized vertically (S1 < 0)
    assert np.all(z["regions"][:, 1] < 0) and np.all(np.abs(z["regions"][:, 2]) < 0.05 * z["regions"][:, 0])


@pytest.mark.parametrize("name", LINEAR)
def test_single_scattering_dop_matches_max_depth_2(name):
    """Mitsuba's max_depth = 2 with the Mueller phase function is the model's single scattering: its DOP
    (eq. 15 generalised, docs/physics.md §5) within 0.01 per region."""
    truth = dop(_truth(name, 2))
    ours = _model(name, "reference", "single")[3]
    np.testing.assert_allclose(ours, truth, atol=0.01)


@pytest.mark.parametrize("name", LINEAR)
def test_single_scattering_frames_match_max_depth_2(name):
    """The frames through the analyzer at 0° (E_b) and 90° (E_w) equal Mitsuba's max_depth = 2 within 1 %
    (plus the seed spread) per region: the intensity includes m12·Q_in (docs/physics.md §5)."""
    z = _load(name, 2)
    e_b, e_w, _ = _truth_frames(z["regions"].mean(0))
    ours = _model(name, "reference", "single")
    tol = 0.01 + float(z["spread"][0].max())
    np.testing.assert_allclose(ours[1] / e_b, 1.0, atol=tol, err_msg=f"{name}: E_b")
    np.testing.assert_allclose(ours[2] / e_w, 1.0, atol=tol, err_msg=f"{name}: E_w")


@pytest.mark.parametrize("level", list(LEVEL_TOL))
@pytest.mark.parametrize("name", LINEAR)
def test_all_orders_frames_match_the_truth(name, level):
    """All orders: E_b and E_w per region within the level's intensity tolerance (10 % standard, 25 %
    preview; docs/physics.md §10.5) plus the truth's seed spread."""
    z = _load(name, -1)
    e_b, e_w, _ = _truth_frames(z["regions"].mean(0))
    ours = _model(name, level, "all")
    tol = LEVEL_TOL[level] + float(z["spread"][0].max())
    np.testing.assert_allclose(ours[1] / e_b, 1.0, atol=tol, err_msg=f"{name} at {level}: E_b")
    np.testing.assert_allclose(ours[2] / e_w, 1.0, atol=tol, err_msg=f"{name} at {level}: E_w")


@pytest.mark.parametrize("level", list(LEVEL_TOL))
@pytest.mark.parametrize("name", LINEAR)
def test_all_orders_dop_matches_the_truth(name, level):
    """All orders: the backscatter DOP per region within 0.03 of the polarized truth (docs/physics.md
    §10.4)."""
    truth = dop(_truth(name, -1))
    ours = _model(name, level, "all")[3]
    np.testing.assert_allclose(ours, truth, atol=DOP_TOL, err_msg=f"{name} at {level}: DOP model vs truth")


def test_order_two_keeps_kappa_of_order_one_for_isotropic_scattering():
    """With isotropic scattering (hardly any forward cone) the truth's second order keeps κ of the first
    order's DOP at the image centre, κ the pair quadrature of the full phase function (docs/physics.md
    §10.4): the Mueller product with m12 in each event's intensity, not the per-event normalised one."""
    s1, s2 = _truth("iso_a08_s5", 2), _truth("iso_a08_s5", 3)
    ratio = dop(s2 - s1)[2] / dop(s1)[2]
    kappa = pair_retention(lambda a, b: np.full(np.shape(a), 0.25 / np.pi), 0.2)
    assert ratio == pytest.approx(kappa, abs=0.04)


def test_dop_falls_with_order_in_the_default_tank():
    """Per order (max_depth k + 1 minus k) the truth's DOP falls monotonically at the image centre, by about
    1 − δ per order in the paper's TTHG 0.8 (most scatterings are inside the forward cone)."""
    depths = SCENES["tthg08_s5"][4][:-1]
    prev, dops = None, []
    for d in depths:
        s = _truth("tthg08_s5", d)
        dops.append(dop(s if prev is None else s - prev)[2])
        prev = s
    assert all(a > b for a, b in zip(dops, dops[1:], strict=False)), dops
    ratios = np.array(dops[1:]) / np.array(dops[:-1])
    assert np.all(np.abs(ratios - 0.8) < 0.08), ratios


# ------------------------------------------------------------------------------------- the dictionary

@pytest.fixture
def no_mitsuba(monkeypatch):
    monkeypatch.setitem(sys.modules, "mitsuba", None)
    monkeypatch.setitem(sys.modules, "drjit", None)


def test_polarized_dictionary(no_mitsuba):
    scene = polarized_scene("tthg08_s5")
    d = to_mitsuba_polarized(scene, max_depth=2, native=False)
    assert d["integrator"] == {"type": "stokes", "integrator": {"type": "volpath", "max_depth": 2,
                                                                "rr_depth": 100000}}
    ph = d["water"]["phase"]
    assert ph["type"] == PHASE and ph["depolarization"] == 0.2 and ph["m12"] is True
    assert (ph["g1"], ph["g2"], ph["w1"]) == lobes(scene.medium.phase)
    assert d["light"]["intensity"]["value"] == 2.0                   # the ideal polarizer passes half
    sheet = d["polarizer"]
    assert sheet["bsdf"] == {"type": POLARIZER, "angle_deg": 90.0}
    m = sheet["to_world"]
    f = np.subtract(scene.projector.look_at, scene.projector.position)
    # a proper transform: local x, y = projector right, up and z = r × u = −f (a mirrored frame turns the
    # sheet's axis angle a into −a)
    np.testing.assert_allclose(m[:3, 2], -f / np.linalg.norm(f))
    assert np.linalg.det(m[:3, :3]) > 0
    np.testing.assert_allclose(m[:3, 3], scene.projector.position + 1e-3 * f / np.linalg.norm(f))
    # the sheet covers the tank as seen from the source and stays clear of the camera
    assert np.linalg.norm(m[:3, 3] - scene.camera.position) > 0.1
    unpol = scene.replace(projector=scene.projector.replace(
        polarization=scene.projector.polarization.replace(dop=0.0)))
    d0 = to_mitsuba_polarized(unpol, native=False)
    assert "polarizer" not in d0 and d0["light"]["intensity"]["value"] == 1.0
    with pytest.raises(SceneError, match="dop"):
        to_mitsuba_polarized(scene.replace(projector=scene.projector.replace(
            polarization=scene.projector.polarization.replace(dop=0.5))), native=False)
    with pytest.raises(SceneError, match="point"):
        to_mitsuba_polarized(scene.replace(projector=scene.projector.replace(model="pinhole")), native=False)


@pytest.mark.parametrize("model,g", [("tthg", 0.8), ("hg", 0.95), ("isotropic", 0.0)])
def test_mueller_elements_are_the_phase_function_times_the_normalised_rayleigh_matrix(model, g):
    """m11 is P; m12, m22, m33 are P·(M_R/m11_R) of docs/physics.md §5; the lobes add up to P."""
    from polarstripe.sim.scene import Phase

    mu = np.linspace(-1, 1, 41)
    ph = Phase(model, g)
    p = evaluate(ph, 1 - mu, 1 + mu)
    m11, m12, m22, m33, _ = mueller_elements(mu, p, 0.2)
    r11, r12, r22, r33 = rayleigh_mueller(1 - mu, 1 + mu, 0.2)
    np.testing.assert_allclose(m11, p, rtol=1e-12)
    np.testing.assert_allclose([m12, m22, m33], [p * r12 / r11, p * r22 / r11, p * r33 / r11], rtol=1e-12)
    g1, g2, w1 = lobes(ph)

    def hg(gg):
        return (1 - gg * gg) / (4 * np.pi * (1 + gg * gg - 2 * gg * mu) ** 1.5)

    np.testing.assert_allclose(w1 * hg(g1) + (1 - w1) * hg(g2), p, rtol=1e-9)


# ------------------------------------------------------------------------------- renders (need Mitsuba)

@pytest.mark.long
def test_rayleigh_scattering_at_90_degrees_is_fully_polarized():
    """Gate of the truth: an unpolarized source, pure Rayleigh (δ = 0), a thin slab seen at 90° to the light
    by a narrow camera: S1/S0 → −1 (polarized ⊥ the scattering plane, i.e. vertical in the image) as
    1 − cos²θ/(1 + cos²θ) ≥ 0.99 over the camera's few degrees."""
    pytest.importorskip("mitsuba")
    from polarstripe.sim.mitsuba_polarized import render_stokes
    from polarstripe.sim.scene import Medium, Phase, load_scene

    s = load_scene(None)
    med = Medium(sigma_t=1.0, albedo=1.0, phase=Phase("isotropic", 0.0), extent=s.medium.extent.replace(
        min=(-0.3, -0.3, 0.19), max=(0.3, 0.3, 0.21)), dop=s.medium.dop.replace(depolarization=0.0))
    cam = s.camera.replace(position=(0.0, 0.0, -0.05), look_at=(0.0, 0.0, 0.2), fov_deg=4.0,
                           resolution=(4, 4))
    src = s.projector.replace(model="point", position=(0.5, 0.0, 0.2), look_at=(0.0, 0.0, 0.2),
                              polarization=s.projector.polarization.replace(dop=0.0))
    st = render_stokes(s.replace(medium=med, camera=cam, projector=src, objects=()), max_depth=2, spp=4096)
    tot = st.reshape(4, -1).sum(1)
    assert -tot[1] / tot[0] > 0.99 and abs(tot[2] / tot[0]) < 0.01
