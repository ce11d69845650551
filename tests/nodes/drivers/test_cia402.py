"""Cia402Stage against the simulated CiA 402 drive running in another process over ZmqCanBus.

Faults (EMCY, heartbeat loss, bus-off, a failed send, the drive's own limit) must become a fault text and no
angle, and the drive's fault-reset sequence must bring the stage back.
"""

from __future__ import annotations

import ctypes
import struct
import time

import can
import canopen
import pytest
from polarstripe.nodes.drivers import cia402_states as cia
from polarstripe.nodes.drivers.cia402 import Cia402Stage
from polarstripe.nodes.drivers.errors import DriverError, StageFault
from polarstripe.nodes.drivers.sim402_axis import Axis402
from polarstripe.nodes.drivers.simdrive import SimCia402Drive
from polarstripe.nodes.drivers.zmqcan import ZmqCanBus


def _wait_fault(stage, text="", timeout=1.5):
    """The stage's fault text once it contains ``text`` (or whatever it is after ``timeout``)."""
    deadline = time.monotonic() + timeout
    while text not in (stage.fault or "") and time.monotonic() < deadline:
        time.sleep(0.005)
    return stage.fault or ""


@pytest.fixture
def stage(drive_process):
    drive = drive_process
    with Cia402Stage(
        drive.channel, drive.node_id, counts_per_deg=1000, speed_deg_s=720.0, min_deg=-90, max_deg=90
    ) as stage:
        yield stage


def test_statusword_patterns_are_the_standards():
    # CiA 402 table "state coding": xxxx xxxx x0xx 0000 not ready, x1xx 0000 switch on disabled,
    # x01x 0001 ready, x01x 0011 switched on, x01x 0111 operation enabled, x00x 0111 quick stop,
    # x0xx 1111 fault reaction, x0xx 1000 fault
    assert cia.decode_statusword(0x0250) is cia.State.SWITCH_ON_DISABLED
    assert cia.decode_statusword(0x0231) is cia.State.READY_TO_SWITCH_ON
    assert cia.decode_statusword(0x0233) is cia.State.SWITCHED_ON
    assert cia.decode_statusword(0x1637) is cia.State.OPERATION_ENABLED
    assert cia.decode_statusword(0x0217) is cia.State.QUICK_STOP_ACTIVE
    assert cia.decode_statusword(0x021F) is cia.State.FAULT_REACTION_ACTIVE
    assert cia.decode_statusword(0x0218) is cia.State.FAULT
    assert cia.decode_statusword(0x0000) is cia.State.NOT_READY_TO_SWITCH_ON
    assert cia.TRANSITIONS[15][2] == 0x80 and cia.TRANSITIONS[2][2] == 0x06
    assert cia.TRANSITIONS[3][2] == 0x07 and cia.TRANSITIONS[4][2] == 0x0F


_WALK = {  # controlwords that bring a freshly powered axis into a state
    cia.State.SWITCH_ON_DISABLED: [],
    cia.State.READY_TO_SWITCH_ON: [0x06],
    cia.State.SWITCHED_ON: [0x06, 0x07],
    cia.State.OPERATION_ENABLED: [0x06, 0x07, 0x0F],
    cia.State.QUICK_STOP_ACTIVE: [0x06, 0x07, 0x0F, 0x02],
}


def _axis_in(state):
    axis = Axis402(lambda index, subindex: 0)
    if state is cia.State.FAULT:
        axis.fault()
    for cw in _WALK.get(state, []):
        axis.controlword(cw)
    assert cia.decode_statusword(axis.statusword()) is state
    return axis


COMMANDED = [n for n, (src, _, cw) in cia.TRANSITIONS.items() if src and cw is not None]


@pytest.mark.parametrize("number", COMMANDED)
def test_every_commanded_transition_of_the_table_takes_the_simulated_drive_there(number):
    """The table the driver walks (TRANSITIONS) against the device: the controlword moves the drive from the
    transition's state to its target state, and the statusword says so."""
    source, destination, cw = cia.TRANSITIONS[number]
    axis = _axis_in(source)
    axis.controlword(cw)
    assert cia.decode_statusword(axis.statusword()) is destination


@pytest.mark.parametrize("start", list(_WALK) + [cia.State.FAULT])
def test_the_drivers_path_reaches_operation_enabled_from_every_state(start):
    """PATH_TO_OPERATION_ENABLED as Cia402Stage._enable walks it (disable voltage before a fault reset, so
    bit 7 rises) ends in OPERATION ENABLED within four commands."""
    axis = _axis_in(start)
    for _ in range(4):
        state = cia.decode_statusword(axis.statusword())
        if state is cia.State.OPERATION_ENABLED:
            break
        number = cia.PATH_TO_OPERATION_ENABLED[state]
        if number == 15:
            axis.controlword(cia.CW_DISABLE_VOLTAGE)
        axis.controlword(cia.TRANSITIONS[number][2])
    assert cia.decode_statusword(axis.statusword()) is cia.State.OPERATION_ENABLED


def test_simulated_drive_walks_the_state_machine_for_raw_controlwords():
    """The simulator on python-can's in-process virtual bus, driven by plain SDO writes of 0x6040."""
    with SimCia402Drive("ps-sim-sm", 7, interface="virtual") as drive:
        net = canopen.Network()
        net.connect(interface="virtual", channel="ps-sim-sm")
        try:
            node = canopen.RemoteNode(7, drive.node.object_dictionary)
            net.add_node(node)
            assert node.sdo[0x1000].raw == 0x00020192

            def statusword_after(cw):
                node.sdo[0x6040].raw = cw
                return node.sdo[0x6041].raw

            assert statusword_after(0x06) & 0x6F == 0x21  # transition 2
            assert statusword_after(0x07) & 0x6F == 0x23  # 3
            assert statusword_after(0x0F) & 0x6F == 0x27  # 4
            assert statusword_after(0x02) & 0x6F == 0x07  # 11 quick stop
            assert statusword_after(0x0F) & 0x6F == 0x27  # 16
            assert statusword_after(0x00) & 0x4F == 0x40  # 9 disable voltage
            drive.inject_emcy(0x5530)
            assert node.sdo[0x6041].raw & 0x4F == 0x08
            assert node.sdo[0x603F].raw == 0x5530
            assert statusword_after(0x06) & 0x4F == 0x08  # shutdown does not leave FAULT
            assert statusword_after(0x80) & 0x4F == 0x40  # 15 on the rising edge of bit 7
        finally:
            net.disconnect()


def test_connect_configures_the_drive(stage):
    assert stage.drive_state is cia.State.OPERATION_ENABLED
    sdo = stage.node.sdo
    assert sdo[0x6060].raw == 1  # profile position
    assert sdo[0x607D][1].raw == -90_000 and sdo[0x607D][2].raw == 90_000
    assert sdo[0x6081].raw == 720_000
    assert sdo[0x1017].raw == 100


def test_position_is_in_counts_per_degree(stage):
    stage.move_to(12.345)
    stage.wait_settled(2.0)
    assert stage.node.sdo[0x6064].raw == 12_345


def test_emcy_is_a_fault_naming_the_code(stage, drive_process):
    drive_process.cmd("emcy 0x8611")
    assert "EMCY 0x8611" in _wait_fault(stage, "EMCY 0x8611")
    assert stage.angle is None and not stage.settled
    stage.reset_fault()
    assert stage.fault is None and stage.drive_state is cia.State.OPERATION_ENABLED


def test_fault_reset_sends_bit7_edge_then_shutdown_switch_on_enable(stage, drive_process):
    drive_process.cmd("emcy 0x7305")
    _wait_fault(stage)
    time.sleep(0.05)
    with ZmqCanBus(drive_process.channel, hub=False) as spy:
        spy.set_filters([{"can_id": 0x205, "can_mask": 0x7FF, "extended": False}])  # RPDO1 of node 5
        stage.reset_fault()
        words = []
        while (msg := spy.recv(0.05)) is not None:
            words.append(struct.unpack_from("<H", msg.data)[0])
    first_edge = next(i for i, w in enumerate(words) if w & 0x80)
    assert all(not w & 0x80 for w in words[:first_edge]) and first_edge > 0  # bit 7 rises from 0
    after = [w & 0x8F for w in words[first_edge + 1 :]]
    assert after[:3] == [0x06, 0x07, 0x0F]


def test_heartbeat_loss_is_a_fault_and_recovers(stage, drive_process):
    stage.move_to(5.0)
    stage.wait_settled(2.0)
    drive_process.cmd("heartbeat_stop")
    start = time.monotonic()
    assert "heartbeat of node 5 lost" in _wait_fault(stage, "heartbeat of node 5 lost")
    assert time.monotonic() - start < stage.heartbeat_timeout_s + 0.5  # a loaded machine wakes us late
    assert stage.angle is None
    with pytest.raises(StageFault, match="heartbeat"):
        stage.reset_fault()  # the cause persists: the fault stays
    assert stage.fault is not None
    drive_process.cmd("heartbeat_resume")
    time.sleep(0.1)
    stage.reset_fault()
    assert stage.fault is None and stage.angle == pytest.approx(5.0)


def _hold_the_gil(seconds: float) -> None:
    """Stall this whole process, as a long garbage collection does: a C sleep that keeps the GIL (ctypes'
    PyDLL does not release it), so no other thread runs. The hub's forwarding (C, GIL released) goes on."""
    ctypes.PyDLL(None).usleep(int(seconds * 1e6))


def test_a_stall_of_this_process_is_not_a_lost_heartbeat(stage, drive_process):
    """The drive's heartbeats and TPDOs wait in the socket while this process cannot run; the consumer
    timeouts count only the time it listened (nodes/drivers/cia402_watch.py)."""
    stage.move_to(5.0)
    stage.wait_settled(2.0)
    _hold_the_gil(3 * stage.heartbeat_timeout_s)
    time.sleep(0.3)  # the notifier reads what waited
    assert stage.fault is None and stage.angle == pytest.approx(5.0)


def test_a_heartbeat_that_stops_during_a_stall_is_still_lost(stage, drive_process):
    stage.move_to(5.0)
    stage.wait_settled(2.0)
    drive_process.cmd("heartbeat_stop")
    _hold_the_gil(3 * stage.heartbeat_timeout_s)
    start = time.monotonic()
    assert "heartbeat of node 5 lost" in _wait_fault(stage, "heartbeat of node 5 lost")
    assert time.monotonic() - start < stage.heartbeat_timeout_s + 0.3
    drive_process.cmd("heartbeat_resume")
    time.sleep(0.1)
    stage.reset_fault()


def test_bus_off_is_a_fault_sends_fail_and_reset_works_after_restart(stage, drive_process):
    drive_process.cmd("bus_off 0.5")
    assert "bus-off" in _wait_fault(stage, "bus-off")
    with pytest.raises(StageFault):
        stage.move_to(10.0)
    with pytest.raises(StageFault):
        stage.reset_fault()  # still off
    time.sleep(0.6)
    stage.reset_fault()
    stage.move_to(10.0)
    assert stage.wait_settled(2.0) == pytest.approx(10.0)


class _FlakyBus(ZmqCanBus):
    """A bus whose sends can be made to fail, as an unplugged adapter's do."""

    fail = False

    def send(self, msg, timeout=None):
        if self.fail:
            raise can.CanOperationError("No buffer space available", error_code=105)
        super().send(msg, timeout)


def test_a_failed_send_is_a_fault_not_an_angle(drive_process):
    bus = _FlakyBus(drive_process.channel, hub=False)
    with Cia402Stage(drive_process.channel, bus=bus, counts_per_deg=1000, min_deg=-90, max_deg=90) as stage:
        bus.fail = True
        with pytest.raises(StageFault, match="send failed"):
            stage.move_to(20.0)
        assert "send failed" in stage.fault and "No buffer space" in stage.fault
        assert stage.angle is None
        bus.fail = False
        stage.reset_fault()
        stage.move_to(20.0)
        assert stage.wait_settled(2.0) == pytest.approx(20.0)
    bus.shutdown()


def test_the_drives_own_position_limit_is_a_fault(stage, drive_process):
    drive_process.cmd("position_limit -30000 30000")
    stage.move_to(60.0)  # inside this stage's limits, beyond the drive's
    assert "internal limit active" in _wait_fault(stage, "internal limit active")
    assert stage.angle is None and not stage.settled
    stage.reset_fault()  # holds where the drive stopped, never beyond its limit
    assert stage.wait_settled(1.0) <= 30.0 + 1e-9
    assert stage.fault is None


def test_an_absent_drive_is_a_clear_error(drive_process):
    start = time.monotonic()
    with pytest.raises(DriverError, match=r"CiA 402 node 9 .*SDO"):
        Cia402Stage(drive_process.channel, 9, sdo_timeout_s=0.2)
    assert time.monotonic() - start < 2.0


def test_a_drive_found_in_fault_is_reset_on_connect_and_says_so(drive_process):
    drive_process.cmd("emcy 0x2310")
    with Cia402Stage(drive_process.channel, counts_per_deg=1000, min_deg=-90, max_deg=90) as stage:
        assert stage.fault is None and stage.drive_state is cia.State.OPERATION_ENABLED
        assert any("FAULT" in text for text in stage.startup_faults)


def test_an_unreachable_bus_is_a_driver_error(can_channel):
    with pytest.raises(DriverError, match=r"cannot open CAN interface 'zmq'.*no hub"):
        Cia402Stage(can_channel, hub=False, join_timeout=0.2)


def test_the_drive_process_can_host_the_hub_itself(can_channel, spawn_drive):
    spawn_drive(can_channel, node_id=6)  # nobody hosts the hub yet: the drive does (hub="auto")
    with Cia402Stage(can_channel, 6, counts_per_deg=500, min_deg=0, max_deg=180) as stage:
        assert stage.network.bus._hub is None  # this side only connected
        stage.move_to(90.0)
        assert stage.wait_settled(2.0) == pytest.approx(90.0)
        assert stage.node.sdo[0x6064].raw == 45_000


def test_embedded_drive_and_stage_in_one_process_on_the_virtual_bus():
    with SimCia402Drive("ps-embedded", 3, interface="virtual"):
        with Cia402Stage("ps-embedded", 3, interface="virtual", counts_per_deg=100) as stage:
            stage.move_to(-12.5)
            assert stage.wait_settled(2.0) == pytest.approx(-12.5)


def test_close_after_the_bus_failed_logs_and_never_raises(drive_process, caplog):
    stage = Cia402Stage(
        drive_process.channel, drive_process.node_id, counts_per_deg=1000, min_deg=-90, max_deg=90
    )
    stage.network.bus.shutdown()  # the interface goes away under the stage (a pulled adapter)
    assert _wait_fault(stage, "CAN receive failed")  # the notifier thread died with an exception
    with caplog.at_level("WARNING", logger="polarstripe.nodes.drivers.cia402"):
        stage.close()
        stage.close()  # idempotent
    closing = [r for r in caplog.records if "closing" in r.getMessage()]
    assert len(closing) == 1 and "CiA 402 node 5" in closing[0].getMessage()
