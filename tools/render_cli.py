"""``polarstripe render``: one frame of a scene with the light-transport model, written to a folder.

Writes ``image.png`` (16-bit DN from the EMVA 1288 sensor), ``meta.json`` (the resolved scene, pattern,
fidelity, the orders of scattering modelled and the error to expect, seconds) and with ``--components``
``D.npy``, ``A.npy``, ``B.npy`` (float64 radiance W·sr⁻¹·m⁻², shape (h, w), before the analyzer).
``--orders single`` renders the paper's single-scattering model; the default ``all`` adds every higher order
where the scene needs them (docs/physics.md §10).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import cv2
import numpy as np
from polarstripe.errors import PolarstripeError
from polarstripe.runtime.params import check_frame_size
from polarstripe.sim.orders import ORDERS
from polarstripe.sim.patterns import parse_pattern
from polarstripe.sim.render import render_frame, resolve_fidelity
from polarstripe.sim.scene import load_scene, parse_size, scene_to_dict
from polarstripe.sim.threads import set_threads

HELP = "render one frame of a scene with the light-transport model"


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scene", nargs="?", default=None,
                        help="scene TOML file (docs/scene-format.md); omitted: the paper's default tank")
    parser.add_argument("--pattern", default="flood",
                        help="flood | stripe:K/N[:xSHEETS] | checker:SIZE:SHIFT | "
                             "gray:BIT:col|row:INV[:xorBASE] (stripe:I/N:xK: K sheets at once, positions I, "
                             "I + ceil(N/K), ...; Gray code bit BIT, its inverse with INV = 1, XOR the "
                             "column code's bit BASE)")
    parser.add_argument("--polarizer", type=float, default=None, metavar="DEG",
                        help="analyzer angle [deg] from image right toward image up "
                             "(default: camera.polarizer.angle_deg of the scene; none there = no analyzer)")
    parser.add_argument("--fidelity", default="standard",
                        help="preview | standard | reference | 'xi=N,theta=N,phi=N,grid=WxH|none,cells=N'")
    parser.add_argument("--orders", default="all", choices=ORDERS,
                        help="all: every order of scattering where the scene needs them (default); "
                             "single: the paper's single-scattering model")
    parser.add_argument("--components", action="store_true", help="also write D.npy, A.npy, B.npy")
    parser.add_argument("--resolution", default=None, metavar="WxH", help="override the camera resolution")
    parser.add_argument("--seed", type=int, default=None, help="sensor noise seed (default: camera.seed)")
    parser.add_argument("--threads", type=int, default=0,
                        help="model threads (default 0: the cores of this process's CPU affinity); the frame "
                             "is the same for any count")
    parser.add_argument("-o", "--out", required=True, help="output folder (created)")



def main(args: argparse.Namespace) -> int:

    if args.threads < 0:
        raise PolarstripeError(f"--threads must be >= 0 (0: the CPU affinity), got {args.threads}")
    threads = set_threads(args.threads)
    pattern = parse_pattern(args.pattern)
    fidelity = resolve_fidelity(args.fidelity)
    scene = load_scene(args.scene)
    if args.resolution:
        size = parse_size(args.resolution, "--resolution")
        scene = scene.replace(camera=scene.camera.replace(resolution=size))
    try:  # before the output folder exists: a refused size leaves nothing behind
        check_frame_size(*scene.camera.resolution, what="--resolution" if args.resolution else "resolution")
    except ValueError as exc:
        raise PolarstripeError(str(exc)) from None
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    angle = args.polarizer if args.polarizer is not None else scene.camera.polarizer.angle_deg
    dn, comp = render_frame(scene, pattern, angle, fidelity, seed=args.seed, orders=args.orders)
    seconds = time.perf_counter() - t0
    if not cv2.imwrite(str(out / "image.png"), dn):
        raise OSError(f"cannot write {out / 'image.png'}")
    if args.components:
        for name in ("D", "A", "B"):
            np.save(out / f"{name}.npy", np.ascontiguousarray(getattr(comp, name), dtype=np.float64))
    meta = {
        "scene": scene_to_dict(scene),
        "scene_file": None if args.scene is None else str(args.scene),
        "pattern": str(pattern),
        "polarizer_deg": angle,
        "fidelity": {"name": fidelity.name, "xi_nodes": fidelity.xi_nodes, "hemi_theta": fidelity.hemi_theta,
                     "hemi_phi": fidelity.hemi_phi, "a_grid": fidelity.a_grid,
                     "higher": dataclasses.asdict(fidelity.higher)},
        "orders": comp.orders.as_dict(),
        "seconds": seconds,
        "threads": threads,
        "units": {"image.png": "DN (uint16)", "D/A/B.npy": "W sr^-1 m^-2, before the analyzer"},
        "seed": scene.camera.seed if args.seed is None else args.seed,
        "saturated_pixels": int(np.count_nonzero(dn >= (1 << scene.camera.bits) - 1)),
    }
    (out / "meta.json").write_text(json.dumps(meta, indent=2))
    kind = "all orders" if comp.orders.modelled else "single scattering"
    print(f"wrote {out}/image.png ({dn.shape[1]}x{dn.shape[0]}, {pattern}, {fidelity.name}, {kind}, "
          f"expected error {100 * comp.orders.expected_error:.0f} %, {seconds:.2f} s)")
    return 0
