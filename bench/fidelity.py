"""``polarstripe bench fidelity``: each fidelity level's error against all orders and single scattering, its
frame time, and Mitsuba's time at equal error — in one run.

* **Against all orders** (the truth: Mitsuba 3 ``volpath``, every order, stored in ``tests/data/mitsuba``):
  model ÷ truth over the left half, right half and central 8×8 block of a 32×32 image, for the paper's tank
  under a point source (σ_t = 1, 2.5, 5, 8 1/m, with the back-wall plane and medium only) and the own
  scenes of :mod:`polarstripe.sim.validation_scenes` (stripes, checkers, clear water, albedo 0.5–1, HG and
  TTHG 0.5–0.95, a sphere); per level with all orders, and single scattering (``orders="single"``). The
  model is rendered at 640×640 and box-filtered to 32×32, as Mitsuba's pixels are.
* **Single scattering** (``orders="single"``, the paper's model) against Mitsuba's ``max_depth = 2`` (medium
  only, σ_t = 1…8) and, at sampled pixels of the default 640×480 tank, against the converged ``reference``
  level (median / max relative error of D, A, B).
* **Polarization** against the polarized references (``tests/data/mitsuba_polarized``: Mitsuba with the
  model's Mueller matrix, every order, a source polarized at 90°): the backscatter's DOP per region (from
  the Stokes means) and the frames through the analyzer at 0° (E_b) and 90° (E_w) ÷ the truth's, per level.
* **Time**: CPU seconds of a 640×480 frame of the default tank (stripe 14/30 and flood) per level, with all
  orders and single scattering (best of ``--repeat``; one core: one model thread, sim/threads.py): a scan's
  frame, whose pattern-independent geometry the previous frame left in
  :mod:`polarstripe.sim.geometry_cache`, and (``preview``, ``standard``) the same frame without the cache,
  as a scan's first frame costs.
* **Mitsuba at equal error**: the per-pixel relative noise of the stored references (from their two seeds)
  gives the samples Mitsuba needs for the model's error per level; its time scales with samples and pixels
  to a 640×480 frame (``seconds`` of the references on this machine class).

``--render-references`` renders the own scenes with Mitsuba first (``pip install mitsuba``; libLLVM ≥ 17).
Targets (the issue): standard within 10 % of all orders (20 % at σ_t = 8), preview within 25 %, standard
≥ 10 frames/s and preview ≥ 40 frames/s at 640×480 on one core (one model thread). ``--threads N`` adds the
scaling with N threads against one: one stripe frame, and a scan's frames N at a time (bench/scaling.py;
the frames are the same for any count, :mod:`polarstripe.sim.threads`).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from polarstripe.bench.scaling import describe, scaling
from polarstripe.errors import PolarstripeError
from polarstripe.sim import geometry_cache
from polarstripe.sim.render import render_components
from polarstripe.sim.scene import load_scene
from polarstripe.sim.threads import available, set_threads
from polarstripe.sim.validation_scenes import cases, file_stem

LEVELS = ("preview", "standard", "reference")
DATA = Path(__file__).resolve().parents[1] / "tests" / "data" / "mitsuba"
DATA_POLARIZED = DATA.parent / "mitsuba_polarized"
SIGMAS = (1.0, 2.5, 5.0, 8.0)
SS = 20                    # 32×32 references → 640×640 renders (preview's half-resolution path applies)


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--repeat", type=int, default=2, help="timing repeats (best of)")
    parser.add_argument("--samples", type=int, default=120, help="pixels compared against 'reference'")
    parser.add_argument("--data", type=Path, default=DATA, help="folder of the stored Mitsuba references")
    parser.add_argument("--data-polarized", type=Path, default=DATA_POLARIZED,
                        help="folder of the stored polarized Mitsuba references")
    parser.add_argument("--render-references", action="store_true",
                        help="render the own scenes with Mitsuba into --data first (needs mitsuba)")
    parser.add_argument("--quick", action="store_true", help="skip the 'reference' level's frame time")
    parser.add_argument("--threads", type=int, default=1,
                        help="also time one stripe frame with N model threads and 2N stripe frames N at "
                             "a time, against one thread (wall clock: the scaling); the CPU times above are "
                             "one thread's")


def regions(img: np.ndarray) -> np.ndarray:
    """Means over the left half, the right half and the central 8×8 block."""
    h, w = img.shape
    return np.array([img[:, : w // 2].mean(), img[:, w // 2:].mean(),
                     img[h // 2 - 4: h // 2 + 4, w // 2 - 4: w // 2 + 4].mean()])


def _model(scene, pattern: str, level: str, orders: str = "all") -> np.ndarray:
    w, h = scene.camera.resolution
    big = scene.replace(camera=scene.camera.replace(resolution=(w * SS, h * SS)))
    c = render_components(big, pattern, level, orders=orders)
    return (c.D + c.A + c.B).reshape(h, SS, w, SS).mean(axis=(1, 3))


def _noise(images: np.ndarray) -> float:
    """Per-pixel relative noise of one seed: std of the two seeds' difference / √2, over the mean."""
    a, b = images.astype(float)
    return float(np.std(a - b) / np.sqrt(2) / max(np.mean(0.5 * (a + b)), 1e-300))


def _references(data: Path) -> list[dict]:
    refs = []
    for sigma in SIGMAS:
        for case in ("all_plane", "all_medium"):
            refs.append({"name": f"{case} σ={sigma:g}", "stem": f"{case}_sigma{sigma:g}", "sigma": sigma})
    for name in cases():
        refs.append({"name": name, "stem": file_stem(name), "sigma": None})
    out = []
    for r in refs:
        f = data / f"{r['stem']}.npz"
        if f.exists():
            z = np.load(f)
            r.update(pattern=str(z["pattern"]) if "pattern" in z.files else "flood",
                     truth=regions(z["images"].astype(float).mean(0)), spread=z["spread"],
                     noise=_noise(z["images"]),
                     spp=int(z["spp"]), seconds=float(np.mean(z["seconds"])),
                     scene=load_scene(data / f"{r['stem']}.toml"))
            out.append(r)
    return out


def accuracy(data: Path) -> dict:
    """Model ÷ truth per reference and level (all orders) and for single scattering (standard)."""
    rows = []
    for r in _references(data):
        single = regions(_model(r["scene"], r["pattern"], "standard", "single")) / r["truth"]
        row = {"name": r["name"], "sigma": r["sigma"], "spread": r["spread"].tolist(), "noise": r["noise"],
               "single": single.tolist()}
        for level in LEVELS:
            row[level] = (regions(_model(r["scene"], r["pattern"], level)) / r["truth"]).tolist()
        row["mitsuba_s_per_seed"], row["mitsuba_spp"] = r["seconds"], r["spp"]
        rows.append(row)
    single = []
    for sigma in SIGMAS:
        f = data / f"single_medium_sigma{sigma:g}.npz"
        if f.exists():
            z = np.load(f)
            scene = load_scene(data / f"single_medium_sigma{sigma:g}.toml")
            truth = regions(z["images"].astype(float).mean(0))
            single.append({"sigma": sigma, "spread": z["spread"].tolist(), "ratio": {
                lv: (regions(_model(scene, "flood", lv, "single")) / truth).tolist() for lv in LEVELS}})
    return {"rows": rows, "single_vs_max_depth_2": single}


def polarization(data: Path) -> list[dict]:
    """Per polarized reference (all orders): the truth's DOP per region and, per level, the model's DOP and
    its E_b, E_w ÷ the truth's (analyzer at 0° and 90°, ideal; the model at 640×640, box-filtered); for the
    circular references (``circ_``) |V|/S0 and the frames through the circular analyzers, ½(S0 ± S3)."""
    from polarstripe.bench.mitsuba_polarized_references import SCENES, dop, polarized_scene
    from polarstripe.bench.mitsuba_polarized_references import file_stem as stem

    rows = []
    for name in SCENES:
        f = data / f"{stem(name, -1)}.npz"
        if not f.exists():
            continue
        z = np.load(f)
        t = z["regions"].mean(0)
        # circular light (docs/physics.md §5.1): the DOP a circular analyzer sees, |V|/S0, and its frames
        k = 3 if name.startswith("circ_") else 1

        def seen(s, k=k):
            return np.abs(s[3]) / s[0] if k == 3 else dop(s)

        row = {"name": name, "truth_dop": seen(t).tolist(), "spread": z["spread"].tolist()}
        scene = polarized_scene(name)
        w, h = scene.camera.resolution
        big = scene.replace(camera=scene.camera.replace(resolution=(w * SS, h * SS)))
        for level in ("preview", "standard"):
            c = render_components(big, "flood", level, need=("B", "p"))
            st = np.stack([regions(a.reshape(h, SS, w, SS).mean(axis=(1, 3)))
                           for a in (c.B, c.Bq, c.Bu, c.Bv)])
            row[level] = {"dop": seen(st).tolist(), "e_b": ((st[0] + st[k]) / (t[0] + t[k])).tolist(),
                          "e_w": ((st[0] - st[k]) / (t[0] - t[k])).tolist()}
        rows.append(row)
    return rows


def _uncached(scene, pattern: str, level: str):
    with geometry_cache.disabled():
        return render_components(scene, pattern, level)


def _timed(fn, repeat: int) -> float:
    best = np.inf
    for _ in range(repeat):
        c = time.process_time()
        fn()
        best = min(best, time.process_time() - c)
    return best


def _rel_err(x, r):
    x, r = np.asarray(x), np.asarray(r)
    if r.max() <= 0:
        return 0.0, 0.0
    sel = r > 1e-3 * r.max()
    e = np.abs(x[sel] - r[sel]) / r[sel]
    return float(np.median(e)), float(np.max(e))


def timing(repeat: int, quick: bool, samples: int, threads: int = 1) -> dict:
    """CPU seconds per 640×480 frame of the default tank, all orders and single, on one model thread;
    single-scattering error against the converged reference at sampled pixels; with ``threads`` > 1 the
    scaling at that many threads against one (bench/scaling.py)."""
    set_threads(1)
    scene = load_scene(None)
    t0 = time.perf_counter()
    probe = render_components(scene, "flood", "preview", orders="single")
    out: dict = {"first_call_s": time.perf_counter() - t0, "levels": {}}
    rng = np.random.default_rng(0)
    px = np.argwhere(np.ones((scene.camera.resolution[1], scene.camera.resolution[0]), bool))
    px = px[rng.choice(len(px), samples, replace=False)]
    ref = {p: render_components(scene, p, "reference", pixels=px, orders="single")
           for p in ("flood", "stripe:14/30")}
    del probe
    for level in LEVELS:
        row: dict = {}
        for name, pat in (("stripe", "stripe:14/30"), ("flood", "flood")):
            for orders in ("all", "single"):
                if level == "reference" and (quick or orders == "single"):
                    continue
                render_components(scene, pat, level, orders=orders)                     # warm
                row[f"{name}_{orders}_s"] = _timed(lambda p=pat, lv=level, o=orders: render_components(
                    scene, p, lv, orders=o), 1 if level == "reference" else repeat)
                if orders == "all" and level != "reference":    # a scan's first frame: no cached geometry
                    row[f"{name}_all_uncached_s"] = _timed(lambda p=pat, lv=level: _uncached(scene, p, lv),
                                                           repeat)
            if level != "reference":
                c = render_components(scene, pat, level, orders="single")
                for k in "DAB":
                    row[f"{name}_single_{k}_max"] = _rel_err(getattr(c, k)[px[:, 0], px[:, 1]],
                                                             getattr(ref[pat], k))[1]
        out["levels"][level] = row
    if threads > 1:
        out["threads"] = {"count": threads, "available": available(),
                          "levels": scaling(scene, threads, repeat)}
    return out


def summarize(acc: dict, tim: dict) -> dict:
    """Worst errors per level, Mitsuba's time at equal error, the targets."""
    rows = acc["rows"]
    summ: dict = {"levels": {}}
    for level in LEVELS:
        errs = [max(abs(v - 1) for v in r[level]) for r in rows]
        err8 = [max(abs(v - 1) for v in r[level]) for r in rows if r["sigma"] != 8.0]
        # Mitsuba: spp for per-pixel noise = our worst error, scaled to 640×480 from 32×32
        worst = max(max(errs), 1e-3)
        ratios = [r["mitsuba_s_per_seed"] * (r["noise"] / worst) ** 2 * (640 * 480) / (32 * 32) for r in rows]
        t = tim["levels"].get(level, {}).get("stripe_all_s")
        summ["levels"][level] = {"max_err": max(errs), "max_err_below_8": max(err8), "median_err":
                                 float(np.median(errs)), "mitsuba_s_equal_error": float(np.median(ratios)),
                                 "frame_s": t, "ratio": float(np.median(ratios)) / t if t else None}
    single = [max(abs(v - 1) for v in r["single"]) for r in rows]
    summ["single_max_err"] = max(single)
    pol = acc.get("polarization") or []
    summ["polarization"] = {lv: {"max_dop_err": max(abs(m - t) for r in pol for m, t in
                                                    zip(r[lv]["dop"], r["truth_dop"], strict=True)),
                                 "max_frame_err": max(abs(v - 1) for r in pol for k in ("e_b", "e_w")
                                                      for v in r[lv][k])}
                            for lv in ("preview", "standard")} if pol else {}
    md2 = acc["single_vs_max_depth_2"]
    summ["single_vs_max_depth_2_max"] = max((max(abs(v - 1) - s for v, s in zip(x["ratio"]["standard"],
                                                                                   x["spread"], strict=True))
                                             for x in md2), default=None)
    st, pv = summ["levels"]["standard"], summ["levels"]["preview"]
    summ["targets"] = {
        "standard_10pct": st["max_err_below_8"] <= 0.10 and st["max_err"] <= 0.20,
        "preview_25pct": pv["max_err"] <= 0.25,
        "standard_10fps": (st["frame_s"] or 1) <= 0.1,
        "preview_40fps": (pv["frame_s"] or 1) <= 1 / 40,
        "single_matches_max_depth_2": summ["single_vs_max_depth_2_max"] is not None
        and summ["single_vs_max_depth_2_max"] <= 0.01,
    }
    return summ


def _fmt(v) -> str:
    return " ".join(f"{x:5.2f}" for x in v)


def _table(res: dict) -> str:
    acc, tim, summ = res["accuracy"], res["timing"], res["summary"]
    lines = ["model ÷ Mitsuba all orders (left half, right half, centre 8×8 of 32×32; model rendered at "
             "640×640)", f"{'scene':<22}{'single':>18}{'preview':>18}{'standard':>18}{'reference':>18}"
             f"{'seed spread %':>17}"]
    for r in acc["rows"]:
        lines.append(f"{r['name']:<22}{_fmt(r['single']):>18}{_fmt(r['preview']):>18}{_fmt(r['standard']):>18}"
                     f"{_fmt(r['reference']):>18}{_fmt(100 * np.array(r['spread'])):>17}")
    for x in acc["single_vs_max_depth_2"]:
        lines.append(f"single scattering ÷ Mitsuba max_depth=2, σ_t={x['sigma']:g} (medium): "
                     + ", ".join(f"{lv} {_fmt(x['ratio'][lv])}" for lv in LEVELS))
    if acc.get("polarization"):
        lines.append("")
        lines.append("backscatter DOP (left, right, centre; circ_: |V|/S0) vs the polarized references; E_b, "
                     "E_w ÷ truth")
        lines.append(f"{'scene':<16}{'truth':>18}{'preview':>18}{'standard':>18}{'E_b standard':>18}"
                     f"{'E_w standard':>18}")
        for r in acc["polarization"]:
            lines.append(f"{r['name']:<16}{_fmt(r['truth_dop']):>18}{_fmt(r['preview']['dop']):>18}"
                         f"{_fmt(r['standard']['dop']):>18}{_fmt(r['standard']['e_b']):>18}"
                         f"{_fmt(r['standard']['e_w']):>18}")
        lines.append("worst |DOP − truth|: " + ", ".join(
            f"{lv} {v['max_dop_err']:.3f} (E_b, E_w {100 * v['max_frame_err']:.1f} %)"
            for lv, v in summ["polarization"].items()))
    lines.append("")
    lines.append(f"{'level':<10}{'max err':>9}{'(σ<8)':>8}{'median':>8}{'frame s':>9}{'fps':>6}"
                 f"{'single s':>10}{'flood s':>9}{'Mitsuba s at equal err':>24}{'ratio':>8}")
    for lv in LEVELS:
        s, t = summ["levels"][lv], tim["levels"].get(lv, {})
        fs = s["frame_s"]
        frame = f"{fs:>9.3f}{1 / fs:>6.1f}" if fs else f"{'—':>9}{'':>6}"
        single_s, flood_s = t.get("stripe_single_s", float("nan")), t.get("flood_all_s", float("nan"))
        lines.append(f"{lv:<10}{100 * s['max_err']:>8.1f}%{100 * s['max_err_below_8']:>7.1f}%"
                     f"{100 * s['median_err']:>7.1f}%" + frame + f"{single_s:>10.3f}{flood_s:>9.3f}"
                     f"{s['mitsuba_s_equal_error']:>24.0f}" + (f"{s['ratio']:>8.0f}x" if s["ratio"] else ""))
    for lv in ("preview", "standard"):
        t = tim["levels"][lv]
        lines.append(f"{lv}: a scan's frames (pattern-independent geometry cached, sim/geometry_cache.py) "
                     f"stripe {t['stripe_all_s']:.3f} s, flood {t['flood_all_s']:.3f} s; without the cache "
                     f"(a scan's first frame) {t['stripe_all_uncached_s']:.3f} s, "
                     f"{t['flood_all_uncached_s']:.3f} s: "
                     f"{t['stripe_all_uncached_s'] / t['stripe_all_s']:.2f}x, "
                     f"{t['flood_all_uncached_s'] / t['flood_all_s']:.2f}x")
    for lv in ("preview", "standard"):
        t = tim["levels"][lv]
        lines.append(f"single scattering ({lv}) vs its 'reference' level, max rel. error: "
                     + ", ".join(f"{k} {t[f'stripe_single_{k}_max']:.1e}" for k in "DAB") + " (stripe), "
                     + ", ".join(f"{k} {t[f'flood_single_{k}_max']:.1e}" for k in "DAB") + " (flood)")
    lines.append(f"single scattering ÷ all orders: worst {100 * summ['single_max_err']:.0f} % off; frame "
                 "times are CPU seconds at 640×480 (stripe 14/30 unless noted), first call of this process "
                 f"{tim['first_call_s']:.2f} s")
    if tim.get("threads"):
        lines.append(describe(tim["threads"]))
    lines.append("targets: " + ", ".join(f"{k} {'met' if v else 'MISSED'}"
                                         for k, v in summ["targets"].items()))
    return "\n".join(lines)


def render_references(data: Path) -> None:
    """Render the own validation scenes with Mitsuba (two seeds each) into ``data``."""
    import mitsuba as mi
    from polarstripe.bench.mitsuba_references import scene_toml, write_readme
    from polarstripe.sim.mitsuba_scene import render_truth, select_variant

    variant = select_variant(None)
    for name, case in cases().items():
        imgs, secs = [], []
        for seed in (0, 1):
            t = time.perf_counter()
            imgs.append(render_truth(case.scene, case.pattern, max_depth=-1, spp=case.spp, seed=seed,
                                     variant=variant, pass_spp=4096))
            secs.append(time.perf_counter() - t)
        imgs = np.stack(imgs)
        reg = np.stack([regions(im) for im in imgs])
        np.savez_compressed(data / f"{file_stem(name)}.npz", images=imgs.astype(np.float32),
                            seeds=np.array([0, 1]), spp=np.array(case.spp), max_depth=np.array(-1),
                            pattern=np.array(case.pattern),
                            scene_toml=np.array(scene_toml(case.scene)), seconds=np.array(secs), regions=reg,
                            spread=(reg.max(0) - reg.min(0)) / reg.mean(0), what=np.array(case.what),
                            mitsuba_version=np.array(mi.__version__), variant=np.array(variant))
        (data / f"{file_stem(name)}.toml").write_text(scene_toml(case.scene))
        print(f"{name}: {' / '.join(f'{s:.0f}' for s in secs)} s", flush=True)
    write_readme(data)  # the README lists the tank's references and these


def run(args: argparse.Namespace) -> dict:
    if args.render_references:
        render_references(args.data)
    acc = accuracy(args.data)
    acc["polarization"] = polarization(getattr(args, "data_polarized", DATA_POLARIZED))
    if args.threads < 1:
        raise PolarstripeError(f"--threads must be >= 1, got {args.threads}")
    tim = timing(args.repeat, args.quick, args.samples, args.threads)
    return {"accuracy": acc, "timing": tim, "summary": summarize(acc, tim)}


def main(args: argparse.Namespace) -> int:
    res = run(args)
    print(json.dumps(res, default=float) if getattr(args, "json", False) else _table(res))
    return 0
