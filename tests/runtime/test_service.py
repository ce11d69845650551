"""Services (runtime/service.py): a ROUTER server for named services, DEALER clients with timeouts; every
failure is a reply or an exception naming the service, never a wedge."""

import threading
import time

import pytest
import zmq
from polarstripe.msgs import Ack, Empty, Log, MessageError
from polarstripe.runtime.bus import BusError, ServiceError, ServiceTimeout
from polarstripe.runtime.service import ServiceClient, ServiceServer


def _log(i):
    return Log(level="INFO", node="t", text=str(i))


@pytest.fixture
def ipc(tmp_path):
    return lambda name: f"ipc://{tmp_path}/{name}"


class _Serving:
    """A ServiceServer answered by a thread (the node loop does this in real nodes)."""

    def __init__(self, endpoint):
        self.server = ServiceServer(endpoint)
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._loop)

    def _loop(self):
        while not self.stop.is_set():
            if self.server.socket.poll(20):
                self.server.handle_ready()

    def __enter__(self):
        self.thread.start()
        return self.server

    def __exit__(self, *exc):
        self.stop.set()
        self.thread.join()
        self.server.close()


def test_service_call_error_and_unknown_service(ipc):
    served = _Serving(ipc("s.srv"))
    calls = []

    def echo(req):
        calls.append(req.text)
        if req.text == "boom":
            raise RuntimeError("handler exploded")
        return Ack(ok=True, detail=req.text.upper())

    served.server.add("/t/echo", Log, Ack, echo)
    with served as server:
        with ServiceClient(server.endpoint, "/t/echo", Log, Ack, timeout_s=2) as c:
            assert c.call(_log("hi")).detail == "HI"
            with pytest.raises(ServiceError, match="RuntimeError: handler exploded"):
                c.call(_log("boom"))
            assert c.call(_log("again")).detail == "AGAIN"
        with ServiceClient(server.endpoint, "/t/nonesuch", Empty, Ack, timeout_s=2) as c:
            with pytest.raises(ServiceError, match="'/t/nonesuch' is not served"):
                c.call(Empty())
        with ServiceClient(server.endpoint, "/t/echo", Empty, Ack, timeout_s=2) as c:  # wrong request type
            with pytest.raises(ServiceError, match="expected 'log', got 'empty'"):
                c.call(Empty())
        # a raw malformed request (garbage header) gets an error reply and is counted
        dealer = zmq.Context.instance().socket(zmq.DEALER)
        dealer.connect(server.endpoint)
        dealer.send_multipart([b"/t/echo", b"12345678", b"\xc1"])
        assert dealer.poll(2000)
        reply = dealer.recv_multipart()
        assert reply[2] == b"error" and b"not a MessagePack header" in reply[3]
        dealer.close(0)
    assert calls == ["hi", "boom", "again"]
    assert server.stats.bad == 3 and server.stats.errors == 1


def test_service_timeout_when_the_server_is_down_and_no_stale_request_later(ipc):
    ep = ipc("s.srv")
    client = ServiceClient(ep, "/t/echo", Log, Ack, timeout_s=0.3)
    t0 = time.monotonic()
    with pytest.raises(ServiceTimeout, match=r"service '/t/echo' at ipc://.*s.srv: no reply within 0.3 s"):
        client.call(_log("lost"))
    assert 0.25 < time.monotonic() - t0 < 1.5
    assert isinstance(ServiceTimeout("x"), TimeoutError)
    served = _Serving(ep)
    seen = []
    served.server.add("/t/echo", Log, Ack, lambda r: seen.append(r.text) or Ack(ok=True))
    with served:
        assert client.call(_log("now"), timeout_s=3).ok
        time.sleep(0.1)
    assert seen == ["now"]  # the request of the timed-out call was dropped with its socket


def test_request_type_is_checked_before_sending(ipc):
    c = ServiceClient(ipc("none.srv"), "/t/echo", Log, Ack)
    with pytest.raises(MessageError, match="expected 'log', got Empty"):
        c.call(Empty())




def test_a_handler_returning_the_wrong_type_is_an_error_reply_and_the_server_goes_on(ipc):
    served = _Serving(ipc("s.srv"))
    served.server.add("/t/odd", Log, Ack, lambda r: Empty() if r.text == "odd" else Ack(ok=True))
    with served as server, ServiceClient(server.endpoint, "/t/odd", Log, Ack, timeout_s=2) as c:
        with pytest.raises(ServiceError, match="handler returned Empty, expected 'ack'"):
            c.call(_log("odd"))
        assert c.call(_log("fine")).ok
    assert server.stats.errors == 1 and server.stats.per_service == {"/t/odd": 2}
    assert server.services["/t/odd"].calls == 2 and server.services["/t/odd"].errors == 1


def test_a_service_is_served_once_per_server(ipc):
    with ServiceServer(ipc("s.srv")) as server:
        server.add("/t/a", Empty, Ack, lambda r: Ack(ok=True))
        with pytest.raises(BusError, match="'/t/a' is already served here"):
            server.add("/t/a", Empty, Ack, lambda r: Ack(ok=False))


def test_handle_ready_answers_what_waits_and_counts_a_truncated_request(ipc):
    with ServiceServer(ipc("s.srv")) as server:
        server.add("/t/a", Empty, Ack, lambda r: Ack(ok=True, detail="a"))
        assert server.handle_ready() == []  # nothing waiting: returns at once
        dealer = zmq.Context.instance().socket(zmq.DEALER)
        dealer.linger = 0
        dealer.connect(server.endpoint)
        try:
            dealer.send_multipart([b"/t/a", b"1"])  # no header frame: malformed, not answered
            assert server.socket.poll(2000)
            problems = server.handle_ready()
            assert len(problems) == 1 and isinstance(problems[0], MessageError)
            assert "malformed request (3 frames)" in server.stats.last_error and server.stats.bad == 1
            assert not dealer.poll(100)
        finally:
            dealer.close(0)


def test_a_late_reply_to_an_abandoned_call_is_not_taken_for_the_next(ipc):
    """The client drops its socket after a timeout: the slow handler's reply to the first call can never be
    read as the reply to the second."""
    served = _Serving(ipc("s.srv"))
    served.server.add("/t/slow", Log, Ack, lambda r: time.sleep(float(r.text)) or Ack(ok=True, detail=r.text))
    with served as server, ServiceClient(server.endpoint, "/t/slow", Log, Ack, timeout_s=0.2) as c:
        with pytest.raises(ServiceTimeout):
            c.call(_log("0.5"))
        assert c.call(_log("0"), timeout_s=3).detail == "0"
        assert c.calls == 2 and c.timeouts == 1


def test_a_deferred_reply_goes_out_when_the_node_gives_it_and_is_checked_like_any(ipc):
    """A handler may return a Deferred and answer later from its loop; the server answers others meanwhile."""
    from polarstripe.runtime.node_bus import Deferred

    later: dict[str, Deferred] = {}

    def slow(req):
        later[req.text] = Deferred()
        return later[req.text]

    def call(endpoint, service, request, out, key):
        with ServiceClient(endpoint, service, type(request), Ack, timeout_s=5) as c:
            try:
                out[key] = c.call(request).detail
            except ServiceError as exc:
                out[key] = str(exc)

    with ServiceServer(ipc("s.srv")) as server:
        server.add("/t/slow", Log, Ack, slow)
        server.add("/t/fast", Empty, Ack, lambda r: Ack(ok=True, detail="fast"))
        out: dict[str, str] = {}
        threads = [threading.Thread(target=call, args=(server.endpoint, "/t/slow", _log(k), out, k))
                   for k in ("ok", "wrong", "fail")]
        threads.append(threading.Thread(target=call, args=(server.endpoint, "/t/fast", Empty(), out, "fast")))
        for t in threads:
            t.start()
        deadline = time.monotonic() + 5
        while (len(later) < 3 or "fast" not in out) and time.monotonic() < deadline:  # the node's loop
            if server.socket.poll(20):
                server.handle_ready()
        assert out == {"fast": "fast"} and sorted(later) == ["fail", "ok", "wrong"]  # three still waiting
        later["ok"].reply(Ack(ok=True, detail="later"))
        later["wrong"].reply(Empty())
        later["fail"].fail(RuntimeError("gave up"))
        for t in threads:
            t.join(5)
    assert out["ok"] == "later"
    assert "handler returned Empty, expected 'ack'" in out["wrong"] and "RuntimeError: gave up" in out["fail"]
    assert server.stats.errors == 2 and server.services["/t/slow"].errors == 2
    with pytest.raises(RuntimeError, match="already given"):
        later["ok"].reply(Ack(ok=True))


def test_a_call_whose_request_cannot_be_sent_times_out(ipc):
    """A DEALER with no peer blocks its send (a CURVE server that refused our key drops the connection; CI
    once hung 180 s in tests/runtime/test_auth.py so). The call waits for room within its timeout and then
    raises ServiceTimeout, as for a missing reply. Here the socket cannot send: ``immediate`` and nothing
    listening."""
    with ServiceClient(ipc("nobody.srv"), "/t/echo", Log, Log) as c:
        c._drop()
        s = zmq.Context.instance().socket(zmq.DEALER)
        s.linger, s.immediate = 0, True
        s.connect(ipc("nobody.srv"))
        c.socket = s
        t0 = time.monotonic()
        with pytest.raises(ServiceTimeout, match="no reply within 0.3 s"):
            c.call(Log(level="INFO", node="n", text="hi"), timeout_s=0.3)
        assert time.monotonic() - t0 < 5.0
        assert c.socket is None and s.closed        # dropped: nothing queued leaks into the next call
