"""Frames through shared memory between real processes (runtime/shm_bus.py, runtime/shm_ring.py): bit-exact
round trips in every receive form, a slot overwritten before a slow reader reads it (or before its chunk
reaches the file) is a counted gap and never a torn frame, and the segments are gone when the publisher is."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from polarstripe.msgs import Frame, pack, unpack
from polarstripe.runtime.bag import BagWriter
from polarstripe.runtime.bus import Subscriber
from polarstripe.runtime.shm_bus import lease_of
from polarstripe.runtime.shm_ring import PREFIX, sweep_dead

pytestmark = pytest.mark.skipif(not Path("/dev/shm").is_dir(), reason="POSIX shared memory in /dev/shm")

TOPIC, SHAPE = "/t/frame", (480, 640)  # 0.6 MB: above the ring form's inline limit

PUBLISHER = """
import sys, time
import numpy as np
from polarstripe.msgs import Frame
from polarstripe.runtime.bus import PubSocket

ep, slots, need = sys.argv[1], int(sys.argv[2]), sys.argv[3]  # need: "ring", "plain" or "both"
with PubSocket(ep, shm_slots=slots) as ps:
    pub = ps.publisher("/t/frame", Frame)
    deadline = time.monotonic() + 20
    while True:
        plain, ring = ps.shm.wants(b"/t/frame")
        if (ring or need == "plain") and (plain or need == "ring") or time.monotonic() > deadline:
            break
        time.sleep(0.02)
    print("ready", flush=True)
    for line in sys.stdin:
        cmd, *n = line.split()
        if cmd == "quit":
            break
        for _ in range(int(n[0])):
            img = ((np.arange(480 * 640, dtype=np.uint32) * 7 + pub.seq * 7919) % 65536).astype(np.uint16)
            pub.publish(Frame(image=img.reshape(480, 640), exposure_s=0.01, step=pub.seq))
        print("sent", flush=True)
"""


def expected(seq: int) -> np.ndarray:
    return ((np.arange(SHAPE[0] * SHAPE[1], dtype=np.uint32) * 7 + seq * 7919) % 65536).astype(
        np.uint16).reshape(SHAPE)


def segments(pid: int) -> list[str]:
    return [p.name for p in Path("/dev/shm").iterdir() if p.name.startswith(f"{PREFIX}{pid}_")]


class Publisher:
    """The publisher in its own process, driven line by line on its stdin."""

    def __init__(self, tmp_path, slots: int, need: str):
        self.ep = f"ipc://{tmp_path}/pub.sock"
        self.proc = subprocess.Popen([sys.executable, "-c", PUBLISHER, self.ep, str(slots), need],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                     text=True)

    def ready(self) -> None:
        assert self.proc.stdout.readline().strip() == "ready", self.proc.stderr.read()

    def send(self, n: int) -> None:
        self.proc.stdin.write(f"pub {n}\n")
        self.proc.stdin.flush()
        assert self.proc.stdout.readline().strip() == "sent", self.proc.stderr.read()

    def quit(self) -> str:
        _, err = self.proc.communicate("quit\n", timeout=20)
        assert self.proc.returncode == 0, err
        return err


def recv_all(sub: Subscriber, n: int) -> list[Frame]:
    return [sub.recv(10.0) for _ in range(n)]


def test_frames_round_trip_bit_exact_in_every_form_and_the_ring_goes_with_the_publisher(tmp_path):
    pub = Publisher(tmp_path, slots=10, need="both")
    with (Subscriber([pub.ep], TOPIC, Frame, mode="all", shm="view") as view,
          Subscriber([pub.ep], TOPIC, Frame, mode="all", shm="copy") as copy,
          Subscriber([pub.ep], TOPIC, Frame, mode="all") as plain):
        pub.ready()
        pub.send(9)
        got = {name: recv_all(s, 9) for name, s in (("view", view), ("copy", copy), ("plain", plain))}
        assert len(segments(pub.proc.pid)) == 1  # one ring for the topic, in /dev/shm
        for name, msgs in got.items():
            assert [m.header.seq for m in msgs] == list(range(9)), name
            for m in msgs:
                assert np.array_equal(m.image, expected(m.header.seq)) and m.step == m.header.seq, name
        assert all(lease_of(m).valid() for m in got["view"])  # 9 writes into 10 slots: none reused
        assert lease_of(got["copy"][0]) is None and lease_of(got["plain"][0]) is None
        assert view.stats.gaps == copy.stats.gaps == plain.stats.gaps == 0
        with BagWriter(tmp_path / "views.mcap", chunk_size=1 << 30) as w:  # written from the slots
            for k, m in enumerate(got["view"]):
                w.add_message(TOPIC, m)
                assert w.stats.chunk_count == (1 if k >= 7 else 0)  # 8 leases close a chunk (of 1 GB)
        with open(tmp_path / "views.mcap", "rb") as f:
            recs = [m for _, _, m in make_reader(f, validate_crcs=True).iter_messages()]
        assert [r.data for r in recs] == [pack(m, topic=TOPIC) for m in got["plain"]]
        err = pub.quit()
    assert segments(pub.proc.pid) == []  # unlinked by the publisher as it closed
    assert "leaked" not in err  # its resource tracker found nothing to clean up
    for m in got["view"]:  # mapped still: the reader's views outlive the unlink
        assert np.array_equal(m.image, expected(m.header.seq))


def test_a_slot_overwritten_before_it_is_read_or_written_out_is_a_gap_never_a_torn_frame(tmp_path):
    pub = Publisher(tmp_path, slots=2, need="ring")
    with (Subscriber([pub.ep], TOPIC, Frame, mode="all", shm="view") as view,
          Subscriber([pub.ep], TOPIC, Frame, mode="all", shm="copy") as copy):
        pub.ready()
        pub.send(3)  # seq 0 in slot 0, seq 1 in slot 1, seq 2 in slot 0 again: seq 0 is gone unread
        for sub in (view, copy):
            msgs = recv_all(sub, 2)
            assert [m.header.seq for m in msgs] == [1, 2]
            assert all(np.array_equal(m.image, expected(m.header.seq)) for m in msgs)
            assert (sub.stats.gaps, sub.stats.overwritten, sub.unseen_overwritten) == (1, 1, 1)
        # the recorder's case: views kept in an open chunk while the publisher moves on
        torn: list[str] = []
        with BagWriter(tmp_path / "rec.mcap", chunk_size=64 << 20, on_torn=torn.append) as w:
            pub.send(1)  # seq 3 → slot 1
            held = recv_all(view, 1)  # seq 3, slot 1 (ticket 4)
            w.add_message(TOPIC, held[0])
            packed_3 = pack(held[0], topic=TOPIC)
            pub.send(1)  # seq 4 → slot 0 (ticket 5)
            held += recv_all(view, 1)
            w.add_message(TOPIC, held[1])
            packed_4 = pack(held[1], topic=TOPIC)
            pub.send(1)  # seq 5 → slot 1: seq 3's bytes are overwritten before the chunk is written
            assert not lease_of(held[0]).valid() and lease_of(held[1]).valid()
        assert torn == [TOPIC]  # dropped and reported once
        with open(tmp_path / "rec.mcap", "rb") as f:
            reader = make_reader(f, validate_crcs=True)
            recs = [m for _, _, m in reader.iter_messages()]
            stats = reader.get_summary().statistics
        assert [r.sequence for r in recs] == [4] and stats.message_count == 1
        assert recs[0].data == packed_4 and packed_3 != packed_4
        assert np.array_equal(unpack(recs[0].data, expect=Frame).image, expected(4))
        pub.quit()


READER = """
import sys
from polarstripe.msgs import Frame
from polarstripe.runtime.bus import Subscriber
with Subscriber([sys.argv[1]], "/t/frame", Frame, mode="all", shm="view") as sub:
    print("subscribed", flush=True)
    m = sub.recv(20.0)
    print("got", m.header.seq, int(m.image[1, 1]), flush=True)
    if sys.argv[2] == "hang":
        sys.stdin.read()
"""


def test_readers_that_exit_or_crash_leave_the_ring_and_a_killed_publisher_leaves_nothing(tmp_path):
    pub = Publisher(tmp_path, slots=4, need="ring")
    readers = [subprocess.Popen([sys.executable, "-c", READER, pub.ep, how], stdin=subprocess.PIPE,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
               for how in ("exit", "hang")]
    for r in readers:
        assert r.stdout.readline().strip() == "subscribed", r.stderr.read()
    pub.ready()
    time.sleep(0.3)  # both subscriptions have reached the publisher (the first made it ready)
    pub.send(1)
    for r in readers:
        assert r.stdout.readline().split() == ["got", "0", str(expected(0)[1, 1])]
    _, err = readers[0].communicate(timeout=20)
    assert readers[0].returncode == 0 and "leaked" not in err and "resource_tracker" not in err
    readers[1].send_signal(signal.SIGKILL)
    readers[1].wait(timeout=10)
    time.sleep(0.2)
    assert len(segments(pub.proc.pid)) == 1  # neither reader took the publisher's segment along
    pub.send(1)  # and the publisher goes on
    pub.proc.send_signal(signal.SIGKILL)
    pub.proc.wait(timeout=10)
    deadline = time.monotonic() + 5
    while segments(pub.proc.pid) and time.monotonic() < deadline:  # its resource tracker unlinks it
        time.sleep(0.1)
    sweep_dead()  # where the tracker died too (killed with its process group): the next ring sweeps
    assert segments(pub.proc.pid) == []
    assert not any(n.startswith(f"{PREFIX}{os.getpid()}_") for n in os.listdir("/dev/shm"))


def test_a_ring_outgrown_is_replaced_and_let_go_without_unmapping_a_frame_still_held(tmp_path):
    """The publisher's next, larger message makes a new ring and unlinks the old one; a reader that keeps one
    mapping lets the old one go, and a message still viewing it reads its bytes intact."""
    from polarstripe.runtime.bus import PubSocket

    ep = f"ipc://{tmp_path}/grow.sock"
    small, large = expected(1)[:240], expected(2)
    with PubSocket(ep, shm_slots=2) as ps, Subscriber([ep], TOPIC, Frame, mode="all", shm="view") as sub:
        sub._ring.reader.keep = 1
        pub = ps.publisher(TOPIC, Frame)
        deadline = time.monotonic() + 10
        while not ps.shm.wants(TOPIC.encode())[1]:
            assert time.monotonic() < deadline
            time.sleep(0.02)
        pub.publish(Frame(image=small, exposure_s=0.01))
        first = sub.recv(10.0)
        old = ps.shm.rings[TOPIC.encode()].name
        pub.publish(Frame(image=large, exposure_s=0.01))
        second = sub.recv(10.0)
        assert ps.shm.rings[TOPIC.encode()].name != old and not (Path("/dev/shm") / old).exists()
        assert list(sub._ring.reader._rings) == [ps.shm.rings[TOPIC.encode()].name]
        assert np.array_equal(first.image, small) and np.array_equal(second.image, large)


def test_a_ring_that_cannot_be_made_leaves_the_frames_inline(tmp_path):
    """A ring the kernel refuses (here one of 2**40 slots: no address space maps it) is said once, and the
    topic's ring form carries its bytes inline: nothing is lost, nothing is left in /dev/shm."""
    from polarstripe.runtime.bus import PubSocket

    ep = f"ipc://{tmp_path}/huge.sock"
    with PubSocket(ep, shm_slots=2**40) as ps, Subscriber([ep], TOPIC, Frame, mode="all", shm="view") as sub:
        ps.shm.max_bytes = 0  # no cap on the ring's size
        pub = ps.publisher(TOPIC, Frame)
        deadline = time.monotonic() + 10
        while not ps.shm.wants(TOPIC.encode())[1]:
            assert time.monotonic() < deadline
            time.sleep(0.02)
        for k in range(2):
            pub.publish(Frame(image=expected(k), exposure_s=0.01))
        got = recv_all(sub, 2)
        assert TOPIC.encode() in ps.shm.failed and not ps.shm.rings
        assert [np.array_equal(m.image, expected(k)) for k, m in enumerate(got)] == [True, True]
        assert lease_of(got[0]) is None and sub.stats.gaps == 0
    assert segments(os.getpid()) == []
