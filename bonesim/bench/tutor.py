"""Benchmark of the tutoring link over loopback (:mod:`bonesim.tutoring`).

``tutor_loopback_latency_p99_ms``: a sender process sends STATE-sized
tutoring packets (authenticated, :mod:`bonesim.net.packets`) at the haptic rate,
1 kHz, to a receiver in this process over 127.0.0.1 for a few seconds. Each
packet carries its send time on the shared monotonic clock; the receiver
blocks on its socket, checks each datagram through an
:class:`~bonesim.net.packets.Inbox` and records ``receive time - send time``: the
one-way latency of encoding, the UDP stack and decoding. The trainee's servo
polls its socket once per tick, which adds up to one more period (1 ms) on
top of this. Loss is the fraction of sent packets never accepted. Figures
are wall-clock on whatever machine runs them.
"""
from __future__ import annotations

import multiprocessing as mp
import socket
import time

import numpy as np

from bonesim.runtime.shared import end_process

__all__ = ["RATE_HZ", "PAYLOAD_BYTES", "bench_tutor"]

#: Send rate [Hz].
RATE_HZ = 1000.0
#: Payload bytes (a STATE packet, 134 bytes, with one 83-byte tissue event or so).
PAYLOAD_BYTES = 200
_KEY = bytes(range(32))
_KIND = 16


def _sender(port: int, nonce: int, seconds: float, conn) -> None:
    from bonesim.net import packets as net

    codec = net.Codec(_KEY)
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    payload = bytes(PAYLOAD_BYTES)
    period = 1.0 / RATE_HZ
    clock = time.monotonic
    n = int(seconds * RATE_HZ)
    conn.send("ready")
    conn.recv()                                       # go
    deadline = clock()
    for _ in range(n):
        s.sendto(codec.encode_into(_KIND, payload, nonce, t_s=clock()), ("127.0.0.1", port))
        deadline += period
        rest = deadline - clock()
        if rest > 0:
            time.sleep(rest)
    s.close()
    conn.send(n)


def bench_tutor(quick: bool = False) -> dict:
    from bonesim.net import packets as net

    seconds = 1.0 if quick else 5.0
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
    rx.settimeout(0.5)
    nonce = net.new_nonce()
    inbox = net.Inbox(net.Codec(_KEY), nonce, stale_s=1.0)
    ctx = mp.get_context("spawn")
    mine, theirs = ctx.Pipe()
    proc = ctx.Process(target=_sender, args=(rx.getsockname()[1], nonce, seconds, theirs),
                       name="bonesim-bench-tutor-sender", daemon=True)
    proc.start()
    lat = np.zeros(int(seconds * RATE_HZ) + 16)
    got = 0
    buf = bytearray(net.MAX_DATAGRAM)
    try:
        if not mine.poll(60.0):
            raise RuntimeError("the benchmark's sender process did not start")
        mine.recv()
        mine.send("go")
        clock = time.monotonic
        while True:
            try:
                n = rx.recv_into(buf)
            except socket.timeout:
                break                                 # the sender is done
            now = clock()
            p = inbox.accept(memoryview(buf)[:n], now)
            if p is not None and got < len(lat):
                lat[got] = now - p.t_s
                got += 1
        sent = mine.recv() if mine.poll(10.0) else int(seconds * RATE_HZ)
    finally:
        end_process(proc, 10.0)
        rx.close()
    ms = lat[:got] * 1e3
    loss = 1.0 - got / sent if sent else 1.0
    p50 = round(float(np.percentile(ms, 50)), 4) if got else None
    p99 = round(float(np.percentile(ms, 99)), 4) if got else None
    detail = {"packets_sent": int(sent), "packets_accepted": int(got),
              "payload_bytes": PAYLOAD_BYTES, "rate_hz": RATE_HZ, "seconds": seconds,
              "drops": {k: v for k, v in inbox.counters.items() if k != "accepted"},
              "setup": "sender process -> this process over 127.0.0.1 UDP, HMAC-SHA256 "
                       "packets, blocking receive; the trainee's 1 kHz polling adds up to "
                       "1 ms"}
    return {
        "tutor_loopback_latency_p99_ms": {"value": p99, "unit": "ms", "p50_ms": p50,
                                          "max_ms": round(float(ms.max()), 4) if got
                                          else None, "loss_fraction": round(loss, 5),
                                          **detail},
        "tutor_loopback_latency_p50_ms": {"value": p50, "unit": "ms"},
        "tutor_loopback_loss_fraction": {"value": round(loss, 5), "unit": "fraction",
                                         "packets_sent": int(sent)},
    }
