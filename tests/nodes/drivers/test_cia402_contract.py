"""The polarizer drive against CiA 301 and CiA 402, driven by canopen's own client, not by our driver.

The client is ``canopen.profiles.p402.BaseNode402`` plus raw frames where the standard is about frames (NMT,
heartbeat, RPDO, TPDO timing, EMCY). One suite for the role, like python-can's back-to-back tests: it runs on
the simulated drive (another process on a zmq CAN segment) always, and on a real drive with ``--hardware
can0`` (socketcan; ``--hardware-node-id``, ``--hardware-eds``). Tests that inject a fault are skipped on
hardware. On a real drive the suite enables the power stage and moves the axis by at most ``2 * STEP`` counts
from where it stands, at ``SPEED`` counts/s; every test starts with an NMT reset node, and the module ends
with one.

The numbers in the test names are the points of the conformance list in ``docs/hardware.md``.
"""

from __future__ import annotations

import statistics
import struct
import time
from dataclasses import dataclass, field

import can
import canopen
import pytest
from canopen.profiles.p402 import BaseNode402, OperationMode
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError
from polarstripe.nodes.drivers import cia402_states as cia
from polarstripe.nodes.drivers.cia402_states import EDS_PATH, State

STEP = 20_000  # counts
SPEED = 100_000  # counts/s: a STEP takes 0.2 s
TOLERANCE = 50  # counts: a real drive's position window


@dataclass
class Target:
    name: str
    channel: str
    interface: str
    node_id: int
    eds: str
    inject: object = None  # the simulated drive's stdin command, None on hardware
    bus_kwargs: dict = field(default_factory=dict)


@pytest.fixture(scope="module")
def target(can_device, request):
    if can_device == "sim":
        drive = request.getfixturevalue("drive_process")
        yield Target("sim", drive.channel, "zmq", drive.node_id, EDS_PATH, drive.cmd, {"hub": False})
        return
    config = request.config
    hw = Target(
        can_device,
        can_device,
        "socketcan",
        config.getoption("hardware_node_id"),
        config.getoption("hardware_eds") or EDS_PATH,
    )
    yield hw
    with Peer(hw) as peer:
        peer.reset_node()  # leave the drive on its power-on values


class Peer(can.Listener):
    """canopen's BaseNode402 on a network of its own, and every frame it saw: (timestamp, COB-ID, data)."""

    def __init__(self, target: Target):
        self.target, self.id = target, target.node_id
        self.frames: list[tuple[float, int, bytes]] = []
        self.network = canopen.Network()
        self.network.NOTIFIER_CYCLE = 0.05
        self.network.connect(interface=target.interface, channel=target.channel, **target.bus_kwargs)
        self.network.notifier.add_listener(self)
        self.node = BaseNode402(target.node_id, target.eds)
        self.network.add_node(self.node)
        self.node.sdo.RESPONSE_TIMEOUT = 0.3

    def on_message_received(self, msg: can.Message) -> None:
        self.frames.append((msg.timestamp, msg.arbitration_id, bytes(msg.data)))

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.network.disconnect()

    # -- raw services -------------------------------------------------------------------------------------
    def seen(self, cob_id: int, since: float) -> list[tuple[float, bytes]]:
        return [(t, d) for t, i, d in list(self.frames) if i == cob_id and t >= since]

    def nmt(self, command: int) -> float:
        mark = time.time()
        self.network.send_message(0, bytes([command, self.id]))
        return mark

    def wait_frame(self, cob_id: int, since: float, timeout: float = 2.0, data: bytes | None = None):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            for t, d in self.seen(cob_id, since):
                if data is None or d[: len(data)] == data:
                    return t, d
            time.sleep(0.002)
        raise AssertionError(f"no frame 0x{cob_id:03X} {data!r} within {timeout} s")

    def reset_node(self) -> float:
        """NMT reset node; returns when the boot-up was seen (the time of the command)."""
        mark = self.nmt(0x81)
        self.wait_frame(0x700 + self.id, mark, data=b"\x00")
        return mark

    def rpdo(self, controlword: int, target: int = 0) -> None:
        self.network.send_message(0x200 + self.id, struct.pack("<Hi", controlword, target))

    def read(self, index: int, subindex: int = 0) -> int:
        return self.node.sdo[index].raw if subindex == 0 else self.node.sdo[index][subindex].raw

    def write(self, index: int, subindex: int, value: int) -> None:
        if subindex == 0:
            self.node.sdo[index].raw = value
        else:
            self.node.sdo[index][subindex].raw = value

    def state(self) -> State:
        return cia.decode_statusword(self.read(0x6041))

    # -- profile position through BaseNode402 -------------------------------------------------------------
    def enable_pp(self) -> int:
        """Reset node, 0x6081 = SPEED, NMT start, profile position, OPERATION ENABLED; the position."""
        self.reset_node()
        self.node.setup_402_state_machine()
        self.write(0x6081, 0, SPEED)
        mark = self.nmt(0x01)
        self.wait_frame(0x180 + self.id, mark)
        self.node.op_mode = "PROFILED POSITION"
        self.node.state = "OPERATION ENABLED"
        return self.read(0x6064)

    def setpoint(self, value: int, bits: int = cia.CW_CHANGE_SET_IMMEDIATELY) -> int:
        """Target ``value`` with the new set-point handshake; the statusword after bit 4 fell."""
        self.node.rpdo_pointers[0x607A].raw = value
        self.node.controlword = cia.CW_ENABLE_OPERATION | cia.CW_NEW_SETPOINT | bits
        deadline = time.monotonic() + 1.0
        while not self.read(0x6041) & cia.SW_SETPOINT_ACK:
            assert time.monotonic() < deadline, "set-point not acknowledged"
        self.node.controlword = cia.CW_ENABLE_OPERATION | (bits & ~cia.CW_NEW_SETPOINT)
        return self.read(0x6041)

    def wait_reached(self, timeout: float = 3.0) -> int:
        deadline = time.monotonic() + timeout
        while not (sw := self.read(0x6041)) & cia.SW_TARGET_REACHED or sw & cia.SW_SETPOINT_ACK:
            assert time.monotonic() < deadline, f"target not reached (statusword 0x{sw:04X})"
            time.sleep(0.005)
        return self.read(0x6064)

    def positions(self, since: float) -> list[int]:
        return [struct.unpack_from("<i", d, 2)[0] for _, d in self.seen(0x180 + self.id, since)]


@pytest.fixture
def peer(target):
    with Peer(target) as p:
        yield p


def needs_injection(target: Target) -> None:
    if target.inject is None:
        pytest.skip(f"{target.name}: no fault injection on real hardware")


# -- 1: NMT reset node / reset communication (CiA 301 7.2.8.3.2) ------------------------------------------
def test_1_reset_node_boots_once_into_pre_operational_on_power_on_values(peer):
    peer.reset_node()
    heartbeat_ms, speed = peer.read(0x1017), peer.read(0x6081)
    peer.write(0x1017, 0, 80 if heartbeat_ms != 80 else 90)
    peer.write(0x6081, 0, speed // 2 + 1)
    peer.node.setup_402_state_machine()
    peer.nmt(0x01)
    peer.node.op_mode = "PROFILED POSITION"
    peer.node.state = "OPERATION ENABLED"
    assert peer.state() is State.OPERATION_ENABLED

    mark = peer.reset_node()
    time.sleep(max(0.35, 3.5 * heartbeat_ms / 1000))
    states = [d[0] for _, d in peer.seen(0x700 + peer.id, mark)]
    assert states[0] == 0x00 and states.count(0x00) == 1, states  # one boot-up
    if heartbeat_ms:
        assert len(states) >= 3 and set(states[1:]) == {0x7F}, states  # then PRE-OPERATIONAL
    assert peer.read(0x1017) == heartbeat_ms and peer.read(0x6081) == speed  # power-on values
    assert peer.state() is State.SWITCH_ON_DISABLED
    boot_at = peer.wait_frame(0x700 + peer.id, mark, data=b"\x00")[0]
    assert peer.seen(0x180 + peer.id, boot_at) == []  # no PDO in PRE-OPERATIONAL


def test_1_reset_communication_resets_only_the_communication_objects(peer):
    peer.reset_node()
    heartbeat_ms, speed = peer.read(0x1017), peer.read(0x6081)
    peer.write(0x1017, 0, 80 if heartbeat_ms != 80 else 90)
    peer.write(0x6081, 0, speed // 2 + 1)
    mark = peer.nmt(0x82)
    peer.wait_frame(0x700 + peer.id, mark, data=b"\x00")
    time.sleep(0.05)
    assert [d[0] for _, d in peer.seen(0x700 + peer.id, mark)].count(0x00) == 1
    assert peer.read(0x1017) == heartbeat_ms  # 0x1000-0x1FFF: power-on values
    assert peer.read(0x6081) == speed // 2 + 1  # the application keeps its values


# -- 2: services per NMT state (CiA 301 7.3.2.2, table of services) ---------------------------------------
def test_2_pre_operational_drive_ignores_rpdos_and_sends_no_tpdos(peer):
    peer.reset_node()
    for cw in (cia.CW_SHUTDOWN, cia.CW_SWITCH_ON, cia.CW_ENABLE_OPERATION):
        peer.write(0x6040, 0, cw)  # SDO works in PRE-OPERATIONAL
    assert peer.state() is State.OPERATION_ENABLED
    mark = time.time()
    peer.rpdo(cia.CW_DISABLE_VOLTAGE)
    time.sleep(0.1)
    assert peer.state() is State.OPERATION_ENABLED
    assert peer.seen(0x180 + peer.id, mark) == []
    peer.nmt(0x01)
    time.sleep(0.02)
    peer.rpdo(cia.CW_DISABLE_VOLTAGE)  # in OPERATIONAL the same RPDO disables the drive (transition 9)
    time.sleep(0.05)
    assert peer.state() is State.SWITCH_ON_DISABLED


def test_2_stopped_drive_serves_no_sdo_and_keeps_its_heartbeat(peer):
    peer.reset_node()
    peer.write(0x1017, 0, 20)
    mark = peer.nmt(0x02)
    time.sleep(0.05)
    with pytest.raises(SdoCommunicationError):
        peer.read(0x1000)
    time.sleep(0.1)
    states = [d[0] for _, d in peer.seen(0x700 + peer.id, mark + 0.03)]
    assert states and set(states) == {0x04}, states
    peer.nmt(0x80)
    time.sleep(0.02)
    assert peer.read(0x1000) & 0xFFFF == 402


def test_2_no_heartbeat_reports_a_state_the_drive_has_left(peer):
    """Between the first TPDO after an NMT start (the drive is OPERATIONAL) and the next command, every
    heartbeat must say OPERATIONAL: one composed before the start and sent after it is a false state
    change."""
    peer.reset_node()
    peer.write(0x1017, 0, 1)
    hb, tpdo, stale = 0x700 + peer.id, 0x180 + peer.id, []
    for _ in range(40):
        start = peer.nmt(0x01)
        first_tpdo = peer.wait_frame(tpdo, start)[0]
        time.sleep(0.004)
        stale += [d[0] for t, d in peer.seen(hb, first_tpdo) if d[0] != 0x05]
        peer.wait_frame(hb, peer.nmt(0x80), data=b"\x7f")
    assert stale == []


# -- 3: profile position controlword bits (CiA 402-2, profile position mode) ---------------------------------
def test_3_bit6_relative_setpoint_counts_from_the_preceding_target(peer):
    p0 = peer.enable_pp()
    peer.setpoint(p0 + STEP)
    assert abs(peer.wait_reached() - (p0 + STEP)) <= TOLERANCE
    peer.setpoint(STEP // 2, cia.CW_CHANGE_SET_IMMEDIATELY | cia.CW_RELATIVE)
    assert abs(peer.wait_reached() - (p0 + STEP + STEP // 2)) <= TOLERANCE


def test_3_bit8_halt_stops_the_axis_with_target_reached_and_release_resumes(peer):
    p0 = peer.enable_pp()
    peer.setpoint(p0 + 2 * STEP)
    time.sleep(0.1)
    peer.node.controlword = cia.CW_ENABLE_OPERATION | cia.CW_HALT
    time.sleep(0.1)
    here = peer.read(0x6064)
    time.sleep(0.05)
    assert peer.read(0x6064) == here and p0 < here < p0 + 2 * STEP  # stands still short of the target
    assert peer.read(0x6041) & cia.SW_TARGET_REACHED  # halt: bit 10 = velocity 0
    peer.node.controlword = cia.CW_ENABLE_OPERATION
    assert abs(peer.wait_reached() - (p0 + 2 * STEP)) <= TOLERANCE


@pytest.mark.parametrize("immediately", [False, True])
def test_3_bit5_clear_finishes_the_current_setpoint_first(peer, immediately):
    p0 = peer.enable_pp()
    mark = time.time()
    peer.setpoint(p0 + 2 * STEP)
    time.sleep(0.05)
    bits = cia.CW_CHANGE_SET_IMMEDIATELY if immediately else 0
    sw = peer.setpoint(p0, bits)
    if not immediately:
        assert sw & cia.SW_SETPOINT_ACK  # bit 4 low, the buffered set-point still waits
    assert abs(peer.wait_reached() - p0) <= TOLERANCE
    farthest = max(peer.positions(mark))
    if immediately:
        assert farthest < p0 + 2 * STEP - TOLERANCE  # turned back at once
    else:
        assert abs(farthest - (p0 + 2 * STEP)) <= TOLERANCE  # went all the way first


@pytest.mark.parametrize("moved", [False, True], ids=["after_power_on", "after_a_move"])
@pytest.mark.parametrize("timer_ms", [10, 0], ids=["event_timer", "on_change_only"])
def test_3_a_setpoint_at_the_present_position_is_acknowledged(peer, moved, timer_ms):
    """A set-point equal to the position actual value is a set-point like any other: bit 12 while bit 4 is
    high, seen in a TPDO (the way BaseNode402 reads its statusword), then bit 10 without any motion; also
    with TPDO1 sent only on a change (event timer 0), where a drive that sees "nothing to do" sends none."""
    p0 = peer.enable_pp()
    if moved:
        peer.setpoint(p0 + STEP)
        p0 = peer.wait_reached()
    peer.write(0x1800, 5, timer_ms)
    time.sleep(0.05)
    mark = time.time()
    peer.node.rpdo_pointers[0x607A].raw = p0
    peer.node.controlword = cia.CW_ENABLE_OPERATION | cia.CW_NEW_SETPOINT | cia.CW_CHANGE_SET_IMMEDIATELY
    deadline = time.monotonic() + 1.0
    while not peer.node.statusword & cia.SW_SETPOINT_ACK:  # the newest TPDO1's statusword
        assert time.monotonic() < deadline, f"set-point at {p0} not acknowledged (TPDO statusword " \
                                            f"0x{peer.node.statusword:04X})"
        peer.node.check_statusword(timeout=0.3)
    peer.node.controlword = cia.CW_ENABLE_OPERATION
    assert peer.wait_reached() == p0
    assert set(peer.positions(mark)) == {p0}  # nothing moved


# -- 4: homing on the current position (CiA 402-2 homing methods 35 and 37) --------------------------------
@pytest.mark.parametrize("method", [35, 37])
def test_4_homing_on_the_current_position_does_not_move(peer, method):
    p0 = peer.enable_pp()
    peer.setpoint(p0 + STEP)
    before = peer.wait_reached()
    offset = peer.read(0x607C) if 0x607C in peer.node.object_dictionary else 0
    peer.write(0x6098, 0, method)
    mark, start = time.time(), time.monotonic()
    assert peer.node.homing(timeout=2.0)
    assert time.monotonic() - start < 0.5
    assert peer.read(0x6064) == offset
    assert set(peer.positions(mark)) <= {before, offset}  # no position in between: no motion
    assert peer.read(0x6098) == method


def test_4_homing_method_must_be_one_the_drive_runs(peer, target):
    needs_injection(target)  # which methods a real drive runs is its own
    peer.reset_node()
    with pytest.raises(SdoAbortedError):
        peer.write(0x6098, 0, 1)
    assert peer.read(0x6098) == 0


# -- 5: error register and EMCY (CiA 301 7.2.7) -----------------------------------------------------------
def test_5_error_register_is_cleared_with_the_emcy_error_reset(peer, target):
    needs_injection(target)
    peer.enable_pp()
    mark = time.time()
    target.inject("emcy 0x8611")
    _, emcy = peer.wait_frame(0x80 + peer.id, mark)
    code, register = struct.unpack_from("<HB", emcy)
    assert code == 0x8611 and register & 0x01
    assert peer.read(0x1001) == register
    mark = time.time()
    peer.node.reset_from_fault()
    _, emcy = peer.wait_frame(0x80 + peer.id, mark)
    assert struct.unpack_from("<HB", emcy) == (0x0000, 0x00)
    assert peer.read(0x1001) == 0x00 and peer.read(0x603F) == 0
    assert peer.node.state == "OPERATION ENABLED"


def test_5_no_emcy_in_stopped(peer, target):
    needs_injection(target)
    peer.reset_node()
    mark = peer.nmt(0x02)
    time.sleep(0.05)  # the command and the injection travel different ways
    target.inject("emcy 0x8611")
    time.sleep(0.1)
    assert peer.seen(0x80 + peer.id, mark) == []


# -- 6: modes of operation (CiA 402-2 0x6060, 0x6502) -----------------------------------------------------
def test_6_a_mode_0x6502_does_not_list_is_refused(peer, target):
    peer.reset_node()
    supported = peer.read(0x6502)
    if target.inject is not None:
        assert supported == 0x21  # profile position and homing
    name = next(
        (
            n
            for n in ("PROFILED VELOCITY", "VELOCITY", "PROFILED TORQUE", "INTERPOLATED POSITION")
            if not supported & OperationMode.SUPPORTED[n]
        ),
        None,
    )
    if name is None:
        pytest.skip(f"{target.name}: 0x6502 = 0x{supported:X} lists every mode tried")
    before = peer.read(0x6061)
    with pytest.raises(SdoAbortedError) as refused:
        peer.write(0x6060, 0, OperationMode.NAME2CODE[name])
    if target.inject is not None:
        assert refused.value.code == 0x06090030
    assert peer.read(0x6061) == before
    with pytest.raises(TypeError, match="not suppported"):  # canopen's own check of 0x6502 (its spelling)
        peer.node.op_mode = name


# -- 7: TPDO1 transmission (CiA 301 7.2.2.3: event timer 0x1800:05, event-driven) --------------------------
def _intervals(peer, since: float) -> list[float]:
    times = [t for t, _ in peer.seen(0x180 + peer.id, since)]
    return [b - a for a, b in zip(times, times[1:], strict=False)]


def test_7_tpdo1_follows_its_event_timer_and_changes(peer):
    peer.reset_node()
    peer.nmt(0x01)  # the drive stands in SWITCH ON DISABLED: nothing changes, only the timer sends
    time.sleep(0.05)
    for timer_ms in (peer.read(0x1800, 5), 50):
        peer.write(0x1800, 5, timer_ms)
        mark = time.time() + timer_ms / 1000
        time.sleep(max(0.3, 8 * timer_ms / 1000))
        gaps = _intervals(peer, mark)
        assert len(gaps) >= 4 and statistics.median(gaps) == pytest.approx(timer_ms / 1000, rel=0.25), gaps
    peer.write(0x1800, 5, 0)
    time.sleep(0.06)
    mark = time.time()
    time.sleep(0.2)
    assert peer.seen(0x180 + peer.id, mark) == []  # no timer: nothing while nothing changes
    peer.write(0x6040, 0, cia.CW_SHUTDOWN)
    t, data = peer.wait_frame(0x180 + peer.id, mark, timeout=0.1)
    assert cia.decode_statusword(struct.unpack_from("<H", data)[0]) is State.READY_TO_SWITCH_ON
