"""The serial trigger driver (nodes/drivers/serial_trigger.py) against boxes on a pty that answer what the
test scripts (docs/hardware.md, protocol 1): the request lines, the identify check, the reply count and its
wrap, replies it must refuse, ``ERR`` parsing, exposure checks, stale input, timeouts. (test_display.py runs
the display contract and the happy path against SimTriggerBox.)"""

from __future__ import annotations

import time

import pytest
from hypothesis import given
from hypothesis import strategies as st
from polarstripe.msgs.patterns import PatternSpec, parse
from polarstripe.nodes.drivers.errors import DeviceError, DriverError, DriverTimeout, DriverValueError
from polarstripe.nodes.drivers.pty_device import PtyDevice
from polarstripe.nodes.drivers.serial_trigger import ERROR_CODES, SerialTriggerDisplay, pattern_command
from polarstripe.nodes.drivers.sim_trigger import SimTriggerBox


class ScriptedBox(PtyDevice):
    """Answers ``ID?`` with ``ident`` and every other line with the next of ``replies`` (None: silence)."""

    def __init__(self, replies=(), ident="ID scripted 0.1 1"):
        super().__init__()
        self.ident, self.replies, self.lines = ident, list(replies), []
        self._buf = b""

    def feed(self, data: bytes) -> None:
        self._buf += data
        while b"\n" in self._buf:
            line, self._buf = self._buf.split(b"\n", 1)
            text = line.decode()
            self.lines.append(text)
            answer = self.ident if text == "ID?" else (self.replies.pop(0) if self.replies else None)
            if answer is not None:
                self.reply(answer.encode() + b"\n")


@pytest.mark.parametrize(
    "spec, line",
    [("flood", "PAT FLOOD"), ("off", "PAT OFF"), ("stripe:0/1", "PAT STRIPE 0 1"),
     ("stripe:29/30", "PAT STRIPE 29 30"), ("checker:16:8", "PAT CHECKER 16 8"),
     ("checker:3:0", "PAT CHECKER 3 0")],
)
def test_pattern_commands(spec, line):
    assert pattern_command(parse(spec)) == line


@given(st.integers(1, 10**6).flatmap(lambda n: st.tuples(st.integers(0, n - 1), st.just(n))))
def test_every_stripe_command_is_one_the_box_accepts(kn):
    k, n = kn
    box = SimTriggerBox()
    assert box.handle(pattern_command(PatternSpec("stripe", k, n))) == "OK 0"
    assert box.pattern == f"stripe:{k}/{n}"


@pytest.mark.parametrize(
    "ident, match",
    [("ID scripted 0.1 2", r"'ID scripted 0.1 2' is not an ID reply of protocol 1"),
     ("ID scripted 1", "is not an ID reply"), ("HELLO there box 1", "'HELLO there box 1' is not an ID reply"),
     ("ERR 1 unknown command ID?", r"'ID\?' refused: ERR 1 unknown command ID\?")],
)
def test_identify_must_be_protocol_1(ident, match):
    with ScriptedBox(ident=ident) as box:
        with pytest.raises(DeviceError, match=match) as info:
            SerialTriggerDisplay(box.port, timeout_s=0.5)
        assert box.port in str(info.value)  # the text names the port


def test_model_and_firmware_come_from_the_id_reply():
    with ScriptedBox(ident="ID laserline 4.2 1") as box, SerialTriggerDisplay(box.port) as d:
        assert (d.model, d.firmware, d.name) == ("laserline", "4.2", f"trigger box on {box.port}")


def test_a_missing_port_is_a_driver_error():
    with pytest.raises(DriverError, match="trigger box on /nonexistent/ttyX: cannot open the port"):
        SerialTriggerDisplay("/nonexistent/ttyX")


def test_a_pyserial_url_that_echoes_is_not_a_box():
    with pytest.raises(DeviceError, match=r"loop://: 'ID\?' is not an ID reply of protocol 1"):
        SerialTriggerDisplay("loop://", timeout_s=0.2)


def test_the_reply_count_wraps_at_65536():
    replies = ["OK 65534", "OK 65535", "OK 0", "OK 1", "OK 2"]
    with ScriptedBox(replies) as box, SerialTriggerDisplay(box.port) as d:
        for spec in ("flood", "off", "stripe:1/2", "checker:2:0"):
            d.show(spec)
        assert str(d.current) == "checker:2:0"


def test_an_unexpected_count_is_an_error_and_the_next_one_follows_it():
    with ScriptedBox(["OK 7", "OK 9", "OK 10", "OK 11"]) as box, SerialTriggerDisplay(box.port) as d:
        d.show("flood")
        with pytest.raises(DeviceError, match=r"count 9 after 'PAT OFF' \(box restarted, or a reply"):
            d.show("off")
        assert d.current.kind == "flood"  # not shown
        d.show("off")  # counted on from 9


@pytest.mark.parametrize("reply", ["OK", "OK seven", "OK 1 2", "READY", "ok 1"])
def test_a_reply_that_is_not_ok_n_is_refused(reply):
    with ScriptedBox([reply]) as box, SerialTriggerDisplay(box.port) as d:
        with pytest.raises(DeviceError, match=f"unexpected reply '{reply}' to 'PAT FLOOD'"):
            d.show("flood")


@pytest.mark.parametrize(
    "reply, text",
    [("ERR 4", "ERR 4 busy"), ("ERR 5", "ERR 5 hardware fault"),
     ("ERR 2 stripe 9 of 3", "ERR 2 stripe 9 of 3"), ("ERR x", "ERR 0 "), ("ERR", "ERR 0 "),
     ("ERR 77", "ERR 77 ")],
)
def test_err_replies_name_the_code_and_text(reply, text):
    with ScriptedBox([reply]) as box, SerialTriggerDisplay(box.port) as d:
        with pytest.raises(DeviceError) as info:
            d.trigger(0.01)
        assert str(info.value).endswith(f"'TRIG 10000' refused: {text}")
    assert set(ERROR_CODES) == {1, 2, 3, 4, 5}


@pytest.mark.parametrize("exposure_s, us", [(0.0125, 12500), (1e-6, 1), (33.3e-6, 33), (99.0, 99_000_000)])
def test_trigger_sends_microseconds(exposure_s, us):
    with SimTriggerBox() as box, SerialTriggerDisplay(box.port) as d:
        before = time.monotonic()
        assert before <= d.trigger(exposure_s) <= time.monotonic()
        assert box.triggers == [us]


@pytest.mark.parametrize("exposure_s", [0.0, -0.01, 100.0, float("nan"), float("inf")])
def test_a_bad_exposure_is_refused_before_the_box(exposure_s):
    with SimTriggerBox() as box, SerialTriggerDisplay(box.port) as d:
        with pytest.raises(DriverValueError, match=r"exposure_s=.* must be in \[0.5 µs, 100 s\)"):
            d.trigger(exposure_s)
        assert bytes(box.received) == b"ID?\n"


def test_an_exposure_that_rounds_to_zero_microseconds_is_a_value_error():
    with SimTriggerBox() as box, SerialTriggerDisplay(box.port) as d:
        with pytest.raises(DriverValueError):
            d.trigger(1e-7)


def test_stale_input_is_dropped_before_a_request():
    with ScriptedBox(["OK 0", "OK 1"]) as box, SerialTriggerDisplay(box.port) as d:
        box.reply(b"OK 41\n")  # a late reply to something earlier
        deadline = time.monotonic() + 2.0
        while d._serial.in_waiting < 6 and time.monotonic() < deadline:  # the pty delivers it to the host
            time.sleep(0.001)
        d.show("flood")  # takes OK 0, not the stale OK 41
        d.show("off")  # and counts on from 0
        assert box.lines == ["ID?", "PAT FLOOD", "PAT OFF"]


def test_a_box_that_goes_silent_is_a_timeout_naming_the_request_and_close_still_works():
    with ScriptedBox(["OK 0", None, None]) as box:
        d = SerialTriggerDisplay(box.port, timeout_s=0.2)
        d.show("stripe:1/3")
        t0 = time.monotonic()
        with pytest.raises(DriverTimeout, match=r"no reply to 'PAT STRIPE 2 3' within 0.2 s"):
            d.show("stripe:2/3")
        assert 0.15 < time.monotonic() - t0 < 1.0
        d.close()  # tries to blank (no answer), closes anyway
        assert box.lines[-1] == "PAT OFF"
        with pytest.raises(DriverError, match="closed"):
            d.show("flood")
