"""ZmqCanBus: one virtual CAN segment shared by processes over a ZeroMQ hub (loopback ipc only)."""

from __future__ import annotations

import multiprocessing as mp
import time

import can
import pytest
from polarstripe.nodes.drivers.zmqcan import ZmqCanBus, ZmqCanHub, hub_endpoints


def _echo(channel: str, ready, done) -> None:
    """Another process: answer each 0x601 frame with 0x581 and the bytes reversed."""
    with can.Bus(interface="zmq", channel=channel) as bus:
        ready.set()
        while not done.is_set():
            msg = bus.recv(0.05)
            if msg is not None and msg.arbitration_id == 0x601:
                bus.send(can.Message(arbitration_id=0x581, data=bytes(msg.data)[::-1], is_extended_id=False))


def test_the_python_can_interface_name_reaches_this_backend(can_channel):
    with can.Bus(interface="zmq", channel=can_channel) as bus:
        assert isinstance(bus, ZmqCanBus)


def test_frames_cross_processes_both_ways(can_channel):
    ctx = mp.get_context("spawn")
    ready, done = ctx.Event(), ctx.Event()
    with ZmqCanBus(can_channel) as bus:
        child = ctx.Process(target=_echo, args=(can_channel, ready, done))
        child.start()
        try:
            assert ready.wait(10)
            time.sleep(0.05)
            for payload in ([1, 2, 3], [0xFF] * 8, []):
                bus.send(can.Message(arbitration_id=0x601, data=payload, is_extended_id=False))
                reply = bus.recv(2.0)
                assert reply is not None and reply.arbitration_id == 0x581
                assert bytes(reply.data) == bytes(payload[::-1])
        finally:
            done.set()
            child.join(5)
    assert child.exitcode == 0


def test_every_node_sees_the_others_but_not_itself(can_channel):
    with ZmqCanBus(can_channel) as a, ZmqCanBus(can_channel) as b, ZmqCanBus(can_channel) as c:
        a.send(can.Message(arbitration_id=0x123, data=[7], is_extended_id=False))
        for other in (b, c):
            msg = other.recv(1.0)
            assert msg.arbitration_id == 0x123 and bytes(msg.data) == b"\x07"
        assert a.recv(0.1) is None


def test_receive_own_messages_and_flags_round_trip(can_channel):
    with ZmqCanBus(can_channel, receive_own_messages=True) as a:
        sent = can.Message(
            arbitration_id=0x1ABCDE, data=b"\x01\x02", is_extended_id=True, is_remote_frame=False
        )
        a.send(sent)
        got = a.recv(1.0)
        assert got.arbitration_id == 0x1ABCDE and got.is_extended_id and bytes(got.data) == b"\x01\x02"
        a.send(can.Message(arbitration_id=0x7FF, is_remote_frame=True, dlc=0, is_extended_id=False))
        assert a.recv(1.0).is_remote_frame


def test_filters_apply(can_channel):
    only_581 = [{"can_id": 0x581, "can_mask": 0x7FF, "extended": False}]
    with ZmqCanBus(can_channel) as a, ZmqCanBus(can_channel, can_filters=only_581) as b:
        a.send(can.Message(arbitration_id=0x182, data=[1], is_extended_id=False))
        a.send(can.Message(arbitration_id=0x581, data=[2], is_extended_id=False))
        msg = b.recv(1.0)
        assert msg.arbitration_id == 0x581
        assert b.recv(0.1) is None


def test_the_first_participant_hosts_the_hub_and_a_second_does_not(can_channel):
    with ZmqCanBus(can_channel) as first, ZmqCanBus(can_channel) as second:
        assert first._hub is not None and second._hub is None


def test_no_hub_is_a_clear_error(can_channel):
    start = time.monotonic()
    with pytest.raises(can.CanInitializationError, match=r"no hub carried frames within 0.3 s"):
        ZmqCanBus(can_channel, hub=False, join_timeout=0.3)
    assert time.monotonic() - start < 1.5


def test_a_bus_off_error_frame_makes_sends_fail_until_restarted(can_channel):
    with ZmqCanHub(can_channel), ZmqCanBus(can_channel, hub=False) as host, ZmqCanBus(can_channel) as drive:
        drive.send(
            can.Message(arbitration_id=0x040, is_error_frame=True, data=bytes(8), is_extended_id=False)
        )
        err = host.recv(1.0)
        assert err.is_error_frame and err.arbitration_id == 0x040
        assert host.state is can.BusState.ERROR
        with pytest.raises(can.CanOperationError, match="bus-off"):
            host.send(can.Message(arbitration_id=0x601, data=[1], is_extended_id=False))
        drive.send(
            can.Message(arbitration_id=0x100, is_error_frame=True, data=bytes(8), is_extended_id=False)
        )
        host.recv(1.0)
        assert host.state is can.BusState.ACTIVE
        host.send(can.Message(arbitration_id=0x601, data=[1], is_extended_id=False))
        assert drive.recv(1.0).arbitration_id == 0x601


def test_shutdown_is_idempotent_and_final(can_channel):
    bus = ZmqCanBus(can_channel)
    bus.shutdown()
    bus.shutdown()
    with pytest.raises(can.CanOperationError, match="shut down"):
        bus.send(can.Message(arbitration_id=1, data=[], is_extended_id=False))


@pytest.mark.parametrize(
    ("channel", "expected"),
    [
        ("ipc:///tmp/x/bus", ("ipc:///tmp/x/bus.in", "ipc:///tmp/x/bus.out")),
        ("tcp://127.0.0.1:29536", ("tcp://127.0.0.1:29536", "tcp://127.0.0.1:29537")),
    ],
)
def test_hub_endpoints(channel, expected):
    assert hub_endpoints(channel) == expected


@pytest.mark.parametrize("bad", ["udp://239.0.0.1:5", "tcp://127.0.0.1", "a/b"])
def test_bad_channels_are_refused(bad):
    with pytest.raises(ValueError, match="CAN channel"):
        hub_endpoints(bad)
