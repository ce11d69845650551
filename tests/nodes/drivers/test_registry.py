"""The backend registry: built-in table, entry points, runtime registration, lazy import errors."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
from polarstripe.nodes.drivers import registry
from polarstripe.nodes.drivers.display import NullDisplay
from polarstripe.nodes.drivers.errors import BackendUnavailable


def test_builtin_names():
    assert {"cia402", "ell14", "sim"} <= set(registry.backend_names("stage"))
    assert {"null", "window", "serial"} <= set(registry.backend_names("display"))
    assert {"v4l2", "file"} <= set(registry.backend_names("camera"))


def test_entry_points_extend_the_table(monkeypatch):
    fake = [
        SimpleNamespace(name="display.blinker", value="polarstripe.nodes.drivers.display:NullDisplay"),
        SimpleNamespace(name="camera", value="ignored:NoRole"),
    ]
    monkeypatch.setattr(
        registry, "entry_points", lambda group: fake if group == registry.ENTRY_POINT_GROUP else []
    )
    assert "blinker" in registry.backend_names("display")
    assert registry.load_backend("display", "blinker") is NullDisplay


def test_registered_backends_load_lazily(monkeypatch):
    monkeypatch.setitem(registry.BACKENDS, "camera", dict(registry.BACKENDS["camera"]))
    registry.register_backend("camera", "ghost", "polarstripe.nodes.drivers.no_such_module:GhostCamera")
    assert "ghost" in registry.backend_names("camera")  # nothing imported yet
    with pytest.raises(BackendUnavailable, match=r"camera backend 'ghost' needs module .*no_such_module"):
        registry.load_backend("camera", "ghost")
    with pytest.raises(BackendUnavailable, match="not 'module:Class'"):
        registry.register_backend("camera", "bad", "just_a_module")


def test_open_backend_passes_arguments():
    display = registry.open_backend("display", "null", width=8, height=4)
    assert isinstance(display, NullDisplay) and (display.width, display.height) == (8, 4)


def test_a_missing_class_is_named(monkeypatch):
    monkeypatch.setitem(registry.BACKENDS, "display", {"odd": "polarstripe.nodes.drivers.display:NoSuch"})
    with pytest.raises(BackendUnavailable, match="has no NoSuch"):
        registry.load_backend("display", "odd")
