"""The surface term A from the source side: the pattern-pixel rule's solid angles and a thin beam's A."""

import math

import numpy as np
import pytest
from polarstripe.sim.patterns import parse_pattern
from polarstripe.sim.scene import Medium, Phase, PlaneObject, Projector, Scene, load_scene
from polarstripe.sim.surface_term import beam_nodes, surface_scatter_beams
from polarstripe.sim.transport import make_source
from scipy.integrate import quad


def _rect_solid_angle(a0, a1, b0, b1):
    """Solid angle of the rectangle [a0, a1]×[b0, b1] on the plane at distance 1 (closed form)."""

    def f(a, b):
        return math.atan(a * b / math.sqrt(1 + a * a + b * b))

    return f(a1, b1) - f(a0, b1) - f(a1, b0) + f(a0, b0)


@pytest.mark.parametrize("pattern, cols", [("flood", (0, 1024)), ("stripe:3/30", (102, 136)),
                                           ("stripe:20/30", (682, 716))])
def test_node_weights_add_up_to_the_lit_rectangles_solid_angle(pattern, cols):
    """Σ weights over each point's triangles is ∫ dΩ over the lit rectangle, wherever the point's own pattern
    pixel (the triangles' apex) lies: inside, on the edge of or outside the stripe."""
    scene = load_scene(None)
    src = make_source(scene, parse_pattern(pattern))
    fr = src.frame
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(-0.25, 0.25, 12), rng.uniform(-0.2, 0.2, 12), np.full(12, 0.38)])
    c0, c1 = cols
    a0, a1, b = (c0 - fr.w / 2) * fr.s, (c1 - fr.w / 2) * fr.s, fr.h / 2 * fr.s
    want = _rect_solid_angle(a0, a1, -b, b)
    nodes = beam_nodes(src, pts, 16)
    np.testing.assert_allclose(nodes.weight.sum(axis=1), want, rtol=1e-11)      # converged
    assert nodes.col.min() >= c0 - 1e-9 and nodes.col.max() <= c1 + 1e-9
    np.testing.assert_allclose(beam_nodes(src, pts, 4).weight.sum(axis=1), want, rtol=5e-3)   # side = 4


def test_thin_beam_a_is_its_solid_angle_times_the_line_integral_along_the_axis(ref):
    """A projector of 0.02° lights one beam L + t·k: A(O) → (ρ/π) e^{−σ_t ℓ_CO}·Ω·∫ σ_s P I0
    e^{−σ_t(t + d_XO)} n·(X − O)/d_XO³ dt (docs/physics.md §2.4), Ω its solid angle; adaptive quadrature."""
    st, alb, g, rho = 2.0, 0.9, 0.5, 0.7
    L = np.array([0.1, 0.0, 0.0])
    scene = Scene(medium=Medium(sigma_t=st, albedo=alb, phase=Phase("hg", g)),
                  projector=Projector(position=tuple(L), look_at=(0.1, 0.0, 0.38), fov_deg=0.02,
                                      resolution=(4, 4)),
                  objects=(PlaneObject(point=(0.0, 0.0, 0.38), normal=(0.0, 0.0, -1.0)),))
    src = make_source(scene, parse_pattern("flood"))
    mueller = ref.mueller_intensity(scene)         # the polarized source's m12 (docs/physics.md §5)
    O, n = np.array([0.0, 0.0, 0.38]), np.array([0.0, 0.0, -1.0])
    got = surface_scatter_beams(src, scene.objects, np.zeros(3), O[None], n[None], np.array([rho]), 32, 8)[0]
    k = np.array([0.0, 0.0, 1.0])
    half = math.tan(math.radians(0.01))
    omega = _rect_solid_angle(-half, half, -half, half)

    def f(t):
        v = O - (L + t * k)                           # X → O
        d = np.linalg.norm(v)
        mu = k @ v / d
        p = (1 - g * g) / (4 * math.pi * (1 + g * g - 2 * g * mu) ** 1.5) * mueller(k, v / d)
        return alb * st * p * math.exp(-st * (t + d)) * (-(n @ v)) / d ** 3

    want = rho / math.pi * math.exp(-st * 0.38) * omega * quad(f, 0.0, 0.38, epsabs=0, epsrel=1e-12)[0]
    assert got == pytest.approx(want, rel=1e-6)
