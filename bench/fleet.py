"""Robots per router: N robot-operator pairs through one ``teleop router``, against peer to peer.

Each pair is two Zenoh sessions with the session's keys (``teleop/robots/bench-i/forward`` and
``.../backward``) and QoS (express, DROP, REAL_TIME, ``transport.zenoh.make_config``): the operator
publishes a 70-byte datagram (a teleop data packet's size) at the rate, stamped with its send time;
the robot echoes it at once from Zenoh's callback; the operator takes the round trip when the echo
arrives.  The router's cost is the round trip through it less the round trip peer to peer, at the
same N and rate.  The robots hold their liveliness tokens, as announced robots do.

These are **synthetic endpoints**: two processes hold all the robots and all the operators (real
``teleop`` endpoints take ~15 % of a core each at 1 kHz, so 2 cores fit a handful of pairs), sending
the same datagrams at the same rates.  Every pair sends at the same instant each period (the
worst case for the router: a burst of N).  N doubles until a step breaks: more than 1 % of echoes
lost, the senders below 95 % of their rate, or the median round trip longer than a period (a queue
is building); what broke, and each process's CPU, is recorded.

    python -m bench.fleet [--rates 30,1000] [--max-pairs 256] [--seconds 4] [--out FILE]

Writes ``bench/results/fleet.json`` with the host's load average at each step: on a host others
load, the figures are an upper bound, to be rerun on a quiet one.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench import write_result

CLK_TCK = os.sysconf("SC_CLK_TCK")
DATAGRAM_BYTES = 70
_STAMP = struct.Struct(">IQ")  # pair, send time (ns, this host's monotonic clock)
LOSS_LIMIT = 0.01
RATE_LIMIT = 0.95


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLK_TCK


def _key(i: int, way: str) -> str:
    return f"teleop/robots/bench-{i}/{way}"


def _config(mode: str, router: str, port: int | None, listen: bool) -> Any:
    from transport.zenoh import make_config

    if mode == "router":
        return make_config("client", None, [router], None)
    ep = [f"tcp/127.0.0.1:{port}"]
    return make_config("peer", ep if listen else [], None if listen else ep, None)


def _publisher(session: Any, key: str) -> Any:
    import zenoh

    return session.declare_publisher(
        key, express=True, congestion_control=zenoh.CongestionControl.DROP, priority=zenoh.Priority.REAL_TIME
    )


def robots_worker(mode: str, router: str, ports: list[int]) -> None:
    """Every robot: a token, a subscriber on forward that echoes on backward.  Until stdin closes."""
    import zenoh

    from transport.zenoh import TransportError, open_session

    held = []
    for i, port in enumerate(ports):
        for _ in range(10):  # a port picked free may be taken by the time it binds: another
            try:
                s = open_session(_config(mode, router, port, listen=True))
                break
            except TransportError as e:
                if mode != "peer":
                    raise TransportError(f"robot session {i + 1} of {len(ports)}: {e}") from None
                port = ports[i] = _free_port()
        else:
            raise TransportError(f"no free port for robot {i} in 10 tries")
        pub = _publisher(s, _key(i, "backward"))

        def echo(sample: Any, pub: Any = pub) -> None:
            pub.put(sample.payload)

        sub = s.declare_subscriber(_key(i, "forward"), echo)
        token = s.liveliness().declare_token(f"teleop/robots/bench-{i}")
        held.append((s, pub, sub, token))
    del zenoh
    print("ready " + ",".join(map(str, ports)), flush=True)  # the ports bound (peer mode)
    sys.stdin.read()
    os._exit(0)  # hundreds of sessions: their closes are the router's business, not the bench's


def operators_worker(mode: str, router: str, ports: list[int], rate: float, seconds: float) -> None:
    """Every operator sends at ``rate`` for a warm-up, then ``seconds`` measured; prints the result."""
    from transport.zenoh import TransportError, open_session

    n = len(ports)
    rtts: list[list[int]] = [[] for _ in range(n)]
    got = [0] * n
    measuring = threading.Event()
    window = [2**63]  # the measured window's start (monotonic ns)
    pubs, held = [], []
    for i, port in enumerate(ports):
        try:
            s = open_session(_config(mode, router, port, listen=False))
        except TransportError as e:
            raise TransportError(f"operator session {i + 1} of {n} (robots hold {n} more): {e}") from None

        def back(sample: Any) -> None:
            t = time.monotonic_ns()
            pair, sent = _STAMP.unpack_from(sample.payload.to_bytes())
            got[pair] += 1
            if measuring.is_set() and sent >= window[0]:  # sent in the window: not a warm-up echo
                rtts[pair].append(t - sent)

        held.append((s, s.declare_subscriber(_key(i, "backward"), back)))
        pubs.append(_publisher(s, _key(i, "forward")))
    pad = bytes(DATAGRAM_BYTES - _STAMP.size)
    period = 1e9 / rate

    def send_round() -> None:
        for i, pub in enumerate(pubs):
            pub.put(_STAMP.pack(i, time.monotonic_ns()) + pad)

    # Warm-up: until every pair's route carried an echo (routes are declared asynchronously).
    deadline = time.monotonic() + 30
    while min(got) == 0 and time.monotonic() < deadline:
        send_round()
        time.sleep(0.01)  # the warm-up's pace, not a wait for anything
    warm = min(got) > 0
    print("measuring", flush=True)
    sent = 0
    cpu0 = time.process_time()
    t0 = window[0] = time.monotonic_ns()
    measuring.set()
    k = 0
    while (now := time.monotonic_ns()) - t0 < seconds * 1e9:
        due = t0 + k * period
        if now < due:
            time.sleep((due - now) / 1e9)
            continue
        send_round()
        sent += n
        k += 1
    wall = (time.monotonic_ns() - t0) / 1e9
    cpu = (time.process_time() - cpu0) / wall  # its own: it exits before the orchestrator could read it
    time.sleep(min(1.0, 50 * period / 1e9))  # the last echoes' grace
    measuring.clear()
    all_rtt = np.array([x for r in rtts for x in r], dtype=np.float64) / 1e3
    received = int(all_rtt.size)
    out = {
        "pairs": n,
        "warm": warm,
        "sent": sent,
        "received": received,
        "loss": 1.0 - received / sent if sent else 1.0,
        "rate_achieved": sent / n / wall,
        "cpu_fraction_self": cpu,
        "rtt_us": {
            "p50": float(np.percentile(all_rtt, 50)) if received else None,
            "p99": float(np.percentile(all_rtt, 99)) if received else None,
            "max": float(all_rtt.max()) if received else None,
        },
    }
    print(json.dumps(out), flush=True)
    os._exit(0)


def step(mode: str, pairs: int, rate: float, seconds: float) -> dict[str, Any]:
    """One measurement: a fresh router (router mode), the robots, then the operators."""
    procs: dict[str, subprocess.Popen[str]] = {}
    port = _free_port()
    router = f"tcp/127.0.0.1:{port}"
    ports = [_free_port() for _ in range(pairs)] if mode == "peer" else [0] * pairs
    me = [sys.executable, "-m", "bench.fleet"]
    args = ["--mode", mode, "--router", router, "--ports", ",".join(map(str, ports))]

    # A step that hangs (a session that never opens nor fails) is killed: its readline then ends.
    def kill_all() -> None:
        for p in list(procs.values()):
            p.kill()

    watchdog = threading.Timer(120 + 4 * seconds + pairs * 0.2, kill_all)
    watchdog.start()
    try:
        if mode == "router":
            procs["router"] = subprocess.Popen(
                [sys.executable, "-m", "teleop.cli", "router", "--listen", router],
                stdout=subprocess.DEVNULL,
                text=True,
            )
            deadline = time.monotonic() + 30
            while time.monotonic() < deadline:
                with socket.socket() as s:
                    if s.connect_ex(("127.0.0.1", port)) == 0:
                        break
                time.sleep(0.05)  # polling for the router's listener
        procs["robots"] = subprocess.Popen(
            [*me, "--worker", "robots", *args], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
        )
        assert procs["robots"].stdout is not None
        line = procs["robots"].stdout.readline().strip()
        ready = line.split()
        if not ready or ready[0] != "ready":
            return {"mode": mode, "pairs": pairs, "rate": rate, "broke": f"the robots could not open: {line}"}
        args[-1] = ready[1]  # the ports the robots bound
        ops = subprocess.Popen(
            [*me, "--worker", "operators", *args, "--rate", str(rate), "--seconds", str(seconds)],
            stdout=subprocess.PIPE,
            text=True,
        )
        procs["operators"] = ops
        assert ops.stdout is not None
        line = ops.stdout.readline().strip()
        if line != "measuring":
            return {
                "mode": mode,
                "pairs": pairs,
                "rate": rate,
                "broke": f"the operators could not open: {line}",
            }
        others = {k: p for k, p in procs.items() if k != "operators"}
        cpu0 = {k: _cpu_s(p.pid) for k, p in others.items()}
        t0 = time.monotonic()
        line = ops.stdout.readline()
        if not line.startswith("{"):
            return {
                "mode": mode,
                "pairs": pairs,
                "rate": rate,
                "broke": f"the operators failed: {line.strip()}",
            }
        result: dict[str, Any] = json.loads(line)
        dt = time.monotonic() - t0
        cpu = {k: (_cpu_s(p.pid) - cpu0[k]) / dt for k, p in others.items()}
        cpu["operators"] = result.pop("cpu_fraction_self")
    except (OSError, ValueError, ProcessLookupError, FileNotFoundError) as e:
        return {"mode": mode, "pairs": pairs, "rate": rate, "broke": f"the bench failed: {e}"}
    finally:
        watchdog.cancel()
        for p in procs.values():
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        for p in procs.values():
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
    result.update(mode=mode, rate=rate, cpu_fraction=cpu, load_avg_1min=os.getloadavg()[0])
    result["broke"] = broke(result, rate)
    return result


def limit_worker(router: str, cap: int) -> None:
    """Open plain client sessions to ``router`` one after another until one fails; print how many."""
    from transport.zenoh import TransportError, make_config, open_session

    held: list[Any] = []
    why = f"none refused up to {cap}"
    t0 = took = time.monotonic()
    while len(held) < cap:
        try:
            held.append(open_session(make_config("client", None, [router], None)))
        except TransportError as e:
            why = str(e)
            break
        took = time.monotonic()
    took -= t0  # to open those admitted
    print(json.dumps({"admitted": len(held), "open_s": took, "refused": why}), flush=True)
    os._exit(0)  # hundreds of sessions: no closes


def session_limit(max_sessions: int | None, cap: int = 1200) -> dict[str, Any]:
    """How many client sessions (plain: no declarations) one ``teleop router`` admits, opened one
    after another from one process; with ``max_sessions`` in the router's config, or Zenoh's default."""
    import tempfile

    port = _free_port()
    router = f"tcp/127.0.0.1:{port}"
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [sys.executable, "-m", "teleop.cli", "router", "--listen", router]
        if max_sessions is not None:
            cfg = Path(tmp) / "router.json5"
            cfg.write_text(f"{{ transport: {{ unicast: {{ max_sessions: {max_sessions} }} }} }}")
            cmd += ["--config", str(cfg)]
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, text=True)
        try:
            deadline = time.monotonic() + 30
            while time.monotonic() < deadline:
                with socket.socket() as s:
                    if s.connect_ex(("127.0.0.1", port)) == 0:
                        break
                time.sleep(0.05)  # polling for the router's listener
            worker = [sys.executable, "-m", "bench.fleet", "--worker", "limit", "--router", router]
            out = subprocess.run(
                [*worker, "--max-pairs", str(cap)], capture_output=True, text=True, timeout=300
            )
            got: dict[str, Any] = json.loads(out.stdout)
        finally:
            proc.kill()
            proc.wait(timeout=20)
    return {"max_sessions": max_sessions, **got}


def broke(r: dict[str, Any], rate: float) -> str | None:
    """What broke at this step, or None."""
    if not r["warm"]:
        return "not every pair's route carried an echo within 30 s"
    if r["loss"] > LOSS_LIMIT:
        return f"{r['loss']:.1%} of echoes lost (more than {LOSS_LIMIT:.0%})"
    if r["rate_achieved"] < RATE_LIMIT * rate:
        return f"the senders kept {r['rate_achieved']:.0f} of {rate:g} packets/s"
    if r["rtt_us"]["p50"] > 1e6 / rate:
        return f"median round trip {r['rtt_us']['p50'] / 1e3:.1f} ms, longer than a period: a queue builds"
    return None


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.fleet", description=__doc__.split("\n\n")[0])
    ap.add_argument("--worker", choices=["robots", "operators", "limit"])
    ap.add_argument("--mode", choices=["router", "peer"], default="router")
    ap.add_argument("--router", default="")
    ap.add_argument("--ports", default="")
    ap.add_argument("--rate", type=float, default=1000.0)
    ap.add_argument("--rates", default="30,1000")
    ap.add_argument("--max-pairs", type=int, default=256)
    ap.add_argument("--seconds", type=float, default=4.0)
    ap.add_argument(
        "--no-limit-probe", action="store_true", help="skip counting the sessions a router admits"
    )
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "fleet.json")
    a = ap.parse_args(argv)
    if a.worker == "limit":
        limit_worker(a.router, a.max_pairs)
        return 0
    if a.worker is not None:
        ports = [int(p) for p in a.ports.split(",")]
        try:
            if a.worker == "robots":
                robots_worker(a.mode, a.router, ports)
            else:
                operators_worker(a.mode, a.router, ports, a.rate, a.seconds)
        except Exception as e:  # what broke, in one line to the orchestrator; no session closes
            print(f"failed {type(e).__name__}: {e}", flush=True)
            os._exit(1)
        return 0
    load0 = os.getloadavg()
    limits = [] if a.no_limit_probe else [session_limit(m) for m in (None, 5000, 100)]
    for lim in limits:
        print(f"sessions one router admits: {json.dumps(lim)}", file=sys.stderr, flush=True)
    runs: dict[str, Any] = {}
    for rate in (float(x) for x in a.rates.split(",")):
        steps = []
        pairs, refined = 1, False
        while pairs <= a.max_pairs:
            row: dict[str, Any] = {"pairs": pairs}
            for mode in ("peer", "router"):
                r = step(mode, pairs, rate, a.seconds)
                row[mode] = r
                print(f"{rate:g}/s {pairs:4d} pairs {mode:6s}: {json.dumps(r)}", file=sys.stderr, flush=True)
            p, q = row["peer"], row["router"]
            if p.get("rtt_us", {}).get("p50") is not None and q.get("rtt_us", {}).get("p50") is not None:
                row["router_adds_us"] = {k: q["rtt_us"][k] - p["rtt_us"][k] for k in ("p50", "p99")}
            steps.append(row)
            if refined:
                break
            if q.get("broke"):
                held = [s["pairs"] for s in steps if not s["router"].get("broke")]
                mid = (max(held, default=0) + pairs) // 2
                if held and max(held) < mid < pairs:
                    pairs, refined = mid, True  # once between the last that held and the first that broke
                    continue
                break
            pairs *= 2
        steps.sort(key=lambda s: s["pairs"])
        runs[f"{rate:g}"] = {
            "rate": rate,
            "steps": steps,
            "most_pairs_held": max((s["pairs"] for s in steps if not s["router"].get("broke")), default=0),
            "broke_at": min((s["pairs"] for s in steps if s["router"].get("broke")), default=None),
            "what_broke": next(
                (
                    s["router"]["broke"]
                    for s in sorted(steps, key=lambda s: s["pairs"])
                    if s["router"].get("broke")
                ),
                f"nothing up to {a.max_pairs} pairs (the bench's cap)",
            ),
        }
    write_result(
        a.out,
        {
            "bench": "fleet",
            "synthetic_endpoints": True,
            "datagram_bytes": DATAGRAM_BYTES,
            "seconds_per_step": a.seconds,
            "cpus": os.cpu_count(),
            "load_avg_at_start": list(load0),
            "load_avg_at_end": list(os.getloadavg()),
            "session_limits": limits,
            "runs": runs,
        },
    )
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
