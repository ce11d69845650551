"""The simulated trigger box (nodes/drivers/sim_trigger.py) speaks protocol 1 of docs/hardware.md: request
line -> reply line (``handle``), line framing over the pty (``feed``: ``\\r`` ignored, split writes), the
reply count, refusals with the documented codes, the injected fault and restart."""

from __future__ import annotations

import pytest
import serial
from hypothesis import given
from hypothesis import strategies as st
from polarstripe.nodes.drivers.sim_trigger import SimTriggerBox


def _box(**kw) -> SimTriggerBox:
    return SimTriggerBox(**kw)  # not started: handle() and feed() need no pty


@pytest.mark.parametrize(
    "line, reply, pattern",
    [
        ("PAT FLOOD", "OK 0", "flood"),
        ("PAT OFF", "OK 0", "off"),
        ("PAT STRIPE 3 30", "OK 0", "stripe:3/30"),
        ("PAT stripe 0 1", "OK 0", "stripe:0/1"),  # the kind in any case
        ("PAT CHECKER 16 8", "OK 0", "checker:16:8"),
        ("PAT CHECKER 1 0", "OK 0", "checker:1:0"),
    ],
)
def test_patterns_are_accepted_and_kept_as_tags(line, reply, pattern):
    box = _box()
    assert box.handle(line) == reply and box.pattern == pattern


@pytest.mark.parametrize(
    "line, reply",
    [
        ("", "ERR 1 empty command"),
        ("HELLO", "ERR 1 unknown command HELLO"),
        ("PAT", "ERR 1 unknown command PAT"),
        ("PAT ZEBRA", "ERR 2 unknown pattern ZEBRA"),
        ("PAT STRIPE 3", "ERR 2 bad arguments for stripe: 3"),
        ("PAT STRIPE 3 30 1", "ERR 2 bad arguments for stripe: 3 30 1"),
        ("PAT STRIPE -1 30", "ERR 2 bad arguments for stripe: -1 30"),
        ("PAT STRIPE 30 30", "ERR 2 stripe 30 of 30"),
        ("PAT FLOOD 1", "ERR 2 bad arguments for flood: 1"),
        ("PAT CHECKER 8 x", "ERR 2 bad arguments for checker: 8 x"),
    ],
)
def test_refusals_carry_the_documented_codes_and_change_nothing(line, reply):
    box = _box()
    box.handle("PAT FLOOD")
    assert box.handle(line) == reply
    assert box.pattern == "flood" and box.seq == 0  # a refused command is not counted
    assert box.handle("PAT OFF") == "OK 1"


@pytest.mark.parametrize("line", ["TRIG 0", "TRIG -5", "TRIG x", "TRIG"])
def test_a_bad_trigger_argument_is_err_2(line):
    assert _box().handle(line).startswith("ERR 2 ")


def test_a_checker_on_a_laser_line_is_not_supported():
    box = _box(supported=("flood", "off", "stripe"))
    assert box.handle("PAT CHECKER 8 0") == "ERR 3 pattern checker not supported by this box"
    assert box.handle("PAT STRIPE 1 2") == "OK 0"


def test_identify_names_model_firmware_and_protocol_1():
    assert _box().handle("ID?") == "ID sim-trigger 1.0 1"
    box = _box(model="laser-9", firmware="2.3")
    assert box.handle("ID?") == "ID laser-9 2.3 1"
    assert box.seq == -1  # ID? is not a counted command


def test_triggers_are_counted_and_kept():
    box = _box()
    assert [box.handle(f"TRIG {us}") for us in (12500, 1, 999999)] == ["OK 0", "OK 1", "OK 2"]
    assert box.triggers == [12500, 1, 999999]


def test_injected_fault_answers_the_next_command_only():
    box = _box()
    box.handle("PAT FLOOD")
    box.inject_fault()
    assert box.handle("ID?") == "ID sim-trigger 1.0 1"  # identify still answers, the fault waits
    assert box.handle("PAT OFF") == "ERR 5 lamp driver fault"
    assert box.pattern == "flood"
    assert box.handle("PAT OFF") == "OK 1" and box.pattern == "off"


def test_restart_starts_the_count_again_and_the_count_wraps():
    box = _box()
    box.handle("PAT FLOOD")
    box.handle("PAT OFF")
    box.inject_restart()
    assert box.handle("PAT FLOOD") == "OK 0"
    box.seq = 65534
    assert [box.handle("PAT OFF") for _ in range(3)] == ["OK 65535", "OK 0", "OK 1"]


def test_feed_frames_lines_ignores_cr_and_joins_split_writes():
    box = _box()
    out: list[bytes] = []
    box.reply = out.append  # capture instead of writing to the pty
    box.feed(b"ID?\r\nPAT STR")
    assert out == [b"ID sim-trigger 1.0 1\n"]
    box.feed(b"IPE 2 4\nTRIG 5\n")
    assert out[1:] == [b"OK 0\n", b"OK 1\n"]
    assert box.pattern == "stripe:2/4" and box.triggers == [5]


_commands = st.sampled_from(["PAT FLOOD", "PAT OFF", "PAT STRIPE 1 3", "PAT STRIPE 3 3", "PAT CHECKER 4 2",
                             "PAT CHECKER 0 0", "TRIG 100", "ID?", "NOPE", ""])


@given(st.lists(_commands, max_size=40))
def test_ok_replies_count_consecutively_from_zero(lines):
    box = _box()
    oks = [r for r in map(box.handle, lines) if r.startswith("OK")]
    assert [int(r.split()[1]) for r in oks] == list(range(len(oks)))
    assert box.seq == len(oks) - 1


def test_the_bytes_on_the_pty():
    with SimTriggerBox() as box, serial.Serial(box.port, 115200, timeout=1.0) as port:
        port.write(b"ID?\r\n")
        assert port.read_until(b"\n") == b"ID sim-trigger 1.0 1\n"
        port.write(b"PAT CHECKER 8 4\nTRIG 250\n")
        assert port.read_until(b"\n") == b"OK 0\n" and port.read_until(b"\n") == b"OK 1\n"
        assert bytes(box.received) == b"ID?\r\nPAT CHECKER 8 4\nTRIG 250\n"
    box.stop()  # stopping twice is fine
