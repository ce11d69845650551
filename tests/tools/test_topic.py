"""``polarstripe topic list|echo|hz`` (tools/topic.py) against a graph file and a publisher in this process
(ipc and 127.0.0.1 only): the table, echo's lines and JSON, a bad message, a node's own type, a timeout,
CURVE, and one clear error line when there is no launch or graph."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import threading

import msgpack
import pytest
import zmq
from polarstripe.msgs import Header, Log, encode
from polarstripe.runtime.bus import CurveKeys, PubSocket
from polarstripe.tools.cli import main


@pytest.fixture
def ipc_dir():
    d = tempfile.mkdtemp(prefix="ps-topic-", dir="/tmp")  # ipc paths are limited to ~107 bytes
    yield d
    shutil.rmtree(d, ignore_errors=True)


def _graph(path, pub: str, *, topic="/rig/chatter", type_="log", module="polarstripe.nodes.demo:Talker",
           extra_topics=None) -> str:
    graph = {
        "launch": "t", "namespace": "/rig", "pid": os.getpid(),
        "nodes": {"talker": {"module": module, "pub": pub}, "listener": {"module": "x:Y", "pub": ""}},
        "topics": {topic: {"type": type_, "publishers": ["talker"], "subscribers": ["listener"]},
                   **(extra_topics or {})},
    }
    p = os.path.join(path, "graph.json")
    with open(p, "w") as f:
        json.dump(graph, f)
    return p


class _Publisher:
    """A raw PUB socket sending the given multipart messages over and over (every 2 ms) until closed."""

    def __init__(self, endpoint: str, messages: list[list[bytes]]):
        self.sock = zmq.Context.instance().socket(zmq.PUB)
        self.sock.linger = 0
        self.sock.bind(endpoint)
        self.messages, self.stop = messages, threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self):
        while not self.stop.wait(0.002):
            for m in self.messages:
                self.sock.send_multipart(m)

    def close(self):
        self.stop.set()
        self.thread.join(2)
        self.sock.close(0)


def _log_frames(topic: str, text: str, seq: int) -> list[bytes]:
    msg = Log(level="INFO", node="talker", text=text, header=Header(stamp_ns=123, seq=seq, frame_id="f"))
    return [topic.encode(), *[bytes(memoryview(f).cast("B")) for f in encode(msg, topic=topic)]]


# ---- no launch, no graph: one line, exit 2 ---------------------------------------------------------------
def test_echo_without_a_running_launch_is_one_clear_line(tmp_path):
    env = {**os.environ, "POLARSTRIPE_RUNS": str(tmp_path)}
    r = subprocess.run([sys.executable, "-m", "polarstripe", "topic", "echo", "chatter"], env=env,
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and r.stdout == ""
    assert r.stderr.splitlines() == [
        f"polarstripe topic: error: no running launch found in {tmp_path} (start one with "
        "'polarstripe launch FILE', or pass --graph)"
    ]


@pytest.mark.parametrize(
    "content, needle",
    [(None, "does not exist"), ("{not json", "graph file .*: Expecting property name"),
     ('{"launch": "x"}', r"not a polarstripe graph \(no 'nodes'\)")],
)
def test_a_bad_graph_file_is_one_error_line(tmp_path, capsys, content, needle):
    g = tmp_path / "graph.json"
    if content is not None:
        g.write_text(content)
    assert main(["topic", "--graph", str(g), "list"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and re.search(needle, err[0]) and err[0].startswith("polarstripe topic: error: ")


def test_argument_errors(capsys):
    for argv in (["topic"], ["topic", "echo"], ["topic", "echo", "x", "-n", "many"]):
        with pytest.raises(SystemExit) as exc:
            main(argv)
        assert exc.value.code == 2
    assert "invalid int value: 'many'" in capsys.readouterr().err


# ---- list ------------------------------------------------------------------------------------------------
def test_list_prints_topics_sorted_with_type_publishers_and_subscribers(tmp_path, capsys):
    g = _graph(str(tmp_path), "ipc:///nowhere", extra_topics={
        "/rig/a": {"type": "frame", "publishers": [], "subscribers": ["x", "y"]}})
    assert main(["topic", "list", "--graph", str(tmp_path)]) == 0  # --graph after the action, a run dir
    lines = capsys.readouterr().out.splitlines()
    assert [line.split()[0] for line in lines] == ["/rig/a", "/rig/chatter"]
    assert lines[0].split() == ["/rig/a", "frame", "pub:", "-", "sub:", "x,", "y"]
    assert lines[1].split() == ["/rig/chatter", "log", "pub:", "talker", "sub:", "listener"]
    with open(g) as f:
        graph = json.load(f)
    graph["topics"] = {}
    with open(g, "w") as f:
        json.dump(graph, f)
    assert main(["topic", "--graph", g, "list"]) == 0
    assert capsys.readouterr().out == "no topics\n"


# ---- echo ------------------------------------------------------------------------------------------------
def test_echo_prints_header_and_fields_and_stops_after_n(ipc_dir, capsys):
    ep = f"ipc://{ipc_dir}/talker.pub"
    pub = _Publisher(ep, [_log_frames("/rig/chatter", "hi", 4), _log_frames("/rig/chatterbox", "no", 9)])
    try:
        assert main(["topic", "--graph", _graph(ipc_dir, ep), "echo", "chatter", "-n", "2"]) == 0
    finally:
        pub.close()
    out = capsys.readouterr().out.splitlines()
    assert out == ["[log seq=4 stamp_ns=123 frame_id='f'] level='INFO', node='talker', text='hi'"] * 2


def test_echo_json_and_bad_messages_go_to_stderr(ipc_dir, capsys):
    ep = f"ipc://{ipc_dir}/talker.pub"
    pub = _Publisher(ep, [[b"/rig/chatter", b"\xc1garbage"], _log_frames("/rig/chatter", "ok", 1)])
    try:
        g = _graph(ipc_dir, ep)
        assert main(["topic", "--graph", g, "echo", "/rig/chatter", "-n", "1", "--json"]) == 0
    finally:
        pub.close()
    cap = capsys.readouterr()
    doc = json.loads(cap.out)
    assert doc == {"type": "log", "version": 1, "stamp_ns": 123, "seq": 1, "frame_id": "f",
                   "fields": {"level": "INFO", "node": "talker", "text": "ok"}}
    assert "bad message: topic '/rig/chatter': field 'header'" in cap.err


def test_echo_names_the_fields_of_a_type_declared_by_the_publishers_module(ipc_dir, capsys, monkeypatch):
    mod = "ps_topic_private_node"
    with open(os.path.join(ipc_dir, f"{mod}.py"), "w") as f:
        f.write("from polarstripe.msgs import Message, message\n\n"
                "@message('test_topic_private')\nclass Private(Message):\n    count: int\n    label: str\n")
    monkeypatch.syspath_prepend(ipc_dir)
    monkeypatch.delitem(sys.modules, mod, raising=False)
    head = msgpack.packb(["test_topic_private", 1, 5, 0, "", 42, "x"])
    ep = f"ipc://{ipc_dir}/talker.pub"
    pub = _Publisher(ep, [[b"/rig/private", head]])
    try:
        kw = {"topic": "/rig/private", "type_": "test_topic_private"}
        g_unknown = _graph(ipc_dir, ep, module="no_such_mod:N", **kw)
        assert main(["topic", "--graph", g_unknown, "echo", "private", "-n", "1"]) == 0
        assert capsys.readouterr().out.endswith("] #0=42, #1='x'\n")  # no module: by position
        g_known = _graph(ipc_dir, ep, module=f"{mod}:Node", **kw)
        assert main(["topic", "--graph", g_known, "echo", "private", "-n", "1"]) == 0
        assert capsys.readouterr().out.endswith("] count=42, label='x'\n")
    finally:
        pub.close()


def test_echo_timeout_without_messages_exits_1(ipc_dir, capsys):
    g = _graph(ipc_dir, f"ipc://{ipc_dir}/nobody.pub")
    assert main(["topic", "--graph", g, "echo", "chatter", "--timeout", "0.2"]) == 1
    cap = capsys.readouterr()
    assert cap.out == "" and cap.err == "no message on /rig/chatter within 0.2 s\n"


def test_echo_with_the_rigs_curve_keys_and_without(ipc_dir, capsys, monkeypatch):
    public, secret = zmq.curve_keypair()
    keys = os.path.join(ipc_dir, "rig.keys")
    with open(keys, "w") as f:
        f.write(f"# the rig's keypair\npublic={public.decode()}\nsecret={secret.decode()}\n")
    os.chmod(keys, 0o600)  # a secret key readable by others is refused
    ps = PubSocket("tcp://127.0.0.1:0", curve=CurveKeys(public=public, secret=secret))
    pub = ps.publisher("/rig/chatter", Log)
    stop = threading.Event()

    def run():
        while not stop.wait(0.002):
            pub.publish(Log(level="INFO", node="c", text="secret"))

    t = threading.Thread(target=run, daemon=True)
    t.start()
    try:
        g = _graph(ipc_dir, ps.endpoint)
        monkeypatch.delenv("POLARSTRIPE_CURVE_KEYS", raising=False)
        assert main(["topic", "--graph", g, "echo", "chatter", "--timeout", "0.3"]) == 1  # hears nothing
        monkeypatch.setenv("POLARSTRIPE_CURVE_KEYS", keys)
        assert main(["topic", "--graph", g, "echo", "chatter", "-n", "1", "--timeout", "5"]) == 0
    finally:
        stop.set()
        t.join(2)
        ps.close()
    assert "text='secret'" in capsys.readouterr().out


# ---- hz --------------------------------------------------------------------------------------------------
def test_hz_reports_a_rate_or_how_few_messages_came(ipc_dir, capsys):
    g = _graph(ipc_dir, f"ipc://{ipc_dir}/talker.pub")
    assert main(["topic", "--graph", g, "hz", "chatter", "--window", "0.1", "-n", "1"]) == 0
    assert capsys.readouterr().out == "/rig/chatter: 0 message(s) in 0.1 s\n"
    pub = _Publisher(f"ipc://{ipc_dir}/talker.pub", [_log_frames("/rig/chatter", "x", 0)])
    try:
        assert main(["topic", "--graph", g, "hz", "chatter", "--window", "0.3", "-n", "2"]) == 0
    finally:
        pub.close()
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 2
    assert re.fullmatch(r"/rig/chatter: \d+\.\d\d Hz  \(n=\d+, min \d+\.\d\d ms, max \d+\.\d\d ms, "
                        r"std \d+\.\d\d ms, \d+\.\d{3} MB/s\)", lines[-1]), lines[-1]
