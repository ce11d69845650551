"""Ell14Stage against the simulated ELL14 on a pty: the protocol bytes, busy replies, bad commands, errors."""

from __future__ import annotations

import time

import pytest
import serial
from polarstripe.nodes.drivers.ell14 import Ell14Stage, decode_s32, encode_s32
from polarstripe.nodes.drivers.errors import (
    DeviceError,
    DriverError,
    DriverTimeout,
    DriverValueError,
    StageFault,
)
from polarstripe.nodes.drivers.simell14 import SimEll14


@pytest.fixture
def device():
    with SimEll14(deg_per_s=2000.0) as dev:
        yield dev


@pytest.mark.parametrize(
    ("value", "text"),
    [(0, "00000000"), (-1, "FFFFFFFF"), (17920, "00004600"), (-17920, "FFFFBA00"), (2**31 - 1, "7FFFFFFF")],
)
def test_signed_32_bit_hex(value, text):
    assert encode_s32(value) == text
    assert decode_s32(text) == value


def test_connect_reads_pulses_per_revolution_from_info(device):
    with Ell14Stage(device.port) as stage:
        assert stage.pulses_per_rev == 143_360
        assert stage.info["type"] == 0x0E and stage.info["travel"] == 360
    assert device.received.startswith(b"0in")


def test_a_move_sends_ma_with_pulses_and_reads_the_final_position(device):
    with Ell14Stage(device.port) as stage:
        stage.move_to(45.0)
        assert stage.wait_settled(2.0) == pytest.approx(45.0)
        assert b"0ma00004600" in device.received  # 45 deg = 143360 / 8 pulses
        assert device.position == 17920


def test_a_negative_angle_maps_back_from_the_modulo_position(device):
    with Ell14Stage(device.port) as stage:
        stage.move_to(-30.0)
        assert stage.wait_settled(2.0) == pytest.approx(-30.0, abs=360 / 143360)
        assert device.position == 143360 - 11947


def test_busy_replies_are_retried(device):
    with Ell14Stage(device.port, busy_timeout_s=2.0) as stage:
        device.inject_busy(3)
        stage.move_to(10.0)
        assert stage.wait_settled(2.0) == pytest.approx(10.0, abs=360 / 143360)
        assert device.received.count(b"0ma") == 4  # three GS09 answers, then the move


def test_a_device_busy_too_long_is_a_timeout_fault(device):
    with Ell14Stage(device.port, busy_timeout_s=0.3) as stage:
        device.inject_busy(1000)
        stage.move_to(10.0)
        with pytest.raises(StageFault, match="busy"):
            stage.wait_settled(2.0)
        assert "busy (GS09)" in stage.fault and stage.angle is None
        device.inject_busy(0)
        stage.reset_fault()
        assert stage.fault is None


def test_a_bad_command_is_a_device_error_naming_the_status(device):
    with Ell14Stage(device.port) as stage:
        with pytest.raises(DeviceError, match=r"'zz' failed: GS03 command error or not supported"):
            stage.request("zz")
        assert stage.fault is None  # a rejected query does not fault the stage
        assert stage.request("gs") == "0GS00"


def test_any_command_of_the_manual_keeps_the_line_in_step(device):
    with Ell14Stage(device.port) as stage:
        assert stage.request("sv", "32") == "0GS00"
        assert stage.request("gs") == "0GS00"
        assert stage.request("gp") == "0PO00000000"
        assert stage.velocity == 0x32
        stage.velocity = 80
        assert device.velocity == 80
        info = stage.motor_info(1)
        assert info["loop"] and info["motor"] and 60e3 < info["forward_hz"] < 120e3
        assert stage.request("s1", timeout_s=2.0) == "0GS00"


def test_a_command_with_the_wrong_data_length_is_not_sent(device):
    with Ell14Stage(device.port) as stage:
        sent = len(device.received)
        with pytest.raises(DriverValueError, match=r"'sv' takes 2 data characters, got data='032'"):
            stage.request("sv", "032")
        assert len(device.received) == sent


def test_change_address_follows_the_device_to_its_new_address(device):
    with Ell14Stage(device.port) as stage:
        stage.change_address("3")
        assert device.address == "3" and stage.address == "3" and stage.name.startswith("ELL14 3 ")
        stage.move_to(45.0)
        assert stage.wait_settled(2.0) == pytest.approx(45.0)
        stage.change_address("0")
        assert stage.request("gs") == "0GS00"


def test_a_move_error_is_a_fault_with_its_code(device):
    with Ell14Stage(device.port) as stage:
        device.inject_move_error(0x0D)
        stage.move_to(20.0)
        with pytest.raises(StageFault, match="GS0D over current"):
            stage.wait_settled(2.0)
        assert stage.angle is None


def test_a_silent_device_is_a_clear_timeout(device):
    device.inject_silence(True)
    start = time.monotonic()
    with pytest.raises(DriverTimeout, match=r"no reply to 'in' within 0.2 s"):
        Ell14Stage(device.port, timeout_s=0.2)
    assert time.monotonic() - start < 1.0


def test_other_addresses_are_ignored_by_the_device(device):
    with serial.Serial(device.port, 9600, timeout=0.2) as port:
        port.write(b"1gs")
        assert port.read_until(b"\n") == b""
        port.write(b"0gs\r\n")  # a CR LF terminator is tolerated
        assert port.read_until(b"\n") == b"0GS00\r\n"


def test_a_missing_port_is_a_driver_error():
    with pytest.raises(DriverError, match="cannot open the port"):
        Ell14Stage("/dev/nonexistent-ell14")
