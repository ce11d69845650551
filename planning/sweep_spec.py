"""Design-study specs for ``polarstripe sweep``: the TOML grid a designer asks for, checked before it runs.

A spec names a base scene, the planner's options and a grid; every combination of the grid's axes other than
``separation`` is one scene, and the planner sweeps ``separation`` in each (docs/planning.md §4)::

    scene = "tank.toml"            # optional, relative to the spec; default: the paper's tank
    fidelity = "preview"           # model fidelity of every plan
    modalities = ["flood", "stripes"]
    edge = "margin"                # stripe measure: margin | eq9
    k_detect = 3.0                 # W's detection threshold [noise std]
    orders = "all"                 # the model's orders of scattering: all (as the scene needs) | single
    max_scenes = 10000             # refuse larger grids (raise it here if you mean it)

    [grid]
    separation = {min = 0.01, max = 0.3, n = 30}   # d_LC [m], swept by each plan
    sigma_t = {min = 2.0, max = 10.0, n = 9}       # extinction [1/m]
    albedo = [1.0]                                  # the medium's single-scattering albedo σ_s/σ_t
    mean_cosine = [0.8]                             # TTHG mean cosine of the phase function
    object_albedo = [0.6]                           # albedo of every object (default: the scene's)
    exposure = ["auto", 0.008]                      # "auto", "scene" or seconds
    stripes = [30]                                  # stripes per scan

An axis is a list of values, one value, or ``{min, max, n}`` (n evenly spaced values, both ends included).
Errors (:class:`SweepSpecError`) name the key: an unknown key, a NaN or infinite number, an empty range, a
separation range whose source leaves the medium's front face ("beyond the tank": the model would light the
tank through clear air), a value the scene rejects, or a grid over ``max_scenes``.
"""

from __future__ import annotations

import itertools
import math
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from polarstripe.errors import PolarstripeError
from polarstripe.planning.objectives import EDGES, MODALITIES
from polarstripe.planning.scene_model import SceneModel
from polarstripe.sim.geometry import point_in_box
from polarstripe.sim.orders import ORDERS
from polarstripe.sim.render import resolve_fidelity
from polarstripe.sim.scene import Phase, Scene, SceneError, load_scene, with_separation

AXES = ("sigma_t", "albedo", "mean_cosine", "object_albedo", "exposure", "stripes")
TOP_KEYS = {"scene", "fidelity", "modalities", "edge", "k_detect", "max_scenes", "grid", "orders"}
MAX_SCENES = 10_000
MAX_SEPARATIONS = 1_000


class SweepSpecError(PolarstripeError, ValueError):
    """A sweep spec is invalid; the text names the key and the value."""


@dataclass(frozen=True)
class SweepSpec:
    """A checked spec: the base scene, the planner's options, the separations and the scene axes."""

    base: Scene
    fidelity: str
    modalities: tuple[str, ...]
    edge: str
    k_detect: float
    separations: np.ndarray
    axes: dict[str, tuple]
    source: str = ""
    orders: str = "all"

    @property
    def n_scenes(self) -> int:
        return math.prod(len(v) for v in self.axes.values())

    def scenes(self) -> list[dict[str, Any]]:
        """Every combination of the axes, in row-major order (the last axis fastest)."""
        names = list(self.axes)
        return [dict(zip(names, combo, strict=True)) for combo in itertools.product(*self.axes.values())]


def _number(key: str, v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise SweepSpecError(f"{key} must be a number, got {v!r}")
    if not math.isfinite(v):
        raise SweepSpecError(f"{key} must be a finite number, got {v!r}")
    return v


def _axis(key: str, value: Any, *, integer: bool = False, words: tuple[str, ...] = ()) -> tuple:
    """A list, one value, or {min, max, n} → a tuple of values (numbers, or one of ``words``)."""
    if isinstance(value, dict):
        extra = set(value) - {"min", "max", "n"}
        if extra:
            raise SweepSpecError(f"unknown key {key}.{sorted(extra)[0]} (a range is {{min, max, n}})")
        if not {"min", "max", "n"} <= set(value):
            raise SweepSpecError(f"{key}: a range needs min, max and n, got {value!r}")
        lo, hi, n = (_number(f"{key}.{k}", value[k]) for k in ("min", "max", "n"))
        if n != int(n) or n < 1:
            raise SweepSpecError(f"{key}.n must be a positive integer, got {value['n']!r}")
        if hi < lo or (n > 1 and hi == lo):
            raise SweepSpecError(f"{key}: empty range, min {lo!r} .. max {hi!r}")
        values = np.linspace(lo, hi, int(n)).tolist() if n > 1 else [float(lo)]
    else:
        values = list(value) if isinstance(value, list) else [value]
    if not values:
        raise SweepSpecError(f"{key}: empty range (no values)")
    out = []
    for i, v in enumerate(values):
        if isinstance(v, str) and v in words:
            out.append(v)
            continue
        v = _number(f"{key}[{i}]", v)
        if integer and (v != int(v) or v < 1):
            raise SweepSpecError(f"{key}[{i}] must be a positive integer, got {v!r}")
        out.append(int(v) if integer else float(v))
    if len(set(out)) != len(out):
        raise SweepSpecError(f"{key}: repeated values in {out}")
    return tuple(out)


def scene_for(base: Scene, params: dict[str, Any]) -> Scene:
    """The base scene with one grid point's medium, objects and camera exposure (``exposure`` in seconds;
    ``"auto"`` and ``"scene"`` leave the camera alone and are the plan's exposure rule)."""
    med = base.medium
    kw: dict[str, Any] = {}
    if "sigma_t" in params:
        kw["sigma_t"] = params["sigma_t"]
    if "albedo" in params:
        kw["albedo"] = params["albedo"]
    if "mean_cosine" in params:
        kw["phase"] = Phase(med.phase.model, params["mean_cosine"])
    scene = base.replace(medium=med.replace(**kw)) if kw else base
    if "object_albedo" in params:
        scene = scene.replace(objects=tuple(o.replace(albedo=params["object_albedo"]) for o in scene.objects))
    if isinstance(params.get("exposure"), float):
        scene = scene.replace(camera=scene.camera.replace(exposure_s=params["exposure"]))
    return scene


def _check_separations(base: Scene, seps: np.ndarray) -> None:
    if seps.size < 2 or seps[0] <= 0.0:
        raise SweepSpecError(f"grid.separation: need at least 2 separations, all > 0 m, got {seps.tolist()}")
    if seps.size > MAX_SEPARATIONS:
        raise SweepSpecError(f"grid.separation: {seps.size} separations exceed the limit {MAX_SEPARATIONS}")
    lo, hi = base.medium.extent.min, base.medium.extent.max
    for d in (seps[0], seps[-1]):
        pos = np.asarray(with_separation(base, float(d)).projector.position)
        if not point_in_box(pos[None], lo, hi, tol=1e-9)[0]:
            raise SweepSpecError(
                f"grid.separation: {d:g} m is beyond the tank: the source would sit at "
                f"({pos[0]:.3g}, {pos[1]:.3g}, {pos[2]:.3g}) m, outside the medium's extent {lo} .. {hi} "
                "(the model would light the tank through clear air); shorten the range or widen "
                "medium.extent in the scene")


def parse_spec(data: dict, base_dir: Path | None = None, source: str = "") -> SweepSpec:
    """Check a parsed spec (see the module docstring) and return it; raise :class:`SweepSpecError`."""
    if not isinstance(data, dict):
        raise SweepSpecError("a sweep spec is a TOML table")
    for k in data:
        if k not in TOP_KEYS:
            raise SweepSpecError(f"unknown key {k!r} (allowed: {', '.join(sorted(TOP_KEYS))})")
    scene_path = data.get("scene")
    if scene_path is not None and not isinstance(scene_path, str):
        raise SweepSpecError(f"scene must be a path string, got {scene_path!r}")
    if scene_path is not None and base_dir is not None and not Path(scene_path).is_absolute():
        scene_path = str(base_dir / scene_path)
    base = load_scene(scene_path)
    fidelity = data.get("fidelity", "preview")
    resolve_fidelity(fidelity)
    mods = data.get("modalities", list(MODALITIES))
    if not isinstance(mods, list) or not mods or any(m not in MODALITIES for m in mods) or \
            len(set(mods)) != len(mods):
        raise SweepSpecError(f"modalities must be a non-empty list of distinct {MODALITIES}, got {mods!r}")
    mods = tuple(m for m in MODALITIES if m in mods)
    edge = data.get("edge", "margin")
    if edge not in EDGES:
        raise SweepSpecError(f"edge must be one of {EDGES}, got {edge!r}")
    orders = data.get("orders", "all")
    if orders not in ORDERS:
        raise SweepSpecError(f"orders must be one of {', '.join(ORDERS)}, got {orders!r}")
    k_detect = _number("k_detect", data.get("k_detect", 3.0))
    if k_detect < 0:
        raise SweepSpecError(f"k_detect must be >= 0, got {k_detect!r}")
    limit = data.get("max_scenes", MAX_SCENES)
    if isinstance(limit, bool) or not isinstance(limit, int) or limit < 1:
        raise SweepSpecError(f"max_scenes must be a positive integer, got {limit!r}")
    grid = data.get("grid", {})
    if not isinstance(grid, dict):
        raise SweepSpecError("grid must be a table ([grid])")
    for k in grid:
        if k not in AXES and k != "separation":
            raise SweepSpecError(f"unknown key grid.{k} (allowed: separation, {', '.join(AXES)})")
    seps = np.array(_axis("grid.separation", grid.get("separation", {"min": 0.01, "max": 0.3, "n": 30})))
    if np.any(np.diff(seps) <= 0):
        raise SweepSpecError("grid.separation must increase")
    _check_separations(base, seps)
    SceneModel(base, fidelity=fidelity, edge=edge)  # the observed points must see an object
    axes: dict[str, tuple] = {}
    defaults = {"exposure": ("scene",), "stripes": (30,)}
    for k in AXES:
        if k in grid:
            axes[k] = _axis(f"grid.{k}", grid[k], integer=k == "stripes",
                            words=("auto", "scene") if k == "exposure" else ())
        elif k in defaults:
            axes[k] = defaults[k]
    spec = SweepSpec(base, fidelity, mods, edge, float(k_detect), seps, axes, source, orders)
    if spec.n_scenes > limit:
        sizes = " × ".join(f"{k} {len(v)}" for k, v in axes.items())
        raise SweepSpecError(f"grid: {spec.n_scenes} scenes ({sizes}) exceed max_scenes = {limit}; raise "
                             "max_scenes in the spec if you mean it")
    for name, values in axes.items():  # every value must make a valid scene: fail now, not in a worker
        for v in values:
            try:
                scene_for(base, {name: v})
            except SceneError as exc:
                raise SweepSpecError(f"grid.{name} = {v!r}: {exc}") from None
            if name == "exposure" and isinstance(v, float) and v <= 0:
                raise SweepSpecError(f"grid.exposure = {v!r}: an exposure must be > 0 s")
    return spec


def load_spec(path: str | Path) -> SweepSpec:
    """Read and check a sweep spec TOML file (``OSError`` if it cannot be read)."""
    path = Path(path)
    with open(path, "rb") as fh:
        raw = fh.read()
    try:
        data = tomllib.loads(raw.decode("utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise SweepSpecError(f"{path}: not a valid TOML sweep spec: {exc}") from None
    return parse_spec(data, path.parent, str(path))
