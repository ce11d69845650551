"""Stored polarized Mitsuba 3 references: the backscatter's Stokes images per order of scattering.

``python -m polarstripe.bench.mitsuba_polarized_references -o tests/data/mitsuba_polarized`` renders, with
:func:`polarstripe.sim.mitsuba_polarized.render_stokes` (the model's Mueller matrix in every scattering, the
source behind an ideal polarizer at the scene's angle, 90° by default), the rig of
:func:`polarstripe.bench.mitsuba_references.reference_scene` without an object (medium only: the image is B),
32×32, for the scenes of :data:`SCENES` at the depths of :data:`DEPTHS` (``max_depth`` 2 is single
scattering, k + 1 adds order k, −1 is every order). Each ``<scene>_depth<d>.npz`` ("all" for −1) holds:

* ``stokes`` — seeds × 4 × 32 × 32 float32, S0..S3 [W sr⁻¹ m⁻²] in the camera frame (S1 > 0 along image
  right, S2 > 0 at 45° toward image up), row 0 at the top;
* ``seeds``, ``spp`` (per seed), ``seconds`` (per seed), ``max_depth``, ``scene_toml`` (also written beside
  it as ``<scene>.toml``), ``m12``, ``mitsuba_version``, ``variant``;
* ``regions`` — seeds × 4 × 3: the Stokes means over the left half, right half and central 8×8 block
  (:func:`polarstripe.bench.mitsuba_references.regions`), and ``spread`` — per region, the seed-to-seed
  spread of S0 ((max − min)/mean) and of the DOP (max − min, absolute).

``README.md`` in the same folder tabulates them (DOP per region and per order).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from polarstripe.bench.mitsuba_references import REGIONS, reference_scene, regions, scene_toml
from polarstripe.sim.scene import Phase, Scene

# name: (σ_t [1/m], phase model, g, albedo, depths rendered); the circular scenes ("circ_"): the same with a
# quarter-wave plate after the source's polarizer, its fast axis at 45° (V = +1, docs/physics.md §5.1)
SCENES = {
    "tthg08_s2": (2.0, "tthg", 0.8, 1.0, (2, -1)),
    "tthg08_s5": (5.0, "tthg", 0.8, 1.0, (2, 3, 4, 5, 6, -1)),
    "tthg08_s8": (8.0, "tthg", 0.8, 1.0, (2, -1)),
    "hg05_a08_s5": (5.0, "hg", 0.5, 0.8, (2, 3, -1)),
    "hg095_a08_s5": (5.0, "hg", 0.95, 0.8, (2, 3, -1)),
    "iso_a08_s5": (5.0, "isotropic", 0.0, 0.8, (2, 3, -1)),
    "circ_tthg08_s5": (5.0, "tthg", 0.8, 1.0, (2, 3, -1)),
    "circ_tthg08_s2": (2.0, "tthg", 0.8, 1.0, (2, -1)),
    "circ_hg095_a08_s5": (5.0, "hg", 0.95, 0.8, (2, -1)),
    "circ_iso_a08_s5": (5.0, "isotropic", 0.0, 0.8, (2, -1)),
}
QUARTER_WAVE_DEG = 45.0


def polarized_scene(name: str) -> Scene:
    """The medium-only reference rig with the scene's σ_t, phase function and albedo (point source, 1 W/sr,
    polarized at 90°, 20 cm beside a 32×32 camera, both 5 cm outside the tank)."""
    sigma, model, g, albedo, _ = SCENES[name]
    s = reference_scene(sigma, False)
    pol = s.projector.polarization.replace(dop=1.0, angle_deg=90.0, quarter_wave_deg=(
        QUARTER_WAVE_DEG if name.startswith("circ_") else None))
    return s.replace(medium=s.medium.replace(albedo=albedo, phase=Phase(model, g)),
                     projector=s.projector.replace(polarization=pol))


def depth_tag(depth: int) -> str:
    return "all" if depth < 0 else str(depth)


def file_stem(name: str, depth: int) -> str:
    return f"{name}_depth{depth_tag(depth)}"


def dop(stokes_regions: np.ndarray) -> np.ndarray:
    """Linear DOP √(S1² + S2²)/S0 of Stokes region means (…, 4, regions) → (…, regions)."""
    s = np.asarray(stokes_regions, float)
    return np.hypot(s[..., 1, :], s[..., 2, :]) / s[..., 0, :]


def circular(stokes_regions: np.ndarray) -> np.ndarray:
    """Signed circular polarization S3/S0 of Stokes region means (…, 4, regions) → (…, regions)."""
    s = np.asarray(stokes_regions, float)
    return s[..., 3, :] / s[..., 0, :]


def render_case(name: str, depth: int, spp: int, seeds: tuple[int, ...], pass_spp: int) -> dict:
    """Render one reference with every seed; returns the arrays stored in its npz."""
    import mitsuba as mi
    from polarstripe.sim.mitsuba_polarized import VARIANT, render_stokes

    scene = polarized_scene(name)
    images, seconds = [], []
    for seed in seeds:
        t0 = time.perf_counter()
        images.append(render_stokes(scene, max_depth=depth, spp=spp, seed=seed, pass_spp=pass_spp))
        seconds.append(time.perf_counter() - t0)
    images = np.stack(images)
    reg = np.stack([[regions(c) for c in im] for im in images])            # seeds × 4 × 3
    s0, d, v = reg[:, 0], dop(reg), circular(reg)
    spread = np.stack([(s0.max(0) - s0.min(0)) / s0.mean(0), d.max(0) - d.min(0), v.max(0) - v.min(0)])
    return {"stokes": images.astype(np.float32), "seeds": np.array(seeds), "spp": np.array(spp),
            "seconds": np.array(seconds), "max_depth": np.array(depth),
            "scene_toml": np.array(scene_toml(scene)),
            "m12": np.array(True), "regions": reg, "spread": spread, "region_names": np.array(REGIONS),
            "mitsuba_version": np.array(mi.__version__), "variant": np.array(VARIANT)}


def load(out: Path, name: str, depth: int) -> dict | None:
    f = out / f"{file_stem(name, depth)}.npz"
    if not f.exists():
        return None
    z = np.load(f)
    return {k: z[k] for k in z.files}


def _cells(v, fmt="{:.3f}") -> str:
    return " / ".join(fmt.format(x) for x in v)


_HEADER = ("| file | σ_t [1/m] | phase | albedo | max_depth | spp | seeds | seconds per seed | "
           "S0: left / right / centre | DOP: left / right / centre | V/S0: left / right / centre | "
           "S0 seed spread % | DOP seed spread |\n"
           "|---|---|---|---|---|---|---|---|---|---|---|---|---|")


def write_readme(out: Path) -> None:
    """README.md of the stored files: what they are, cost and spread, and the DOP per scene and order."""
    rows, orders, meta = [], [], {}
    for name, (sigma, model, g, albedo, depths) in SCENES.items():
        prev, every = None, load(out, name, -1)
        s0_all = every["regions"].mean(0)[0] if every is not None else np.full(3, np.nan)
        for depth in sorted(depths, key=lambda d: (d < 0, d)):
            z = load(out, name, depth)
            if z is None:
                continue
            meta = {k: str(z[k]) for k in ("mitsuba_version", "variant")}
            mean = z["regions"].mean(0)
            rows.append(f"| `{file_stem(name, depth)}.npz` | {sigma:g} | {model} {g:g} | {albedo:g} | "
                        f"{depth_tag(depth)} | {int(z['spp'])} | {', '.join(str(s) for s in z['seeds'])} | "
                        f"{_cells(z['seconds'], '{:.0f}')} | {_cells(mean[0], '{:.4g}')} | "
                        f"{_cells(dop(mean))} | {_cells(circular(mean))} | "
                        f"{_cells(100 * z['spread'][0], '{:.2f}')} | "
                        f"{_cells(z['spread'][1])} |")
            if depth > 0 and prev is not None and depth == prev[0] + 1:
                k = depth - 1
                orders.append(f"| {name} | {k} | {_cells(dop(mean - prev[1]))} | "
                              f"{_cells(circular(mean - prev[1]))} | "
                              f"{_cells((mean - prev[1])[0] / s0_all, '{:.3f}')} |")
            elif depth == 2:
                orders.append(f"| {name} | 1 | {_cells(dop(mean))} | {_cells(circular(mean))} | "
                              f"{_cells(mean[0] / s0_all)} |")
            prev = (depth, mean)
    text = f"""# Polarized Mitsuba 3 references (the backscatter's Stokes images, per order)

Written by `python -m polarstripe.bench.mitsuba_polarized_references -o {out}` with Mitsuba
{meta.get('mitsuba_version')} (variant `{meta.get('variant')}`, integrator `stokes` around `volpath`, Russian
roulette from depth 100000, `independent` sampler, box pixel filter), through
`sim/mitsuba_polarized.py`: every scattering applies the model's Mueller matrix M(θ) = P(θ)·M_R(θ)/m11_R(θ)
(P the scene's phase function, M_R the depolarized-Rayleigh reduced matrix of docs/physics.md §5, δ = 0.2),
m12 and m44 included; the point source (1 W/sr) is fully polarized at the model's default 90° (vertical) by an
ideal polarizer sheet, and in the `circ_` scenes made circular (V = +1) by an ideal quarter-wave plate sheet
after it, fast axis at 45° (docs/physics.md §5.1; written with `--scenes circ_tthg08_s5,circ_tthg08_s2,
circ_iso_a08_s5,circ_hg095_a08_s5 --spp 16384 --spp-depth 8192`; `circ_hg095_a08_s5_depthall` has seeds 2
and 3 appended, `render_case` with the same spp, its heavy tail needing them). Read by
`tests/sim/test_mitsuba_polarized.py` and `tests/sim/test_mitsuba_circular.py`, which need no Mitsuba.

Rig: `reference_scene(σ_t, plane=False)` of `bench/mitsuba_references.py` (the default 60 × 60 × 38 cm tank,
camera 32×32, fov 60°, at (0, 0, −0.05) m; source at (0.2, 0, −0.05) m), medium only, with the phase function
and albedo listed. `max_depth` 2 is single scattering; depth k + 1 minus depth k is order k.

Each `<scene>_depth<d>.npz` holds `stokes` (seeds × 4 × 32 × 32 float32: S0..S3 [W sr⁻¹ m⁻²] in the camera
frame, S1 > 0 along image right, S2 > 0 at 45° toward image up, row 0 at the top), `seeds`, `spp` (per seed),
`seconds` (per seed, wall-clock on a 2-core machine shared with other jobs: four for the linear scenes, a
load average of 12–16 for the `circ_` ones), `max_depth`, `scene_toml`
(also `<scene>.toml`), `m12`, `regions` (seeds × 4 × 3: Stokes means over the left half, right half and
central 8×8 block), `spread` (2 × 3, the `circ_` files 3 × 3: seed-to-seed spread of S0, relative, of the
DOP and of V/S0, absolute), `mitsuba_version`, `variant`. S3 > 0 is V > 0 in the convention of
docs/physics.md §5.1 (Mitsuba's; checked through analyzer sheets in front of the camera). Through an ideal
analyzer at φ: I(φ) = ½(S0 + S1 cos 2φ + S2 sin 2φ); E_b is φ = 0° (crossed with the vertical backscatter
polarization), E_w φ = 90°; through a quarter-wave plate at 45° and the analyzer at 90° (E_b of circular
light, whose backscatter has V < 0) ½(S0 + S3), at 0° ½(S0 − S3). The DOP is the linear one, √(S1² + S2²)/S0,
formed from the Stokes means over a region (not averaged per pixel: noise biases a per-pixel DOP up).

{_HEADER}
{chr(10).join(rows)}

## DOP and V/S0 per order (left / right / centre), and the order's share of all orders' S0

| scene | order | DOP | V/S0 | share of S0 |
|---|---|---|---|---|
{chr(10).join(orders)}
"""
    (out / "README.md").write_text(text)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m polarstripe.bench.mitsuba_polarized_references",
                                 description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("-o", "--out", type=Path, default=Path("tests/data/mitsuba_polarized"),
                    help="output folder")
    ap.add_argument("--spp", type=int, default=32768, help="samples per pixel per seed (all orders)")
    ap.add_argument("--spp-depth", type=int, default=16384, help="samples per pixel per seed (max_depth ≥ 2)")
    ap.add_argument("--seeds", default="0,1", help="comma-separated seeds")
    ap.add_argument("--scenes", default=",".join(SCENES), help=f"subset of {', '.join(SCENES)}")
    ap.add_argument("--pass-spp", type=int, default=2048, help="samples per pixel per render pass")
    ap.add_argument("--skip-existing", action="store_true", help="keep files already in --out")
    ap.add_argument("--readme-only", action="store_true", help="only rewrite README.md from the stored files")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    if not args.readme_only:
        seeds = tuple(int(s) for s in args.seeds.split(","))
        for name in (s.strip() for s in args.scenes.split(",")):
            if name not in SCENES:
                ap.error(f"unknown scene {name!r} (choose from {', '.join(SCENES)})")
            (args.out / f"{name}.toml").write_text(scene_toml(polarized_scene(name)))
            for depth in SCENES[name][4]:
                stem = file_stem(name, depth)
                if args.skip_existing and (args.out / f"{stem}.npz").exists():
                    continue
                spp = args.spp if depth < 0 else args.spp_depth
                data = render_case(name, depth, spp, seeds, args.pass_spp)
                np.savez_compressed(args.out / f"{stem}.npz", **data)
                print(f"{stem}: {' / '.join(f'{s:.0f}' for s in data['seconds'])} s, DOP "
                      f"{np.round(dop(data['regions'].mean(0)), 3)}, spread S0 % "
                      f"{np.round(100 * data['spread'][0], 2)}, DOP {np.round(data['spread'][1], 3)}",
                      flush=True)
    write_readme(args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
