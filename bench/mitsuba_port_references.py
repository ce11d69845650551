"""Mitsuba 3 references of a camera behind a flat glass port (docs/physics.md §11), the port model's truth.

``python -m polarstripe.bench.mitsuba_port_references -o tests/data/mitsuba`` writes ``port_<case>.npz`` and
``.toml`` per case, read by ``tests/sim/test_mitsuba_port.py`` (which needs no Mitsuba). The rig is the
stored references' (``bench/mitsuba_references.py``: 32×32 camera and an unpolarized point source 5 cm
outside the tank, 20 cm apart) with the camera behind a port: 5 mm of air, 5 mm of glass (n 1.5), water
(n 1.333, clear up to the tank's face) beyond, Fresnel at both faces. Mitsuba renders the port as two
``dielectric`` rectangles (:func:`polarstripe.sim.mitsuba_scene.to_mitsuba`); ``max_depth = 4`` is single
scattering behind them (two specular vertices, one scattering, the light). The model: D + B (its A is
light → medium → object, depth 5 here).

Cases: ``medium`` (σ_t = 2.5, no object: B), ``chart`` (σ_t = 1, the chart texture on a 0.6 × 0.6 m back
wall: D + B; the bars and the chart's edges place the narrowed field of view); ``all_medium`` (σ_t = 2.5) and
``all_chart`` (σ_t = 2) the same with every order of scattering (``max_depth = −1``: D + A + B of the model's
all orders through the port, docs/physics.md §11).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from polarstripe.bench.mitsuba_references import reference_scene, regions, render_columns, scene_toml
from polarstripe.sim.scene import PlaneObject, Scene
from polarstripe.sim.scene_port import Port

PORT = Port(distance_m=0.005, thickness_m=0.005, n_glass=1.5, n_water=1.333)
CASES = {"medium": (2.5, False, 4), "chart": (1.0, True, 4),      # name: (sigma_t, chart, max_depth)
         "all_medium": (2.5, False, -1), "all_chart": (2.0, True, -1)}
WHAT = {"medium": "medium only: B", "chart": "the chart texture on a 0.6 × 0.6 m back wall: D + B",
        "all_medium": "medium only, all orders: B", "all_chart": "the chart wall, all orders: D + A + B"}


def port_scene(case: str) -> Scene:
    """The reference rig of ``case`` with the camera behind :data:`PORT`."""
    sigma_t, chart, _ = CASES[case]
    s = reference_scene(sigma_t, chart)
    if chart:
        wall = s.objects[0]
        s = s.replace(objects=(PlaneObject(point=wall.point, normal=wall.normal, size=wall.size,
                                           albedo=wall.albedo, texture="chart"),))
    return s.replace(camera=s.camera.replace(port=PORT))


def render_case(case: str, spp: int, seeds: tuple[int, ...], variant: str | None, pass_spp: int) -> dict:
    """Every seed's image of one case and the numbers stored beside it."""
    import mitsuba as mi
    from polarstripe.sim.mitsuba_scene import render_truth, select_variant

    scene = port_scene(case)
    variant = select_variant(variant)
    images, seconds = [], []
    depth = CASES[case][2]
    for seed in seeds:
        t0 = time.perf_counter()
        images.append(render_truth(scene, "flood", max_depth=depth, spp=spp, seed=seed, variant=variant,
                                   pass_spp=pass_spp))
        seconds.append(time.perf_counter() - t0)
    imgs = np.stack(images).astype(np.float32)
    reg = np.stack([regions(im) for im in imgs])
    return {"images": imgs, "seeds": np.array(seeds), "spp": spp, "max_depth": depth,
            "sigma_t": CASES[case][0], "scene_toml": scene_toml(scene), "seconds": np.array(seconds),
            "regions": reg, "spread": (reg.max(0) - reg.min(0)) / reg.mean(0),
            "mitsuba_version": mi.__version__, "variant": variant}


_README = """
## A camera behind a flat glass port (`port_*.npz`)

Written by `python -m polarstripe.bench.mitsuba_port_references -o tests/data/mitsuba` (Mitsuba 3, `volpath`
with `max_depth = 4`: single scattering behind the port's two specular faces, or `max_depth = -1`: all
orders, the `all_*` files; the same sampler and box filter). The rig above with the camera behind a port
(docs/physics.md §11): 5 mm of air, 5 mm of glass (n 1.5), then water (n 1.333, clear up to the tank's
face); Mitsuba's port is two `dielectric` rectangles (`sim/mitsuba_scene.py`), so Fresnel and the n² of
radiance are its own. The source has no port (a delta light behind a dielectric is never reached by a path
tracer). Read by `tests/sim/test_mitsuba_port.py`: the model's D + B (`standard`, single scattering; the
chart at 4×4 pixel centres per Mitsuba pixel) within the seed spread + 1 % in each region (measured 0.15 %
medium, 0.3 % chart, with the port's diattenuation; 0.11 % medium without it), the chart's column profile
within 1.2 %; without the port that profile is off by more than 10 %; all orders (D + A + B, `standard`)
within the seed spread + 10 % (measured 0–2 %; single scattering gives 0.40–0.42 of them).
Each npz holds `images`,
`seeds`, `spp`, `max_depth`, `sigma_t`, `scene_toml`, `seconds` (wall-clock, the shared 2-core machine at
load 8–9), `regions`, `spread`, `mitsuba_version`, `variant`.

| file | what | σ_t [1/m] | spp | seeds | seconds per seed | mean: left / right / centre | seed spread % |
|---|---|---|---|---|---|---|---|
"""


def readme_section(out: Path) -> str:
    """The README section of the ``port_*.npz`` in ``out`` ("" when none): what they are and a row each."""
    rows = []
    for case in CASES:
        f = out / f"port_{case}.npz"
        if not f.exists():
            continue
        z = np.load(f)
        rows.append(f"| `{f.name}` | {WHAT[case]} | {float(z['sigma_t']):g} | {render_columns(z)} |")
    if not rows:
        return ""
    return _README + "\n".join(rows) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m polarstripe.bench.mitsuba_port_references",
                                 description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("-o", "--out", type=Path, default=Path("tests/data/mitsuba"), help="output folder")
    ap.add_argument("--spp", type=int, default=16384, help="samples per pixel per seed (default 16384)")
    ap.add_argument("--seeds", default="0,1", help="seeds (default 0,1)")
    ap.add_argument("--pass-spp", type=int, default=2048, help="samples per pixel per render pass")
    ap.add_argument("--variant", default=None, help="Mitsuba variant (default: the first that works)")
    ap.add_argument("--cases", default=",".join(CASES), help=f"cases (default {','.join(CASES)})")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    seeds = tuple(int(s) for s in args.seeds.split(","))
    for case in args.cases.split(","):
        data = render_case(case, args.spp, seeds, args.variant, args.pass_spp)
        np.savez_compressed(args.out / f"port_{case}.npz", **data)
        (args.out / f"port_{case}.toml").write_text(str(data["scene_toml"]))
        print(f"port_{case}: {data['spp']} spp x {len(seeds)} seeds, {np.round(data['seconds'], 1)} s, "
              f"regions {np.round(data['regions'].mean(0), 5)}, spread {np.round(100 * data['spread'], 2)} %")
    from polarstripe.bench.mitsuba_references import write_readme

    write_readme(args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
