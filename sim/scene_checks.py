"""Scene values checked one by one: the error type, numbers, vectors, sizes and pinhole poses.

Every check names the scene key it is given in its error text (``docs/scene-format.md``); the frozen parts of
:mod:`polarstripe.sim.scene_parts` call them on construction.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from polarstripe.errors import PolarstripeError


class SceneError(PolarstripeError, ValueError):
    """A scene file or scene value is invalid; the text names the key and the bad value."""


Vec3 = tuple[float, float, float]


def finite(key: str, value: Any) -> float:
    """``value`` as a finite float (not a bool)."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise SceneError(f"{key} must be a number, got {value!r}") from None
    if isinstance(value, bool) or not math.isfinite(v):
        raise SceneError(f"{key} must be a finite number, got {value!r}")
    return v


def vec3(key: str, value: Any) -> Vec3:
    """``value`` as a tuple of 3 finite floats."""
    if not isinstance(value, (list, tuple, np.ndarray)) or len(value) != 3:
        raise SceneError(f"{key} must be a list of 3 numbers, got {value!r}")
    return tuple(finite(f"{key}[{i}]", c) for i, c in enumerate(value))  # type: ignore[return-value]


def positive(key: str, value: Any, allow_zero: bool = False) -> float:
    """``value`` as a float > 0 (≥ 0 with ``allow_zero``)."""
    v = finite(key, value)
    if v < 0 or (v == 0 and not allow_zero):
        raise SceneError(f"{key} must be {'>= 0' if allow_zero else '> 0'}, got {value!r}")
    return v


def unit_interval(key: str, value: Any) -> float:
    """``value`` as a float in [0, 1]."""
    v = finite(key, value)
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


def resolution(key: str, value: Any) -> tuple[int, int]:
    """``value`` ([width, height] of positive integers) as a tuple."""
    if not isinstance(value, (list, tuple)) or len(value) != 2:
        raise SceneError(f"{key} must be [width, height], got {value!r}")
    out = []
    for v in value:
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
            raise SceneError(f"{key} must be two positive integers, got {value!r}")
        out.append(int(v))
    return out[0], out[1]


def check_pose(section: str, position, look_at, up, fov_deg):
    """A pinhole pose (position, look_at, up, fov_deg) checked: look_at ≠ position, up not along the view,
    fov in (0, 179) degrees."""
    p, t, u = vec3(f"{section}.position", position), vec3(f"{section}.look_at", look_at), vec3(
        f"{section}.up", up)
    f = np.subtract(t, p)
    if np.linalg.norm(f) < 1e-12:
        raise SceneError(f"{section}.look_at must differ from {section}.position, both are {p}")
    if np.linalg.norm(np.cross(f / np.linalg.norm(f), u)) < 1e-9:
        raise SceneError(f"{section}.up must not be parallel to the viewing direction, got {u}")
    fov = finite(f"{section}.fov_deg", fov_deg)
    if not 0 < fov < 179:
        raise SceneError(f"{section}.fov_deg must be in (0, 179), got {fov_deg!r}")
    return p, t, u, fov
