"""The drivers' error tree (nodes/drivers/errors.py) as callers rely on it: each class is caught by the
built-in class it promises (TimeoutError, ValueError, ImportError) and by PolarstripeError, errors raised by
real drivers land in the right branch, every error class a driver module declares is in the tree, and the
command line shows one as a single line."""

from __future__ import annotations

import importlib
import inspect
import math
import pkgutil
import sys
import types

import pytest
from polarstripe.errors import PolarstripeError
from polarstripe.nodes import drivers
from polarstripe.nodes.drivers.errors import (
    BackendUnavailable,
    DeviceError,
    DeviceLost,
    DriverError,
    DriverTimeout,
    DriverValueError,
    EndOfFrames,
    StageFault,
)
from polarstripe.nodes.drivers.registry import load_backend
from polarstripe.nodes.drivers.serial_trigger import SerialTriggerDisplay
from polarstripe.nodes.drivers.sim_trigger import SimTriggerBox
from polarstripe.nodes.drivers.simstage import SimStage
from polarstripe.tools import cli

BUILTINS = (TimeoutError, ValueError, ImportError)


@pytest.mark.parametrize(
    "cls, builtin",
    [
        (DriverTimeout, TimeoutError),
        (DriverValueError, ValueError),
        (BackendUnavailable, ImportError),
        (DeviceError, None),
        (DeviceLost, None),
        (EndOfFrames, None),
        (StageFault, None),
        (DriverError, None),
    ],
)
def test_each_class_is_caught_as_promised_and_by_nothing_else(cls, builtin):
    err = cls("dev /dev/ttyX: something")
    assert isinstance(err, DriverError) and isinstance(err, PolarstripeError)
    for b in BUILTINS:
        assert isinstance(err, b) == (b is builtin), b
    assert str(err) == "dev /dev/ttyX: something"


def _driver_modules():
    for info in pkgutil.iter_modules(drivers.__path__):
        yield importlib.import_module(f"{drivers.__name__}.{info.name}")


def test_every_error_a_driver_module_declares_is_in_the_tree():
    found = []
    for mod in _driver_modules():
        for name, obj in inspect.getmembers(mod, inspect.isclass):
            if issubclass(obj, BaseException) and obj.__module__ == mod.__name__:
                found.append(obj)
                if mod.__name__.endswith(".zmqcan"):
                    continue  # a python-can interface raises python-can's errors (can.CanError)
                assert issubclass(obj, DriverError), f"{mod.__name__}.{name} is not a DriverError"
    assert StageFault in found and DriverTimeout in found


def test_a_stage_target_beyond_the_limits_is_a_value_error():
    stage = SimStage(min_deg=-90, max_deg=90)
    for bad in (91.0, math.nan):
        with pytest.raises(ValueError) as info:
            stage.move_to(bad)
        assert type(info.value) is DriverValueError and "sim stage" in str(info.value)


def test_a_stage_that_never_settles_is_a_timeout_and_then_a_stage_fault():
    stage = SimStage(deg_per_s=1e6, settle_s=0.0)
    stage.inject_never_settle()
    stage.move_to(1.0)
    with pytest.raises(TimeoutError) as info:
        stage.wait_settled(timeout=0.0)
    assert type(info.value) is DriverTimeout
    with pytest.raises(StageFault) as info:
        stage.move_to(2.0)
    assert not isinstance(info.value, TimeoutError | ValueError)


def test_an_unknown_backend_is_an_import_error():
    with pytest.raises(ImportError) as info:
        load_backend("display", "hologram")
    assert type(info.value) is BackendUnavailable


def test_a_refusing_and_a_silent_device():
    with SimTriggerBox() as box, SerialTriggerDisplay(box.port, timeout_s=0.2) as d:
        box.inject_fault()
        with pytest.raises(DriverError) as info:
            d.show("flood")
        assert type(info.value) is DeviceError and box.port in str(info.value)
        box.feed = lambda data: None  # hears nothing from now on
        with pytest.raises(TimeoutError) as info:
            d.show("off")
        assert type(info.value) is DriverTimeout and box.port in str(info.value)


@pytest.mark.parametrize("cls", [DriverTimeout, DeviceLost, BackendUnavailable, StageFault])
def test_the_command_line_shows_a_driver_error_as_one_line(cls, monkeypatch, capsys):
    mod = types.ModuleType("ps_test_errors_cmd")
    mod.HELP = "raises"
    mod.configure = lambda parser: None

    def main(args):
        raise cls("camera /dev/video0: no frame within 1 s")

    mod.main = main
    monkeypatch.setitem(sys.modules, mod.__name__, mod)
    monkeypatch.setitem(cli.COMMANDS, "raiser", (mod.__name__, "raises"))
    assert cli.main(["raiser"]) == 2
    cap = capsys.readouterr()
    assert cap.err == "polarstripe raiser: error: camera /dev/video0: no frame within 1 s\n" and cap.out == ""
