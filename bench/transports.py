"""UDP vs Zenoh (peer, through a router): round-trip latency and CPU, in one run.

1. **Ping-echo** through the same ``Transport`` interface the session uses: a client sends a
   teleop-sized datagram (70 B) every 1 ms on the real-time scheduler and waits for the echo; an
   echo process answers each one at once.  Round trip from the client's send to the receive
   timestamp of the echo; CPU of every process involved (client, echo, router) from ``/proc``.
2. **Full session**: ``teleop run --codec none`` over each transport (every tick sends a packet
   both ways), CPU per process and the loops' timing, as the report gives them.

    python -m bench.transports [--pings N] [--duration S] [--out FILE]

Writes JSON (default ``bench/results/transports.json``).  Run it on an otherwise idle machine.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import platform
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench import write_result
from shell.realtime import Ticker, percentiles_us, setup_realtime
from transport.base import Transport
from transport.udp import UdpTransport, new_event_loop
from transport.zenoh import ZenohTransport, make_config

CLK_TCK = os.sysconf("SC_CLK_TCK")
PING = b"\x9a" + bytes(69)


def _free_port(kind: int) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _cpu_s(pid: int) -> float:
    """utime + stime of a process, from /proc (children excluded)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLK_TCK


async def _open(mode: str, role: str, endpoint: str, port: int) -> Transport:
    if mode == "udp":
        return await UdpTransport.bind(("127.0.0.1", port if role == "teleoperator" else 0))
    prefix = "bench/transports"
    if mode == "zenoh-peer":
        cfg = (
            make_config("peer", listen=[endpoint])
            if role == "teleoperator"
            else make_config("peer", connect=[endpoint])
        )
    else:
        cfg = make_config("client", connect=[endpoint])
    return await ZenohTransport.open(role, prefix, cfg)


async def _echo(mode: str, endpoint: str, port: int, seconds: float) -> None:
    tr = await _open(mode, "teleoperator", endpoint, port)
    end = time.monotonic() + seconds
    try:
        while time.monotonic() < end:
            if not await tr.wait(0.2):
                continue
            for data, addr, _ in tr.drain():
                if data == b"stop":
                    return
                tr.send(data, addr)
    finally:
        tr.close()


async def _client(mode: str, endpoint: str, port: int, pings: int) -> dict[str, Any]:
    tr = await _open(mode, "operator", endpoint, port)
    peer = ("127.0.0.1", port) if mode == "udp" else ("zenoh", 0)
    try:
        # Warm up: the echo side may still be connecting (Zenoh peers retry every ~0.5 s).
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            tr.send(PING, peer)
            if await tr.wait(0.1):
                tr.drain()
                break
        else:
            raise RuntimeError(f"{mode}: no echo within 10 s")
        cpu0 = time.process_time()
        ticker = Ticker(spin_ns=100_000, capacity=pings + 16)
        ticker.start(time.monotonic_ns() + 10_000_000)
        rtt = np.full(pings, np.nan)
        lost = 0
        for i in range(pings):
            ticker.wait()
            t_send = time.monotonic_ns()
            tr.send(PING, peer)
            got = None
            limit = time.monotonic() + 0.005
            while got is None and time.monotonic() < limit:
                await tr.wait(limit - time.monotonic())
                items = tr.drain()
                if items:
                    got = items[-1][2]
            if got is None:
                lost += 1
            else:
                rtt[i] = got - t_send
        cpu = time.process_time() - cpu0
        wall = ticker.stats().wall_s
        tr.send(b"stop", peer)
        await asyncio.sleep(0.05)
        ok = rtt[~np.isnan(rtt)].astype(np.int64)
        return {"rtt_us": percentiles_us(ok), "pings": pings, "lost": lost, "client_cpu_fraction": cpu / wall}
    finally:
        tr.close()


def ping_echo(mode: str, pings: int) -> dict[str, Any]:
    port = _free_port(socket.SOCK_DGRAM)
    endpoint = f"tcp/127.0.0.1:{_free_port(socket.SOCK_STREAM)}"
    procs: dict[str, subprocess.Popen[bytes]] = {}
    if mode == "zenoh-router":
        procs["router"] = subprocess.Popen(
            [sys.executable, "-m", "teleop.cli", "router", "--listen", endpoint]
        )
        time.sleep(0.5)
    procs["echo"] = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "bench.transports",
            "--echo",
            mode,
            "--endpoint",
            endpoint,
            "--port",
            str(port),
            "--seconds",
            str(pings / 1000 + 30),
        ]
    )
    time.sleep(0.5)
    cpu0 = {k: _cpu_s(p.pid) for k, p in procs.items()}
    t0 = time.monotonic()
    setup_realtime(None)
    loop, _ = new_event_loop()
    try:
        res = loop.run_until_complete(_client(mode, endpoint, port, pings))
    finally:
        loop.close()
    wall = time.monotonic() - t0
    for k, p in procs.items():
        res[f"{k}_cpu_fraction"] = (_cpu_s(p.pid) - cpu0[k]) / wall
    for p in procs.values():
        p.send_signal(signal.SIGINT)
    for p in procs.values():
        try:
            p.wait(timeout=10)
        except subprocess.TimeoutExpired:
            p.kill()
    return res


def session(transport: str, mode: str, duration: float) -> dict[str, Any]:
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [
            sys.executable,
            "-m",
            "teleop.cli",
            "run",
            "--codec",
            "none",
            "--duration",
            str(duration),
            "--out",
            tmp,
            "--no-plots",
            "--no-sim",
            "--transport",
            transport,
        ]
        if transport == "zenoh":
            cmd += ["--zenoh-mode", mode]
        r = subprocess.run(cmd, capture_output=True, text=True)
        if r.returncode != 0:
            raise RuntimeError(f"teleop run over {transport} failed: {r.stderr}")
        rep = json.loads((Path(tmp) / "report.json").read_text())
    out: dict[str, Any] = {}
    for role, p in rep["processes"].items():
        out[role] = {
            "cpu_fraction": p["loop"]["cpu_fraction"],
            "period_error_us": p["loop"]["period_error_us"],
            "overruns": p["loop"]["overruns"],
            "late_payloads_missed": p["grace"]["missed"],
        }
    out["link_delay_ms"] = {d: rep["link"][d]["delay_ms"] for d in ("forward", "backward")}
    out["received"] = {d: rep["wire"][d]["received_packets"] for d in ("forward", "backward")}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--pings", type=int, default=5000)
    ap.add_argument("--duration", type=float, default=10.0)
    ap.add_argument("--out", default="bench/results/transports.json")
    ap.add_argument("--echo", help=argparse.SUPPRESS)
    ap.add_argument("--endpoint", help=argparse.SUPPRESS)
    ap.add_argument("--port", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--seconds", type=float, default=60.0, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.echo:
        loop, _ = new_event_loop()
        try:
            loop.run_until_complete(_echo(a.echo, a.endpoint, a.port, a.seconds))
        finally:
            loop.close()
        return
    res: dict[str, Any] = {
        "what": "UDP vs Zenoh on loopback: ping-echo RTT at 1 kHz and full-session CPU",
        "python": platform.python_version(),
        "pings": a.pings,
        "session_duration_s": a.duration,
        "ping_echo": {},
        "session": {},
    }
    for mode in ("udp", "zenoh-peer", "zenoh-router"):
        r = ping_echo(mode, a.pings)
        res["ping_echo"][mode] = r
        rt = r["rtt_us"]
        cpus = "  ".join(
            f"{k.removesuffix('_cpu_fraction')} {100 * v:.1f}%"
            for k, v in r.items()
            if k.endswith("_cpu_fraction")
        )
        print(
            f"ping-echo {mode:<13} RTT p50 {rt['p50']:7.1f}  p99 {rt['p99']:7.1f}  p99.9 {rt['p999']:7.1f}  "
            f"max {rt['max']:8.1f} us  lost {r['lost']}  CPU {cpus}"
        )
    for transport, mode in (("udp", "-"), ("zenoh", "peer"), ("zenoh", "client")):
        name = transport if transport == "udp" else f"zenoh-{mode}"
        s = session(transport, mode, a.duration)
        res["session"][name] = s
        print(
            f"session   {name:<13} CPU operator {100 * s['operator']['cpu_fraction']:.1f}%  "
            f"teleoperator {100 * s['teleoperator']['cpu_fraction']:.1f}%  late payloads missed "
            f"{s['operator']['late_payloads_missed']}/{s['teleoperator']['late_payloads_missed']}  "
            f"received {s['received']['forward']}/{s['received']['backward']}"
        )
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_result(out, res)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
