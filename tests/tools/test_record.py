"""The recorder with real processes: ``launch --record`` and ``polarstripe record`` write bags that the
mcap package reads back intact; gaps are counted; rotation by size; a recorder killed with SIGKILL loses at
most its open chunk after ``bag recover``."""

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import NonSeekingReader, make_reader
from polarstripe.msgs import Frame, decode, encode, pack, unpack
from polarstripe.runtime.bag import BagError
from polarstripe.runtime.bag_reader import BagReader, check_file, recover
from polarstripe.runtime.bus import PubSocket

SHAPE = (120, 160)

SOURCE = """
import time
import numpy as np
from polarstripe.msgs import Frame
from polarstripe.runtime.node import Node
from polarstripe.runtime.params import NodeParams


class FrameSource(Node):
    class Params(NodeParams):
        count: int = 10
        delay_s: float = 1.5

    PUBLISHES = {"camera/frame": Frame}

    def setup(self):
        self.pub = self.publisher("camera/frame")
        self.n = 0
        self.t0 = time.monotonic()
        self.every(0.02, self.tick)

    def tick(self):
        if time.monotonic() - self.t0 < self.params.delay_s:
            return
        if self.n == self.params.count:
            return self.stop("done")
        img = (np.arange(120 * 160, dtype=np.uint16).reshape(120, 160) + self.n) % 4096
        self.pub.publish(Frame(image=img, exposure_s=0.01, step=self.n, pattern=f"stripe:{self.n}/10"))
        self.n += 1
"""


def expected_image(seq: int) -> np.ndarray:
    return ((np.arange(SHAPE[0] * SHAPE[1]) + seq) % 4096).astype(np.uint16).reshape(SHAPE)


def _env(tmp_path):
    return {**os.environ, "POLARSTRIPE_RUNS": str(tmp_path / "runs"), "PYTHONPATH": str(tmp_path)}


def test_launch_record_writes_every_message_intact(tmp_path):
    (tmp_path / "rec_test_nodes.py").write_text(SOURCE)
    toml = tmp_path / "rec.toml"
    toml.write_text(
        textwrap.dedent("""
        [launch]
        name = "rec"
        namespace = "/lab"
        [[node]]
        name = "source"
        module = "rec_test_nodes:FrameSource"
        params = { count = 25 }
        required = true
    """)
    )
    bag = tmp_path / "run.mcap"
    r = subprocess.run(
        [sys.executable, "-m", "polarstripe", "launch", str(toml), "--once", "--record", str(bag)],
        env=_env(tmp_path),
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 0, r.stderr
    with open(bag, "rb") as f:  # the mcap package's own reader
        reader = make_reader(f, validate_crcs=True)
        frames = [(s, c, m) for s, c, m in reader.iter_messages(topics=["/lab/camera/frame"])]
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
    assert [m.sequence for _, _, m in frames] == list(range(25))
    for schema, channel, rec in frames:
        assert channel.message_encoding == "msgpack" and schema.encoding == "jsonschema"
        msg = unpack(rec.data, expect=Frame)
        assert np.array_equal(msg.image, expected_image(msg.step)) and msg.step == rec.sequence
        assert rec.publish_time == msg.header.stamp_ns
        assert 0 <= rec.log_time - rec.publish_time < 5e9  # log time = receive time, after the stamp
    assert meta["launch"]["toml"] == toml.read_text() and meta["launch"]["namespace"] == "/lab"
    assert json.loads(meta["launch"]["graph"])["nodes"]["source"]["params"] == {"count": 25}
    assert meta["versions"]["mcap"] and meta["versions"]["polarstripe"]
    assert meta["recording"]["gaps"] == "0"
    assert json.loads(meta["recording"]["topics"])["/lab/camera/frame"]["messages"] == 25


# ---- polarstripe record against a hand-made graph: the test process is the publisher -----------------------
def _graph(tmp_path) -> tuple[Path, str]:
    ep = f"ipc://{tmp_path}/cam.pub"
    graph = {
        "launch": "hand",
        "namespace": "/rig",
        "pid": os.getpid(),
        "run_dir": str(tmp_path),
        "nodes": {"cam": {"module": "x", "pub": ep, "srv": ""}},
        "topics": {"/rig/camera/frame": {"type": "frame", "publishers": ["cam"], "subscribers": []}},
    }
    path = tmp_path / "graph.json"
    path.write_text(json.dumps(graph))
    return path, ep


def _on_disk(path) -> list[int]:
    """Sequence numbers of the frames a (possibly unfinished) bag holds in complete chunks."""
    seqs = []
    try:
        with open(path, "rb") as f:
            for _, _, m in NonSeekingReader(f).iter_messages(log_time_order=False):
                seqs.append(m.sequence)
    except Exception:  # the torn or missing tail of a file being written
        pass
    return seqs


def _wait(cond, timeout_s=20.0):
    deadline = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.05)


def _publish(pub, seq: int) -> None:
    pub.seq = seq
    pub.publish(Frame(image=expected_image(seq), exposure_s=0.01, step=seq))


def _start_record(tmp_path, graph, *extra):
    return subprocess.Popen(
        [
            sys.executable,
            "-m",
            "polarstripe",
            "record",
            "-o",
            str(tmp_path / "rec.mcap"),
            "--graph",
            str(graph),
            "camera/frame",
            *extra,
        ],
        env=_env(tmp_path),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def _warm_up(pub, path, proc) -> int:
    """Publish until the recorder has a frame on disk; returns the next sequence number."""
    seq = 0
    deadline = time.monotonic() + 20
    while not _on_disk(path):
        assert proc.poll() is None, proc.communicate()[1]
        assert time.monotonic() < deadline, "the recorder wrote nothing"
        _publish(pub, seq)
        seq += 1
        time.sleep(0.05)
    return seq


def test_sigkill_loses_at_most_the_open_chunk(tmp_path):
    graph, ep = _graph(tmp_path)
    path = tmp_path / "rec.mcap"
    with PubSocket(ep) as ps:
        pub = ps.publisher("/rig/camera/frame", Frame)
        proc = _start_record(tmp_path, graph, "--chunk-age", "0.2", "--chunk-size", "1M")
        try:
            seq = _warm_up(pub, path, proc)
            for _ in range(20):  # these end up in closed chunks (by size or by age) ...
                _publish(pub, seq)
                seq += 1
                time.sleep(0.02)
            last_closed = seq - 1
            _wait(lambda: last_closed in _on_disk(path))
            for _ in range(6):  # ... these may sit in the open chunk when the recorder dies
                _publish(pub, seq)
                seq += 1
            time.sleep(0.01)
        finally:
            proc.send_signal(signal.SIGKILL)
            proc.wait(timeout=10)
    on_disk = _on_disk(path)
    with pytest.raises(BagError, match="truncated"):
        check_file(path)
    r = recover(path, tmp_path / "fixed.mcap")
    with BagReader(tmp_path / "fixed.mcap") as bag:  # indexed: opens with the seeking reader
        got = [(m.header.seq, m) for _, _, m in bag.messages()]
    seqs = [s for s, _ in got]
    assert r.messages == len(got)
    assert set(on_disk) <= set(seqs)  # every complete chunk of the dead writer's file
    assert seqs == list(range(seqs[0], seqs[-1] + 1))  # no hole: only a tail can be missing
    assert seqs[-1] >= last_closed and seq - 1 - seqs[-1] <= 6  # lost: at most the open chunk
    for s, m in got:
        assert np.array_equal(m.image, expected_image(s))


def test_record_counts_gaps_rotates_by_size_and_finishes_on_sigint(tmp_path):
    graph, ep = _graph(tmp_path)
    path = tmp_path / "rec.mcap"
    frame_bytes = SHAPE[0] * SHAPE[1] * 2
    with PubSocket(ep) as ps:
        pub = ps.publisher("/rig/camera/frame", Frame)
        proc = _start_record(tmp_path, graph, "--split-size", str(3 * frame_bytes), "--chunk-size", "1")
        try:
            first = _warm_up(pub, tmp_path / "rec_000.mcap", proc)
            for s in [*range(first, first + 5), *range(first + 8, first + 12)]:  # 3 lost upstream
                _publish(pub, s)
                time.sleep(0.03)
            time.sleep(0.5)
        finally:
            proc.send_signal(signal.SIGINT)
            out, err = proc.communicate(timeout=20)
    assert proc.returncode == 0, err
    files = sorted(tmp_path.glob("rec_*.mcap"))
    assert len(files) >= 3 and not path.exists()
    seqs, gaps = [], []
    for f in files:
        with BagReader(f) as bag:  # each part is a complete, indexed bag with its own metadata
            seqs += [m.header.seq for _, _, m in bag.messages()]
            assert bag.metadata["versions"]["polarstripe"]
            gaps.append(int(bag.metadata["recording"]["gaps"]))
            assert bag.size < 3 * frame_bytes + 2 * frame_bytes  # rotated once past the limit
    assert seqs[-9:] == [*range(first, first + 5), *range(first + 8, first + 12)]
    assert gaps[-1] == 3  # cumulative, in the last part's recording metadata
    assert "3 gaps" in err


def test_a_burst_through_a_small_receive_queue_is_recorded_byte_for_byte(tmp_path):
    """A burst of 40 frames of 0.6 MB (zero-copy on the bus and in the writer) far beyond the recorder's
    receive queue of 2: the backlog waits in the publisher's queue, nothing is lost, and the mcap package
    reads each message back as exactly the bytes of ``pack`` of what was published."""
    graph, ep = _graph(tmp_path)
    path, topic = tmp_path / "rec.mcap", "/rig/camera/frame"
    big = np.arange(480 * 640, dtype=np.uint16).reshape(480, 640) % 4096
    sent = {}

    def publish(pub, seq, img):
        msg, stamp = Frame(image=img, exposure_s=0.01, step=seq), 1_000_000 + seq
        pub.seq = seq
        pub.publish(msg, stamp_ns=stamp)
        wire = encode(msg, topic=topic, seq=seq, stamp_ns=stamp)  # what the recorder receives
        sent[seq] = pack(decode([bytes(wire[0]), *map(memoryview, wire[1:])], topic=topic))

    with PubSocket(ep) as ps:
        pub = ps.publisher(topic, Frame)
        proc = _start_record(tmp_path, graph, "--queue", "2", "--chunk-size", "4M", "--chunk-age", "0.2")
        try:
            seq = 0
            deadline = time.monotonic() + 20
            while not _on_disk(path):  # the recorder is up
                assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()[1]
                publish(pub, seq, expected_image(seq))
                seq += 1
                time.sleep(0.05)
            for s in range(seq, seq + 40):
                publish(pub, s, (big + s) % 4096)
            _wait(lambda: seq + 39 in _on_disk(path))
        finally:
            proc.send_signal(signal.SIGINT)
            _, err = proc.communicate(timeout=20)
    assert proc.returncode == 0, err
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        got = {m.sequence: m.data for _, _, m in reader.iter_messages(topics=[topic])}
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
    first = min(got)  # (the first frames go before the subscription has reached the publisher)
    assert sorted(got) == list(range(first, seq + 40)) and first < seq  # the whole burst, no hole
    assert meta["recording"]["gaps"] == "0"
    assert all(got[s] == sent[s] for s in got)


def test_frames_through_shared_memory_are_recorded_byte_for_byte(tmp_path):
    """``polarstripe record`` (transport shm, the default) against a publisher offering the ring form: the
    recorder writes 0.6 MB frames from the ring's slots, the mcap package reads back exactly ``pack`` of
    what was published, and the bag says which transport carried them."""
    graph, ep = _graph(tmp_path)
    g = json.loads(graph.read_text())
    g["nodes"]["cam"]["shm_slots"] = 64
    graph.write_text(json.dumps(g))
    path, topic = tmp_path / "rec.mcap", "/rig/camera/frame"
    big = np.arange(480 * 640, dtype=np.uint16).reshape(480, 640) % 4096
    sent = {}
    with PubSocket(ep, shm_slots=64) as ps:
        pub = ps.publisher(topic, Frame)
        proc = _start_record(tmp_path, graph, "--chunk-age", "0.2")
        try:
            _wait(lambda: ps.shm.wants(topic.encode())[1] or proc.poll() is not None)
            assert ps.shm.wants(topic.encode()) == (False, True)  # the ring form only
            for s in range(30):
                msg = Frame(image=(big + s) % 4096, exposure_s=0.01, step=s)
                pub.publish(msg, stamp_ns=1_000_000 + s)
                wire = encode(msg, topic=topic, seq=s, stamp_ns=1_000_000 + s)  # what was sent
                sent[s] = pack(decode([bytes(wire[0]), *map(memoryview, wire[1:])], topic=topic))
                time.sleep(0.01)
            _wait(lambda: 29 in _on_disk(path))
        finally:
            proc.send_signal(signal.SIGINT)
            _, err = proc.communicate(timeout=20)
    assert proc.returncode == 0, err
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        got = {m.sequence: m.data for _, _, m in reader.iter_messages(topics=[topic])}
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
    assert sorted(got) == list(range(30)) and all(got[s] == sent[s] for s in got)
    assert meta["recording"]["gaps"] == "0"
    assert json.loads(meta["recording"]["topics"])[topic]["transport"] == "shm"
