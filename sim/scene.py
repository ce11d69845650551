"""Scenes: the TOML rig description parsed into frozen, validated dataclasses (docs/scene-format.md).

``load_scene(None)`` is the paper's tank: 60×60×38 cm of dilute milk, camera and projector on the front face
(z = 0), a contrast chart of albedo up to 0.6 on the back wall (z = 0.38 m). Every key, unit and default is
documented in ``docs/scene-format.md``; a file's objects are the ``[[object]]`` tables it lists (none listed:
no objects, the tank's chart is not inherited). Variants: ``scene.replace(...)`` / ``dataclasses.replace`` on
any part (every part validates itself on construction), :func:`with_separation` for the camera–source
distance.

This module is the public face: the file format (:func:`load_scene`, :func:`scene_from_dict`,
:func:`scene_to_dict`) and every scene name; the parts live in :mod:`polarstripe.sim.scene_parts`, the value
checks and :class:`SceneError` in :mod:`polarstripe.sim.scene_checks`.
"""

from __future__ import annotations

import dataclasses
import tomllib
from pathlib import Path
from typing import Any

import numpy as np
from polarstripe.sim.scene_calibration import with_calibration
from polarstripe.sim.scene_checks import SceneError, Vec3, parse_size, positive, resolution, vec3
from polarstripe.sim.scene_parts import (
    DEFAULT_CHART,
    Box,
    BoxObject,
    Camera,
    DopModel,
    Medium,
    Phase,
    PlaneObject,
    Polarizer,
    Projector,
    Scene,
    SceneObject,
    SourcePolarization,
    SphereObject,
)
from polarstripe.sim.scene_port import GLASS_TANK, Port

__all__ = [
    "DEFAULT_CHART", "Box", "BoxObject", "Camera", "DopModel", "Medium", "Phase", "PlaneObject", "Polarizer",
    "Port", "Projector", "Scene", "SceneError", "glass_tank", "SceneObject", "SourcePolarization",
    "SphereObject", "Vec3", "LIGHTS", "with_light", "baseline_direction",
    "load_scene", "parse_size", "scene_from_dict", "scene_to_dict", "with_separation",
]


LIGHTS = ("linear", "circular")


def with_light(scene: Scene, light: str) -> Scene:
    """The rig with linear or circular light (docs/physics.md §5.1): ``linear`` takes the quarter-wave plates
    out; ``circular`` puts one after the source's polarizer at angle_deg − 45° (V_L = +DOP_L) and one at 45°
    before the analyzer, whose rotation then reaches both circular analyzers (0° and 90°) and the linear
    states between."""
    if light not in LIGHTS:
        raise SceneError(f"light must be one of {', '.join(LIGHTS)}, got {light!r}")
    pol, an = scene.projector.polarization, scene.camera.polarizer
    if light == "linear":
        pol, an = pol.replace(quarter_wave_deg=None), an.replace(quarter_wave_deg=None)
    else:
        pol, an = pol.replace(quarter_wave_deg=pol.angle_deg - 45.0), an.replace(quarter_wave_deg=45.0)
    return scene.replace(projector=scene.projector.replace(polarization=pol),
                         camera=scene.camera.replace(polarizer=an))


def baseline_direction(scene: Scene) -> np.ndarray:
    """The unit vector from the camera toward the projector, perpendicular to the camera's forward axis (the
    camera's right axis if the projector sits on that axis): the direction a translate scan moves the source
    along, and the rig frame's x (sim/motion.py)."""
    c = np.array(scene.camera.position)
    f = np.subtract(scene.camera.look_at, c)
    f /= np.linalg.norm(f)
    e = np.array(scene.projector.position) - c
    e -= f * (e @ f)
    if np.linalg.norm(e) < 1e-12:
        e = np.cross(f, scene.camera.up)
    return e / np.linalg.norm(e)


def with_separation(scene: Scene, d_lc_m: float, aim: bool = True) -> Scene:
    """Move the projector to camera–source distance ``d_lc_m`` along the front face (a translate scan).

    The projector moves in the plane through the camera perpendicular to the camera's forward axis, on the
    side where it already is (the camera's right axis if it sits on the camera). With ``aim`` its look_at is
    kept (the projector turns to keep the chart lit); without, it translates with its orientation unchanged.
    """
    d = positive("separation d_lc_m", d_lc_m, allow_zero=True)
    new_pos = np.array(scene.camera.position) + d * baseline_direction(scene)
    proj = scene.projector
    look = proj.look_at if aim else tuple(new_pos + np.subtract(proj.look_at, proj.position))
    return scene.replace(projector=proj.replace(position=tuple(new_pos.tolist()), look_at=tuple(look)))


# ------------------------------------------------------------------------------------------------- TOML

_SECTIONS = {
    "medium": {"sigma_t", "albedo", "phase", "dop", "extent"},
    "camera": {f.name for f in dataclasses.fields(Camera)},
    "projector": {f.name for f in dataclasses.fields(Projector)},
}


def _check_keys(section: str, table: Any, allowed: set[str]) -> dict:
    if not isinstance(table, dict):
        raise SceneError(f"{section} must be a table, got {table!r}")
    for k in table:
        if k not in allowed:
            raise SceneError(f"unknown key {section}.{k} (allowed: {', '.join(sorted(allowed))})")
    return table


def _medium(t: dict) -> Medium:
    _check_keys("medium", t, _SECTIONS["medium"])
    kw: dict[str, Any] = {k: t[k] for k in ("sigma_t", "albedo") if k in t}
    if "phase" in t:
        ph = _check_keys("medium.phase", t["phase"], {"model", "mean_cosine", "g"})
        model = ph.get("model", "tthg")
        if model == "tthg" and "g" in ph:
            raise SceneError("unknown key medium.phase.g for model tthg (use mean_cosine)")
        if model == "hg" and "mean_cosine" in ph:
            raise SceneError("unknown key medium.phase.mean_cosine for model hg (use g)")
        kw["phase"] = Phase(model, ph.get("mean_cosine", ph.get("g", 0.8 if model != "isotropic" else 0.0)))
    if "dop" in t:
        dp = _check_keys("medium.dop", t["dop"], {"model", "depolarization", "p"})
        kw["dop"] = DopModel(**dp)
    if "extent" in t:
        ex = _check_keys("medium.extent", t["extent"], {"min", "max"})
        kw["extent"] = Box(key="medium.extent", **ex)
    return Medium(**kw)


def _pinhole(section: str, t: dict, nested: str, nested_cls: type, nested_keys: set[str]) -> dict:
    """What `[camera]` and `[projector]` share: a nested table, the pose vectors, the resolution."""
    t = dict(_check_keys(section, t, _SECTIONS[section]))
    if nested in t:
        t[nested] = nested_cls(**_check_keys(f"{section}.{nested}", t[nested], nested_keys))
    for k in ("position", "look_at", "up"):
        if k in t:
            t[k] = vec3(f"{section}.{k}", t[k])
    if "resolution" in t:
        t["resolution"] = resolution(f"{section}.resolution", t["resolution"])
    return t


def _camera(t: dict, base: Scene | None = None) -> Camera:
    kw = _pinhole("camera", t, "polarizer", Polarizer, {"angle_deg", "extinction_ratio", "quarter_wave_deg"})
    return Camera(**kw) if base is None else base.camera.replace(**kw)


def _projector(t: dict, base: Scene | None = None) -> Projector:
    kw = _pinhole("projector", t, "polarization", SourcePolarization,
                  {"dop", "angle_deg", "quarter_wave_deg"})
    return Projector(**kw) if base is None else base.projector.replace(**kw)


PRESETS = ("glass_tank",)


def _preset(name) -> Scene | None:
    """The top-level ``preset`` key: the scene whose camera and projector the file's keys start from."""
    if name is None:
        return None
    if name not in PRESETS:
        raise SceneError(f"preset must be one of {', '.join(PRESETS)}, got {name!r}")
    return glass_tank(Scene())


def glass_tank(scene: Scene) -> Scene:
    """The paper's rig (its §3 and footnote 1): camera and projector outside the tank's glass front wall,
    2 cm in front of 10 mm of anti-reflection coated glass whose outer face is the medium's front face
    (``port = "glass_tank"``, :data:`~polarstripe.sim.scene_port.GLASS_TANK`); each keeps its look_at, and
    its x, y."""
    wall = GLASS_TANK
    z = scene.medium.extent.min[2] - wall.distance_m - wall.thickness_m
    parts = {}
    for name in ("camera", "projector"):
        dev = getattr(scene, name)
        parts[name] = dev.replace(position=(dev.position[0], dev.position[1], z),
                                  port=wall.replace(key=f"{name}.port"))
    return scene.replace(**parts)


def _object(i: int, t: dict, base: Path | None) -> SceneObject:
    key = f"object[{i}]"
    if not isinstance(t, dict) or "type" not in t:
        raise SceneError(f"{key}.type is required (plane, sphere or box)")
    kind, rest = t["type"], {k: v for k, v in t.items() if k != "type"}
    classes = {"plane": PlaneObject, "sphere": SphereObject, "box": BoxObject}
    if kind not in classes:
        raise SceneError(f"{key}.type must be plane, sphere or box, got {kind!r}")
    cls = classes[kind]
    _check_keys(key, rest, {f.name for f in dataclasses.fields(cls)} - {"key"})
    if kind == "plane" and rest.get("texture") not in (None, "chart") and base is not None:
        tex = Path(rest["texture"])
        rest["texture"] = str(tex if tex.is_absolute() else base / tex)
    if "size" in rest and isinstance(rest["size"], list):
        rest["size"] = tuple(rest["size"])
    return cls(key=key, **rest)


def scene_from_dict(data: dict, base: Path | None = None) -> Scene:
    """Build a :class:`Scene` from a parsed TOML mapping; missing keys take the default tank's values.

    The objects are the ``[[object]]`` tables the mapping lists, none when it lists none: the default chart
    hangs on the default tank's back wall, which a file may have moved (a file that set the medium to ±1 m
    and listed no object used to get that 0.3 × 0.2 m chart at z = 0.38 m, cutting the view rays that hit it).
    """
    _check_keys("scene", data, {"medium", "camera", "projector", "object", "calibration", "preset"})
    kw: dict[str, Any] = {}
    preset = _preset(data.get("preset"))
    if "medium" in data:
        kw["medium"] = _medium(data["medium"])
    if "camera" in data or preset is not None:
        kw["camera"] = _camera(data.get("camera", {}), preset)
    if "projector" in data or preset is not None:
        kw["projector"] = _projector(data.get("projector", {}), preset)
    objs = data.get("object", [])
    if not isinstance(objs, list):
        raise SceneError("object must be an array of tables ([[object]])")
    kw["objects"] = tuple(_object(i, o, base) for i, o in enumerate(objs))
    if "calibration" in data:
        return _calibrated(Scene(**kw), data, base)
    return Scene(**kw)


def _calibrated(scene: Scene, data: dict, base: Path | None) -> Scene:
    """The ``calibration`` key: the camera's and projector's pinholes from a rig calibration file
    (sim/scene_calibration.py); the keys it sets may not be set too, the resolutions the file states must
    be the calibration's (the camera's up to an integer binning)."""
    path = data["calibration"]
    if not isinstance(path, str) or not path:
        raise SceneError(f"calibration must be the path of a calibration file, got {path!r}")
    for section, keys in (("camera", ("fov_deg",)), ("projector", ("fov_deg", "position", "look_at", "up"))):
        for key in keys:
            if key in data.get(section, {}):
                raise SceneError(f"{section}.{key} is set by the calibration file: give one or the other")
    full = Path(path) if Path(path).is_absolute() or base is None else base / path
    stated = {part: getattr(scene, part).resolution if "resolution" in data.get(part, {}) else None
              for part in ("camera", "projector")}
    ports = tuple(part for part in ("camera", "projector") if "port" in data.get(part, {}))
    return with_calibration(scene, str(full), cam_size=stated["camera"], proj_size=stated["projector"],
                            stated_ports=ports)


def load_scene(path: str | Path | None = None) -> Scene:
    """Read a TOML scene file (None: the paper's default tank).

    Raises
    ------
    SceneError
        Unknown key, bad value (negative σ, albedo outside [0, 1], NaN, look_at == position, ...) or
        a file that is not valid TOML; the text names the key. ``OSError`` if the file cannot be read.
    """
    if path is None:
        return Scene()
    path = Path(path)
    with open(path, "rb") as fh:
        raw = fh.read()
    try:
        data = tomllib.loads(raw.decode("utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise SceneError(f"{path}: not a valid TOML scene file: {exc}") from None
    return scene_from_dict(data, base=path.parent)


def scene_to_dict(scene: Scene) -> dict:
    """The resolved scene as plain JSON-able data, with the same keys as the TOML file."""

    def conv(obj):
        if dataclasses.is_dataclass(obj):
            return {f.name: conv(getattr(obj, f.name)) for f in dataclasses.fields(obj) if f.name != "key"}
        if isinstance(obj, tuple):
            return [conv(v) for v in obj]
        return obj

    out = {"medium": conv(scene.medium), "camera": conv(scene.camera), "projector": conv(scene.projector)}
    for part in ("camera", "projector"):
        if out[part]["port"] is not None:
            out[part]["port"] = {k: v for k, v in out[part]["port"].items() if v is not None}
    ph = out["medium"]["phase"]
    out["medium"]["phase"] = ({"model": "tthg", "mean_cosine": ph["g"]} if ph["model"] == "tthg"
                              else {"model": ph["model"], "g": ph["g"]} if ph["model"] == "hg"
                              else {"model": "isotropic"})
    objs = []
    for o in scene.objects:
        d = conv(o)
        d["type"] = {PlaneObject: "plane", SphereObject: "sphere", BoxObject: "box"}[type(o)]
        objs.append({k: v for k, v in d.items() if v is not None})
    out["object"] = objs
    return out
