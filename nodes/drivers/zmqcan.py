"""A python-can bus carried over ZeroMQ, so several processes share one virtual CAN segment.

python-can's ``virtual`` bus does not cross processes and ``udp_multicast`` leaves the host, so the simulator
and the multi-process tests use this backend. It is registered as the python-can interface ``zmq``::

    bus = can.Bus(interface="zmq", channel="ipc:///tmp/rig-can")

Topology: a hub (an XSUB/XPUB forwarder) at two endpoints derived from the channel (``ipc://P`` gives
``ipc://P.in`` and ``ipc://P.out``; ``tcp://H:N`` gives ports N and N+1). Every participant connects a PUB to
the hub's input and a SUB to its output, so every participant sees every other participant's frames and, like
a real controller, not its own (``receive_own_messages=True`` turns that on). With ``hub="auto"`` (default)
the first participant hosts the hub in a thread (decided by a lock file for ``ipc``, by the bind for ``tcp``);
the others only connect. If the host leaves, the others lose the segment until a new participant becomes the
hub (ZeroMQ reconnects them). ``python -m polarstripe.nodes.drivers.zmqcan --channel …`` runs a hub by itself.
Only ``ipc://`` and loopback ``tcp://`` are meant; never multicast. A plain name (``rig``) means an ipc socket
under ``$XDG_RUNTIME_DIR`` (or the temp dir; /tmp with a hashed name where the path is too long for a socket).

What it models (like python-can's ``virtual.py``, it says what it does not): frames, ids, flags, DLC and data,
error frames passed through as frames. A received bus-off error frame (class ``0x040``) puts the receiving bus
in the bus-off state: ``send`` raises :class:`can.CanOperationError` until a "restarted" error frame
(``0x100``) arrives, as socketcan does after ``ip link … restart``. Not modelled: arbitration, bit timing,
ACK, error counters, bus load; frames are delivered in hub order, and a frame sent before the hub exists is
lost.
"""

from __future__ import annotations

import argparse
import fcntl
import hashlib
import os
import signal
import struct
import tempfile
import threading
import time
import uuid

import can
import zmq

# sender id (16 bytes), timestamp [s], arbitration id, flags, data length; then the data bytes
_HDR = struct.Struct("<16sdIBB")
_EXT, _RTR, _ERR, _FD, _BRS, _ESI, _PROBE = 1, 2, 4, 8, 16, 32, 128
CAN_ERR_BUSOFF = 0x040  # linux/can/error.h
CAN_ERR_RESTARTED = 0x100


def hub_endpoints(channel: str) -> tuple[str, str]:
    """The hub's (input, output) endpoints: ``ipc://P`` → ``P.in``, ``P.out``; ``tcp://H:N`` → N, N+1."""
    if "://" not in channel:
        if not channel or "/" in channel:
            raise ValueError(
                f"CAN channel {channel!r}: give ipc://PATH, tcp://127.0.0.1:PORT or a plain name"
            )
        base = os.environ.get("XDG_RUNTIME_DIR") or tempfile.gettempdir()
        path = os.path.join(base, f"polarstripe-can-{channel}")
        if len(path) > 100:  # socket paths: ~107 bytes at most; a short name, the same in every process
            path = f"/tmp/polarstripe-can-{hashlib.sha1(path.encode()).hexdigest()[:16]}"
        channel = f"ipc://{path}"
    if channel.startswith("ipc://"):
        return channel + ".in", channel + ".out"
    if channel.startswith("tcp://"):
        host, _, port = channel[6:].rpartition(":")
        if not port.isdigit():
            raise ValueError(f"CAN channel {channel!r}: tcp needs a port number, e.g. tcp://127.0.0.1:29536")
        return f"tcp://{host}:{port}", f"tcp://{host}:{int(port) + 1}"
    raise ValueError(f"CAN channel {channel!r}: only ipc:// and tcp:// endpoints are supported")


class HubBusy(can.CanInitializationError):
    """Another process already hosts the hub of this channel."""


class ZmqCanHub:
    """The XSUB/XPUB forwarder of one segment, run in a thread (``start``/``stop``, a context manager).

    For ``ipc`` channels the host holds an ``flock`` on ``PATH.lock`` (released when it stops or dies), so a
    second would-be host cannot steal the socket path.

    :raises HubBusy: on ``start`` when another process hosts this channel's hub.
    :raises can.CanInitializationError: on ``start`` when the endpoints cannot be bound (the text names them).
    """

    def __init__(self, channel: str, ctx: zmq.Context | None = None):
        self.channel = channel
        self.endpoints = hub_endpoints(channel)
        self._ctx = ctx or zmq.Context.instance()
        self._thread: threading.Thread | None = None
        self._control = f"inproc://zmqcan-hub-{uuid.uuid4().hex}"
        self._ready = threading.Event()
        self._error: Exception | None = None
        self._lock_fd: int | None = None

    def _claim(self) -> None:
        front = self.endpoints[0]
        if front.startswith("ipc://"):
            fd = os.open(front[len("ipc://") : -len(".in")] + ".lock", os.O_CREAT | os.O_RDWR, 0o600)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                os.close(fd)
                raise HubBusy(f"zmq CAN hub {self.channel}: another process hosts it") from None
            self._lock_fd = fd
            return
        probe = self._ctx.socket(zmq.XSUB)
        probe.linger = 0
        try:
            probe.bind(front)
        except zmq.ZMQError as exc:
            if exc.errno == zmq.EADDRINUSE:
                raise HubBusy(f"zmq CAN hub {self.channel}: {front} is in use") from None
            raise can.CanInitializationError(
                f"zmq CAN hub {self.channel}: cannot bind {front}: {exc}"
            ) from exc
        finally:
            probe.close()

    def _release(self) -> None:
        if self._lock_fd is not None:
            os.close(self._lock_fd)
            self._lock_fd = None

    def start(self) -> ZmqCanHub:
        try:
            self._claim()
            self._thread = threading.Thread(target=self._run, name=f"zmqcan-hub {self.channel}",
                                            daemon=True)
            self._thread.start()
            self._ready.wait(5.0)
        except BaseException:  # a stop signal mid-start (NodeStopping, KeyboardInterrupt): leave no file
            if self._thread is None:
                self._unlink_files()
            else:
                self._ready.wait(5.0)
                self.stop()
            raise
        if self._error is not None:
            self._thread.join(1.0)
            self._thread = None
            self._release()
            raise can.CanInitializationError(f"zmq CAN hub {self.channel}: {self._error}") from self._error
        return self

    def _run(self) -> None:
        xsub, xpub = self._ctx.socket(zmq.XSUB), self._ctx.socket(zmq.XPUB)
        control = self._ctx.socket(zmq.PAIR)
        for sock in (xsub, xpub, control):
            sock.linger = 0
        try:
            control.bind(self._control)
            for sock, endpoint in ((xsub, self.endpoints[0]), (xpub, self.endpoints[1])):
                try:
                    sock.bind(endpoint)
                except zmq.ZMQError as exc:
                    raise zmq.ZMQError(exc.errno, f"cannot bind {endpoint}: {exc}") from exc
        except zmq.ZMQError as exc:
            self._error = exc
            self._ready.set()
            for sock in (xsub, xpub, control):
                sock.close()
            return
        self._ready.set()
        try:
            zmq.proxy_steerable(xsub, xpub, None, control)
        except zmq.ZMQError:
            pass
        finally:
            for sock in (xsub, xpub, control):
                sock.close()

    def stop(self) -> None:
        """Stop forwarding and unbind; idempotent."""
        if self._thread is None:
            return
        ctl = self._ctx.socket(zmq.PAIR)
        ctl.linger = 0
        ctl.connect(self._control)
        ctl.send(b"TERMINATE")
        self._thread.join(5.0)
        ctl.close()
        self._thread = None
        self._unlink_files()

    def _unlink_files(self) -> None:
        """Remove the ipc socket files and the lock file (the lock while still holding it), then release the
        lock: libzmq's own unlink may come late, and a start cut short leaves the lock file alone."""
        front = self.endpoints[0]
        if front.startswith("ipc://") and self._lock_fd is not None:
            base = front[len("ipc://") : -len(".in")]
            for path in (base + ".in", base + ".out", base + ".lock"):
                try:
                    os.unlink(path)
                except OSError:
                    pass
        self._release()

    def __enter__(self) -> ZmqCanHub:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()


class ZmqCanBus(can.BusABC):
    """A python-can bus on a ZeroMQ hub (see the module docstring for the topology).

    :param channel: ``ipc://PATH``, ``tcp://127.0.0.1:PORT`` or a plain name.
    :param hub: ``"auto"`` hosts the hub if nobody does yet, ``True`` always hosts it, ``False`` never.
    :param receive_own_messages: also receive the frames this bus sends.
    :param join_timeout: seconds to wait until the hub carries this bus's frames both ways.
    :raises can.CanInitializationError: no hub answered within ``join_timeout``, or the hub could not bind.
    """

    def __init__(
        self,
        channel: str = "polarstripe",
        can_filters=None,
        hub: str | bool = "auto",
        receive_own_messages: bool = False,
        join_timeout: float = 2.0,
        **kwargs,
    ):
        self._pub = self._sub = None
        self._hub: ZmqCanHub | None = None
        super().__init__(channel=channel, can_filters=can_filters, **kwargs)
        self.channel_info = f"zmq {channel}"
        self._channel = channel
        self._own = receive_own_messages
        self._id = uuid.uuid4().bytes
        self._send_lock = threading.Lock()
        self._bus_off = False
        ctx = zmq.Context.instance()
        front, back = hub_endpoints(channel)
        try:
            if hub is True:
                self._hub = ZmqCanHub(channel, ctx).start()
            elif hub == "auto":
                try:
                    self._hub = ZmqCanHub(channel, ctx).start()
                except HubBusy:
                    self._hub = None
            self._pub, self._sub = ctx.socket(zmq.PUB), ctx.socket(zmq.SUB)
            self._pub.linger = self._sub.linger = 0
            self._pub.connect(front)
            self._sub.connect(back)
            self._sub.setsockopt(zmq.SUBSCRIBE, b"")
            self._join(join_timeout)
        except BaseException:
            self._close_sockets()
            raise

    def _join(self, timeout: float) -> None:
        """Send probes until one comes back: then both paths through the hub carry frames (no slow joiner)."""
        deadline = time.monotonic() + timeout
        probe = _HDR.pack(self._id, 0.0, 0, _PROBE, 0)
        while time.monotonic() < deadline:
            self._pub.send(probe)
            if self._sub.poll(20):
                while self._sub.poll(0):
                    raw = self._sub.recv()
                    if raw[:16] == self._id and _HDR.unpack_from(raw)[3] & _PROBE:
                        return
        raise can.CanInitializationError(
            f"zmq CAN bus {self._channel}: no hub carried frames within {timeout:g} s; start one with "
            f"'python -m polarstripe.nodes.drivers.zmqcan --channel {self._channel}' or use hub='auto'"
        )

    @property
    def state(self) -> can.BusState:
        return can.BusState.ERROR if self._bus_off else can.BusState.ACTIVE

    @state.setter
    def state(self, new_state: can.BusState) -> None:
        raise NotImplementedError("the zmq bus state follows received error frames; it cannot be set")

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Send one frame.

        :raises can.CanOperationError: the bus is off, shut down, or the frame could not be queued in time.
        """
        if self._bus_off:
            raise can.CanOperationError(
                f"zmq CAN bus {self._channel}: bus-off, frame 0x{msg.arbitration_id:X} not sent",
                error_code=105,
            )
        if self._pub is None or self._is_shutdown:
            raise can.CanOperationError(f"zmq CAN bus {self._channel}: bus is shut down")
        flags = (
            (_EXT if msg.is_extended_id else 0)
            | (_RTR if msg.is_remote_frame else 0)
            | (_ERR if msg.is_error_frame else 0)
            | (_FD if msg.is_fd else 0)
            | (_BRS if msg.bitrate_switch else 0)
            | (_ESI if msg.error_state_indicator else 0)
        )
        data = bytes(msg.data)
        frame = _HDR.pack(self._id, time.time(), msg.arbitration_id, flags, len(data)) + data
        with self._send_lock:
            try:
                self._pub.send(frame)  # a PUB socket never blocks: at its high-water mark it drops, like a
                # saturated bus loses arbitration, so ``timeout`` has nothing to wait for
            except zmq.ZMQError as exc:
                raise can.CanOperationError(f"zmq CAN bus {self._channel}: send failed: {exc}") from exc

    def _recv_internal(self, timeout: float | None):
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            ms = None if deadline is None else max(0, int((deadline - time.monotonic()) * 1000))
            try:
                if not self._sub.poll(ms):
                    return None, False
                raw = self._sub.recv()
            except zmq.ZMQError as exc:
                raise can.CanOperationError(f"zmq CAN bus {self._channel}: receive failed: {exc}") from exc
            sender, stamp, can_id, flags, length = _HDR.unpack_from(raw)
            if flags & _PROBE or (sender == self._id and not self._own):
                continue
            msg = can.Message(
                timestamp=stamp,
                arbitration_id=can_id,
                is_extended_id=bool(flags & _EXT),
                is_remote_frame=bool(flags & _RTR),
                is_error_frame=bool(flags & _ERR),
                is_fd=bool(flags & _FD),
                bitrate_switch=bool(flags & _BRS),
                error_state_indicator=bool(flags & _ESI),
                dlc=length,
                data=raw[_HDR.size : _HDR.size + length],
                channel=self._channel,
                is_rx=sender != self._id,
            )
            if msg.is_error_frame:
                if can_id & CAN_ERR_BUSOFF:
                    self._bus_off = True
                if can_id & CAN_ERR_RESTARTED:
                    self._bus_off = False
            return msg, False

    def _close_sockets(self) -> None:
        for sock in (self._pub, self._sub):
            if sock is not None:
                sock.close(0)
        self._pub = self._sub = None
        if self._hub is not None:
            self._hub.stop()
            self._hub = None

    def shutdown(self) -> None:
        """Close the sockets and, if this bus hosts the hub, the hub; idempotent."""
        if self._is_shutdown:
            return
        super().shutdown()
        with self._send_lock:
            self._close_sockets()


class GatedBus(can.BusABC):
    """Wraps a bus so a simulated device can fall silent (bus-off) in both directions: while :attr:`silent`,
    nothing is sent and nothing is received; :meth:`send_raw` still sends (the error frames)."""

    def __init__(self, inner: can.BusABC):
        self._inner = inner
        self.silent = False
        super().__init__(channel=getattr(inner, "channel_info", "sim"))
        self.channel_info = inner.channel_info

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if not self.silent:
            self._inner.send(msg, timeout)

    def send_raw(self, msg: can.Message) -> None:
        self._inner.send(msg)

    def _recv_internal(self, timeout):
        msg = self._inner.recv(timeout)
        if msg is not None and self.silent:
            return None, True
        return msg, True

    def shutdown(self) -> None:
        if self._is_shutdown:
            return
        super().shutdown()
        self._inner.shutdown()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m polarstripe.nodes.drivers.zmqcan",
        description="Run the hub of a CAN segment carried over ZeroMQ until SIGINT.",
    )
    parser.add_argument("--channel", required=True, help="ipc://PATH, tcp://127.0.0.1:PORT or a plain name")
    args = parser.parse_args(argv)
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    with ZmqCanHub(args.channel):
        print(f"zmq CAN hub on {' and '.join(hub_endpoints(args.channel))}", flush=True)
        stop.wait()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
