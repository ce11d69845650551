"""Stored Mitsuba 3 references of the paper's tank: the all-orders truth the test suite reads without Mitsuba.

``python -m polarstripe.bench.mitsuba_references -o tests/data/mitsuba`` renders, for σ_t = 1, 2.5, 5, 8 1/m,
the default tank (``load_scene(None)``: 60 × 60 × 38 cm, albedo 1, TTHG mean cosine 0.8) seen by a 32×32
camera at (0, 0, −0.05) m looking along +z and lit by an isotropic point source of 1 W/sr at (0.2, 0, −0.05) m
(both 5 cm outside the entry face z = 0: a point light inside the medium gives an estimator of infinite
variance), in three cases:

* ``all_plane``   — all orders (``max_depth = −1``), a Lambertian plane of albedo 0.6 covering the back wall;
* ``all_medium``  — all orders, medium only (no object);
* ``single_medium`` — single scattering (``max_depth = 2``), medium only: polarstripe's B.

Each case is one ``<case>_sigma<σ>.npz`` with the images of two seeds (float32, W sr⁻¹ m⁻², row 0 at the top),
the scene as TOML text (also written beside it as ``<case>_sigma<σ>.toml`` for ``load_scene``), spp, seeds,
seconds per seed, Mitsuba version and variant, and the seed-to-seed spread on the image regions of
:func:`regions`; ``README.md`` in the same folder summarises them.
"""

from __future__ import annotations

import argparse
import inspect
import json
import math
import sys
import time
import tomllib
from pathlib import Path

import numpy as np
from polarstripe.sim.mitsuba_scene import render_truth, select_variant
from polarstripe.sim.render import render_components
from polarstripe.sim.scene import PlaneObject, Scene, load_scene, scene_from_dict, scene_to_dict
from polarstripe.sim.validation_scenes import cases as own_cases
from polarstripe.sim.validation_scenes import file_stem as own_stem

SIGMAS = (1.0, 2.5, 5.0, 8.0)
CASES = {                   # name: (max_depth, with the back-wall plane, what it is)
    "all_plane": (-1, True, "all orders, Lambertian plane (albedo 0.6) on the back wall"),
    "all_medium": (-1, False, "all orders, medium only"),
    "single_medium": (2, False, "single scattering (max_depth = 2), medium only"),
}
REGIONS = ("left half", "right half", "centre 8x8")
RESOLUTION = 32
OUTSIDE_M = 0.05            # camera and source this far in front of the tank's entry face
SEPARATION_M = 0.2          # source beside the camera (+x: on the image left)


# the single-scattering model: render_components(..., orders="single") where higher orders exist
SINGLE = {"orders": "single"} if "orders" in inspect.signature(render_components).parameters else {}


def single_scattering(scene: Scene) -> np.ndarray:
    """polarstripe's single-scattering flood image [W sr⁻¹ m⁻²]: D + A + B (``standard``) with objects,
    B (``reference``) without."""
    if scene.objects:
        c = render_components(scene, "flood", "standard", need=("D", "A", "B"), **SINGLE)
        return c.D + c.A + c.B
    return render_components(scene, "flood", "reference", need=("B",), **SINGLE).B


REFERENCE_EXPOSURE_S = 0.008


def reference_scene(sigma_t: float, plane: bool, resolution: int = RESOLUTION) -> Scene:
    """The reference rig: the default tank with σ_t [1/m], camera and point source 5 cm outside the entry
    face, 20 cm apart; with ``plane`` a 0.6 × 0.6 m plane of albedo 0.6 on the back wall, else no object."""
    s = load_scene(None)
    z = s.medium.extent.min[2] - OUTSIDE_M
    # exposure pinned to the value the stored references were made with (radiance does not depend on it)
    cam = s.camera.replace(position=(0.0, 0.0, z), look_at=(0.0, 0.0, s.medium.extent.max[2]),
                           resolution=(resolution, resolution), exposure_s=REFERENCE_EXPOSURE_S)
    src = s.projector.replace(model="point", position=(SEPARATION_M, 0.0, z),   # unpolarized, as the
                             polarization=s.projector.polarization.replace(dop=0.0))  # emitter renders
    lo, hi = s.medium.extent.min, s.medium.extent.max
    wall = PlaneObject(point=(0.0, 0.0, hi[2]), normal=(0.0, 0.0, -1.0), size=(hi[0] - lo[0], hi[1] - lo[1]),
                       albedo=0.6)
    objs = (wall,) if plane else ()
    return s.replace(medium=s.medium.replace(sigma_t=float(sigma_t)), camera=cam, projector=src, objects=objs)


def regions(img: np.ndarray) -> np.ndarray:
    """Means of an (h, w) image over (left half, right half, centre 8×8 block): shape (3,)."""
    h, w = img.shape[-2:]
    return np.array([img[..., :, : w // 2].mean(), img[..., :, w // 2:].mean(),
                     img[..., h // 2 - 4: h // 2 + 4, w // 2 - 4: w // 2 + 4].mean()])


def render_columns(z) -> str:
    """A stored reference's render columns of the data README's tables: spp | seeds | seconds per seed |
    mean of its regions (left / right / centre) | seed spread %."""
    return (f"{int(z['spp'])} | {', '.join(str(s) for s in z['seeds'])} | "
            f"{' / '.join(f'{s:.0f}' for s in z['seconds'])} | "
            f"{' / '.join(f'{v:.4g}' for v in z['regions'].mean(0))} | "
            f"{' / '.join(f'{100 * v:.2f}' for v in z['spread'])}")


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return repr(v) if math.isfinite(v) else ("inf" if v > 0 else "-inf") if not math.isnan(v) else "nan"
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k} = {_toml_value(x)}" for k, x in v.items() if x is not None) + "}"
    raise TypeError(f"cannot write {v!r} as TOML")


def scene_toml(scene: Scene) -> str:
    """A scene as TOML text that :func:`~polarstripe.sim.scene.load_scene` reads back to an equal Scene."""
    d = scene_to_dict(scene)
    lines = [] if d["object"] else ["object = []  # none", ""]
    for section in ("medium", "camera", "projector"):
        lines.append(f"[{section}]")
        lines += [f"{k} = {_toml_value(v)}" for k, v in d[section].items() if v is not None]
        lines.append("")
    for obj in d["object"]:
        lines.append("[[object]]")
        lines += [f"{k} = {_toml_value(v)}" for k, v in obj.items() if v is not None]
        lines.append("")
    text = "\n".join(lines)
    if scene_from_dict(tomllib.loads(text)) != scene:
        raise AssertionError("scene TOML does not read back to the same scene")
    return text


def render_case(case: str, sigma_t: float, spp: int, seeds: tuple[int, ...], variant: str | None,
                pass_spp: int) -> dict:
    """Render one reference with every seed; returns the arrays stored in its npz."""
    import mitsuba as mi

    depth, plane, _ = CASES[case]
    scene = reference_scene(sigma_t, plane)
    variant = select_variant(variant)
    images, seconds = [], []
    for seed in seeds:
        t0 = time.perf_counter()
        images.append(render_truth(scene, "flood", max_depth=depth, spp=spp, seed=seed, variant=variant,
                                   pass_spp=pass_spp))
        seconds.append(time.perf_counter() - t0)
    images = np.stack(images)
    reg = np.stack([regions(im) for im in images])
    spread = (reg.max(0) - reg.min(0)) / reg.mean(0)
    return {"images": images.astype(np.float32), "seeds": np.array(seeds), "spp": np.array(spp),
            "max_depth": np.array(depth), "sigma_t": np.array(sigma_t), "plane": np.array(plane),
            "pattern": np.array("flood"), "scene_toml": np.array(scene_toml(scene)),
            "seconds": np.array(seconds), "regions": reg, "spread": spread,
            "region_names": np.array(REGIONS), "mitsuba_version": np.array(mi.__version__),
            "variant": np.array(variant)}


def file_stem(case: str, sigma_t: float) -> str:
    return f"{case}_sigma{sigma_t:g}"


_HEADER = ("| file | case | σ_t [1/m] | max_depth | spp | seeds | seconds per seed | "
           "mean: left / right / centre | seed spread % (left / right / centre) |\n"
           "|---|---|---|---|---|---|---|---|---|")


def _model_section(out: Path) -> str:
    """polarstripe's single-scattering model against the stored references (region means of the seed mean)."""
    lines = []
    for sigma in SIGMAS:
        got = {}
        for case in CASES:
            f = out / f"{file_stem(case, sigma)}.npz"
            if f.exists():
                got[case] = regions(np.load(f)["images"].astype(float).mean(0))
        if len(got) < len(CASES):
            continue
        plane = regions(single_scattering(reference_scene(sigma, True)))
        b = regions(single_scattering(reference_scene(sigma, False)))
        cells = [got["single_medium"] / b, plane / got["all_plane"], b / got["all_medium"]]
        lines.append(f"| {sigma:g} | " + " | ".join(" / ".join(f"{v:.3f}" for v in x) for x in cells) + " |")
    if not lines:
        return ""
    return ("\n## polarstripe's single-scattering model against these references\n\n"
            "Values per region (left half / right half / centre 8×8), from the mean of the seeds. The\n"
            "model is `render_components(scene, \"flood\")`, single scattering only: D + A + B (`standard`)\n"
            "with the plane, B (`reference`) without. The gap single ÷ all orders is what a\n"
            "multiple-scattering model must close.\n\n"
            "| σ_t [1/m] | Mitsuba max_depth=2 ÷ model B (medium only) | single ÷ all orders, with the plane "
            "| single ÷ all orders, medium only |\n|---|---|---|---|\n" + "\n".join(lines) + "\n")


_OWN_HEADER = ("| file | what | pattern | spp | seeds | seconds per seed | mean: left / right / centre | "
               "seed spread % (left / right / centre) |\n|---|---|---|---|---|---|---|---|")


def _own_section(out: Path) -> str:
    """The README section of the own validation scenes (``own_*.npz``, written by ``polarstripe bench
    fidelity --render-references``), in the order of :func:`polarstripe.sim.validation_scenes.cases`; "" when
    ``out`` holds none."""
    order = {own_stem(name): k for k, name in enumerate(own_cases())}
    files = sorted(out.glob("own_*.npz"), key=lambda f: (order.get(f.stem, len(order)), f.stem))
    rows = []
    for f in files:
        z = np.load(f)
        rows.append(f"| `{f.name}` | {z['what']} | `{z['pattern']}` | {render_columns(z)} |")
    if not rows:
        return ""
    return ("\n## Own validation scenes of the all-orders model (`sim/validation_scenes.py`)\n\n"
            "Rendered by `polarstripe bench fidelity --render-references` (all orders, `max_depth = -1`, the "
            "same\nintegrator, sampler and filter as above) and read by `tests/sim/test_all_orders.py`. Each "
            "scene is the tank\nwith camera and source 5 cm in front of the entry face, 20 cm apart, a 32×32 "
            "camera and (except\n`medium_hg08_s3`) a 0.6 × 0.6 m wall of albedo 0.6; the scene is in "
            "`<stem>.toml` and in the npz's\n`scene_toml`, the pattern in `pattern`.\n\n"
            f"{_OWN_HEADER}\n" + "\n".join(rows) + "\n")


def write_readme(out: Path) -> None:
    """README.md of every npz in ``out``: the tank's references (:data:`CASES`), the single-scattering model
    against them, and the own validation scenes (``own_*``) when present."""
    rows, meta = [], {}
    for case in CASES:
        for f in sorted(out.glob(f"{case}_sigma*.npz"), key=lambda p: float(p.stem.split("sigma")[1])):
            z = np.load(f)
            meta = {k: str(z[k]) for k in ("mitsuba_version", "variant")}
            m = z["regions"].mean(0)
            rows.append(f"| `{f.name}` | {case} | {float(z['sigma_t']):g} | {int(z['max_depth'])} | "
                        f"{int(z['spp'])} | {', '.join(str(s) for s in z['seeds'])} | "
                        f"{' / '.join(f'{s:.0f}' for s in z['seconds'])} | "
                        f"{' / '.join(f'{v:.4g}' for v in m)} | "
                        f"{' / '.join(f'{100 * v:.2f}' for v in z['spread'])} |")
    text = f"""# Mitsuba 3 references (all-orders truth)

Written by `python -m polarstripe.bench.mitsuba_references -o {out}` with Mitsuba
{meta.get('mitsuba_version')} (variant `{meta.get('variant')}`, integrator `volpath`, Russian roulette from
depth 100000, `independent` sampler, box pixel filter: each pixel is the mean radiance over its footprint).
Read by `tests/sim/test_mitsuba_references.py`, which needs no Mitsuba.

Scene: the default tank (`load_scene(None)`: 60 × 60 × 38 cm, albedo 1, TTHG mean cosine 0.8) at σ_t
[1/m] as listed; camera 32×32, fov 60°, at (0, 0, −0.05) m looking along +z; isotropic point source of
1 W/sr at (0.2, 0, −0.05) m (world +x is on the image left, so the left half is nearer the source). Camera
and source sit 5 cm outside the entry face: a point light inside the medium gives an estimator of infinite
variance. Mitsuba's emitters are unpolarized, and every scene says so (`projector.polarization.dop = 0`):
a polarized source changes the model's intensity through the Mueller matrix's m12 (docs/physics.md §5).
Cases:

{chr(10).join(f'- `{c}`: {d}' for c, (_, _, d) in CASES.items())}

Each `<case>_sigma<σ>.npz` holds `images` (seeds × 32 × 32, float32, radiance W sr⁻¹ m⁻², row 0 at the
top, as polarstripe's `render_components` D + A + B), `seeds`, `spp` (per seed), `max_depth`, `sigma_t`,
`plane`, `pattern`, `scene_toml` (the scene; also written beside it as `<case>_sigma<σ>.toml`, for
`load_scene`), `seconds` (per seed), `regions` (seeds × 3: means over the left half, right half and central
8×8 block), `spread` (per region: (max − min)/mean over the seeds), `mitsuba_version`, `variant`.
The seconds are wall-clock on a 2-core machine shared with other jobs (load average 3–7 while these ran),
so they overstate the cost: unloaded, 4096 spp of a 32×32 all-orders image take 1–3 s with `llvm_ad_mono`.

{_HEADER}
{chr(10).join(rows)}
{_model_section(out)}{_own_section(out)}{_port_section(out)}"""
    (out / "README.md").write_text(text)


def _port_section(out: Path) -> str:
    from polarstripe.bench.mitsuba_port_polarized import readme_section as polarized  # they build on
    from polarstripe.bench.mitsuba_port_references import readme_section  # this module

    return readme_section(out) + polarized(out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m polarstripe.bench.mitsuba_references", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("-o", "--out", type=Path, default=Path("tests/data/mitsuba"), help="output folder")
    ap.add_argument("--spp", type=int, default=131072, help="samples per pixel per seed")
    ap.add_argument("--seeds", default="0,1", help="comma-separated seeds")
    ap.add_argument("--sigmas", default=",".join(f"{s:g}" for s in SIGMAS), help="σ_t values [1/m]")
    ap.add_argument("--cases", default=",".join(CASES), help=f"subset of {', '.join(CASES)}")
    ap.add_argument("--variant", default=None, help="Mitsuba variant (default: llvm_ad_mono if it works)")
    ap.add_argument("--pass-spp", type=int, default=4096, help="samples per pixel per render pass")
    ap.add_argument("--readme-only", action="store_true", help="only rewrite README.md from the stored files")
    args = ap.parse_args(argv)
    if args.readme_only:
        if not args.out.is_dir():
            ap.error(f"--out {args.out}: no such folder of references")
        write_readme(args.out)
        return 0
    seeds = tuple(int(s) for s in args.seeds.split(","))
    cases = [c.strip() for c in args.cases.split(",")]
    for c in cases:
        if c not in CASES:
            ap.error(f"unknown case {c!r} (choose from {', '.join(CASES)})")
    args.out.mkdir(parents=True, exist_ok=True)
    t_all = time.perf_counter()
    for sigma in (float(s) for s in args.sigmas.split(",")):
        for case in cases:
            data = render_case(case, sigma, args.spp, seeds, args.variant, args.pass_spp)
            stem = file_stem(case, sigma)
            np.savez_compressed(args.out / f"{stem}.npz", **data)
            (args.out / f"{stem}.toml").write_text(str(data["scene_toml"]))
            print(f"{stem}: {' / '.join(f'{s:.1f}' for s in data['seconds'])} s, mean "
                  f"{np.round(data['regions'].mean(0), 5)}, spread % {np.round(100 * data['spread'], 2)}",
                  flush=True)
    write_readme(args.out)
    print(f"total {time.perf_counter() - t_all:.0f} s", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
