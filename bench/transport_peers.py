"""The two processes of ``polarstripe bench transport``: each transport's sender and receiver sides, the
receiver's child process and the measuring sender (latency, then windowed throughput, for each payload).

The method is described in :mod:`polarstripe.bench.transport`, which runs these and prints the table.
"""

from __future__ import annotations

import multiprocessing as mp
import time

import msgpack
import numpy as np
import zmq
from polarstripe.msgs import Frame
from polarstripe.runtime.bus import PubSocket, Subscriber

SIZES = {  # name -> (shape, dtype, latency rate [Hz], latency count, window)
    "frame 2.6 MB": ((1024, 1280), np.uint16, 100, 100, 4),
    "64 KiB": ((65536,), np.uint8, 500, 300, 64),
    "100 B": ((100,), np.uint8, 1000, 500, 1000),
}
TOPIC = "/bench/frame"
HWM = 5000  # publisher queue [messages] for both transports: above every window, so flow control, not HWM,
# bounds what is in flight (a loss would be a real one)
_END, _DATA, _PING, _QUIT = 2, 0, 1, 3


# ---- the transports, sender and receiver sides ------------------------------------------------------------
class _BusTx:
    def __init__(self, endpoint, ctx):

        self.Frame = Frame
        self.sock = PubSocket(endpoint, hwm=HWM, ctx=ctx)
        self.pub = self.sock.publisher(TOPIC, Frame)

    def send(self, payload, t_ns, flag):
        return self.pub.publish(self.Frame(image=payload, exposure_s=0.0, step=flag), stamp_ns=t_ns)

    def close(self):
        self.sock.close()


class _BusRx:
    def __init__(self, endpoint, ctx):

        self.sub = Subscriber([endpoint], TOPIC, Frame, mode="all", ctx=ctx)
        self.socket = self.sub.socket

    def recv(self):
        """-> (seq, t_send_ns, flag, first element) of the next message (blocks)."""
        m = self.sub.recv()
        return m.header.seq, m.header.stamp_ns, m.step, m.image.flat[0]

    def close(self):
        self.sub.close()


class _RawTx:
    def __init__(self, endpoint, ctx):
        self.sock = ctx.socket(zmq.PUB)
        self.sock.linger = 0
        self.sock.sndhwm = HWM
        self.sock.bind(endpoint)
        self.seq = 0
        self.topic = TOPIC.encode()

    def send(self, payload, t_ns, flag):
        hdr = msgpack.packb((self.seq, t_ns, flag, payload.dtype.str, payload.shape))
        self.sock.send_multipart([self.topic, hdr, payload], copy=False)
        self.seq += 1
        return self.seq - 1

    def close(self):
        self.sock.close(0)


class _RawRx:
    def __init__(self, endpoint, ctx):
        self.socket = ctx.socket(zmq.SUB)
        self.socket.linger = 0
        self.socket.rcvhwm = 0
        self.socket.setsockopt(zmq.SUBSCRIBE, TOPIC.encode())
        self.socket.connect(endpoint)

    def recv(self):
        frames = self.socket.recv_multipart(copy=False)
        seq, t_ns, flag, dtype, shape = msgpack.unpackb(frames[1].bytes)
        arr = np.frombuffer(frames[2].buffer, dtype=dtype).reshape(shape)
        return seq, t_ns, flag, arr.flat[0]

    def close(self):
        self.socket.close(0)


class _PartsTx(_RawTx):
    """Raw pyzmq, part by part (``send(…, SNDMORE)``): what ``send_multipart`` does minus its per-part
    checks; the bus sends this way."""

    def send(self, payload, t_ns, flag):
        hdr = msgpack.packb((self.seq, t_ns, flag, payload.dtype.str, payload.shape))
        send = self.sock.send
        send(self.topic, zmq.SNDMORE)
        send(hdr, zmq.SNDMORE)
        send(payload, copy=False)
        self.seq += 1
        return self.seq - 1


class _PartsRx(_RawRx):
    """Raw pyzmq, part by part (``recv(copy=False)`` and each frame's ``more``, instead of
    ``recv_multipart``'s ``getsockopt(RCVMORE)`` per part); the bus receives this way."""

    def recv(self):
        recv = self.socket.recv
        part = recv(copy=False)
        parts = []
        while part.more:
            part = recv(copy=False)
            parts.append(part)
        seq, t_ns, flag, dtype, shape = msgpack.unpackb(parts[0].bytes)
        arr = np.frombuffer(parts[1].buffer, dtype=dtype).reshape(shape)
        return seq, t_ns, flag, arr.flat[0]


TRANSPORTS = {"bus": (_BusTx, _BusRx), "pyzmq": (_RawTx, _RawRx), "pyzmq-parts": (_PartsTx, _PartsRx)}


def _receiver(kind: str, endpoint: str, ack_endpoint: str) -> None:
    """Child process: receive until an END message; ack pings and throughput seqs; report latencies/counts."""
    ctx = zmq.Context()
    rx = TRANSPORTS[kind][1](endpoint, ctx)
    ack = ctx.socket(zmq.PUSH)
    ack.linger = 1000
    ack.connect(ack_endpoint)
    try:
        while True:  # one phase per loop: until END
            lat, received, first_seq, last_seq, cpu0 = [], 0, None, None, None
            ack_every = 1
            while True:
                seq, t_ns, flag, _ = rx.recv()
                now = time.perf_counter_ns()
                if flag == _PING:
                    ack.send(msgpack.packb(("ping", seq)))
                    continue
                if flag == _QUIT:
                    return
                if flag == _END:
                    cpu = time.process_time() - cpu0 if cpu0 is not None else 0.0
                    ack.send(msgpack.packb(("end", received, first_seq, last_seq, lat, cpu)))
                    break
                if flag >= 100:  # throughput message; flag - 100 = ack interval
                    if cpu0 is None:
                        cpu0 = time.process_time()
                    ack_every = flag - 100
                    received += 1
                    first_seq = seq if first_seq is None else first_seq
                    last_seq = seq
                    if received % ack_every == 0:
                        ack.send(msgpack.packb(("ack", received)))
                else:
                    received += 1
                    first_seq = seq if first_seq is None else first_seq
                    last_seq = seq
                    lat.append(now - t_ns)
    except KeyboardInterrupt:
        pass
    finally:
        rx.close()
        ack.close()
        ctx.term()


def _run_transport(kind, size_names, seconds, quick, tmp):
    ctx = zmq.Context()
    endpoint, ack_ep = f"ipc://{tmp}/{kind}.pub", f"ipc://{tmp}/{kind}.ack"
    tx = TRANSPORTS[kind][0](endpoint, ctx)
    acks = ctx.socket(zmq.PULL)
    acks.linger = 0
    acks.bind(ack_ep)
    child = mp.get_context("fork").Process(target=_receiver, args=(kind, endpoint, ack_ep), daemon=True)
    child.start()
    results = {}
    try:
        ping = np.zeros(1, np.uint8)
        while True:  # slow joiner: ping until the receiver answers
            tx.send(ping, time.perf_counter_ns(), _PING)
            if acks.poll(20):
                acks.recv()
                break
        time.sleep(0.05)
        while acks.poll(50):
            acks.recv()
        for name in size_names:
            shape, dtype, rate, count, window = SIZES[name]
            payload = (np.arange(int(np.prod(shape))) % 251).astype(dtype).reshape(shape)
            if quick:
                count = max(20, count // 4)
            # warm-up (first-run effects: page faults, allocator, caches), results discarded
            for _ in range(max(10, count // 5)):
                tx.send(payload, time.perf_counter_ns(), _DATA)
                time.sleep(0.5 / rate)
            tx.send(ping, time.perf_counter_ns(), _END)
            _recv(acks, 10)
            # latency: paced
            period = 1.0 / rate
            t_next = time.perf_counter()
            for _ in range(count):
                delay = t_next - time.perf_counter()
                if delay > 0:  # sleep, not spin: a spinning sender would steal the receiver's core
                    time.sleep(delay)
                tx.send(payload, time.perf_counter_ns(), _DATA)
                t_next += period
            tx.send(ping, time.perf_counter_ns(), _END)
            _, n_lat, _, _, lat, _ = msgpack.unpackb(_recv(acks, 10))
            lat_us = np.array(lat) / 1e3
            # throughput: windowed
            ack_every = max(1, window // 4)
            sent, acked = 0, 0  # acked = messages the receiver has confirmed
            cpu0 = time.process_time()
            t0 = time.perf_counter()
            t_end = t0 + seconds
            while time.perf_counter() < t_end:
                while acks.poll(0):
                    acked = max(acked, msgpack.unpackb(acks.recv())[1])
                if sent - acked >= window:
                    if acks.poll(1000):
                        acked = max(acked, msgpack.unpackb(acks.recv())[1])
                    continue
                tx.send(payload, time.perf_counter_ns(), 100 + ack_every)
                sent += 1
            tx.send(ping, time.perf_counter_ns(), _END)
            reply = None
            while reply is None or reply[0] != "end":
                reply = msgpack.unpackb(_recv(acks, 10))
            tx_cpu = time.process_time() - cpu0
            _, received, rx_first, rx_last, _, rx_cpu = reply
            elapsed = time.perf_counter() - t0
            nbytes = payload.nbytes
            results[name] = {
                "msgs_per_s": received / elapsed,
                "MB_per_s": received * nbytes / elapsed / 1e6,
                "p50_us": float(np.percentile(lat_us, 50)),
                "p99_us": float(np.percentile(lat_us, 99)),
                "latency_samples": n_lat,
                "latency_sent": count,
                "sent": sent,
                "received": received,
                "lost": sent - received + (count - n_lat),
                "tx_cpu_us": tx_cpu / max(sent, 1) * 1e6,  # CPU time per message: steady under load
                "rx_cpu_us": rx_cpu / max(received, 1) * 1e6,
            }
        tx.send(ping, time.perf_counter_ns(), _QUIT)
    finally:
        tx.close()
        child.join(3)
        if child.is_alive():
            child.kill()
            child.join()
        acks.close()
        ctx.term()
    return results


def _recv(sock, timeout_s):
    if not sock.poll(int(timeout_s * 1000)):
        raise TimeoutError("benchmark receiver did not answer")
    return sock.recv()
