"""The floor reference: the least CPU a pair of 1 kHz Python processes on this design can spend.

Each of the two processes does only what any loop of ``teleop run`` must do every tick: sleep until
``--spin-us`` (100 us) before the deadline, spin on the clock for the rest, seal a 40-byte body
with keyed BLAKE2s (``teleop.session.auth.Sealer``), send it to the other over loopback UDP, drain the
socket and verify what arrived (``teleop.session.auth.Opener``).  No models, no codec, no wire format, no
counters, no recorder, no event loop.  ``bench.cpu`` runs the pair beside ``teleop run`` and
divides each process's CPU by this one's.

The empty loop is the other reference, for timing: the session's scheduler
(``shell.realtime.Ticker``, same spin, same real-time setup, one event-loop pass per tick) with
nothing to do, run as a process of its own beside a session, so that a shared host's stalls hit
both and a session's period error is judged against it (``bench.cpu``).

    python -m bench.floor --duration S [--spin-us US] [--out FILE]     # the pair, one JSON
    python -m bench.floor --empty FILE --duration S [--spin-us US] [--fixed-spin]   # the empty loop
"""

from __future__ import annotations

import argparse
import asyncio
import json
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from bench import write_result
from shell.realtime import HostMarks, Ticker, setup_realtime
from teleop.session.auth import Opener, Sealer
from transport.udp import new_event_loop

KEY = bytes(range(32))
BODY = bytes(40)
PERIOD_NS = 1_000_000


def one_side(
    sock: socket.socket, peer: tuple[str, int], side: int, t0: int, ticks: int, spin_ns: int
) -> dict[str, Any]:
    """One process's loop: ``ticks`` ticks from monotonic ``t0``; returns its CPU figures."""
    sealer = Sealer(KEY, 1, side)
    opener = Opener(KEY, 1, 1 - side)
    sock.setblocking(False)
    clock, sleep = time.monotonic_ns, time.sleep
    received = verified = 0
    remaining = t0 - clock()
    if remaining > 0:
        sleep(remaining / 1e9)
    cpu0, wall0 = time.process_time(), clock()
    for k in range(ticks):
        deadline = t0 + k * PERIOD_NS
        remaining = deadline - clock()
        if remaining > spin_ns:
            sleep((remaining - spin_ns) / 1e9)
        while clock() < deadline:
            pass
        sock.sendto(sealer.seal(BODY), peer)
        while True:
            try:
                data = sock.recv(2048)
            except BlockingIOError:
                break
            received += 1
            counter, _ = opener.verify(data)
            opener.accept(counter, k * 1e-3)
            verified += 1
    cpu, wall = time.process_time() - cpu0, (clock() - wall0) / 1e9
    return {
        "ticks": ticks,
        "received": received,
        "verified": verified,
        "cpu_s": cpu,
        "wall_s": wall,
        "cpu_fraction": cpu / wall,
    }


async def _empty_loop(duration: float, spin_us: int, fixed_spin: bool = False) -> dict[str, Any]:
    min_spin = spin_us * 1000 if fixed_spin else 10_000
    ticker = Ticker(spin_ns=spin_us * 1000, capacity=int(duration * 1000) + 16, min_spin_ns=min_spin)
    ticker.start(time.monotonic_ns() + 50_000_000)
    n = int(duration * 1000)
    while ticker.k < n:
        ticker.wait()
        await asyncio.sleep(0)
    return ticker.stats().summary()


def run_empty(duration: float, spin_us: int, out: Path, fixed_spin: bool = False) -> None:
    """The empty loop; ``fixed_spin``: always spin ``spin_us`` (the scheduler before issue 22)."""
    warnings = setup_realtime(10)
    loop, name = new_event_loop()
    host0 = HostMarks.now()
    try:
        summary = loop.run_until_complete(_empty_loop(duration, spin_us, fixed_spin))
    finally:
        loop.close()
    host = HostMarks.now() - host0  # what the host did meanwhile, as a session's loop figures say
    summary.update(major_faults=host.major_faults, host_steal_ms=host.steal_ms)
    out.write_text(json.dumps({**summary, "event_loop": name, "warnings": warnings}))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--duration", type=float, default=10.0)
    ap.add_argument("--spin-us", type=int, default=100)
    ap.add_argument("--out", default=None, help="JSON file (default: print only)")
    ap.add_argument("--empty", metavar="FILE", type=Path, help="run the empty loop instead, its JSON to FILE")
    ap.add_argument("--fixed-spin", action="store_true", help="the empty loop always spins --spin-us")
    ap.add_argument("--side", type=int, choices=(0, 1), help=argparse.SUPPRESS)
    ap.add_argument("--fd", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--peer-port", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--t0", type=int, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.empty is not None:
        run_empty(a.duration, a.spin_us, a.empty, a.fixed_spin)
        return
    ticks = round(a.duration * 1000)
    if a.side is not None:  # one of the pair, started below: print its JSON on stdout
        warnings = setup_realtime(10)
        sock = socket.socket(fileno=a.fd)
        res = one_side(sock, ("127.0.0.1", a.peer_port), a.side, a.t0, ticks, a.spin_us * 1000)
        print(json.dumps({**res, "warnings": warnings}))
        return
    socks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(2)]
    for s in socks:
        s.bind(("127.0.0.1", 0))
    ports = [s.getsockname()[1] for s in socks]
    t0 = time.monotonic_ns() + 1_000_000_000  # both start on the same deadline, after their imports
    procs = []
    for side in (0, 1):
        fd = socks[side].fileno()
        cmd = [
            sys.executable,
            "-m",
            "bench.floor",
            "--side",
            str(side),
            "--fd",
            str(fd),
            "--peer-port",
            str(ports[1 - side]),
            "--t0",
            str(t0),
            "--duration",
            str(a.duration),
            "--spin-us",
            str(a.spin_us),
        ]
        procs.append(subprocess.Popen(cmd, pass_fds=(fd,), stdout=subprocess.PIPE, text=True))
    outs = [p.communicate(timeout=a.duration + 60)[0] for p in procs]
    for s in socks:
        s.close()
    if any(p.returncode for p in procs):
        sys.exit("bench.floor: a side failed")
    sides = [json.loads(o) for o in outs]
    res = {"duration_s": a.duration, "spin_us": a.spin_us, "body_bytes": len(BODY), "sides": sides}
    for i, s in enumerate(sides):
        print(f"floor side {i}: CPU {100 * s['cpu_fraction']:5.1f}%  received {s['received']}/{ticks}")
    if a.out:
        write_result(a.out, res)


if __name__ == "__main__":
    main()
