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
            assert ready.wait(60)  # a spawned child imports python-can and numpy: seconds when loaded
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


def test_a_plain_name_under_a_long_runtime_dir_still_fits_a_socket_path(monkeypatch, tmp_path):
    monkeypatch.setenv("XDG_RUNTIME_DIR", "/tmp/short")
    assert hub_endpoints("rig")[0] == "ipc:///tmp/short/polarstripe-can-rig.in"
    monkeypatch.setenv("XDG_RUNTIME_DIR", "/tmp/" + "d" * 120)
    front, back = hub_endpoints("rig")
    assert len(back) - len("ipc://") <= 107 and front.startswith("ipc:///tmp/polarstripe-can-")
    assert hub_endpoints("rig") == (front, back) and hub_endpoints("other") != (front, back)
    hub = ZmqCanHub("rig").start()  # binds: the kernel takes the path
    hub.stop()


@pytest.mark.parametrize("bad", ["udp://239.0.0.1:5", "tcp://127.0.0.1", "a/b"])
def test_bad_channels_are_refused(bad):
    with pytest.raises(ValueError, match="CAN channel"):
        hub_endpoints(bad)


class _Interrupted(Exception):
    """Stands for NodeStopping or KeyboardInterrupt raised by a stop signal."""


@pytest.mark.parametrize("where", ["claimed", "started"])
def test_a_hub_start_cut_short_leaves_no_file_and_frees_the_channel(tmp_path, monkeypatch, where):
    """A stop signal while the hub starts (the simulator's setup, Ctrl-C seconds into a launch) raises out of
    ``start``: its socket and lock files are gone and the next hub can claim the channel."""
    import polarstripe.nodes.drivers.zmqcan as zmqcan

    channel = f"ipc://{tmp_path}/seg"
    hub = ZmqCanHub(channel)
    if where == "claimed":  # the lock file made, the forwarding thread not yet
        def interrupted(*args, **kwargs):
            raise _Interrupted

        monkeypatch.setattr(zmqcan.threading, "Thread", interrupted)
    else:  # the thread has bound its sockets: the signal lands in the wait for it
        ready = hub._ready

        class FirstWaitInterrupted:
            calls = 0

            def wait(self, timeout=None):
                self.calls += 1
                ready.wait(timeout)
                if self.calls == 1:
                    raise _Interrupted
                return True

            def set(self):
                ready.set()

        monkeypatch.setattr(hub, "_ready", FirstWaitInterrupted())
    with pytest.raises(_Interrupted):
        hub.start()
    monkeypatch.undo()
    assert sorted(p.name for p in tmp_path.iterdir()) == []
    with ZmqCanHub(channel):  # the channel is free again
        assert {p.name for p in tmp_path.iterdir()} >= {"seg.in", "seg.out", "seg.lock"}


def test_a_simulated_drive_cut_short_while_starting_leaves_its_bus_and_hub(tmp_path, monkeypatch):
    """The simulator's drive hosts the segment's hub through its bus: a stop signal while it joins the CANopen
    network (the simulator's setup) leaves no hub files behind, so the launch ends with no socket left."""
    import canopen
    from polarstripe.nodes.drivers.simdrive import SimCia402Drive

    def interrupted(self, *args, **kwargs):
        raise _Interrupted

    monkeypatch.setattr(canopen.Network, "connect", interrupted)
    channel = f"ipc://{tmp_path}/seg"
    with pytest.raises(_Interrupted):
        SimCia402Drive(channel, 5).start()
    assert sorted(p.name for p in tmp_path.iterdir()) == []
