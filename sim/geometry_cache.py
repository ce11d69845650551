"""The pattern-independent geometry of a render, kept across the frames of a scan (docs/physics.md §10.6).

A scan renders one scene many times with only the pattern changing: the camera rays, what they hit, the
surface under each pixel, the rays' in-medium intervals, the shadow rays from the source and the unscattered
light D at every hit (before the pattern selects the lit ones) are the same for every frame. They are
computed once per scene and kept here, keyed by the (frozen, hashable) :class:`~polarstripe.sim.scene.Scene`
and a name; a changed camera, projector, medium or object is a different scene and recomputes (what the
projector does not change is kept under :func:`camera_only`'s key, for every projector pose). Values are
made read-only so that no caller can change what the next frame reads. Per-point kernels compute each point
independently, so a cached frame is bit-identical to an uncached one (``tests/sim/test_geometry_cache.py``).

:func:`disabled` turns the cache off (the uncached path, for tests and ``polarstripe bench fidelity``).
"""

from __future__ import annotations

import os
import threading
from collections import OrderedDict
from collections.abc import Callable
from contextlib import contextmanager
from typing import Any

import numpy as np

MAX_SCENES = 4          # scenes kept (the simulator renders stripes and checkers at two resolutions per pose)
_store: OrderedDict = OrderedDict()       # scene -> {name: value}
_lock = threading.Lock()
_making: dict = {}                        # (scene, name) -> Event set once another thread has made it
_state = {"enabled": True, "hits": 0, "misses": 0}


def _freeze(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        value.flags.writeable = False
    elif isinstance(value, tuple):          # NamedTuples and dataclass-like tuples of arrays
        for v in value:
            _freeze(v)
    elif hasattr(value, "__dataclass_fields__"):
        for name in value.__dataclass_fields__:
            _freeze(getattr(value, name))
    return value


def cached(scene, name: tuple | str, make: Callable[[], Any]) -> Any:
    """``make()`` for (``scene``, ``name``), computed once while the scene stays among the last
    :data:`MAX_SCENES` used; arrays in the value are made read-only. A value another thread is making is
    waited for, not made again (frames of one scan render in parallel: sim/threads.py)."""
    if not _state["enabled"]:
        return make()
    key = (scene, name)
    while True:
        with _lock:
            entry = _store.get(scene)
            if entry is not None:
                _store.move_to_end(scene)
                if name in entry:
                    _state["hits"] += 1
                    return entry[name]
            busy = _making.get(key)
            if busy is None:
                busy = _making[key] = threading.Event()
                break
        busy.wait()
    try:
        value = _freeze(make())
        with _lock:
            _state["misses"] += 1
            entry = _store.setdefault(scene, {})
            entry[name] = value
            _store.move_to_end(scene)
            while len(_store) > MAX_SCENES:
                _store.popitem(last=False)
    finally:
        with _lock:
            del _making[key]
        busy.set()
    return value


def camera_only(scene):
    """The key under which :func:`cached` keeps what only the camera, the objects and the medium fix, not the
    projector (the camera's rays and hits, the view rays' table, the glow's patches and weights): one entry
    for every projector pose, e.g. the separations of a plan, which differ in the projector alone."""
    return ("camera only", scene.medium, scene.camera, scene.objects)


def enabled() -> bool:
    """False inside :func:`disabled`."""
    return _state["enabled"]


def clear() -> None:
    """Forget every cached scene."""
    with _lock:
        _store.clear()


def stats() -> dict:
    """{"hits", "misses", "scenes"} since the process started."""
    with _lock:
        return {"hits": _state["hits"], "misses": _state["misses"], "scenes": len(_store)}


def _after_fork_in_child() -> None:
    """A forked child has one thread: values the parent's other threads were making will never come, and a
    lock one of them held stays held. Both are forgotten (the made values stay)."""
    global _lock
    _lock = threading.Lock()
    _making.clear()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_after_fork_in_child)


@contextmanager
def disabled():
    """Within the block every render recomputes its geometry (the uncached path)."""
    with _lock:
        before = _state["enabled"]
        _state["enabled"] = False
    try:
        yield
    finally:
        with _lock:
            _state["enabled"] = before
