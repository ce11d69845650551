"""The node's service client (runtime/client.py) against a server in a real process: a call pending when the
server is killed fails as soon as its heartbeats stop (liveness, ~1 s), not at its 30 s timeout; a call to a
lost server fails at once; a respawned server is waited for and answers."""

import os
import signal
import subprocess
import sys
import threading
import time

import pytest
from polarstripe.msgs import Ack, Log
from polarstripe.runtime.bus import ServiceError
from polarstripe.runtime.client import ServiceLost
from polarstripe.runtime.graph import write_graph
from polarstripe.runtime.liveness import PeerLost
from polarstripe.runtime.node import Node
from polarstripe.runtime.runner import ZmqNodeBus

SERVER = '''
import time
from polarstripe.msgs import Ack, Log
from polarstripe.runtime.node import Node


class Slow(Node):
    SERVES = {"slow/wait": (Log, Ack)}

    def setup(self):
        self.serve("slow/wait", self.wait)

    def wait(self, req):
        time.sleep(float(req.text))  # a busy handler: the heartbeat thread still beats
        return Ack(ok=True, detail=req.text)
'''


def _wait(seconds: str) -> Log:
    return Log(level="INFO", node="caller", text=seconds)


@pytest.fixture
def rig(tmp_path):
    (tmp_path / "slow_server.py").write_text(SERVER)
    nodes = {n: {"pub": f"ipc://{tmp_path}/{n}.pub", "srv": f"ipc://{tmp_path}/{n}.srv"}
             for n in ("slow", "caller")}
    graph = {"launch": "t", "namespace": "/t", "nodes": nodes,
             "services": {"/t/slow/wait": {"node": "slow", "endpoint": nodes["slow"]["srv"]}}}
    write_graph(tmp_path / "graph.json", graph)
    procs = []

    def start(incarnation: int = 0) -> subprocess.Popen:
        env = dict(os.environ, PYTHONPATH=f"{tmp_path}{os.pathsep}{os.environ.get('PYTHONPATH', '')}",
                   POLARSTRIPE_INCARNATION=str(incarnation))
        graph_file = str(tmp_path / "graph.json")
        code = ("import sys; from polarstripe.runtime.runner import run_node; "
                f"sys.exit(run_node('slow_server:Slow', name='slow', graph_file={graph_file!r}))")
        procs.append(subprocess.Popen([sys.executable, "-c", code], env=env, stderr=subprocess.DEVNULL))
        return procs[-1]

    bus = ZmqNodeBus("caller", pub=nodes["caller"]["pub"], srv=nodes["caller"]["srv"], graph=graph)
    caller = Node("caller", bus=bus, namespace="/t")
    server = start()
    client = caller.client("slow/wait", Log, Ack, timeout_s=30.0)
    assert client is caller.client("slow/wait", Log, Ack, timeout_s=30.0)  # one client, made once
    assert client.wait_for_service(60.0), "the server never beat ready"
    yield start, server, client
    for p in procs:
        if p.poll() is None:
            p.kill()
        p.wait(10)
    bus.close()


def test_a_pending_call_fails_when_its_server_is_killed_not_at_its_timeout(rig):
    _, server, client = rig
    assert client.call(_wait("0")).detail == "0"

    killed = []

    def kill():
        killed.append(time.monotonic())
        server.send_signal(signal.SIGKILL)

    threading.Timer(1.0, kill).start()
    with pytest.raises(ServiceLost) as lost:
        client.call(_wait("30"))  # the handler sleeps 30 s; the server dies 1 s into it
    after_kill = time.monotonic() - killed[0]
    assert after_kill < 2.0, f"the failure came {after_kill:.2f} s after the kill"
    assert isinstance(lost.value, PeerLost) and isinstance(lost.value, ServiceError)
    assert lost.value.node == "slow" and "no heartbeat for" in str(lost.value)
    assert str(lost.value).startswith("service '/t/slow/wait': node 'slow' lost")

    t0 = time.monotonic()
    with pytest.raises(ServiceLost):
        client.call(_wait("0"))  # the server is known lost: at once, nothing sent
    assert time.monotonic() - t0 < 0.5


def test_a_call_with_retries_waits_for_the_respawned_server(rig):
    start, server, client = rig
    server.send_signal(signal.SIGKILL)
    server.wait(10)
    time.sleep(1.5)  # its beats have stopped: lost
    assert not client.wait_for_service(0.2)
    start(incarnation=1)
    assert client.call(_wait("0"), retry_s=60.0).detail == "0"  # lost at first, then back and answering
