"""What reading and refusing one flood datagram costs the UDP transport, per class of bench.flood.

For each class, ``n`` datagrams are queued in a socket on 127.0.0.1 and read back two ways:

* ``drain``: :meth:`transport.udp.UdpTransport.drain` as a 2-DoF session's teleoperator runs it
  (``max_datagram`` narrowed to ``teleop.session.wire.max_session_datagram_bytes(2)``: a longer datagram is
  received with ``MSG_TRUNC`` into the preallocated buffer and counted by its true length);
* ``recvfrom``: one ``recvfrom(65536)`` per datagram, a bytes object of its full length, which is
  what asyncio's datagram transport (uvloop's too) did before anything could refuse it.

Prints ns per datagram (best of ``--repeat``); nothing is written.  A noisy host gives noisy
figures: run it on a quiet one.  Only 127.0.0.1 is used.

    python -m bench.refusal [--n 2000] [--repeat 5]
"""

from __future__ import annotations

import argparse
import asyncio
import socket
import sys
import time

from bench.flood import UDP_CLASSES, payloads
from teleop.session import auth, wire
from transport.udp import UdpTransport


def _queue(tx: socket.socket, dst: tuple[str, int], data: list[bytes], n: int) -> None:
    for i in range(n):
        tx.sendto(data[i % len(data)], dst)


async def _measure(kind: str, n: int, repeat: int) -> dict[str, float]:
    data = payloads(kind, auth.generate_key())
    n = min(n, 200) if max(map(len, data)) > 10_000 else n  # what a 64 MiB buffer surely holds
    rx = await UdpTransport.bind(("127.0.0.1", 0), rcvbuf=64 << 20)
    rx.max_datagram = wire.max_session_datagram_bytes(2)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock = rx._sock
    assert sock is not None
    best = {"drain": float("inf"), "recvfrom": float("inf")}
    try:
        for _ in range(repeat):
            _queue(tx, rx.local_address, data, n)
            t0, got = time.perf_counter_ns(), 0
            while got + rx.oversize < n:
                got += len(rx.drain())
            best["drain"] = min(best["drain"], (time.perf_counter_ns() - t0) / n)
            rx.oversize = 0
            _queue(tx, rx.local_address, data, n)
            t0 = time.perf_counter_ns()
            for _ in range(n):
                sock.recvfrom(65536)
            best["recvfrom"] = min(best["recvfrom"], (time.perf_counter_ns() - t0) / n)
    finally:
        tx.close()
        rx.close()
    return best


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.refusal", description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=2000, help="datagrams per class and repeat (60 kB: 200)")
    ap.add_argument("--repeat", type=int, default=5)
    a = ap.parse_args(argv)
    if a.n < 1 or a.repeat < 1:
        ap.error("--n and --repeat must be >= 1")
    print(f"{'class':15s} {'drain [ns]':>11s} {'recvfrom [ns]':>14s}   (per datagram, best of {a.repeat})")
    for kind in UDP_CLASSES:
        r = asyncio.run(_measure(kind, a.n, a.repeat))
        print(f"{kind:15s} {r['drain']:11.0f} {r['recvfrom']:14.0f}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
