import time

import msgpack
import numpy as np
import pytest
import zmq
from polarstripe.msgs import Frame, Log, MessageError, encode
from polarstripe.runtime.bus import BusError, BusTimeout, CurveKeys, PubSocket, Subscriber


def _log(i):
    return Log(level="INFO", node="t", text=str(i))


def _joined(pub, sub, make=_log):
    """Publish until the subscription has reached the publisher (ZeroMQ's slow joiner), then drain."""
    for _ in range(200):
        pub.publish(make(-1))
        if sub.socket.poll(10):
            break
    else:
        raise AssertionError("subscriber never joined")
    time.sleep(0.02)
    sub.take()
    sub.stats.gaps = sub.stats.received = sub.stats.delivered = sub.stats.skipped = 0


@pytest.fixture
def ipc(tmp_path):
    return lambda name: f"ipc://{tmp_path}/{name}"


def test_all_mode_delivers_every_message_in_order_with_no_gaps(ipc):
    with PubSocket(ipc("a.pub"), hwm=1000) as ps, Subscriber([ps.endpoint], "/t/x", Log, mode="all") as sub:
        pub = ps.publisher("/t/x", Log)
        _joined(pub, sub)
        for i in range(500):
            pub.publish(_log(i))
        got = [sub.recv(timeout_s=2).text for _ in range(500)]
        assert got == [str(i) for i in range(500)]
        assert sub.stats.gaps == 0 and sub.stats.bad == 0


def test_messages_over_the_publisher_hwm_are_dropped_but_never_silently(ipc):
    with PubSocket(ipc("a.pub"), hwm=10) as ps, Subscriber([ps.endpoint], "/t/x", Log, mode="all") as sub:
        pub = ps.publisher("/t/x", Log)
        _joined(pub, sub)
        first = pub.seq
        for i in range(2000):  # a burst far beyond the queue
            pub.publish(_log(i))
        time.sleep(0.3)
        pub.publish(_log("last"))  # a gap shows when the next message arrives
        got = []
        while not got or got[-1] != "last":
            got.append(sub.recv(timeout_s=2).text)
        assert sub.stats.gaps > 0
        assert len(got) + sub.stats.gaps == pub.seq - first
        assert [int(t) for t in got[:-1]] == sorted(int(t) for t in got[:-1])


def test_latest_mode_keeps_only_the_newest(ipc):
    with PubSocket(ipc("a.pub")) as ps, Subscriber([ps.endpoint], "/t/x", Log, mode="latest") as sub:
        pub = ps.publisher("/t/x", Log)
        _joined(pub, sub)
        for i in range(3):
            pub.publish(_log(i))
        time.sleep(0.05)
        items = sub.take()
        assert [m.text for m in items] == ["2"]
        assert sub.stats.skipped == 2


def test_exact_topic_match_only(ipc):
    with PubSocket(ipc("a.pub")) as ps, Subscriber([ps.endpoint], "/t/x", Log, mode="all") as sub:
        longer, pub = ps.publisher("/t/xy", Log), ps.publisher("/t/x", Log)
        _joined(pub, sub)
        longer.publish(_log("other"))
        pub.publish(_log("mine"))
        assert sub.recv(timeout_s=2).text == "mine"
        assert sub.take() == []


def test_sequence_gaps_and_restarts_are_counted(ipc):
    raw = zmq.Context.instance().socket(zmq.PUB)
    raw.bind(ipc("raw.pub"))
    with Subscriber([ipc("raw.pub")], "/t/x", Log, mode="all") as sub:
        for _ in range(200):
            raw.send_multipart([b"/t/x", *encode(_log(0), seq=0)])
            if sub.socket.poll(10):
                break
        sub.take()
        for seq in (1, 2, 6, 7, 0, 1):  # 3 lost (3, 4, 5), then the publisher restarted
            raw.send_multipart([b"/t/x", *encode(_log(seq), seq=seq)])
        got = [sub.recv(timeout_s=2).header.seq for _ in range(6)]
        assert got == [1, 2, 6, 7, 0, 1]
        assert sub.stats.gaps == 3
        assert sub.stats.restarts == 1
    raw.close(0)


def test_bad_messages_are_counted_and_returned_not_raised(ipc):
    raw = zmq.Context.instance().socket(zmq.PUB)
    raw.bind(ipc("raw.pub"))
    with Subscriber([ipc("raw.pub")], "/t/x", Log, mode="all", max_bytes=10_000) as sub:
        for _ in range(200):
            raw.send_multipart([b"/t/x", *encode(_log(0))])
            if sub.socket.poll(10):
                break
        sub.take()
        raw.send_multipart([b"/t/x", b"\xc1junk"])
        raw.send_multipart([b"/t/x", *encode(Frame(image=np.zeros(3), exposure_s=1.0))])
        raw.send_multipart([b"/t/x", b"x" * 20_000])
        raw.send_multipart([b"/t/x", *encode(_log("good"))])
        time.sleep(0.1)
        items = sub.take()
        assert [type(i) for i in items] == [MessageError, MessageError, MessageError, Log]
        assert [i.field for i in items[:3]] == ["header", "type", "size"]
        assert sub.stats.bad == 3
    raw.close(0)


def test_malformed_multipart_messages_never_shift_the_next_ones(ipc):
    """The subscriber reads part by part: a message of any number of parts is read whole, good or bad."""
    raw = zmq.Context.instance().socket(zmq.PUB)
    raw.bind(ipc("raw.pub"))
    img = np.arange(6, dtype=np.uint16).reshape(2, 3)
    with Subscriber([ipc("raw.pub")], "/t/x", Frame, mode="all") as sub:
        for _ in range(200):
            raw.send_multipart([b"/t/x", *encode(Frame(image=img, exposure_s=0.0))])
            if sub.socket.poll(10):
                break
        sub.take()
        good = encode(Frame(image=img, exposure_s=1.0))
        raw.send(b"/t/x")  # the topic alone
        raw.send_multipart([b"/t/x", *good, b"stray", b"stray"])  # two frames too many
        raw.send_multipart([b"/t/x", good[0]])  # its buffer missing
        raw.send_multipart([b"/t/xy", *good, b"more"])  # another topic, four parts
        raw.send_multipart([b"/t/x", *good])
        time.sleep(0.1)
        items = sub.take()
        assert [type(i) for i in items] == [MessageError, MessageError, MessageError, Frame]
        assert [i.field for i in items[:3]] == ["header", "buffers", "image"]
        assert items[3].image.tolist() == img.tolist() and not items[3].image.flags.writeable
        assert sub.stats.bad == 3 and sub.take() == []
    raw.close(0)


def test_recv_times_out(ipc):
    with PubSocket(ipc("a.pub")) as ps, Subscriber([ps.endpoint], "/t/x", Log) as sub:
        t0 = time.monotonic()
        with pytest.raises(BusTimeout, match="'/t/x': nothing received within 0.2 s"):
            sub.recv(timeout_s=0.2)
        assert 0.15 < time.monotonic() - t0 < 1.0


def test_subscriber_survives_a_publisher_restart(ipc):
    ep = ipc("a.pub")
    sub = Subscriber([ep], "/t/x", Log, mode="all")
    with PubSocket(ep) as ps:
        pub = ps.publisher("/t/x", Log)
        _joined(pub, sub)
        pub.publish(_log("first life"))
        assert sub.recv(timeout_s=2).text == "first life"
    with PubSocket(ep) as ps:  # same endpoint, new process-like publisher, seq starts at 0 again
        pub = ps.publisher("/t/x", Log)
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline:
            pub.publish(_log("second life"))
            if sub.socket.poll(50):
                break
        assert sub.recv(timeout_s=2).text == "second life"
    assert sub.stats.restarts >= 1
    sub.close()


def test_tcp_and_curve(ipc):
    server_public, server_secret = zmq.curve_keypair()
    server = CurveKeys(public=server_public, secret=server_secret)
    with PubSocket("tcp://127.0.0.1:0", curve=server) as ps:
        assert ps.endpoint.startswith("tcp://127.0.0.1:") and not ps.endpoint.endswith(":0")
        pub = ps.publisher("/t/img", Frame)
        with Subscriber(
            [ps.endpoint], "/t/img", Frame, mode="all", curve=CurveKeys(server_public=server_public)
        ) as sub:
            img = np.arange(64 * 1024, dtype=np.uint16)
            _joined(pub, sub, make=lambda i: Frame(image=img, exposure_s=0.1))
            pub.publish(Frame(image=img, exposure_s=0.2))
            got = sub.recv(timeout_s=2)
            assert got.exposure_s == 0.2 and np.array_equal(got.image, img)
        # a client with the wrong server key never gets anything
        wrong_public, _ = zmq.curve_keypair()
        with Subscriber([ps.endpoint], "/t/img", Frame, curve=CurveKeys(server_public=wrong_public)) as bad:
            for _ in range(5):
                pub.publish(Frame(image=img, exposure_s=0.3))
            with pytest.raises(BusTimeout):
                bad.recv(timeout_s=0.3)


def test_bind_failure_names_the_endpoint(tmp_path):
    with pytest.raises(BusError, match="cannot bind tcp://256.0.0.1:1"):
        PubSocket("tcp://256.0.0.1:1")


def test_wire_layout_is_topic_header_buffers(ipc):
    with PubSocket(ipc("a.pub")) as ps:
        pub = ps.publisher("/t/img", Frame)
        raw = zmq.Context.instance().socket(zmq.SUB)
        raw.setsockopt(zmq.SUBSCRIBE, b"")
        raw.connect(ps.endpoint)
        img = np.arange(6, dtype=np.uint16).reshape(2, 3)
        for _ in range(200):
            pub.publish(Frame(image=img, exposure_s=0.5))
            if raw.poll(10):
                break
        topic, header, buf = raw.recv_multipart()
        h = msgpack.unpackb(header)
        assert topic == b"/t/img"
        # [type, version, stamp_ns, seq, frame_id, *Frame's fields in declared order]; image first
        assert h[:2] == ["frame", Frame.VERSION] and h[4] == "" and h[5] == [0, "<u2", [2, 3]] and h[6] == 0.5
        assert buf == img.tobytes()
        raw.close(0)


def test_a_bounded_receive_queue_leaves_the_backlog_with_the_publisher_and_loses_nothing(ipc):
    """A subscriber whose receive queue holds 2 messages, behind by a burst of 60 frames of 0.6 MB: ZeroMQ
    stops reading its socket instead of dropping, the burst waits in the publisher's queue (hwm 100)."""
    img = np.arange(480 * 640, dtype=np.uint16).reshape(480, 640)
    with (
        PubSocket(ipc("a.pub"), hwm=100) as ps,
        Subscriber([ps.endpoint], "/t/f", Frame, mode="all", hwm=2) as sub,
    ):
        pub = ps.publisher("/t/f", Frame)
        _joined(pub, sub, make=lambda i: Frame(image=img, exposure_s=0.01, step=0))
        assert sub.socket.rcvhwm == 2
        first = pub.seq
        for i in range(60):
            pub.publish(Frame(image=img + i, exposure_s=0.01, step=i))
        time.sleep(0.3)  # the receive queue is full long before this
        got = [sub.recv(timeout_s=2) for _ in range(60)]
        assert [m.header.seq - first for m in got] == list(range(60))
        assert all(np.array_equal(m.image, img + m.step) for m in got)
        assert sub.stats.gaps == 0 and sub.stats.bad == 0
