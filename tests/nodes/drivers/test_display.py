"""Display / trigger backends: one contract for all, the projector image conventions, the serial protocol."""

from __future__ import annotations

import importlib.util
import sys
import time

import numpy as np
import pytest
from polarstripe import msgs
from polarstripe.msgs.patterns import PatternSpec
from polarstripe.nodes.drivers.display import NullDisplay, as_pattern, render_pattern
from polarstripe.nodes.drivers.errors import (
    BackendUnavailable,
    DeviceError,
    DriverError,
    DriverTimeout,
    DriverValueError,
)
from polarstripe.nodes.drivers.registry import load_backend
from polarstripe.nodes.drivers.serial_trigger import SerialTriggerDisplay
from polarstripe.nodes.drivers.sim_trigger import SimTriggerBox

HAVE_PYGAME = importlib.util.find_spec("pygame") is not None


@pytest.fixture(params=["null", "serial", "window"])
def display(request, monkeypatch):
    if request.param == "null":
        yield NullDisplay(64, 48)
    elif request.param == "serial":
        with SimTriggerBox() as box:
            yield SerialTriggerDisplay(box.port, width=64, height=48)
    else:
        if not HAVE_PYGAME:
            pytest.skip("pygame-ce (the 'display' extra) is not installed")
        monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
        from polarstripe.nodes.drivers.window_display import WindowDisplay

        yield WindowDisplay(64, 48, fullscreen=False)


# -- the contract ------------------------------------------------------------------------------------------
def test_show_returns_when_and_remembers_what(display):
    with display:
        before = time.monotonic()
        stamp = display.show("stripe:3/30")
        assert before <= stamp <= time.monotonic()
        assert display.current == PatternSpec("stripe", index=3, count=30)
        display.show("checker:8:4")
        assert str(display.current) == "checker:8:4"
        display.blank()
        assert display.current.kind == "off"


def test_a_bad_pattern_is_refused_before_the_output(display):
    with display:
        display.show("flood")
        for bad in ("stripe:30/30", "checker:0:1", "zebra", "stripe:-1/4"):
            with pytest.raises(DriverValueError, match="pattern"):
                display.show(bad)
        assert display.current.kind == "flood"


def test_close_is_idempotent_and_final(display):
    display.show("flood")
    display.close()
    display.close()
    with pytest.raises(DriverError, match="closed"):
        display.show("flood")


# -- the image conventions (the model's) -------------------------------------------------------------------
@pytest.mark.parametrize(("width", "n"), [(1280, 30), (640, 7), (97, 97), (10, 3)])
def test_stripes_tile_the_width_without_overlap(width, n):
    total = np.zeros(width, int)
    for k in range(n):
        row = render_pattern(f"stripe:{k}/{n}", width, 2)[0] > 0
        lit = np.nonzero(row)[0]
        assert lit[0] == k * width // n and lit[-1] == (k + 1) * width // n - 1
        assert np.all(np.diff(lit) == 1)
        total += row
    assert np.all(total == 1)


@pytest.mark.parametrize(("size", "shift"), [(1, 0), (4, 0), (4, 3), (5, 5), (8, 13)])
def test_checker_follows_the_documented_rule(size, shift):
    image = render_pattern(f"checker:{size}:{shift}", 23, 17)
    for row in range(17):
        for col in range(23):
            expected = ((col - shift) // size + row // size) % 2 == 0
            assert (image[row, col] == 255) == expected


def test_checker_shift_by_size_swaps_lit_and_dark():
    a = render_pattern("checker:6:0", 48, 36) > 0
    b = render_pattern("checker:6:6", 48, 36) > 0
    assert np.array_equal(a, ~b)
    assert a.mean() == pytest.approx(0.5)


def test_flood_off_and_black_level():
    assert np.all(render_pattern("flood", 5, 4) == 255)
    assert np.all(render_pattern("off", 5, 4, dark=12) == 12)


def test_patterns_come_from_messages_and_specs_and_bad_ones_are_driver_errors():
    assert as_pattern(msgs.Pattern(kind="stripe", index=2, count=9)) == PatternSpec("stripe", 2, 9)
    assert as_pattern("checker:16:8") == PatternSpec("checker", size=16, shift=8)
    with pytest.raises(DriverValueError, match="index=9 count=9"):
        as_pattern(msgs.Pattern(kind="stripe", index=9, count=9))
    with pytest.raises(DriverValueError, match="not flood, off"):
        render_pattern("stripes:1/2", 8, 8)


# -- backends ----------------------------------------------------------------------------------------------
def test_null_display_keeps_history_and_image():
    d = NullDisplay(40, 10)
    d.show("stripe:1/4")
    d.show("flood")
    assert [str(p) for p in d.shown] == ["stripe:1/4", "flood"]
    assert np.all(d.image() == 255)


@pytest.mark.skipif(not HAVE_PYGAME, reason="pygame-ce (the 'display' extra) is not installed")
def test_window_shows_the_rendered_image(monkeypatch):
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    from polarstripe.nodes.drivers.window_display import WindowDisplay

    with WindowDisplay(80, 60, fullscreen=False) as d:
        for spec in ("stripe:2/5", "checker:7:3", "flood", "off"):
            d.show(spec)
            assert np.array_equal(d.screenshot(), render_pattern(spec, 80, 60))


def test_window_without_pygame_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "pygame", None)
    from polarstripe.nodes.drivers.window_display import WindowDisplay

    assert load_backend("display", "window") is WindowDisplay
    with pytest.raises(BackendUnavailable, match=r"pygame-ce .*pip install 'polarstripe\[display\]'"):
        WindowDisplay(10, 10)


def test_registry_errors_name_role_and_backend():
    with pytest.raises(BackendUnavailable, match="unknown display backend 'hologram'"):
        load_backend("display", "hologram")
    with pytest.raises(BackendUnavailable, match="unknown driver role 'laser'"):
        load_backend("laser", "x")


def test_serial_protocol_bytes():
    with SimTriggerBox() as box, SerialTriggerDisplay(box.port) as d:
        d.show("stripe:3/30")
        d.show("checker:16:8")
        d.trigger(0.0125)
        assert box.pattern == "checker:16:8" and box.triggers == [12500]
        assert bytes(box.received) == b"ID?\nPAT STRIPE 3 30\nPAT CHECKER 16 8\nTRIG 12500\n"
        assert (d.model, d.firmware) == ("sim-trigger", "1.0")
    assert bytes(box.received).endswith(b"TRIG 12500\nPAT OFF\n")  # close() blanks


def test_serial_box_refusals_are_device_errors():
    with SimTriggerBox(supported=("flood", "off", "stripe")) as box, SerialTriggerDisplay(box.port) as d:
        with pytest.raises(
            DeviceError, match=r"'PAT CHECKER 8 0' refused: ERR 3 pattern checker"
        ):
            d.show("checker:8:0")
        box.inject_fault()
        with pytest.raises(DeviceError, match="ERR 5"):
            d.show("flood")
        d.show("flood")  # the next command works again
        box.inject_restart()
        with pytest.raises(DeviceError, match="restarted"):
            d.show("stripe:0/2")


def test_a_silent_box_is_a_timeout():
    with SimTriggerBox() as box:
        box.feed = lambda data: None  # hears nothing, says nothing
        start = time.monotonic()
        with pytest.raises(DriverTimeout, match=r"no reply to 'ID\?' within 0.2 s"):
            SerialTriggerDisplay(box.port, timeout_s=0.2)
        assert time.monotonic() - start < 1.0
