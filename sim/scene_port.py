"""Flat refractive ports: the window a camera or projector housing looks through (docs/scene-format.md
"Ports", docs/physics.md §11).

A port is two parallel faces at ``distance_m`` and ``distance_m + thickness_m`` from the device's pinhole
along its ``normal`` (the device's forward axis when not given), air between the pinhole and the glass, water
beyond the outer face. No port (``None``, the default) is the bare pinhole every scene had before ports.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np
from polarstripe.sim.scene_checks import SceneError, Vec3, finite, positive, vec3

N_WATER = 1.333
"""Refractive index of water at 532 nm (fresh water, 20 °C)."""


@dataclass(frozen=True)
class Port:
    """A flat window: inner face at ``distance_m`` [m] from the pinhole along ``normal`` (None: the device's
    forward axis), glass ``thickness_m`` [m] thick (0: a bare air–water interface), refractive indices of
    air, glass and water, ``coated``: anti-reflection coated faces (no Fresnel loss; the paper's tank)."""

    distance_m: float = 0.01
    thickness_m: float = 0.01
    n_air: float = 1.0
    n_glass: float = 1.5
    n_water: float = N_WATER
    normal: Vec3 | None = None
    coated: bool = False
    key: str = dataclasses.field(default="port", compare=False, repr=False)

    def __post_init__(self):
        k = self.key
        object.__setattr__(self, "distance_m", positive(f"{k}.distance_m", self.distance_m, allow_zero=True))
        object.__setattr__(self, "thickness_m",
                           positive(f"{k}.thickness_m", self.thickness_m, allow_zero=True))
        for name in ("n_air", "n_glass", "n_water"):
            v = finite(f"{k}.{name}", getattr(self, name))
            if not 1.0 <= v <= 4.0:
                raise SceneError(f"{k}.{name} must be a refractive index in [1, 4], got "
                                 f"{getattr(self, name)!r}")
            object.__setattr__(self, name, v)
        if self.n_water < self.n_air:
            raise SceneError(f"{k}.n_water must be >= n_air (light enters the water), got "
                             f"{self.n_water!r} < {self.n_air!r}")
        if self.normal is not None:
            n = np.array(vec3(f"{k}.normal", self.normal))
            if np.linalg.norm(n) < 1e-12:
                raise SceneError(f"{k}.normal must be non-zero, got {self.normal!r}")
            object.__setattr__(self, "normal", tuple(float(c) for c in n / np.linalg.norm(n)))
        if not isinstance(self.coated, bool):
            raise SceneError(f"{k}.coated must be true or false, got {self.coated!r}")

    def replace(self, **changes: Any) -> Port:
        return dataclasses.replace(self, **changes)


GLASS_TANK = Port(distance_m=0.02, thickness_m=0.01, n_glass=1.52, n_water=N_WATER, normal=(0.0, 0.0, 1.0),
                  coated=True)
"""The paper's tank wall (§3: "the glass facades are antireflection coated"; footnote 1): 10 mm of glass
(n 1.52) whose outer face is the tank's front face z = 0, the device 2 cm in front of it."""

PORT_PRESETS = {"glass_tank": GLASS_TANK}


def parse_port(section: str, value: Any) -> Port | None:
    """A scene file's ``port``: a table of :class:`Port` keys or a preset name (:data:`PORT_PRESETS`)."""
    key = f"{section}.port"
    if value is None or isinstance(value, Port):
        return value
    if isinstance(value, str):
        if value not in PORT_PRESETS:
            raise SceneError(f"{key} must be a table or one of {', '.join(PORT_PRESETS)}, got {value!r}")
        return PORT_PRESETS[value].replace(key=key)
    if not isinstance(value, dict):
        raise SceneError(f"{key} must be a table or a preset name, got {value!r}")
    allowed = {f.name for f in dataclasses.fields(Port)} - {"key"}
    for k in value:
        if k not in allowed:
            raise SceneError(f"unknown key {key}.{k} (allowed: {', '.join(sorted(allowed))})")
    return Port(key=key, **value)


def check_port(section: str, port: Port | None, position, look_at, up, fov_deg: float, resolution) -> None:
    """Every pixel's ray must reach the port's inner face: the image corners within 89.9° of its normal."""
    if port is None:
        return
    if not isinstance(port, Port):
        raise SceneError(f"{section}.port must be a Port, got {type(port).__name__}")
    f = np.subtract(look_at, position)
    f = f / np.linalg.norm(f)
    r = np.cross(f, up)
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    normal = f if port.normal is None else np.asarray(port.normal)
    tx = np.tan(np.radians(fov_deg) / 2.0)
    ty = tx * resolution[1] / resolution[0]
    for sx in (-1, 1):
        for sy in (-1, 1):
            d = f + sx * tx * r + sy * ty * u
            if d @ normal / np.linalg.norm(d) < 1.7e-3:
                raise SceneError(f"{section}.port: the image corner ({sx:+d}, {sy:+d}) does not look "
                                 f"through the port (normal {tuple(np.round(normal, 4))}, fov {fov_deg} deg)")
