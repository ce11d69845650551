"""A polarstripe :class:`~polarstripe.sim.scene.Scene` as a Mitsuba 3 scene: an all-orders Monte Carlo truth.

>>> from polarstripe.sim.mitsuba_scene import render_truth, to_mitsuba
>>> from polarstripe.sim.scene import load_scene
>>> spec = to_mitsuba(load_scene(None), "stripe:14/30", native=False)   # plain dict, no mitsuba needed
>>> img = render_truth(load_scene(None), "flood", spp=1024, seed=0)     # doctest: +SKIP

Mapping (lengths [m], radiance [W sr⁻¹ m⁻²] as :func:`polarstripe.sim.render.render_components`):

* medium → ``homogeneous`` (σ_t [1/m], albedo) inside a ``cube`` with a ``null`` BSDF scaled to
  ``medium.extent``; Haltrin's TTHG α·HG(g_F) + (1 − α)·HG(−g_B) → ``blendphase`` with ``weight = 1 − α``,
  ``phase_0 = hg(g_F)``, ``phase_1 = hg(−g_B)``; ``hg`` → ``hg``; ``isotropic`` → ``isotropic``.
* camera → ``perspective`` (horizontal fov), ``hdrfilm`` with a ``box`` filter and ``luminance`` pixels: a
  pixel is the mean radiance over its footprint (polarstripe samples its centre). Mitsuba's ``look_at`` puts
  world +x on the image left for a camera looking along +z with up +y, as polarstripe (image right = f × up).
* projector ``point`` → ``point`` emitter of ``intensity_w_sr`` [W/sr] (exact: no ``source_radius_m``);
  ``pinhole`` → Mitsuba's ``projector`` emitter with the pattern as its texture (:func:`projector_texture`).
* objects → ``rectangle`` (plane; an unbounded one becomes a square twice the tank's diagonal), ``sphere``,
  ``cube`` (box), with a one-sided ``diffuse`` BSDF. A textured plane (chart or PNG) gets a ``bitmap`` of
  polarstripe's own albedo on a texel grid (nearest-neighbour), not a mean albedo. Objects inside the medium
  box get the medium on both sides; a plane on a face of the box (the default chart on the back wall) is
  moved 0.1 mm into the box, off the tank's null boundary.
* a camera port (docs/physics.md §11) → two ``rectangle`` faces (2·PORT_HALF_M square) with ``dielectric``
  BSDFs, air → glass and glass → water (Fresnel and the n² of radiance included by Mitsuba); single
  scattering behind it needs ``max_depth`` 4 (two more specular vertices). A projector port is refused: a
  delta light behind a dielectric is never reached.
* a camera or light inside the box gets the medium; one *on* a face of the box (the default tank's, z = 0)
  is moved 0.1 mm out of it, orientation kept: Mitsuba misses a boundary crossed at t ≈ 0, and its paths
  would never enter the medium.

``max_depth`` is Mitsuba's path depth: 2 is single scattering (B without an object, D + B with one; the
paper's A, light → medium → object → camera, needs depth 3, where double medium scattering enters too);
−1 is all orders. Russian roulette starts at ``rr_depth`` (large by default: it adds variance otherwise).
"""

from __future__ import annotations

import glob
import os
import re
import subprocess
import sys
import warnings

import numpy as np
from polarstripe.sim.geometry import Hits, pinhole_frame, plane_axes
from polarstripe.sim.patterns import PatternSpec, gray_lit, parse_pattern, sheet_columns
from polarstripe.sim.phase import tthg_parameters
from polarstripe.sim.port import port_geometry
from polarstripe.sim.scene import BoxObject, PlaneObject, Scene, SceneError, SphereObject
from polarstripe.sim.surface import surface_info

PLANE_OFFSET_M = 1e-4          # a plane on a face of the medium box is moved this far into the box
ENDPOINT_OFFSET_M = 1e-4       # a camera or light on a face of the medium box is moved this far out of it
TEXELS = 512                   # texel columns of a textured plane's albedo bitmap
DEFAULT_VARIANTS = ("llvm_ad_mono", "llvm_ad_rgb", "scalar_rgb")
_LLVM_HINT = ("install libLLVM >= 17 (apt-get install -y libllvm19) and set "
              "DRJIT_LIBLLVM_PATH=/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1")
_MEDIUM_ID = "water"


def _affine(x_axis, y_axis, z_axis, origin) -> np.ndarray:
    """4×4 matrix with the given columns (images of the local axes) and translation."""
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x_axis, y_axis, z_axis, origin
    return m


def _look_at(position, look_at, up) -> np.ndarray:
    """4×4 camera-to-world matrix as Mitsuba's ``look_at``: columns (left, up, forward, position)."""
    f = np.asarray(look_at, float) - np.asarray(position, float)
    f /= np.linalg.norm(f)
    left = np.cross(np.asarray(up, float), f)
    left /= np.linalg.norm(left)
    return _affine(left, np.cross(f, left), f, np.asarray(position, float))


def _box(lo, hi) -> np.ndarray:
    """4×4 matrix taking Mitsuba's cube [−1, 1]³ to the box [lo, hi]."""
    c, e = 0.5 * (np.add(lo, hi)), 0.5 * np.subtract(hi, lo)
    return _affine((e[0], 0, 0), (0, e[1], 0), (0, 0, e[2]), c)


def _inside(p, lo, hi, margin: float = 0.0) -> bool:
    p = np.asarray(p, float)
    return bool(np.all(p > lo + margin) and np.all(p < hi - margin))


def _off_boundary(p, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """A point within ENDPOINT_OFFSET_M of the box surface, moved ENDPOINT_OFFSET_M outside it (per axis)."""
    p = np.array(p, float)
    tol = ENDPOINT_OFFSET_M
    if not np.all((p >= lo - tol) & (p <= hi + tol)) or _inside(p, lo, hi, tol):
        return p
    p = np.where(np.abs(p - lo) < tol, lo - tol, p)
    return np.where(np.abs(p - hi) < tol, hi + tol, p)


def _phase(phase) -> dict:
    """Mitsuba phase function of a polarstripe :class:`~polarstripe.sim.scene.Phase`."""
    if phase.model == "isotropic":
        return {"type": "isotropic"}
    if phase.model == "hg":
        return {"type": "hg", "g": float(phase.g)}
    gf, gb, alpha = tthg_parameters(float(phase.g))
    if alpha == 0.0:
        return {"type": "isotropic"}
    return {"type": "blendphase", "weight": float(1.0 - alpha),
            "phase_0": {"type": "hg", "g": float(gf)}, "phase_1": {"type": "hg", "g": float(-gb)}}


def projector_texture(scene: Scene, pattern: str | PatternSpec) -> np.ndarray:
    """Irradiance texture (H, W) float32 of Mitsuba's ``projector`` for a pinhole projector and a pattern.

    Mitsuba's projector sends π·E/cos³θ [W/sr] for a texel E at angle θ from its axis (uv from its perspective
    mapping, as its camera's). The texture is lit(row, col)·I0·cos³θ/π at each pattern pixel's centre, with
    lit ∈ {1, black_level} and I0 = ``intensity_w_sr`` [W/sr], nearest-neighbour: I0 [W/sr] through every
    lit pattern pixel, as polarstripe. Row 0 is the pattern's top row, column 0 its left column.
    """
    pr = scene.projector
    pat = parse_pattern(pattern)
    w, h = pr.resolution
    s = 2.0 * np.tan(np.radians(pr.fov_deg) / 2.0) / w
    x = (np.arange(w) + 0.5 - w / 2.0) * s
    y = (np.arange(h) + 0.5 - h / 2.0) * s
    cos3 = (1.0 + x[None, :] ** 2 + y[:, None] ** 2) ** -1.5
    rows, cols = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    if pat.kind == "flood":
        lit = np.ones((h, w), bool)
    elif pat.kind == "stripe":       # every sheet of it
        lit = np.logical_or.reduce([(cols >= c0) & (cols < c1) for c0, c1 in sheet_columns(pat, w)])
    elif pat.kind == "gray":
        lit = gray_lit(pat, cols + 0.5, rows + 0.5)
    else:
        shift = pat.shift % (2 * pat.size)
        lit = (np.floor((cols - shift) / pat.size) + np.floor(rows / pat.size)) % 2 == 0
    level = np.where(lit, 1.0, pr.black_level)
    return (level * pr.intensity_w_sr * cos3 / np.pi).astype(np.float32)


def plane_albedo_texture(obj: PlaneObject, texels: int = TEXELS) -> np.ndarray:
    """Albedo bitmap (rows, texels) float32 of a textured plane, sampled from polarstripe's own lookup.

    Row 0 is the plane's *bottom* edge (Mitsuba's rectangle maps its local −y to uv.y = 0, the first row);
    column 0 is its left edge seen from the front.
    """
    sw, sh = obj.size
    rows = max(2, int(round(texels * sh / sw)))
    ra, ua = plane_axes(obj)
    fx = (np.arange(texels) + 0.5) / texels - 0.5
    fy = (np.arange(rows) + 0.5) / rows - 0.5                 # bottom → top
    pts = (np.asarray(obj.point)[None, None, :] + fx[None, :, None] * sw * ra
           + fy[:, None, None] * sh * ua).reshape(-1, 3)
    n = pts.shape[0]
    hits = Hits(np.ones(n), np.zeros(n, np.int64), np.broadcast_to(obj.normal, (n, 3)).copy(), pts)
    return surface_info((obj,), hits).albedo.reshape(rows, texels).astype(np.float32)


def _bsdf(albedo_or_texture) -> dict:
    if np.ndim(albedo_or_texture) == 0:
        return {"type": "diffuse", "reflectance": float(albedo_or_texture)}
    return {"type": "diffuse", "reflectance": {"type": "bitmap", "data": albedo_or_texture[..., None],
                                               "filter_type": "nearest", "wrap_mode": "clamp", "raw": True}}


def _objects(scene: Scene, lo: np.ndarray, hi: np.ndarray, texels: int) -> dict:
    out = {}
    ref = {"type": "ref", "id": _MEDIUM_ID}
    diag = float(np.linalg.norm(hi - lo))
    for k, o in enumerate(scene.objects):
        if isinstance(o, PlaneObject):
            n = np.asarray(o.normal)
            p = np.asarray(o.point, float)
            if not _inside(p, lo, hi, PLANE_OFFSET_M / 2) and _inside(p + PLANE_OFFSET_M * n, lo, hi):
                p = p + PLANE_OFFSET_M * n
            ra, ua = plane_axes(o)
            if o.size is None:
                c = 0.5 * (lo + hi)
                p = p + ra * ((c - p) @ ra) + ua * ((c - p) @ ua)
                half_w = half_h = diag
            else:
                half_w, half_h = 0.5 * o.size[0], 0.5 * o.size[1]
            d = {"type": "rectangle", "to_world": _affine(ra * half_w, ua * half_h, n, p),
                 "bsdf": _bsdf(plane_albedo_texture(o, texels) if o.texture else o.albedo)}
            inside = _inside(p, lo, hi)
        elif isinstance(o, SphereObject):
            r = o.radius
            d = {"type": "sphere", "to_world": _affine((r, 0, 0), (0, r, 0), (0, 0, r), o.center),
                 "bsdf": _bsdf(o.albedo)}
            inside = _inside(o.center, lo, hi)
        elif isinstance(o, BoxObject):
            d = {"type": "cube", "to_world": _box(o.min, o.max), "bsdf": _bsdf(o.albedo)}
            inside = _inside(0.5 * np.add(o.min, o.max), lo, hi)
        else:
            raise SceneError(f"object[{k}]: type {type(o).__name__} has no Mitsuba counterpart")
        if inside:
            d["interior"], d["exterior"] = dict(ref), dict(ref)
        out[f"object_{k}"] = d
    return out


def to_mitsuba(scene: Scene, pattern: str | PatternSpec = "flood", *, max_depth: int = -1, spp: int = 1024,
               seed: int = 0, rr_depth: int = 100000, texels: int = TEXELS, native: bool = True) -> dict:
    """The Mitsuba 3 scene dictionary of a polarstripe scene lit by one pattern.

    Parameters
    ----------
    scene : Scene
        Any polarstripe scene (see ``docs/scene-format.md``); lengths [m], σ_t [1/m], I0 [W/sr].
    pattern : ``flood``, ``stripe:K/N``, ``checker:SIZE:SHIFT`` or a PatternSpec (``point`` source: flood
        only).
    max_depth : Mitsuba path depth (2 = single scattering, −1 = all orders).
    spp, seed : samples per pixel and seed of the ``independent`` sampler.
    rr_depth : depth at which Russian roulette starts.
    texels : texel columns of a textured plane's albedo bitmap.
    native : True: ready for ``mitsuba.load_dict`` (imports mitsuba, needs a variant set: transforms become
        ``ScalarTransform4f``, bitmaps ``TensorXf``). False: the same tree with 4×4 numpy matrices and numpy
        arrays, without importing mitsuba.

    Returns
    -------
    dict with keys ``type`` (``scene``), ``integrator``, ``sensor``, ``water`` (the medium), ``tank``,
    ``light`` and ``object_<k>`` per object. Raises SceneError for a non-flood pattern with a point source.
    The emitter is unpolarized whatever ``projector.polarization`` says: compare its intensities with the
    model of the same scene with ``projector.polarization.dop = 0`` (a polarized source changes the model's
    intensity through the Mueller matrix's m12, docs/physics.md §5).
    """
    if not isinstance(scene, Scene):
        raise SceneError(f"scene must be a Scene (see load_scene), got {type(scene).__name__}")
    pat = parse_pattern(pattern)
    pr, cam, med = scene.projector, scene.camera, scene.medium
    if pr.model == "point" and pat.kind != "flood":
        raise SceneError(f"pattern {str(pat)!r} needs projector.model = 'pinhole' "
                         "(the point source is flood only)")
    lo, hi = np.asarray(med.extent.min, float), np.asarray(med.extent.max, float)
    ref = {"type": "ref", "id": _MEDIUM_ID}
    w, h = cam.resolution
    cpos, ppos = _off_boundary(cam.position, lo, hi), _off_boundary(pr.position, lo, hi)
    sensor = {"type": "perspective", "fov": float(cam.fov_deg), "fov_axis": "x", "near_clip": 1e-6,
              "far_clip": 1e4,
              "to_world": _look_at(cpos, cpos + np.subtract(cam.look_at, cam.position), cam.up),
              "film": {"type": "hdrfilm", "width": int(w), "height": int(h), "pixel_format": "luminance",
                       "component_format": "float32", "rfilter": {"type": "box"}},
              "sampler": {"type": "independent", "sample_count": int(spp), "seed": int(seed)}}
    if _inside(cpos, lo, hi):
        sensor["medium"] = dict(ref)
    if pr.model == "point":
        light = {"type": "point", "position": [float(c) for c in ppos],
                 "intensity": {"type": "uniform", "value": float(pr.intensity_w_sr)}}
    else:
        frame = pinhole_frame(pr.position, pr.look_at, pr.up, pr.fov_deg, pr.resolution)
        light = {"type": "projector", "fov": float(pr.fov_deg), "fov_axis": "x",
                 "to_world": _look_at(ppos, ppos + frame.f, frame.u),
                 "irradiance": {"type": "bitmap", "data": projector_texture(scene, pat)[..., None],
                                "filter_type": "nearest", "wrap_mode": "clamp", "raw": True}}
    if _inside(ppos, lo, hi):
        light["medium"] = dict(ref)
    out = {
        "type": "scene",
        "integrator": {"type": "volpath", "max_depth": int(max_depth), "rr_depth": int(rr_depth)},
        "sensor": sensor,
        _MEDIUM_ID: {"type": "homogeneous", "sigma_t": float(med.sigma_t), "albedo": float(med.albedo),
                     "scale": 1.0, "phase": _phase(med.phase)},
        "tank": {"type": "cube", "to_world": _box(lo, hi), "bsdf": {"type": "null"}, "interior": dict(ref)},
        "light": light,
    }
    out.update(_objects(scene, lo, hi, texels))
    out.update(_port_faces(scene, cpos))
    return _native(out) if native else out


PORT_HALF_M = 0.02     # half the side of a port's faces in Mitsuba (they must cover the camera's view)


def _port_faces(scene: Scene, cpos: np.ndarray) -> dict:
    """A camera port as two ``rectangle`` faces with ``dielectric`` BSDFs (docs/physics.md §11): the inner
    face air → glass, the outer glass → water; each rectangle's normal faces the camera (its exterior side).
    A projector port has no Mitsuba counterpart: a point or projector light cannot be reached through a
    specular interface by next-event estimation, and a path never hits it by chance."""
    cam, pr = scene.camera, scene.projector
    if pr.port is not None:
        raise SceneError("projector.port has no Mitsuba truth: a delta light behind a dielectric is "
                         "never reached by a path tracer (docs/physics.md §11)")
    if cam.port is None:
        return {}
    frame = pinhole_frame(cam.position, cam.look_at, cam.up, cam.fov_deg, cam.resolution)
    g = port_geometry(cam.port, cpos, frame.f)
    e1 = np.cross(g.normal, [0.0, 1.0, 0.0] if abs(g.normal[1]) < 0.9 else [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(e1, g.normal)            # (e1, e2, −n) right-handed: the rectangle's normal is −n
    out = {}
    faces = [("port_inner", g.d, g.n_a, g.n_g), ("port_outer", g.d + g.t, g.n_g, g.n_w)]
    if g.t <= 0.0:
        faces = [("port_outer", g.d, g.n_a, g.n_w)]
    for name, dist, n_ext, n_int in faces:
        m = _affine(e1 * PORT_HALF_M, e2 * PORT_HALF_M, -g.normal, g.apex + dist * g.normal)
        out[name] = {"type": "rectangle", "to_world": m,
                     "bsdf": {"type": "dielectric", "int_ior": float(n_int), "ext_ior": float(n_ext)}}
    return out


def _native(tree):
    """Numpy 4×4 matrices under ``to_world`` → ScalarTransform4f, numpy arrays under ``data`` → TensorXf."""
    import mitsuba as mi

    def conv(k, v):
        if isinstance(v, dict):
            return {kk: conv(kk, vv) for kk, vv in v.items()}
        if k == "to_world" and isinstance(v, np.ndarray):
            return mi.ScalarTransform4f(v)
        if k == "data" and isinstance(v, np.ndarray):
            return mi.TensorXf(np.ascontiguousarray(v, np.float32))
        return v

    return conv("", tree)


_PROBE = ("from polarstripe.sim.mitsuba_scene import render_truth\n"
          "from polarstripe.sim.scene import load_scene\n"
          "s = load_scene(None)\n"
          "render_truth(s.replace(camera=s.camera.replace(resolution=(4, 3))), spp=4, variant={variant!r})\n")
_VARIANT_OK: dict[str, bool] = {}


def _llvm_env() -> None:
    """Point drjit at the newest libLLVM ≥ 17 found, unless DRJIT_LIBLLVM_PATH is already set."""
    if os.environ.get("DRJIT_LIBLLVM_PATH") or "drjit" in sys.modules:
        return
    found = [(int(m.group(1)), f) for f in glob.glob("/usr/lib/*/libLLVM.so.*")
             if (m := re.search(r"libLLVM\.so\.(\d+)", f)) and int(m.group(1)) >= 17]
    if found:
        os.environ["DRJIT_LIBLLVM_PATH"] = max(found)[1]


def _works(variant: str) -> bool:
    """Run a tiny medium render in a subprocess (an LLVM that cannot compile it aborts the process)."""
    if variant not in _VARIANT_OK:
        if variant.startswith("scalar"):
            _VARIANT_OK[variant] = True
        else:
            r = subprocess.run([sys.executable, "-c", _PROBE.format(variant=variant)], capture_output=True,
                               timeout=300, env=os.environ.copy())
            _VARIANT_OK[variant] = r.returncode == 0
    return _VARIANT_OK[variant]


def select_variant(variant: str | None = None) -> str:
    """Set and return a Mitsuba variant: ``variant``, else the first working of ``llvm_ad_mono``,
    ``llvm_ad_rgb``, ``scalar_rgb`` (a one-line warning says how to fix libLLVM on the fallback)."""
    _llvm_env()
    import mitsuba as mi

    if variant is None:
        have = mi.variants()
        for v in DEFAULT_VARIANTS:
            if v in have and _works(v):
                variant = v
                break
        else:
            raise RuntimeError(f"no usable Mitsuba variant among {DEFAULT_VARIANTS} (installed: {have})")
        if variant.startswith("scalar"):
            warnings.warn(f"mitsuba: LLVM variants unusable, falling back to slow {variant}; to fix, "
                          f"{_LLVM_HINT}", RuntimeWarning, stacklevel=3)
    if mi.variant() != variant:
        mi.set_variant(variant)
    return variant


def render_truth(scene: Scene, pattern: str | PatternSpec = "flood", *, max_depth: int = -1, spp: int = 4096,
                 seed: int = 0, variant: str | None = None, pass_spp: int = 2048,
                 rr_depth: int = 100000) -> np.ndarray:
    """Mitsuba's Monte Carlo radiance image of a polarstripe scene (all orders by default).

    Parameters
    ----------
    scene, pattern : as :func:`to_mitsuba`.
    max_depth : path depth (2: single scattering, −1: all orders).
    spp : samples per pixel in total, rendered in passes of ``pass_spp`` (bounds the memory of a pass).
    seed : base seed; pass k uses sampler seed ``seed·65537 + k`` (distinct seeds → independent estimates).
    variant : Mitsuba variant, None = :func:`select_variant`'s choice.
    rr_depth : depth at which Russian roulette starts.

    Returns
    -------
    float64 (h, w) radiance [W sr⁻¹ m⁻²] before any analyzer, row 0 at the top, as D + A + B of
    :func:`polarstripe.sim.render.render_components` (each pixel averaged over its footprint).
    """
    select_variant(variant)
    import mitsuba as mi

    spec = to_mitsuba(scene, pattern, max_depth=max_depth, spp=min(spp, pass_spp), seed=seed,
                      rr_depth=rr_depth, native=True)
    mscene = mi.load_dict(spec)
    w, h = scene.camera.resolution
    acc, done, k = np.zeros((h, w)), 0, 0
    while done < spp:
        n = min(pass_spp, spp - done)
        img = np.array(mi.render(mscene, spp=n, seed=int(seed) * 65537 + k), dtype=np.float64)
        acc += n * (img[..., 0] if img.ndim == 3 else img)
        done, k = done + n, k + 1
    return acc / spp
