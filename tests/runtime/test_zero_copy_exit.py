"""A process that exits while large frames it sent zero-copy are still queued for a slow subscriber exits
cleanly (runtime/zero_copy.py). Before, its ZeroMQ I/O thread went on writing them from buffers the
interpreter had freed at exit: SIGSEGV, or SIGABRT on libzmq's "Bad address" assertion (33 of 36 runs of
the kinds below, at a12a302).

Real processes on loopback tcp, all started at once: each publishes small frames until the subscriber in
this process has one, then a burst of BURST 2.6 MB frames, and exits while that subscriber, reading one
every READ_EVERY_S, is still taking them in: a plain script that closes its socket with a linger, one that
leaves it open to the interpreter's exit, and a node stopping through run_node's shutdown path
(runtime/runner.py) followed by the interpreter's exit, as ``polarstripe replay`` ends. (``polarstripe
node`` ends with ``os._exit``, which never frees the buffers: __main__.py.) Frames are unmapped when freed
(glibc's ``MALLOC_MMAP_THRESHOLD_``), so a write from a freed one faults rather than sending stale bytes."""

import os
import socket
import subprocess
import sys
import threading
import time
import weakref

import numpy as np
import zmq
from polarstripe.msgs import Frame
from polarstripe.runtime.bus import PubSocket

_SCRIPT = '''
import os, sys, time
import numpy as np
from polarstripe.msgs import Frame
from polarstripe.runtime.bus import PubSocket

endpoint, go, how, n = sys.argv[1:5]
sock = PubSocket(endpoint)
pub = sock.publisher("/t/frame", Frame)
while not os.path.exists(go):  # a small frame until the subscriber has one
    pub.publish(Frame(image=np.zeros((1, 1), np.uint16), exposure_s=0.01))
    time.sleep(0.005)
for i in range(int(n)):
    pub.publish(Frame(image=np.full((1024, 1280), i, np.uint16), exposure_s=0.01))
if how == "close":
    sock.close(linger_s=0.25)
'''

_NODE = '''
import os
import numpy as np
from polarstripe.msgs import Frame
from polarstripe.runtime.node import Node
from polarstripe.runtime.params import NodeParams


class Flood(Node):
    class Params(NodeParams):
        go: str = ""
        n: int = 1

    def setup(self):
        self.pub = self.publisher("/t/frame", Frame)
        self.every(0.005, self.tick)

    def tick(self):
        if not os.path.exists(self.params.go):  # a small frame until the subscriber has one
            self.pub.publish(Frame(image=np.zeros((1, 1), np.uint16), exposure_s=0.01))
            return
        for i in range(self.params.n):
            self.pub.publish(Frame(image=np.full((1024, 1280), i, np.uint16), exposure_s=0.01))
        self.stop("sent")
'''

FRAME_BYTES = 1024 * 1280 * 2
BURST = 24
READ_EVERY_S = 0.01
RUNS = 2  # of each kind


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class _SlowReader(threading.Thread):
    """Reads a frame every READ_EVERY_S; creates the file ``go`` once it has one (small or large) and
    counts the large ones."""

    def __init__(self, ctx: zmq.Context, endpoint: str, go: str):
        super().__init__(daemon=True)
        self.sock = ctx.socket(zmq.SUB)
        self.sock.linger = 0
        self.sock.rcvhwm = 2
        self.sock.subscribe(b"/t/frame")
        self.sock.connect(endpoint)
        self.go, self.received, self.done = go, 0, threading.Event()

    def run(self):
        try:
            self._read()
        finally:
            self.sock.close()

    def _read(self):
        while not self.done.is_set():
            if self.sock.poll(50):
                parts = self.sock.recv_multipart(copy=False)
                if not os.path.exists(self.go):
                    open(self.go, "w").close()
                if len(parts) == 3 and len(parts[2]) == FRAME_BYTES:
                    self.received += 1
                    time.sleep(READ_EVERY_S)


def run_all(tmp_path, commands: dict[str, list[str]], runs: int = RUNS) -> dict[str, list[tuple[int, int]]]:
    """Start ``runs`` of every command (argv with ``{ep}`` and ``{go}`` to fill) at once, each with its slow
    reader; ``(exit code, frames received)`` of each run, by command name."""
    (tmp_path / "pub.py").write_text(_SCRIPT)
    (tmp_path / "flood_mod.py").write_text(_NODE)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")]),
           "MALLOC_MMAP_THRESHOLD_": str(1 << 20)}  # glibc: a freed frame is unmapped, never reused
    ctx = zmq.Context()
    started = []
    try:
        for name, argv in commands.items():
            for k in range(runs):
                ep, go = f"tcp://127.0.0.1:{_free_port()}", str(tmp_path / f"{name}{k}.go")
                proc = subprocess.Popen([a.format(ep=ep, go=go) for a in argv], cwd=tmp_path, env=env,
                                        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
                reader = _SlowReader(ctx, ep, go)
                reader.start()
                started.append((name, proc, reader))
        out: dict[str, list] = {name: [] for name in commands}
        for name, proc, reader in started:
            try:
                _, err = proc.communicate(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
                _, err = proc.communicate()
            reader.done.set()
            reader.join(5)
            assert proc.returncode <= 0, err.decode(errors="replace")[-2000:]  # a crash is a signal
            out[name].append((proc.returncode, reader.received))
        return out
    finally:
        for _, proc, reader in started:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
            reader.done.set()
            reader.join(5)
        ctx.term()


COMMANDS = {
    "script, socket closed": [sys.executable, "pub.py", "{ep}", "{go}", "close", f"{BURST}"],
    "script, socket left open": [sys.executable, "pub.py", "{ep}", "{go}", "open", f"{BURST}"],
    # run_node's shutdown path, then the interpreter's exit (as `polarstripe replay` does)
    "node": [sys.executable, "-c", "import sys; from polarstripe.runtime.runner import run_node; "
             "sys.exit(run_node('flood_mod:Flood', name='flood', pub=sys.argv[1], "
             "srv='ipc://' + sys.argv[2] + '.srv', params={{'go': sys.argv[2], 'n': sys.argv[3]}}))",
             "{ep}", "{go}", f"{BURST}"],
}


def test_processes_exiting_with_frames_queued_for_a_slow_subscriber_exit_cleanly(tmp_path):
    got = run_all(tmp_path, COMMANDS)
    assert all(n > 0 for runs in got.values() for _, n in runs)  # the frames were on their way
    assert {name: [code for code, _ in runs] for name, runs in got.items()} == {
        name: [0] * RUNS for name in COMMANDS
    }


def test_a_close_returns_once_zeromq_has_let_go_of_the_arrays_it_was_sending():
    """In one process: frames queued for a subscriber that reads nothing are released (pyzmq drops its
    reference, the array is freed) by the time ``close(linger_s)`` has returned (give or take pyzmq's thread
    noting it), not ``linger_s`` later."""
    linger_s = 1.0
    ps = PubSocket("tcp://127.0.0.1:0")
    sub = zmq.Context.instance().socket(zmq.SUB)
    sub.linger, sub.rcvhwm = 0, 1
    sub.setsockopt(zmq.RCVBUF, 4096)
    sub.subscribe(b"/t/frame")
    sub.connect(ps.endpoint)
    try:
        pub = ps.publisher("/t/frame", Frame)
        while not sub.poll(10):  # ZeroMQ's slow joiner: small frames until one arrives
            pub.publish(Frame(image=np.zeros((1, 1), np.uint16), exposure_s=0.01))
        arrays = []
        for i in range(6):
            image = np.full((1024, 1280), i, np.uint16)
            arrays.append(weakref.ref(image))
            pub.publish(Frame(image=image, exposure_s=0.01))
            del image
        time.sleep(0.1)
        assert sum(a() is not None for a in arrays) > 0  # queued: nothing reads them
        ps.close(linger_s=linger_s)
        deadline = time.monotonic() + linger_s / 2
        while any(a() is not None for a in arrays) and time.monotonic() < deadline:
            time.sleep(0.01)
        assert [a() is None for a in arrays] == [True] * 6
    finally:
        sub.close()


def test_a_guard_does_not_need_pyzmqs_default_monitor_address():
    """pyzmq's default monitor address names the socket's file descriptor, which the OS gives again to a later
    socket while ZeroMQ may still be ending the earlier one's monitor (a full suite once failed with "Address
    already in use" making a service server). Here another socket's monitor holds that address first: the
    guard still gets its own monitor and still sees its socket end."""
    from polarstripe.runtime.zero_copy import ZeroCopyGuard

    ctx = zmq.Context.instance()
    other, sock = ctx.socket(zmq.PUB), ctx.socket(zmq.PUB)
    held = other.get_monitor_socket(zmq.EVENT_MONITOR_STOPPED, addr=f"inproc://monitor.s-{sock.FD}")
    try:
        guard = ZeroCopyGuard(sock)
        assert guard.close(0.0)
    finally:
        other.disable_monitor()
        held.close(0)
        other.close(0)
