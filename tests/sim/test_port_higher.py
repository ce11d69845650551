"""The higher orders through flat ports (sim/port_higher.py, docs/physics.md §11): the source side by power
conservation (the grid's flux against I0·∫T dΩ over the projector's frustum, T from Fresnel's equations
written here), and a port of indices 1 against the pinhole model's all orders (both sides). The camera side
against Mitsuba: tests/sim/test_mitsuba_port.py."""

from __future__ import annotations

import dataclasses
import math
import sys
from pathlib import Path

import numpy as np
import pytest
from polarstripe.sim.grid_sources import source_field
from polarstripe.sim.multiple import make_grid
from polarstripe.sim.patterns import parse_pattern
from polarstripe.sim.port import port_geometry
from polarstripe.sim.render import render_components, resolve_fidelity
from polarstripe.sim.scene import load_scene
from polarstripe.sim.scene_port import Port
from polarstripe.sim.transport import make_source

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_port import UNIT, _scene  # noqa: E402

N_G, N_W = 1.5, 1.333


def _fresnel_t(sin_a: np.ndarray) -> np.ndarray:
    """½(T_s1·T_s2 + T_p1·T_p2), air → glass → water, from the Fresnel amplitude coefficients."""
    def face(n1, n2, s1):
        c1, s2 = np.sqrt(1 - s1 ** 2), n1 * s1 / n2
        c2 = np.sqrt(1 - s2 ** 2)
        ts = 2 * n1 * c1 / (n1 * c1 + n2 * c2)
        tp = 2 * n1 * c1 / (n2 * c1 + n1 * c2)
        k = (n2 * c2) / (n1 * c1)
        return k * ts ** 2, k * tp ** 2, s2

    s1, p1, s_g = face(1.0, N_G, sin_a)
    s2, p2, _ = face(N_G, N_W, s_g)
    return 0.5 * (s1 * s2 + p1 * p2)


def _projector_source(port):
    s = load_scene(None)
    pr = s.projector.replace(model="pinhole", position=(0.0, 0.0, 0.0), look_at=(0.0, 0.0, 1.0),
                             up=(0.0, 1.0, 0.0), port=port)
    s = s.replace(projector=pr, objects=())
    src = make_source(s, parse_pattern("flood"))
    return s, dataclasses.replace(src, sigma_t=0.0, dop_l=0.0)     # unpolarized: the port passes T


@pytest.mark.parametrize("glass", [False, True])
def test_source_beams_through_a_port_carry_the_power_that_leaves_it(glass):
    """In a clear box beyond the port every beam crosses the box from face to face, so Σ F_z·V / L_z over the
    cells is the power that left the projector: I0·Ω (Ω = 4·asin(sin α·sin β) of the frustum) without a port,
    I0·∫T dΩ through glass (T from Fresnel's equations, midpoint rule over the frame). The beams are the air
    rays refracted (water_rays), each carrying I0·ΔΩ_air·T."""
    port = Port(distance_m=0.01, thickness_m=0.01, n_glass=N_G, n_water=N_W) if glass else None
    scene, src = _projector_source(port)
    fr = src.frame
    grid = make_grid((-1.5, -1.5, 0.1), (1.5, 1.5, 0.5), 24)
    geo = port_geometry(port, scene.projector.position, fr.f) if glass else None
    field = source_field(grid, src, (), 2.0, geo)
    vol = float(np.prod(grid.h))
    power = float(field.flux[..., 2].sum()) * vol / 0.4
    a, b = math.atan(fr.w / 2 * fr.s), math.atan(fr.h / 2 * fr.s)
    if not glass:
        expect = src.intensity * 4 * math.asin(math.sin(a) * math.sin(b))
    else:
        k = 400
        x = (np.arange(k) + 0.5) / k - 0.5
        X, Y = np.meshgrid(x * fr.w * fr.s, x * fr.h * fr.s, indexing="ij")
        r2 = X ** 2 + Y ** 2
        d_omega = (fr.w * fr.s / k) * (fr.h * fr.s / k) / (1 + r2) ** 1.5
        expect = src.intensity * float((_fresnel_t(np.sqrt(r2 / (1 + r2))) * d_omega).sum())
        assert 0.9 < expect / (src.intensity * 4 * math.asin(math.sin(a) * math.sin(b))) < 0.96
    assert power == pytest.approx(expect, rel=0.01)


def _no_interpolation(level):
    """``level`` with B's single wide-angle scattering at every pixel (the port's B has no coarse grid)."""
    f = resolve_fidelity(level)
    return dataclasses.replace(f, higher=dataclasses.replace(f.higher, b_div=1))


@pytest.mark.parametrize("pattern", ["flood", "stripe:12/30", "checker:64:32"])
def test_all_orders_through_a_port_of_index_one_are_the_pinhole(pattern):
    """Camera and projector behind ports of indices 1: every order equals the pinhole model's (validated
    against Mitsuba): D, A, B and B's Stokes to 1e-3 of their peaks (measured 2e-4) on whole frames and at
    pixels (the forward-cone stencils)."""
    fid = _no_interpolation("preview")
    px = np.array([[18, c] for c in range(4, 44, 3)])
    for pixels in (None, px):
        pin = render_components(_scene(sigma_t=4.0), pattern, fid, pixels=pixels)
        port = render_components(_scene(UNIT, UNIT, sigma_t=4.0), pattern, fid, pixels=pixels)
        assert pin.orders.modelled and port.orders.modelled
        for k, tol in (("D", 1e-3), ("A", 1e-3), ("B", 1e-3), ("Bq", 1e-3), ("Bu", 1e-3)):
            a, b = getattr(pin, k), getattr(port, k)
            assert np.abs(a).max() > 0 and np.abs(a - b).max() <= tol * np.abs(a).max(), (k, pixels is None)


def test_glass_ports_all_orders_add_to_single_scattering():
    """Behind glass ports the higher orders add light to every term but D (which is the same), the frame's
    B grows by more than single scattering's η = 1 − e^{−σ_s ℓ} would say is missing (0.5 here) relative to
    single scattering, and the stripe's light stays a stripe (the peak column lit)."""
    port = Port(distance_m=0.02, thickness_m=0.01, n_glass=N_G, n_water=N_W)
    s = _scene(port, port, sigma_t=3.0)
    one = render_components(s, "stripe:14/30", "preview", orders="single")
    every = render_components(s, "stripe:14/30", "preview")
    assert every.orders.modelled and not one.orders.modelled
    np.testing.assert_array_equal(every.D, one.D)
    assert every.A.sum() > 1.2 * one.A.sum() and every.B.sum() > 1.5 * one.B.sum()
    row = every.D.shape[0] // 2
    assert np.argmax((every.D + every.A)[row]) == np.argmax(one.D[row])


def test_stripes_through_glass_ports_add_up_to_the_flood():
    """Every order through glass ports is linear in the pattern (the beams' lit fractions and the glow
    patches' pattern averages are exact, the grid's map is linear): six stripes' D, A and B add up to the
    flood's to 1e-3 of its peak (measured 0, 1e-7, 7e-5)."""
    port = Port(distance_m=0.02, thickness_m=0.01, n_glass=N_G, n_water=N_W)
    s = _scene(port, port, sigma_t=3.0)
    flood = render_components(s, "flood", "preview")
    stripes = [render_components(s, f"stripe:{k}/6", "preview") for k in range(6)]
    assert flood.orders.modelled
    for k in ("D", "A", "B"):
        total = sum(getattr(c, k) for c in stripes)
        assert np.abs(total - getattr(flood, k)).max() <= 1e-3 * getattr(flood, k).max(), k
