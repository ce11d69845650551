"""The ELL14 against the ELLx protocol manual, driven by a client written from the manual, not by our driver.

The client below knows only what the manual says: 9600 8N1, a command is ``<address><two letters>[data]``
with no terminator and a fixed number of data characters, a reply is ``<address><TWO LETTERS>[data]`` ended by
CR LF. One suite for the role: on the simulated ELL14 (a pty) always, and on a real one with ``--hardware
/dev/ttyUSB0`` (``--hardware-address``). On a real device the suite sets the velocity, runs a frequency search
(``s1``, not saved) and changes the address, restoring both; it does not move the mount.

The numbers in the test names are the points of the conformance list in ``docs/hardware.md``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import pytest
import serial
from polarstripe.nodes.drivers.simell14 import SimEll14

#: the reply each query of the manual gets, and its data length
REPLIES = {"in": ("IN", 30), "gs": ("GS", 2), "gp": ("PO", 8), "go": ("HO", 8), "gj": ("GJ", 8),
           "gv": ("GV", 2), "i1": ("I1", 22), "i2": ("I2", 22)}  # fmt: skip
HEX = set("0123456789ABCDEF")


class ElliptecClient:
    """The host side of the ELLx protocol, as the manual has it."""

    def __init__(self, port: str, address: str):
        self.address = address
        self.line = serial.Serial(port, 9600, bytesize=8, parity="N", stopbits=1, timeout=0.02)

    def close(self) -> None:
        self.line.close()

    def write(self, text: str) -> None:
        self.line.write(text.encode("ascii"))

    def replies(self, count: int = 1, timeout: float = 1.0) -> list[str]:
        """Up to ``count`` reply lines (without CR LF) within ``timeout`` seconds."""
        lines, buffer, deadline = [], b"", time.monotonic() + timeout
        while len(lines) < count and time.monotonic() < deadline:
            buffer += self.line.read(64)
            while b"\r\n" in buffer and len(lines) < count:
                line, buffer = buffer.split(b"\r\n", 1)
                lines.append(line.decode("ascii"))
        return lines

    def ask(self, command: str, timeout: float = 1.0, address: str | None = None) -> str:
        self.line.reset_input_buffer()
        self.write(f"{address or self.address}{command}")
        lines = self.replies(1, timeout)
        assert lines, f"no reply to {command!r} within {timeout} s"
        return lines[0]


@dataclass
class Device:
    name: str
    port: str
    address: str
    sim: SimEll14 | None


@pytest.fixture(scope="module")
def device(ell_device, request):
    if ell_device == "sim":
        with SimEll14(deg_per_s=2000.0) as sim:
            yield Device("sim", sim.port, "0", sim)
    else:
        yield Device(ell_device, ell_device, request.config.getoption("hardware_address").upper(), None)


@pytest.fixture
def client(device):
    c = ElliptecClient(device.port, device.address)
    yield c
    c.close()


def sim_only(device: Device) -> None:
    if device.sim is None:
        pytest.skip(f"{device.name}: what this checks is the simulator's own choice")


# -- 8: every command of the manual is answered, and the next one too ---------------------------------------
@pytest.mark.parametrize("query", list(REPLIES))
def test_8_every_query_of_the_manual_gets_its_reply(client, query):
    reply = client.ask(query)
    code, size = REPLIES[query]
    assert reply[:3] == client.address + code, reply
    body = reply[3:]
    assert len(body) >= size and set(body[:size]) <= HEX, reply


def test_8_set_velocity_is_acknowledged_and_read_back(client):
    before = client.ask("gv")[3:5]
    try:
        assert client.ask("sv32") == f"{client.address}GS00"
        assert client.ask("gv") == f"{client.address}GV32"
        assert client.ask("gs") == f"{client.address}GS00"
    finally:
        client.ask(f"sv{before}")


@pytest.mark.parametrize("motor", ["1", "2"])
def test_8_a_frequency_search_ends_in_a_status_and_the_next_command_is_answered(client, motor):
    assert client.ask(f"s{motor}", timeout=30.0) == f"{client.address}GS00"
    assert client.ask("gs") == f"{client.address}GS00"
    assert client.ask("gp")[:3] == f"{client.address}PO"


def test_8_change_address_answers_from_the_new_address(client):
    old = client.address
    new = "1" if old != "1" else "2"
    assert client.ask(f"ca{new}") == f"{new}GS00"
    try:
        assert client.ask("gs", address=new) == f"{new}GS00"
        client.write(f"{old}gs")
        assert client.replies(1, 0.3) == []  # nobody answers at the old address
    finally:
        assert client.ask(f"ca{old}", address=new) == f"{old}GS00"
    assert client.ask("gs") == f"{old}GS00"


def test_8_an_unknown_command_gets_gs03_and_swallows_nothing(client):
    client.line.reset_input_buffer()
    client.write(f"{client.address}zz")
    client.write(f"{client.address}gs")
    assert client.replies(2) == [f"{client.address}GS03", f"{client.address}GS00"]
    for _ in range(3):  # and the line stays in step
        assert client.ask("gs") == f"{client.address}GS00"


def test_8_a_command_whose_data_stop_short_is_a_communication_timeout(client, device):
    sim_only(device)  # the manual names status 01; when a device gives up waiting is its own
    client.line.reset_input_buffer()
    client.write(f"{client.address}ma0000")
    assert client.replies(1, 1.0) == [f"{client.address}GS01"]
    assert client.ask("gs") == f"{client.address}GS00"


def test_8_a_command_for_another_address_is_skipped_whole(client, device):
    sim_only(device)  # a real line may have a device at the other address: it would move
    other, a = ("E" if client.address != "E" else "D"), client.address
    client.line.reset_input_buffer()
    client.write(f"{other}ma00000000{a}gs")  # skipping only "Ema" would read "000" as a command for us
    assert client.replies(3, 0.3) == [f"{a}GS00"]


# -- 9: commands back to back in one write -----------------------------------------------------------------
@pytest.mark.parametrize("separator", ["", "\r\n"])
def test_9_two_commands_in_one_write_are_both_answered_in_order(client, separator):
    a = client.address
    client.line.reset_input_buffer()
    client.write(f"{a}gs{separator}{a}gp{separator}")
    lines = client.replies(2)
    assert len(lines) == 2 and lines[0] == f"{a}GS00" and lines[1][:3] == f"{a}PO", lines


# -- 10: velocity and motor information ------------------------------------------------------------------
def test_10_velocity_is_a_percentage(client):
    assert 0 < int(client.ask("gv")[3:5], 16) <= 100


@pytest.mark.parametrize("motor", ["1", "2"])
def test_10_motor_info_gives_states_and_resonant_frequencies(client, motor):
    body = client.ask(f"i{motor}")[3:]
    assert body[0] in "01" and body[1] in "01"  # loop, motor
    forward, backward = int(body[14:18], 16), int(body[18:22], 16)
    for period in (forward, backward):  # 14.74 MHz over the period: the motors resonate near 80-100 kHz
        assert 60e3 < 14.74e6 / period < 120e3, body


def test_10_velocity_outside_1_to_100_percent_is_refused(client, device):
    sim_only(device)
    assert client.ask("sv00") == f"{client.address}GS04"
    assert client.ask("svC8") == f"{client.address}GS04"
    assert client.ask("gv") == f"{client.address}GV64"
