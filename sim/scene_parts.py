"""The parts of a scene: frozen dataclasses that validate themselves on construction (docs/scene-format.md).

The defaults are the paper's tank. ``part.replace(**changes)`` (or ``dataclasses.replace``) returns a
validated copy; the values are checked by :mod:`polarstripe.sim.scene_checks`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from polarstripe.sim.scene_checks import (
    SceneError,
    Vec3,
    check_pose,
    finite,
    positive,
    resolution,
    unit_interval,
    vec3,
)
from polarstripe.sim.scene_port import Port, check_port, parse_port


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
        g = finite("medium.phase.g", self.g)
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
        d = finite("medium.dop.depolarization", self.depolarization)
        if not 0.0 <= d < 0.5:
            raise SceneError(f"medium.dop.depolarization must be in [0, 0.5), got {self.depolarization!r}")
        object.__setattr__(self, "depolarization", d)
        object.__setattr__(self, "p", unit_interval("medium.dop.p", self.p))


@dataclass(frozen=True)
class Box(_Part):
    """Axis-aligned box [m]; ``key`` is only used in error messages."""

    min: Vec3 = (-0.3, -0.3, 0.0)
    max: Vec3 = (0.3, 0.3, 0.38)
    key: str = field(default="box", compare=False, repr=False)

    def __post_init__(self):
        lo, hi = vec3(f"{self.key}.min", self.min), vec3(f"{self.key}.max", self.max)
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
        object.__setattr__(self, "sigma_t", positive("medium.sigma_t", self.sigma_t, allow_zero=True))
        object.__setattr__(self, "albedo", unit_interval("medium.albedo", self.albedo))

    @property
    def sigma_s(self) -> float:
        """Scattering coefficient σ_s = albedo·σ_t [1/m]."""
        return self.albedo * self.sigma_t


@dataclass(frozen=True)
class Polarizer(_Part):
    """Analyzer in front of the camera: angle [deg] from the image right axis toward image up; an optional
    quarter-wave plate in front of it, its fast axis at ``quarter_wave_deg`` in the same sense (the plate at
    angle_deg ∓ 45° makes a circular analyzer; docs/physics.md §5.1)."""

    angle_deg: float | None = None
    extinction_ratio: float = 1000.0
    quarter_wave_deg: float | None = None

    def __post_init__(self):
        if self.angle_deg is not None:
            object.__setattr__(self, "angle_deg", finite("camera.polarizer.angle_deg", self.angle_deg))
        if self.quarter_wave_deg is not None:
            object.__setattr__(self, "quarter_wave_deg",
                               finite("camera.polarizer.quarter_wave_deg", self.quarter_wave_deg))
        er = finite("camera.polarizer.extinction_ratio", self.extinction_ratio)
        if er < 1:
            raise SceneError(f"camera.polarizer.extinction_ratio must be >= 1, got {self.extinction_ratio!r}")
        object.__setattr__(self, "extinction_ratio", er)


@dataclass(frozen=True)
class Camera(_Part):
    """Pinhole camera (docs/scene-format.md "Geometry") with an EMVA 1288 sensor and an optional analyzer."""

    position: Vec3 = (0.0, 0.0, 0.0)
    look_at: Vec3 = (0.0, 0.0, 0.38)
    up: Vec3 = (0.0, 1.0, 0.0)
    resolution: tuple[int, int] = (640, 480)
    fov_deg: float = 60.0
    exposure_s: float = 0.001      # all orders of scattering: ~7x single scattering's light (was 8 ms)
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
    port: Port | None = None

    def __post_init__(self):
        p, t, u, fov = check_pose("camera", self.position, self.look_at, self.up, self.fov_deg)
        for k, v in (("position", p), ("look_at", t), ("up", u), ("fov_deg", fov)):
            object.__setattr__(self, k, v)
        object.__setattr__(self, "resolution", resolution("camera.resolution", self.resolution))
        object.__setattr__(self, "port", parse_port("camera", self.port))
        check_port("camera", self.port, p, t, u, fov, self.resolution)
        for k in ("exposure_s", "full_well_e", "gain_e_per_dn", "aperture_m", "wavelength_nm"):
            object.__setattr__(self, k, positive(f"camera.{k}", getattr(self, k)))
        for k in ("read_noise_e", "dark_current_e_s", "offset_dn"):
            object.__setattr__(self, k, positive(f"camera.{k}", getattr(self, k), allow_zero=True))
        object.__setattr__(self, "qe", unit_interval("camera.qe", self.qe))
        if isinstance(self.bits, bool) or not isinstance(self.bits, int) or not 1 <= self.bits <= 16:
            raise SceneError(f"camera.bits must be an integer in [1, 16], got {self.bits!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int):
            raise SceneError(f"camera.seed must be an integer, got {self.seed!r}")

    def resized(self, resolution: tuple[int, int]) -> Camera:
        """This camera at ``resolution`` (w, h), the exposure scaled by (w/w₀)² to keep a frame's DN level:
        at the same field of view a pixel's solid angle, and so the light it collects, goes as 1/w²."""
        exposure_s = self.exposure_s * (resolution[0] / self.resolution[0]) ** 2
        return self.replace(resolution=resolution, exposure_s=exposure_s)


@dataclass(frozen=True)
class SourcePolarization(_Part):
    """Source polarization: degree ``dop`` and angle [deg] from the projector's right axis toward its up;
    an optional quarter-wave plate after the polarizer, its fast axis at ``quarter_wave_deg`` in the same
    sense (angle_deg ± 45°: circular light; docs/physics.md §5.1)."""

    dop: float = 1.0
    angle_deg: float = 90.0
    quarter_wave_deg: float | None = None

    def __post_init__(self):
        object.__setattr__(self, "dop", unit_interval("projector.polarization.dop", self.dop))
        object.__setattr__(self, "angle_deg", finite("projector.polarization.angle_deg", self.angle_deg))
        if self.quarter_wave_deg is not None:
            object.__setattr__(self, "quarter_wave_deg",
                               finite("projector.polarization.quarter_wave_deg", self.quarter_wave_deg))


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
    port: Port | None = None

    def __post_init__(self):
        if self.model not in ("pinhole", "point"):
            raise SceneError(f"projector.model must be pinhole or point, got {self.model!r}")
        p, t, u, fov = check_pose("projector", self.position, self.look_at, self.up, self.fov_deg)
        for k, v in (("position", p), ("look_at", t), ("up", u), ("fov_deg", fov)):
            object.__setattr__(self, k, v)
        object.__setattr__(self, "resolution", resolution("projector.resolution", self.resolution))
        object.__setattr__(self, "port", parse_port("projector", self.port))
        if self.model == "pinhole":
            check_port("projector", self.port, p, t, u, fov, self.resolution)
        object.__setattr__(self, "intensity_w_sr",
                           positive("projector.intensity_w_sr", self.intensity_w_sr, allow_zero=True))
        b = finite("projector.black_level", self.black_level)
        if not 0.0 <= b < 1.0:
            raise SceneError(f"projector.black_level must be in [0, 1), got {self.black_level!r}")
        object.__setattr__(self, "black_level", b)
        object.__setattr__(self, "source_radius_m",
                           positive("projector.source_radius_m", self.source_radius_m, allow_zero=True))


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
        object.__setattr__(self, "point", vec3(f"{k}.point", self.point))
        n = np.array(vec3(f"{k}.normal", self.normal))
        if np.linalg.norm(n) < 1e-12:
            raise SceneError(f"{k}.normal must be non-zero, got {self.normal!r}")
        object.__setattr__(self, "normal", tuple(float(c) for c in n / np.linalg.norm(n)))
        up = np.array(vec3(f"{k}.up", self.up))
        if np.linalg.norm(np.cross(up, n)) < 1e-9 * max(np.linalg.norm(up), 1e-300):
            raise SceneError(f"{k}.up must not be parallel to the normal, got {self.up!r}")
        object.__setattr__(self, "up", tuple(float(c) for c in up))
        if self.size is not None:
            if not isinstance(self.size, (list, tuple)) or len(self.size) != 2:
                raise SceneError(f"{k}.size must be [width, height], got {self.size!r}")
            object.__setattr__(self, "size", tuple(positive(f"{k}.size", s) for s in self.size))
        object.__setattr__(self, "albedo", unit_interval(f"{k}.albedo", self.albedo))
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
        object.__setattr__(self, "center", vec3(f"{self.key}.center", self.center))
        object.__setattr__(self, "radius", positive(f"{self.key}.radius", self.radius))
        object.__setattr__(self, "albedo", unit_interval(f"{self.key}.albedo", self.albedo))


@dataclass(frozen=True)
class BoxObject(_Part):
    min: Vec3 = (-0.05, -0.05, 0.25)
    max: Vec3 = (0.05, 0.05, 0.35)
    albedo: float = 0.6
    key: str = field(default="object[0]", compare=False, repr=False)

    def __post_init__(self):
        Box(self.min, self.max, key=self.key)
        object.__setattr__(self, "min", vec3(f"{self.key}.min", self.min))
        object.__setattr__(self, "max", vec3(f"{self.key}.max", self.max))
        object.__setattr__(self, "albedo", unit_interval(f"{self.key}.albedo", self.albedo))


SceneObject = PlaneObject | SphereObject | BoxObject

DEFAULT_CHART = PlaneObject(point=(0.0, 0.0, 0.38), normal=(0.0, 0.0, -1.0), size=(0.3, 0.2), albedo=0.6,
                            texture="chart")


MIN_SEPARATION_M = 1e-6
"""A point source (radius 0) closer than this to the camera is refused (:class:`Scene`)."""


@dataclass(frozen=True)
class Scene(_Part):
    """A whole rig: medium, camera, projector and objects (the default is the paper's tank)."""

    medium: Medium = Medium()
    camera: Camera = Camera()
    projector: Projector = Projector()
    objects: tuple[SceneObject, ...] = (DEFAULT_CHART,)

    def __post_init__(self):
        object.__setattr__(self, "objects", tuple(self.objects))
        if self.separation_m() < MIN_SEPARATION_M and self.projector.source_radius_m == 0.0:
            # the path from a point source through the medium starts at the camera: ∫ dt/t² along the ray
            # has no bound (docs/physics.md: B and D use 1/(d² + r_s²)); the model cannot represent it
            raise SceneError(
                f"projector.position {self.projector.position} is at the camera (d_LC = "
                f"{self.separation_m():.3g} m) with projector.source_radius_m = 0: a point source on the "
                f"camera has no finite backscatter in this model; move the source or give it a radius "
                f"(e.g. source_radius_m = 0.001)")

    def __hash__(self) -> int:    # kept: the model's caches look a scene up some 30 times a frame
        h = self.__dict__.get("_hash")
        if h is None:
            h = hash((self.medium, self.camera, self.projector, self.objects))
            object.__setattr__(self, "_hash", h)
        return h

    def __getstate__(self) -> dict:  # a kept hash is this process's (str hashes are salted per process)
        return {k: v for k, v in self.__dict__.items() if k != "_hash"}

    def separation_m(self) -> float:
        """Camera–source distance d_LC [m]."""
        return float(np.linalg.norm(np.subtract(self.projector.position, self.camera.position)))
