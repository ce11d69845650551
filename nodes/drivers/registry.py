"""Backends by name: a role → name → ``"module:Class"`` table, extended by the ``polarstripe.drivers`` entry
points; :func:`open_backend` makes one from its options.

Modules are imported only when a backend is asked for (like python-can's ``can/interfaces/__init__.py`` and
``can/interface.py``), so a missing optional extra costs nothing until it is used, and then the error names
the backend, the module and the extra to install.

A distribution adds backends with entry point names ``"<role>.<name>"``; the class subclasses the role's ABC
(:class:`~polarstripe.nodes.drivers.camera.Camera`, :class:`~polarstripe.nodes.drivers.display.Display`,
:class:`~polarstripe.nodes.drivers.stage.RotationStage`) and declares its ``Options``
(nodes/drivers/backend.py)::

    [project.entry-points."polarstripe.drivers"]
    "camera.acme" = "mypkg.acme_camera:AcmeCamera"

A launch file then names it like a built-in one: ``camera = "acme"``, ``camera_options = {...}``. A built-in
name wins over an entry point of the same name.
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping
from importlib.metadata import entry_points
from typing import Any

from polarstripe.nodes.drivers.backend import Backend, BackendContext, BackendOptions
from polarstripe.nodes.drivers.errors import BackendUnavailable
from polarstripe.runtime.params import ParamError, build_params

ENTRY_POINT_GROUP = "polarstripe.drivers"
_PKG = "polarstripe.nodes.drivers"

#: role -> the ABC every backend of the role subclasses
ROLES: dict[str, str] = {
    "stage": f"{_PKG}.stage:RotationStage",
    "display": f"{_PKG}.display:Display",
    "camera": f"{_PKG}.camera:Camera",
}

#: role -> backend name -> "module:Class": the built-in backends (their simulated twins included)
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
        "sim_polarization": f"{_PKG}.sim_polarization_camera:SimPolarizationCamera",
        "aravis": f"{_PKG}.aravis_camera:AravisCamera",
    },
}

#: "role.name" -> the optional extra (pyproject ``[project.optional-dependencies]``) that backend needs.
EXTRAS: dict[str, str] = {"display.window": "display", "camera.aravis": "aravis"}


def _table(role: str) -> dict[str, str]:
    if role not in BACKENDS:
        raise BackendUnavailable(f"unknown driver role {role!r} (choose from {', '.join(BACKENDS)})")
    table = dict(BACKENDS[role])
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        ep_role, _, ep_name = ep.name.partition(".")
        if ep_role == role and ep_name:
            table.setdefault(ep_name, ep.value)
    return table


def _import(target: str, what: str, extra: str | None = None) -> type:
    module_name, _, class_name = target.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        hint = f"; install it with: pip install 'polarstripe[{extra}]'" if extra else ""
        raise BackendUnavailable(
            f"{what} needs module {module_name}, which failed to import: {exc}{hint}") from exc
    try:
        return getattr(module, class_name)
    except AttributeError as exc:
        raise BackendUnavailable(f"{what}: module {module_name} has no {class_name}") from exc


def register_backend(role: str, name: str, target: str) -> None:
    """Add backend ``name`` of ``role`` as ``"module:Class"`` (imported only when used), for backends that
    live outside a distribution, e.g. ``register_backend("camera", "acme", "acme_camera:AcmeCamera")``."""
    module, _, cls = target.partition(":")
    if not module or not cls:
        raise BackendUnavailable(f"backend target {target!r} is not 'module:Class'")
    BACKENDS.setdefault(role, {})[name] = target


def backend_names(role: str) -> list[str]:
    """The backend names available for ``role`` ("stage", "display", "camera"), built-in and entry points."""
    return sorted(_table(role))


def load_backend(role: str, name: str) -> type:
    """Import and return the backend class ``name`` of ``role``.

    :raises BackendUnavailable: unknown role or name, the module failed to import (the text names the
        backend, the module and the optional extra to install), or the class is not a backend of the role.
    """
    table = _table(role)
    if name not in table:
        raise BackendUnavailable(f"unknown {role} backend {name!r} (choose from {', '.join(sorted(table))})")
    what = f"{role} backend {name!r}"
    cls = _import(table[name], what, EXTRAS.get(f"{role}.{name}"))
    base = _import(ROLES[role], f"{role} role") if role in ROLES else Backend
    if not (isinstance(cls, type) and issubclass(cls, base)):
        raise BackendUnavailable(
            f"{what}: {table[name]} is not a subclass of {base.__module__}.{base.__name__}")
    return cls


def backend_options(role: str, name: str, options: Mapping[str, Any] | None = None) -> BackendOptions:
    """The checked ``Options`` of backend ``name`` of ``role`` from a launch file's table ``options``.

    :raises BackendUnavailable: as :func:`load_backend`.
    :raises ParamError: an unknown or missing option, or a bad value (one line naming backend and key).
    """
    cls = load_backend(role, name)
    return build_params(cls.Options, dict(options or {}), what=f"{role} backend {name!r}", noun="option")


def check_backend(role: str, name: str, options: Mapping[str, Any] | None = None) -> None:
    """For a node's ``Params.validate``: raise ``ValueError`` (one line) when backend ``name`` does not exist
    or cannot be imported, or ``options`` do not fit its ``Options``."""
    try:
        backend_options(role, name, options)
    except (BackendUnavailable, ParamError) as exc:
        raise ValueError(str(exc)) from None


def open_backend(role: str, name: str, options: Mapping[str, Any] | None = None, *,
                 context: BackendContext | None = None, **common):
    """Make backend ``name`` of ``role`` from its ``options`` (checked by its ``Options``), lending it the
    node's ``context`` and passing ``common``, the settings the node owns for every backend of the role.

    :raises BackendUnavailable: as :func:`load_backend`.
    :raises ParamError: bad options.
    :raises DriverError: the backend failed to open (its own errors).
    """
    cls = load_backend(role, name)
    return cls.from_options(backend_options(role, name, options), context, **common)
