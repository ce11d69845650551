"""Scenes: the TOML rig description parsed into frozen, validated dataclasses (DESIGN.md §5).

``load_scene(None)`` is the paper's tank: 60×60×38 cm of dilute milk, camera and projector on the front face
(z = 0), a contrast chart of albedo up to 0.6 on the back wall (z = 0.38 m). Every key, unit and default is
documented in ``docs/scene-format.md``. Variants: ``scene.replace(...)`` / ``dataclasses.replace`` on any part
(every part validates itself on construction), :func:`with_separation` for the camera–source distance.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from polarstripe.errors import PolarstripeError


class SceneError(PolarstripeError, ValueError):
    """A scene file or scene value is invalid; the text names the key and the bad value."""


Vec3 = tuple[float, float, float]


def _finite(key: str, value: Any) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise SceneError(f"{key} must be a number, got {value!r}") from None
    if isinstance(value, bool) or not math.isfinite(v):
        raise SceneError(f"{key} must be a finite number, got {value!r}")
    return v


def _vec3(key: str, value: Any) -> Vec3:
    if not isinstance(value, (list, tuple, np.ndarray)) or len(value) != 3:
        raise SceneError(f"{key} must be a list of 3 numbers, got {value!r}")
    return tuple(_finite(f"{key}[{i}]", c) for i, c in enumerate(value))  # type: ignore[return-value]


def _positive(key: str, value: Any, allow_zero: bool = False) -> float:
    v = _finite(key, value)
    if v < 0 or (v == 0 and not allow_zero):
        raise SceneError(f"{key} must be {'>= 0' if allow_zero else '> 0'}, got {value!r}")
    return v


def _unit_interval(key: str, value: Any) -> float:
    v = _finite(key, value)
    if not 0.0 <= v <= 1.0:
        raise SceneError(f"{key} must be in [0, 1], got {value!r}")
    return v


def parse_size(text: str, what: str = "resolution") -> tuple[int, int]:
    """``"640x480"`` → ``(640, 480)``: the one parser of ``WxH`` text (command lines, node params).

    Raises :class:`SceneError` (a ``ValueError``) naming ``what`` and the text.
    """
    w, sep, h = str(text).strip().lower().partition("x")
    if not sep or not w.isdigit() or not h.isdigit() or int(w) < 1 or int(h) < 1:
        raise SceneError(f"{what} must be WxH with positive integers (e.g. 640x480), got {text!r}")
    return int(w), int(h)


def _resolution(key: str, value: Any) -> tuple[int, int]:
    if not isinstance(value, (list, tuple)) or len(value) != 2:
        raise SceneError(f"{key} must be [width, height], got {value!r}")
    out = []
    for v in value:
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
            raise SceneError(f"{key} must be two positive integers, got {value!r}")
        out.append(int(v))
    return out[0], out[1]


class _Part:
    """Mixin: ``part.replace(**changes)`` returns a validated copy."""

    def replace(self, **changes: Any):
        return dataclasses.replace(self, **changes)


@dataclass(frozen=True)
class Phase(_Part):
    """Phase function: ``tthg`` (Haltrin, by mean cosine ``g``), ``hg`` (asymmetry ``g``) or ``isotropic``."""

    model: str = "tthg"
    g: float = 0.8

    def __post_init__(self):
        if self.model not in ("tthg", "hg", "isotropic"):
            raise SceneError(f"medium.phase.model must be tthg, hg or isotropic, got {self.model!r}")
        g = _finite("medium.phase.g", self.g)
        lo = 0.0 if self.model == "tthg" else -0.999999
        if not lo <= g <= 0.999999:
            key = "mean_cosine" if self.model == "tthg" else "g"
            raise SceneError(f"medium.phase.{key} must be in [{lo}, 0.999999], got {self.g!r}")
        object.__setattr__(self, "g", g)


@dataclass(frozen=True)
class DopModel(_Part):
    """Backscatter DOP: ``rayleigh`` (Mueller, depolarization δ) or ``constant`` (p)."""

    model: str = "rayleigh"
    depolarization: float = 0.2
    p: float = 0.8

    def __post_init__(self):
        if self.model not in ("rayleigh", "constant"):
            raise SceneError(f"medium.dop.model must be rayleigh or constant, got {self.model!r}")
        d = _finite("medium.dop.depolarization", self.depolarization)
        if not 0.0 <= d < 0.5:
            raise SceneError(f"medium.dop.depolarization must be in [0, 0.5), got {self.depolarization!r}")
        object.__setattr__(self, "depolarization", d)
        object.__setattr__(self, "p", _unit_interval("medium.dop.p", self.p))


@dataclass(frozen=True)
class Box(_Part):
    """Axis-aligned box [m]; ``key`` is only used in error messages."""

    min: Vec3 = (-0.3, -0.3, 0.0)
    max: Vec3 = (0.3, 0.3, 0.38)
    key: str = field(default="box", compare=False, repr=False)

    def __post_init__(self):
        lo, hi = _vec3(f"{self.key}.min", self.min), _vec3(f"{self.key}.max", self.max)
        if not all(a < b for a, b in zip(lo, hi, strict=True)):
            raise SceneError(f"{self.key}.max must exceed {self.key}.min on every axis, got {lo} .. {hi}")
        object.__setattr__(self, "min", lo)
        object.__setattr__(self, "max", hi)


@dataclass(frozen=True)
class Medium(_Part):
    """Homogeneous medium: extinction ``sigma_t`` [1/m], ``albedo`` = σ_s/σ_t, phase, DOP, extent box."""

    sigma_t: float = 5.0
    albedo: float = 1.0
    phase: Phase = Phase()
    dop: DopModel = DopModel()
    extent: Box = Box(key="medium.extent")

    def __post_init__(self):
        object.__setattr__(self, "sigma_t", _positive("medium.sigma_t", self.sigma_t, allow_zero=True))
        object.__setattr__(self, "albedo", _unit_interval("medium.albedo", self.albedo))

    @property
    def sigma_s(self) -> float:
        """Scattering coefficient σ_s = albedo·σ_t [1/m]."""
        return self.albedo * self.sigma_t


@dataclass(frozen=True)
class Polarizer(_Part):
    """Analyzer in front of the camera: angle [deg] from the image right axis toward image up."""

    angle_deg: float | None = None
    extinction_ratio: float = 1000.0

    def __post_init__(self):
        if self.angle_deg is not None:
            object.__setattr__(self, "angle_deg", _finite("camera.polarizer.angle_deg", self.angle_deg))
        er = _finite("camera.polarizer.extinction_ratio", self.extinction_ratio)
        if er < 1:
            raise SceneError(f"camera.polarizer.extinction_ratio must be >= 1, got {self.extinction_ratio!r}")
        object.__setattr__(self, "extinction_ratio", er)


def _check_pose(section: str, position, look_at, up, fov_deg):
    p, t, u = _vec3(f"{section}.position", position), _vec3(f"{section}.look_at", look_at), _vec3(
        f"{section}.up", up)
    f = np.subtract(t, p)
    if np.linalg.norm(f) < 1e-12:
        raise SceneError(f"{section}.look_at must differ from {section}.position, both are {p}")
    if np.linalg.norm(np.cross(f / np.linalg.norm(f), u)) < 1e-9:
        raise SceneError(f"{section}.up must not be parallel to the viewing direction, got {u}")
    fov = _finite(f"{section}.fov_deg", fov_deg)
    if not 0 < fov < 179:
        raise SceneError(f"{section}.fov_deg must be in (0, 179), got {fov_deg!r}")
    return p, t, u, fov


@dataclass(frozen=True)
class Camera(_Part):
    """Pinhole camera (issue 3 geometry) with an EMVA 1288 sensor and an optional analyzer."""

    position: Vec3 = (0.0, 0.0, 0.0)
    look_at: Vec3 = (0.0, 0.0, 0.38)
    up: Vec3 = (0.0, 1.0, 0.0)
    resolution: tuple[int, int] = (640, 480)
    fov_deg: float = 60.0
    exposure_s: float = 0.008
    qe: float = 0.4
    full_well_e: float = 50000.0
    read_noise_e: float = 12.0
    dark_current_e_s: float = 1.0
    gain_e_per_dn: float = 12.0
    bits: int = 12
    offset_dn: float = 64.0
    aperture_m: float = 0.005
    wavelength_nm: float = 532.0
    seed: int = 0
    polarizer: Polarizer = Polarizer()

    def __post_init__(self):
        p, t, u, fov = _check_pose("camera", self.position, self.look_at, self.up, self.fov_deg)
        for k, v in (("position", p), ("look_at", t), ("up", u), ("fov_deg", fov)):
            object.__setattr__(self, k, v)
        object.__setattr__(self, "resolution", _resolution("camera.resolution", self.resolution))
        for k in ("exposure_s", "full_well_e", "gain_e_per_dn", "aperture_m", "wavelength_nm"):
            object.__setattr__(self, k, _positive(f"camera.{k}", getattr(self, k)))
        for k in ("read_noise_e", "dark_current_e_s", "offset_dn"):
            object.__setattr__(self, k, _positive(f"camera.{k}", getattr(self, k), allow_zero=True))
        object.__setattr__(self, "qe", _unit_interval("camera.qe", self.qe))
        if isinstance(self.bits, bool) or not isinstance(self.bits, int) or not 1 <= self.bits <= 16:
            raise SceneError(f"camera.bits must be an integer in [1, 16], got {self.bits!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int):
            raise SceneError(f"camera.seed must be an integer, got {self.seed!r}")


@dataclass(frozen=True)
class SourcePolarization(_Part):
    """Source polarization: degree ``dop`` and angle [deg] from the projector's right axis toward its up."""

    dop: float = 1.0
    angle_deg: float = 90.0

    def __post_init__(self):
        object.__setattr__(self, "dop", _unit_interval("projector.polarization.dop", self.dop))
        object.__setattr__(self, "angle_deg", _finite("projector.polarization.angle_deg", self.angle_deg))


@dataclass(frozen=True)
class Projector(_Part):
    """Pinhole projector (patterns) or isotropic point source (``model = "point"``, flood only)."""

    model: str = "pinhole"
    position: Vec3 = (0.2, 0.0, 0.0)
    look_at: Vec3 = (0.0, 0.0, 0.38)
    up: Vec3 = (0.0, 1.0, 0.0)
    resolution: tuple[int, int] = (1024, 768)
    fov_deg: float = 60.0
    intensity_w_sr: float = 1.0
    black_level: float = 0.0
    source_radius_m: float = 1e-3
    polarization: SourcePolarization = SourcePolarization()

    def __post_init__(self):
        if self.model not in ("pinhole", "point"):
            raise SceneError(f"projector.model must be pinhole or point, got {self.model!r}")
        p, t, u, fov = _check_pose("projector", self.position, self.look_at, self.up, self.fov_deg)
        for k, v in (("position", p), ("look_at", t), ("up", u), ("fov_deg", fov)):
            object.__setattr__(self, k, v)
        object.__setattr__(self, "resolution", _resolution("projector.resolution", self.resolution))
        object.__setattr__(self, "intensity_w_sr",
                           _positive("projector.intensity_w_sr", self.intensity_w_sr, allow_zero=True))
        b = _finite("projector.black_level", self.black_level)
        if not 0.0 <= b < 1.0:
            raise SceneError(f"projector.black_level must be in [0, 1), got {self.black_level!r}")
        object.__setattr__(self, "black_level", b)
        object.__setattr__(self, "source_radius_m",
                           _positive("projector.source_radius_m", self.source_radius_m, allow_zero=True))


@dataclass(frozen=True)
class PlaneObject(_Part):
    """One-sided plane through ``point``, ``normal`` facing the camera, optional ``size`` [w, h] [m]."""

    point: Vec3 = (0.0, 0.0, 0.38)
    normal: Vec3 = (0.0, 0.0, -1.0)
    size: tuple[float, float] | None = None
    up: Vec3 = (0.0, 1.0, 0.0)
    albedo: float = 0.6
    texture: str | None = None
    key: str = field(default="object[0]", compare=False, repr=False)

    def __post_init__(self):
        k = self.key
        object.__setattr__(self, "point", _vec3(f"{k}.point", self.point))
        n = np.array(_vec3(f"{k}.normal", self.normal))
        if np.linalg.norm(n) < 1e-12:
            raise SceneError(f"{k}.normal must be non-zero, got {self.normal!r}")
        object.__setattr__(self, "normal", tuple(float(c) for c in n / np.linalg.norm(n)))
        up = np.array(_vec3(f"{k}.up", self.up))
        if np.linalg.norm(np.cross(up, n)) < 1e-9 * max(np.linalg.norm(up), 1e-300):
            raise SceneError(f"{k}.up must not be parallel to the normal, got {self.up!r}")
        object.__setattr__(self, "up", tuple(float(c) for c in up))
        if self.size is not None:
            if not isinstance(self.size, (list, tuple)) or len(self.size) != 2:
                raise SceneError(f"{k}.size must be [width, height], got {self.size!r}")
            object.__setattr__(self, "size", tuple(_positive(f"{k}.size", s) for s in self.size))
        object.__setattr__(self, "albedo", _unit_interval(f"{k}.albedo", self.albedo))
        if self.texture is not None:
            if not isinstance(self.texture, str):
                raise SceneError(f"{k}.texture must be 'chart' or a PNG path, got {self.texture!r}")
            if self.size is None:
                raise SceneError(f"{k}.size is required with a texture ({self.texture!r})")


@dataclass(frozen=True)
class SphereObject(_Part):
    center: Vec3 = (0.0, 0.0, 0.3)
    radius: float = 0.05
    albedo: float = 0.6
    key: str = field(default="object[0]", compare=False, repr=False)

    def __post_init__(self):
        object.__setattr__(self, "center", _vec3(f"{self.key}.center", self.center))
        object.__setattr__(self, "radius", _positive(f"{self.key}.radius", self.radius))
        object.__setattr__(self, "albedo", _unit_interval(f"{self.key}.albedo", self.albedo))


@dataclass(frozen=True)
class BoxObject(_Part):
    min: Vec3 = (-0.05, -0.05, 0.25)
    max: Vec3 = (0.05, 0.05, 0.35)
    albedo: float = 0.6
    key: str = field(default="object[0]", compare=False, repr=False)

    def __post_init__(self):
        Box(self.min, self.max, key=self.key)
        object.__setattr__(self, "min", _vec3(f"{self.key}.min", self.min))
        object.__setattr__(self, "max", _vec3(f"{self.key}.max", self.max))
        object.__setattr__(self, "albedo", _unit_interval(f"{self.key}.albedo", self.albedo))


SceneObject = PlaneObject | SphereObject | BoxObject

DEFAULT_CHART = PlaneObject(point=(0.0, 0.0, 0.38), normal=(0.0, 0.0, -1.0), size=(0.3, 0.2), albedo=0.6,
                            texture="chart")


@dataclass(frozen=True)
class Scene(_Part):
    """A whole rig: medium, camera, projector and objects (the default is the paper's tank)."""

    medium: Medium = Medium()
    camera: Camera = Camera()
    projector: Projector = Projector()
    objects: tuple[SceneObject, ...] = (DEFAULT_CHART,)

    def __post_init__(self):
        object.__setattr__(self, "objects", tuple(self.objects))

    def separation_m(self) -> float:
        """Camera–source distance d_LC [m]."""
        return float(np.linalg.norm(np.subtract(self.projector.position, self.camera.position)))


def with_separation(scene: Scene, d_lc_m: float, aim: bool = True) -> Scene:
    """Move the projector to camera–source distance ``d_lc_m`` along the front face (a translate scan).

    The projector moves in the plane through the camera perpendicular to the camera's forward axis, on the
    side where it already is (the camera's right axis if it sits on the camera). With ``aim`` its look_at is
    kept (the projector turns to keep the chart lit); without, it translates with its orientation unchanged.
    """
    d = _positive("separation d_lc_m", d_lc_m, allow_zero=True)
    c, pr = np.array(scene.camera.position), np.array(scene.projector.position)
    f = np.subtract(scene.camera.look_at, c)
    f /= np.linalg.norm(f)
    e = pr - c
    e -= f * (e @ f)
    if np.linalg.norm(e) < 1e-12:
        e = np.cross(f, scene.camera.up)
    e /= np.linalg.norm(e)
    new_pos = c + d * e
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
            t[k] = _vec3(f"{section}.{k}", t[k])
    if "resolution" in t:
        t["resolution"] = _resolution(f"{section}.resolution", t["resolution"])
    return t


def _camera(t: dict) -> Camera:
    return Camera(**_pinhole("camera", t, "polarizer", Polarizer, {"angle_deg", "extinction_ratio"}))


def _projector(t: dict) -> Projector:
    return Projector(**_pinhole("projector", t, "polarization", SourcePolarization, {"dop", "angle_deg"}))


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
    """Build a :class:`Scene` from a parsed TOML mapping; missing keys take the default tank's values."""
    _check_keys("scene", data, {"medium", "camera", "projector", "object"})
    kw: dict[str, Any] = {}
    if "medium" in data:
        kw["medium"] = _medium(data["medium"])
    if "camera" in data:
        kw["camera"] = _camera(data["camera"])
    if "projector" in data:
        kw["projector"] = _projector(data["projector"])
    if "object" in data:
        objs = data["object"]
        if not isinstance(objs, list):
            raise SceneError("object must be an array of tables ([[object]])")
        kw["objects"] = tuple(_object(i, o, base) for i, o in enumerate(objs))
    return Scene(**kw)


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
