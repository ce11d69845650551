"""``polarstripe figure``: the model's curves as PNG (matplotlib, Agg backend).

- ``ds``: D/S versus optical thickness σ_t·z_object (the paper's Fig. 5), from render_components on the
  scene's lit object pixels (mean over a few pixels), flood light; with all orders of scattering (the model's
  default; S = D + A then includes the forward-scattered light, so D/S falls faster, as the paper notes) and,
  dashed, with single scattering (the paper's curve).
- ``dop``: DOP of singly scattered light versus scattering angle (the paper's Fig. 11), Mueller model with the
  scene's depolarization δ, for source DOP_L ∈ {0, 0.5, 1} (polarization ⊥ and ∥ to the scattering plane),
  and pure Rayleigh (δ = 0, unpolarized source) for comparison.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib
import matplotlib.pyplot as plt
import numpy as np
from polarstripe.sim.geometry import intersect, pinhole_frame, pixel_rays
from polarstripe.sim.polarization import dop_backscatter
from polarstripe.sim.render import render_components
from polarstripe.sim.scene import SceneError, load_scene

HELP = "plot the model's curves (D/S vs optical thickness, DOP vs scattering angle) as PNG"


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scene", nargs="?", default=None, help="scene TOML (default: the paper's tank)")
    parser.add_argument("--which", choices=["ds", "dop", "all"], default="all", help="which figure(s)")
    parser.add_argument("--fidelity", default="standard", help="model fidelity for the D/S curve")
    parser.add_argument("--max-thickness", type=float, default=10.0, help="largest optical thickness (ds)")
    parser.add_argument("--orders", choices=["all", "single", "both"], default="both",
                        help="D/S with all orders of scattering, single scattering, or both (default)")
    parser.add_argument("-o", "--out", default=".", help="output folder (created)")


def ds_curve(scene, thickness: np.ndarray, fidelity="standard", n_pixels: int = 9, orders: str = "all"):
    """D/S at lit object pixels for each optical thickness σ_t·z (z: median camera-to-object depth), with
    ``orders`` of scattering (``all`` or ``single``, as :func:`polarstripe.sim.render.render_components`).

    Returns
    -------
    (thickness, ds_mean, ds_min, ds_max) arrays.
    """

    probe = render_components(scene.replace(medium=scene.medium.replace(sigma_t=0.0)), "flood", "preview",
                              need=("D",))
    rows, cols = np.nonzero(probe.object_mask & (probe.D > 0))
    if rows.size == 0:

        raise SceneError("figure ds: no camera pixel sees a lit object in this scene")
    pick = np.linspace(0, rows.size - 1, n_pixels).astype(int)
    px = np.stack([rows[pick], cols[pick]], axis=1)

    c = scene.camera
    cam = pinhole_frame(c.position, c.look_at, c.up, c.fov_deg, c.resolution)
    hits = intersect(scene.objects, cam.position, pixel_rays(cam, px))
    depth = float(np.median((hits.point - cam.position) @ cam.f))        # camera-to-object depth z [m]
    out = []
    for tau in thickness:
        sc = scene.replace(medium=scene.medium.replace(sigma_t=tau / depth))
        c = render_components(sc, "flood", fidelity, pixels=px, need=("D", "A"), orders=orders)
        ds = c.D / np.maximum(c.D + c.A, 1e-300)
        out.append((ds.mean(), ds.min(), ds.max()))
    arr = np.array(out)
    return thickness, arr[:, 0], arr[:, 1], arr[:, 2]


def main(args: argparse.Namespace) -> int:

    matplotlib.use("Agg")

    scene = load_scene(args.scene)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    if args.which in ("ds", "all"):
        tau = np.linspace(0.0, args.max_thickness, 21)
        which = getattr(args, "orders", "both")
        fig, ax = plt.subplots(figsize=(5, 3.6), dpi=120)
        for orders, style in (("all", "o-"), ("single", "s--")):
            if which not in (orders, "both"):
                continue
            t, mean, lo, hi = ds_curve(scene, tau, args.fidelity, orders=orders)
            name = "all orders" if orders == "all" else "single scattering (the paper)"
            ax.plot(t, mean, style, ms=3, label=f"{name}: mean over lit object pixels")
            ax.fill_between(t, lo, hi, alpha=0.2)
        ax.set_xlabel("optical thickness σ_t·z")
        ax.set_ylabel("D / S")
        ax.set_ylim(0, 1.02)
        ph = scene.medium.phase
        ax.set_title(f"D/S (Fig. 5), {ph.model} {ph.g:g}, albedo {scene.medium.albedo:g}")
        ax.grid(alpha=0.3)
        ax.legend()
        fig.tight_layout()
        fig.savefig(out / "fig5_ds_vs_thickness.png")
        plt.close(fig)
        written.append(out / "fig5_ds_vs_thickness.png")
    if args.which in ("dop", "all"):
        th = np.linspace(0.0, 180.0, 361)
        r = np.radians(th)
        delta = scene.medium.dop.depolarization
        fig, ax = plt.subplots(figsize=(5, 3.6), dpi=120)
        for dop_l, psi, style in ((1.0, 90, "-"), (1.0, 0, "--"), (0.5, 90, "-."), (0.0, 90, ":")):
            where = "" if dop_l == 0 else f", {'⊥' if psi == 90 else '∥'} plane"
            curve = dop_backscatter(r, dop_l, np.radians(psi), delta)
            ax.plot(th, curve, style, label=f"DOP_L = {dop_l:g}{where}")
        ax.plot(th, dop_backscatter(r, 0.0, 0.0, 0.0), color="grey", lw=0.8, label="Rayleigh (δ = 0)")
        ax.set_xlabel("scattering angle θ_s [deg]")
        ax.set_ylabel("DOP_B")
        ax.set_title(f"DOP of scattered light (Fig. 11), δ = {delta:g}")
        ax.set_xlim(0, 180)
        ax.set_ylim(0, 1.02)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(out / "fig11_dop_vs_angle.png")
        plt.close(fig)
        written.append(out / "fig11_dop_vs_angle.png")
    for p in written:
        print(f"wrote {p}")
    return 0
