"""Backends by name: a role → name → ``"module:Class"`` table, plus the ``polarstripe.drivers`` entry points.
points.

Modules are imported only when a backend is asked for (like python-can's ``can/interfaces/__init__.py`` and
``can/interface.py``), so a missing optional extra costs nothing until it is used, and then the error names
the backend, the module and the extra to install.

Entry points: a distribution adds backends with names ``"<role>.<name>"``::

    [project.entry-points."polarstripe.drivers"]
    "camera.aravis" = "mypkg.aravis_camera:AravisCamera"
"""

from __future__ import annotations

import importlib
from importlib.metadata import entry_points

from polarstripe.nodes.drivers.errors import BackendUnavailable

ENTRY_POINT_GROUP = "polarstripe.drivers"
_PKG = "polarstripe.nodes.drivers"

#: role -> backend name -> "module:Class". The simulator camera backend is added by the simulator package.
BACKENDS: dict[str, dict[str, str]] = {
    "stage": {
        "cia402": f"{_PKG}.cia402:Cia402Stage",
        "ell14": f"{_PKG}.ell14:Ell14Stage",
        "sim": f"{_PKG}.simstage:SimStage",
    },
    "display": {
        "null": f"{_PKG}.display:NullDisplay",
        "window": f"{_PKG}.window_display:WindowDisplay",
        "serial": f"{_PKG}.serial_trigger:SerialTriggerDisplay",
    },
    "camera": {
        "v4l2": f"{_PKG}.v4l2_camera:V4l2Camera",
        "file": f"{_PKG}.file_camera:FileCamera",
        "sim": f"{_PKG}.sim_camera:SimCamera",
    },
}

#: "role.name" -> the optional extra (pyproject ``[project.optional-dependencies]``) that backend needs.
EXTRAS: dict[str, str] = {"display.window": "display"}


def _table(role: str) -> dict[str, str]:
    if role not in BACKENDS:
        raise BackendUnavailable(f"unknown driver role {role!r} (choose from {', '.join(BACKENDS)})")
    table = dict(BACKENDS[role])
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        ep_role, _, ep_name = ep.name.partition(".")
        if ep_role == role and ep_name:
            table.setdefault(ep_name, ep.value)
    return table


def register_backend(role: str, name: str, target: str) -> None:
    """Add backend ``name`` of ``role`` as ``"module:Class"`` (imported only when used), e.g. the simulator's
    camera: ``register_backend("camera", "sim", "polarstripe.sim.camera:SimCamera")``."""
    module, _, cls = target.partition(":")
    if not module or not cls:
        raise BackendUnavailable(f"backend target {target!r} is not 'module:Class'")
    BACKENDS.setdefault(role, {})[name] = target


def backend_names(role: str) -> list[str]:
    """The backend names available for ``role`` ("stage", "display", "camera"), built-in and entry points."""
    return sorted(_table(role))


def load_backend(role: str, name: str) -> type:
    """Import and return the backend class ``name`` of ``role``.

    :raises BackendUnavailable: unknown role or name, or the module failed to import (the text names the
        backend, the module and the optional extra to install).
    """
    table = _table(role)
    if name not in table:
        raise BackendUnavailable(f"unknown {role} backend {name!r} (choose from {', '.join(sorted(table))})")
    module_name, _, class_name = table[name].partition(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        extra = EXTRAS.get(f"{role}.{name}")
        hint = f"; install it with: pip install 'polarstripe[{extra}]'" if extra else ""
        raise BackendUnavailable(
            f"{role} backend {name!r} needs module {module_name}, which failed to import: {exc}{hint}"
        ) from exc
    try:
        return getattr(module, class_name)
    except AttributeError as exc:
        raise BackendUnavailable(
            f"{role} backend {name!r}: module {module_name} has no {class_name}"
        ) from exc


def open_backend(role: str, name: str, **kwargs):
    """Construct backend ``name`` of ``role`` with ``kwargs`` (the backend's own constructor arguments)."""
    return load_backend(role, name)(**kwargs)
