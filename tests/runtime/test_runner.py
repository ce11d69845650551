"""A node as a process (runtime/runner.py): loading the class, the real ZeroMQ bus behind the node contract,
and run_node's order (params checked before anything binds, setup, loop, teardown, sockets closed)."""

import signal
import threading
import time

import pytest
from polarstripe.errors import PolarstripeError
from polarstripe.msgs import Ack, Empty
from polarstripe.nodes.demo import Talker
from polarstripe.nodes.emitter import Emitter
from polarstripe.nodes.planner import Planner
from polarstripe.runtime.bus import BusError
from polarstripe.runtime.node import Node, NodeError
from polarstripe.runtime.node_bus import NodeBus
from polarstripe.runtime.params import ParamError
from polarstripe.runtime.runner import ZmqNodeBus, load_node_class, run_node
from polarstripe.runtime.service import ServiceClient

_MODULE = '''
from polarstripe.msgs import Ack, Empty
from polarstripe.runtime.node import Node
from polarstripe.runtime.params import NodeParams


class Quitter(Node):
    class Params(NodeParams):
        code: int = 3

    SERVES = {"~/ping": (Empty, Ack)}

    def setup(self):
        self.serve("~/ping", lambda req: Ack(ok=True))
        self.every(0.01, self.quit)

    def quit(self):
        self.log.info("graph has %d nodes", len(self.graph.get("nodes", {})))
        self.stop("done here", exit_code=self.params.code)

    def teardown(self):
        self.log.info("teardown ran")
'''


def test_node_classes_load_by_class_by_node_name_or_by_node_class():
    assert load_node_class("polarstripe.nodes.demo:Talker") is Talker
    assert load_node_class("polarstripe.nodes.emitter") is Emitter  # NODE = Emitter
    assert load_node_class("polarstripe.nodes.planner") is Planner
    with pytest.raises(PolarstripeError, match="module 'polarstripe.nodes.nope' not found"):
        load_node_class("polarstripe.nodes.nope")
    with pytest.raises(PolarstripeError, match="has no class 'Nope'"):
        load_node_class("polarstripe.nodes.demo:Nope")
    with pytest.raises(PolarstripeError, match="NODE attribute naming its Node class"):
        load_node_class("polarstripe.nodes.demo")
    with pytest.raises(PolarstripeError, match="a Node subclass"):
        load_node_class("polarstripe.runtime.params:NodeParams")


def test_a_node_needs_its_bus_at_construction():
    with pytest.raises(NodeError, match="needs a bus"):
        Talker("t", bus=None)


def test_the_zmq_bus_keeps_the_node_contract_and_finds_services_in_the_graph(tmp_path):
    graph = {"services": {"/rig/camera/trigger": {"endpoint": f"ipc://{tmp_path}/g.srv"}}}
    bus = ZmqNodeBus("n", pub=f"ipc://{tmp_path}/n.pub", srv=f"ipc://{tmp_path}/n.srv", graph=graph)
    try:
        assert isinstance(bus, NodeBus) and bus.service_stats() == (0, 0, 0)
        assert abs(bus.now() - time.monotonic()) < 1.0
        client = bus.client("/rig/camera/trigger", Empty, Ack, 0.5)
        assert client.endpoint == f"ipc://{tmp_path}/g.srv"
        with pytest.raises(BusError, match=r"'/rig/x' is not served .*\(known: /rig/camera/trigger\)"):
            bus.client("/rig/x", Empty, Ack, 0.5)
        # a node's subscription: the mode's receive queue, or the one asked for
        assert bus.subscribe("/rig/a", Ack, "latest", 1 << 20).socket.rcvhwm == 4
        assert bus.subscribe("/rig/b", Ack, "all", 1 << 20).socket.rcvhwm == 0  # unlimited
        assert bus.subscribe("/rig/c", Ack, "all", 1 << 20, 8).socket.rcvhwm == 8
    finally:
        bus.close()


def test_service_requests_are_answered_in_the_loop_and_counted_in_the_heartbeat(tmp_path):
    class Pinger(Node):
        SERVES = {"ping": (Empty, Ack)}

        def setup(self):
            self.serve("ping", lambda req: Ack(ok=True, detail="pong"))
            self.every(0.02, name="tick")

    bus = ZmqNodeBus("p", pub=f"ipc://{tmp_path}/p.pub", srv=f"ipc://{tmp_path}/p.srv")
    node = Pinger("p", bus=bus)
    node.setup()
    replies = []
    caller = threading.Thread(target=lambda: replies.append(
        ServiceClient(f"ipc://{tmp_path}/p.srv", "/ping", Empty, Ack, timeout_s=5).call(Empty())))
    caller.start()
    try:
        deadline = time.monotonic() + 10
        for _ in node.events():
            if replies or time.monotonic() > deadline:
                node.stop("answered")
        caller.join(5)
        assert replies and replies[0].detail == "pong"
        hb = node.heartbeat()
        assert hb.counters["requests"] == 1 and hb.counters["service_errors"] == 0 and hb.node == "p"
    finally:
        bus.close()


def test_a_bad_param_fails_before_any_socket_is_bound(tmp_path):
    with pytest.raises(ParamError, match="node 'talker': param 'rate_hz': bad value 'fast'"):
        run_node("polarstripe.nodes.demo:Talker", params={"rate_hz": "fast"}, pub=f"ipc://{tmp_path}/t.pub",
                 srv=f"ipc://{tmp_path}/t.srv")
    assert list(tmp_path.iterdir()) == []


def test_run_node_runs_setup_loop_teardown_and_returns_the_exit_code(tmp_path, monkeypatch, capfd):
    (tmp_path / "quitter_mod.py").write_text(_MODULE)
    monkeypatch.syspath_prepend(str(tmp_path))
    handlers = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    try:
        code = run_node("quitter_mod:Quitter", name="q", namespace="/rig", params={"code": "4"},
                        pub=f"ipc://{tmp_path}/q.pub", srv=f"ipc://{tmp_path}/q.srv")
    finally:
        signal.signal(signal.SIGINT, handlers[0])
        signal.signal(signal.SIGTERM, handlers[1])
    err = capfd.readouterr().err
    assert code == 4
    lines = [line.split(" q: ", 1)[1] for line in err.splitlines() if " q: " in line]
    assert lines[0].startswith("started (pid") and lines[1:] == ["graph has 0 nodes", "teardown ran",
                                                                 "stopped (done here)"]
    assert not (tmp_path / "q.pub").exists()  # the ipc socket file is removed on the way out
