"""The scenes the all-orders model is validated on against Mitsuba 3 (``tests/data/mitsuba/own_*``).

Besides the paper's tank under a point source (``bench/mitsuba_references.py``: σ_t = 1, 2.5, 5, 8 1/m), these
cover what that set does not: projector patterns (stripes, checkers), clear water, albedo 0.5–1, HG and TTHG
phase functions with mean cosines 0.5–0.95, a medium without objects, and a sphere. Every scene is the tank
(60 × 60 × 38 cm) with camera and source 5 cm in front of the entry face (a point light inside the medium
gives Mitsuba's estimator infinite variance), a 32 × 32 camera of 60° looking along +z, the source 20 cm
beside it, aimed at the back wall's centre, and (except ``medium_hg08_s3``) a 0.6 × 0.6 m Lambertian wall of
albedo 0.6.

``polarstripe bench fidelity --render-references`` renders them (two seeds each) and
``tests/sim/test_all_orders.py`` compares the model with the stored images, without Mitsuba.
"""

from __future__ import annotations

from typing import NamedTuple

from polarstripe.sim.scene import Phase, PlaneObject, Scene, SphereObject, load_scene

RESOLUTION = 32
OUTSIDE_M = 0.05
SEPARATION_M = 0.2


class Case(NamedTuple):
    """One validation scene: what it tests, the pattern, and the Mitsuba samples per pixel per seed."""

    scene: Scene
    pattern: str
    spp: int
    what: str


def _tank(sigma_t: float, albedo: float, phase: Phase, *, point: bool = False, wall: bool = True,
          extra=()) -> Scene:
    s = load_scene(None)
    lo, hi = s.medium.extent.min, s.medium.extent.max
    z = lo[2] - OUTSIDE_M
    cam = s.camera.replace(position=(0.0, 0.0, z), look_at=(0.0, 0.0, hi[2]),
                           resolution=(RESOLUTION, RESOLUTION))
    proj = s.projector.replace(model="point" if point else "pinhole", position=(SEPARATION_M, 0.0, z),
                               polarization=s.projector.polarization.replace(dop=0.0),
                               look_at=(0.0, 0.0, hi[2]))
    objs = tuple(extra)
    if wall:
        objs += (PlaneObject(point=(0.0, 0.0, hi[2]), normal=(0.0, 0.0, -1.0),
                             size=(hi[0] - lo[0], hi[1] - lo[1]), albedo=0.6),)
    return s.replace(medium=s.medium.replace(sigma_t=float(sigma_t), albedo=float(albedo), phase=phase),
                     camera=cam, projector=proj, objects=objs)


def cases() -> dict[str, Case]:
    """The validation scenes by name (stable: the stored references are named after them)."""
    tthg = Phase("tthg", 0.8)
    ball = SphereObject(center=(0.03, -0.02, 0.24), radius=0.07, albedo=0.8)
    return {
        "stripe_tthg08_s5": Case(_tank(5.0, 1.0, tthg), "stripe:3/8", 16384,
                                 "a stripe (1/8 of the projector) in the paper's medium, sigma_t = 5"),
        "checker_tthg08_s25": Case(_tank(2.5, 1.0, tthg), "checker:128:0", 16384,
                                   "checkers of 128 projector pixels, sigma_t = 2.5"),
        "clear_coastal_hg09": Case(_tank(0.4, 0.55, Phase("hg", 0.9)), "flood", 8192,
                                   "clear coastal water: c = 0.4 1/m, albedo 0.55, HG 0.9"),
        "hg05_albedo05_s8": Case(_tank(8.0, 0.5, Phase("hg", 0.5)), "flood", 16384,
                                 "absorbing, weakly forward: albedo 0.5, HG 0.5, sigma_t = 8"),
        "hg095_albedo08_s5": Case(_tank(5.0, 0.8, Phase("hg", 0.95)), "flood", 16384,
                                  "strongly forward: albedo 0.8, HG 0.95, sigma_t = 5"),
        "tthg05_albedo09_s6": Case(_tank(6.0, 0.9, Phase("tthg", 0.5)), "stripe:4/8", 16384,
                                   "TTHG 0.5, albedo 0.9, sigma_t = 6, a stripe"),
        "medium_hg08_s3": Case(_tank(3.0, 0.95, Phase("hg", 0.8), point=True, wall=False), "flood", 16384,
                               "medium only, HG 0.8, albedo 0.95, point source, sigma_t = 3"),
        "sphere_checker_s3": Case(_tank(3.0, 0.98, Phase("tthg", 0.9), extra=(ball,)), "checker:64:0", 16384,
                                  "a sphere before the wall, checkers of 64 pixels, TTHG 0.9, sigma_t = 3"),
    }


def file_stem(name: str) -> str:
    return f"own_{name}"
