"""The backend registry: built-in table, entry points, runtime registration, lazy import errors."""

from __future__ import annotations

import dataclasses
import inspect
from types import SimpleNamespace

import pytest
from polarstripe.nodes.drivers import registry
from polarstripe.nodes.drivers.backend import Backend, BackendContext
from polarstripe.nodes.drivers.display import NullDisplay
from polarstripe.nodes.drivers.errors import BackendUnavailable, DriverError
from polarstripe.runtime.params import ParamError


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
    display = registry.open_backend("display", "null", {"width": 8, "height": 4})
    assert isinstance(display, NullDisplay) and (display.width, display.height) == (8, 4)


def test_a_missing_class_is_named(monkeypatch):
    monkeypatch.setitem(registry.BACKENDS, "display", {"odd": "polarstripe.nodes.drivers.display:NoSuch"})
    with pytest.raises(BackendUnavailable, match="has no NoSuch"):
        registry.load_backend("display", "odd")


@pytest.mark.parametrize("role", sorted(registry.BACKENDS))
def test_every_builtin_option_is_a_constructor_keyword_with_the_same_default(role):
    """A backend's Options and its constructor say one thing: a launch file's default is the driver's (a
    backend with its own from_options, the sim camera, maps its options itself)."""
    for name in registry.backend_names(role):
        cls = registry.load_backend(role, name)
        if cls.from_options.__func__ is not Backend.from_options.__func__:
            continue
        signature = inspect.signature(cls.__init__).parameters
        for f in dataclasses.fields(cls.Options):
            assert f.name in signature, (role, name, f.name)
            default = signature[f.name].default
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                assert default is inspect.Parameter.empty, (role, name, f.name)  # required in both
            else:
                mine = f.default if f.default_factory is dataclasses.MISSING else f.default_factory()
                expected = list(default) if isinstance(default, tuple) else default
                assert mine == expected, (role, name, f.name)


def test_options_are_typed_and_checked():
    opts = registry.backend_options("stage", "cia402", {"node_id": "7", "speed_deg_s": "none"})
    assert (opts.node_id, opts.speed_deg_s, opts.interface) == (7, None, "zmq")
    with pytest.raises(ParamError, match=r"^stage backend 'ell14': missing option 'port'$"):
        registry.backend_options("stage", "ell14", {})
    with pytest.raises(ValueError, match=r"^display backend 'null': unknown option 'colour' \(known: heig"):
        registry.check_backend("display", "null", {"colour": "red"})
    with pytest.raises(ValueError, match=r"^unknown display backend 'hologram'"):
        registry.check_backend("display", "hologram", {})


def test_a_class_of_another_role_is_refused(monkeypatch):
    monkeypatch.setitem(registry.BACKENDS, "camera", {"odd": "polarstripe.nodes.drivers.display:NullDisplay"})
    with pytest.raises(BackendUnavailable, match=r"camera backend 'odd': .*NullDisplay is not a subclass of "
                                                 r"polarstripe.nodes.drivers.camera.Camera"):
        registry.load_backend("camera", "odd")


def test_the_node_lends_its_service_calls_to_the_sim_camera():
    calls = []
    context = BackendContext(service=lambda name, req, rep: calls.append((name, req.__name__, rep.__name__)))
    cam = registry.open_backend("camera", "sim", {"render_service": "sim2/render"}, context=context)
    assert calls == [("sim2/render", "RenderRequest", "Frame")]
    cam.close()
    with pytest.raises(DriverError, match="needs the node's service calls"):
        registry.open_backend("camera", "sim")
